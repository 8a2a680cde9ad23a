"""H.264 MP4 video (a turntable browsers play), through PyAV's FFmpeg (libx264, yuv420p)."""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damcap.common.errors import DamcapError


def even_frame(rgb8: np.ndarray) -> np.ndarray:
    """Pad an (H, W, 3) frame by repeating its last row / column to even sides (4:2:0 chroma needs them).

    >>> even_frame(np.zeros((3, 4, 3), np.uint8)).shape
    (4, 4, 3)
    """
    h, w = rgb8.shape[:2]
    return np.pad(rgb8, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


MIN_DURATION_S = 3.0
"""a turntable plays at least this long (a one-second clip is over before a viewer has looked)"""
FPS_FLOOR = 8
"""a turntable with few views slows down to this frame rate before it repeats its orbit"""


@dataclass(frozen=True)
class TurntableTiming:
    """How an orbit of ``views`` frames is played: ``turns`` whole orbits at ``fps``."""

    fps: int
    """frames per second"""
    turns: int
    """how many times the orbit is played (>= 1)"""
    duration_s: float
    """the video's length, ``turns * views / fps``"""


def turntable_timing(views: int, fps_max: int, min_duration_s: float = MIN_DURATION_S, fps_floor: int = FPS_FLOOR) -> TurntableTiming:
    """The frame rate and number of orbits that make a turntable of ``views`` frames last at least ``min_duration_s``.

    The rate is ``views / min_duration_s`` (rounded down) kept within [``fps_floor``, ``fps_max``]
    (a ``fps_max`` below the floor is used as it is); when one orbit at that rate is still shorter
    than ``min_duration_s`` (fewer than ``fps_floor * min_duration_s`` views), the orbit is played
    whole again until it is not.

    >>> turntable_timing(24, 24)
    TurntableTiming(fps=8, turns=1, duration_s=3.0)
    >>> turntable_timing(120, 24)
    TurntableTiming(fps=24, turns=1, duration_s=5.0)
    >>> turntable_timing(4, 24)
    TurntableTiming(fps=8, turns=6, duration_s=3.0)
    """
    if views < 1 or fps_max < 1 or fps_floor < 1 or not min_duration_s > 0:
        raise DamcapError(f"turntable timing: expected views, fps_max, fps_floor >= 1 and min_duration_s > 0, got "
                          f"{views}, {fps_max}, {fps_floor}, {min_duration_s}")
    fps = min(fps_max, max(fps_floor, math.floor(views / min_duration_s)))
    turns = max(1, math.ceil(min_duration_s * fps / views - 1e-9))
    return TurntableTiming(fps, turns, turns * views / fps)


def mp4_top_level_boxes(data: bytes) -> list[str]:
    """The types of an MP4 file's top-level boxes, in file order (ISO/IEC 14496-12, 4.2).

    A file plays before it has fully downloaded ("faststart") when ``moov`` comes before ``mdat``.

    >>> mp4_top_level_boxes(struct.pack(">I4s", 8, b"ftyp") + struct.pack(">I4s", 8, b"moov"))
    ['ftyp', 'moov']
    """
    boxes, i = [], 0
    while i + 8 <= len(data):
        size, kind = struct.unpack(">I4s", data[i:i + 8])
        if size == 1:  # 64-bit size after the type
            if i + 16 > len(data):
                raise DamcapError(f"MP4: a box at byte {i} declares a 64-bit size past the end of the data ({len(data)} bytes)")
            (size,) = struct.unpack(">Q", data[i + 8:i + 16])
        elif size == 0:  # the box runs to the end of the file
            size = len(data) - i
        if size < 8:
            raise DamcapError(f"MP4: a box at byte {i} declares size {size}; expected >= 8")
        boxes.append(kind.decode("latin-1"))
        i += size
    return boxes


class H264Writer:
    """Write RGB frames to an MP4 file as H.264 (yuv420p, constant quality ``crf``).

    Use as a context manager; frames are (H, W, 3) uint8 sRGB, all of one size. The file is
    written "faststart" (its index, ``moov``, before the frames) so that a browser starts playing
    it before it has downloaded.
    """

    def __init__(self, path: str | os.PathLike, fps: int, crf: int = 18) -> None:
        import av

        self.path = Path(path)
        try:
            self._out = av.open(str(self.path), "w", format="mp4", container_options={"movflags": "+faststart"})
        except (OSError, av.FFmpegError) as e:
            raise DamcapError(f"{self.path}: cannot write an MP4 here ({e})") from None
        self._fps, self._crf, self._stream = fps, crf, None

    def write(self, rgb8: np.ndarray) -> None:
        import av

        frame = even_frame(np.ascontiguousarray(rgb8, np.uint8))
        if self._stream is None:
            self._stream = self._out.add_stream("libx264", rate=self._fps, options={"crf": str(self._crf)})
            self._stream.height, self._stream.width = frame.shape[:2]
            self._stream.pix_fmt = "yuv420p"
        self._mux(lambda: self._stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))

    def close(self) -> None:
        if self._stream is not None:
            self._mux(lambda: self._stream.encode())
        self._out.close()

    def _mux(self, packets) -> None:
        """Encode and write (FFmpeg opens the file at the first packet: its errors surface here)."""
        import av

        try:
            for packet in packets():
                self._out.mux(packet)
        except (OSError, av.FFmpegError) as e:
            raise DamcapError(f"{self.path}: cannot write an MP4 here ({e})") from None

    def __enter__(self) -> H264Writer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
