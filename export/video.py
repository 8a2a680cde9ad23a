"""H.264 MP4 video (a turntable browsers play), through PyAV's FFmpeg (libx264, yuv420p)."""

from __future__ import annotations

import os
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


class H264Writer:
    """Write RGB frames to an MP4 file as H.264 (yuv420p, constant quality ``crf``).

    Use as a context manager; frames are (H, W, 3) uint8 sRGB, all of one size.
    """

    def __init__(self, path: str | os.PathLike, fps: int, crf: int = 18) -> None:
        import av

        self.path = Path(path)
        try:
            self._out = av.open(str(self.path), "w", format="mp4")
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
