"""Photos from a video: sharp, well-spread video frames (``damcap frames VIDEO -o PHOTOS/``).

Here "frame" means a video frame (not a capture folder's frame, a view in ``transforms.json``).
People film objects with phones. The video is decoded twice through PyAV (FFmpeg): the first pass
scores every video frame's sharpness (variance of the Laplacian of its grey image, downscaled to
:data:`SCORE_SIDE`), the second writes the chosen video frames as JPEGs. They are chosen by
:func:`pick_video_frames`: the video is cut into ``count`` windows of consecutive video frames
and the sharpest of each window is kept, so the photos spread over the whole video (the camera's
path) and motion blur is avoided where a window has a sharper video frame. ``frames.json``
records the video, each photo's video frame index (``video_frame_index``), time and sharpness.
Video frames are turned upright as the video's display matrix says (phones store portrait video
as rotated landscape frames), as players show them. A video has no EXIF exposure: ``reconstruct`` then treats the photos as sharing one exposure
(as it says).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from damcap.common.atomic import write_json_atomic
from damcap.common.errors import DamcapError
from damcap.common.exr import write_image_u8
from damcap.common.validate import MAX_IMAGE_SIDE, check_ranges, in_range

SCORE_SIDE = 480
"""longer side of the grey image a video frame's sharpness is measured on, pixels"""


@dataclass(frozen=True)
class VideoFrameOptions:
    """Options of ``damcap frames``."""

    count: int = field(default=60, metadata=in_range(2, 100_000))
    """photos to extract (fewer when the video has fewer video frames)"""
    max_side: int = field(default=0, metadata=in_range(0, MAX_IMAGE_SIDE))
    """downscale photos so their longer side is at most this, pixels (0 = as filmed)"""
    quality: int = field(default=95, metadata=in_range(1, 100))
    """JPEG quality"""

    def validate(self) -> None:
        check_ranges(self)


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian of a (H, W) grey image (higher = sharper).

    >>> flat = np.full((32, 32), 128, np.uint8)
    >>> edges = np.tile(np.array([0, 255], np.uint8), (32, 16))
    >>> sharpness(flat), sharpness(edges) > 1000
    (0.0, True)
    """
    import cv2

    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


def pick_video_frames(scores: list[float] | np.ndarray, count: int) -> list[int]:
    """The index of the sharpest video frame of each of ``count`` equal windows of consecutive
    video frames (all of them when there are at most ``count``), in order.

    >>> pick_video_frames([1, 5, 2, 9, 1, 1, 7, 3], 4)
    [1, 3, 4, 6]
    >>> pick_video_frames([1, 2], 5)
    [0, 1]
    """
    n = len(scores)
    if n <= count:
        return list(range(n))
    edges = np.linspace(0, n, count + 1).round().astype(int)
    s = np.asarray(scores, np.float64)
    return [int(a + np.argmax(s[a:b])) for a, b in zip(edges[:-1], edges[1:])]


def _open(path: Path) -> Any:
    import av

    try:
        container = av.open(str(path))
    except (OSError, av.FFmpegError) as e:
        raise DamcapError(f"{path}: cannot read a video here ({str(e).split(':')[0]}); give a video file (MP4, MOV, ...)") from None
    if not container.streams.video:
        container.close()
        raise DamcapError(f"{path}: has no video stream")
    return container


def upright(rgb: np.ndarray, rotation_deg: float) -> np.ndarray:
    """A decoded video frame turned as its display matrix says (a phone filming upright stores
    the sensor's landscape frames and a rotation): ``rotation_deg`` counter-clockwise, FFmpeg's
    ``av_display_rotation_get`` (PyAV's ``VideoFrame.rotation``), rounded to quarter turns.

    >>> img = np.zeros((2, 4), np.uint8); img[:, 0] = 1  # landscape, the left column marked
    >>> upright(img, -90).tolist()  # turned clockwise: portrait, the mark on top
    [[1, 1], [0, 0], [0, 0], [0, 0]]
    """
    turns = int(round(rotation_deg / 90.0)) % 4
    return np.ascontiguousarray(np.rot90(rgb, turns)) if turns else rgb


#: bytes per pixel that scoring a decoded video frame makes of it (its upright copy, grey, the
#: float32 sharpness filter)
VIDEO_WORKING_BYTES = 16


def _video_frames(path: Path) -> Any:
    """Yield (video frame index, time_s, (H, W, 3) uint8 RGB upright, display rotation deg) of every decoded video frame."""
    import av

    from damcap.common.exr import check_header_size

    container = _open(path)
    try:
        stream = container.streams.video[0]
        checked = (stream.codec_context.width, stream.codec_context.height)
        if min(checked) > 0:  # the stream's header: a frame size no memory holds is refused before decoding
            check_header_size(path, checked[0], checked[1], 3, 1, VIDEO_WORKING_BYTES)
        k = 0
        try:
            for frame in container.decode(stream):
                if (frame.width, frame.height) != checked:  # a size the header did not state
                    checked = (frame.width, frame.height)
                    check_header_size(path, frame.width, frame.height, 3, 1, VIDEO_WORKING_BYTES)
                rotation = float(frame.rotation or 0.0)
                yield (k, float(frame.time) if frame.time is not None else float("nan"),
                       upright(frame.to_ndarray(format="rgb24"), rotation), rotation)
                k += 1
        except av.FFmpegError as e:
            if k == 0:
                raise DamcapError(f"{path}: cannot decode the video ({e})") from None
            # a truncated tail: the video frames decoded so far are kept (the record says how many)
    finally:
        container.close()


def _video_frame_count(path: Path) -> int:
    """Video frames the container says the video has (0 when it does not say)."""
    container = _open(path)
    try:
        return int(container.streams.video[0].frames or 0)
    finally:
        container.close()


def _resized(rgb: np.ndarray, max_side: int) -> np.ndarray:
    import cv2

    h, w = rgb.shape[:2]
    if not max_side or max(h, w) <= max_side:
        return rgb
    f = max_side / max(h, w)
    return cv2.resize(rgb, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)


def extract_video_frames(video: str | os.PathLike, out: str | os.PathLike, opts: VideoFrameOptions,
                         progress: Callable[[str, int, int], None] | None = None) -> dict[str, Any]:
    """Write the chosen video frames of ``video`` into ``out`` as ``frame_NNNNN.jpg`` (NNNNN: the
    video frame index) and ``frames.json``.

    Args:
        progress: ``progress(stage, done, total)`` ('scoring' every decoded video frame, total 0
            when the container does not say; 'writing' the chosen ones).

    Returns:
        the record written to ``frames.json``.

    Raises:
        DamcapError: an unreadable video, one without a video stream, or one with fewer than 2 video frames.
    """
    import cv2

    opts.validate()
    video, out = Path(video), Path(out)
    if not video.is_file():
        raise DamcapError(f"{video}: video file not found")
    scores, times, rotations = [], [], set()
    total = _video_frame_count(video) if progress else 0
    for k, t, rgb, rotation in _video_frames(video):
        rotations.add(rotation)
        gray = cv2.cvtColor(_resized(rgb, SCORE_SIDE), cv2.COLOR_RGB2GRAY)
        scores.append(sharpness(gray))
        times.append(t)
        if progress:
            progress("scoring", k + 1, total)
    if len(scores) < 2:
        raise DamcapError(f"{video}: {len(scores)} video frame(s) decoded; a capture needs at least 2")
    chosen = pick_video_frames(scores, opts.count)
    wanted = set(chosen)
    out.mkdir(parents=True, exist_ok=True)
    photos = []
    for k, _, rgb, _ in _video_frames(video):
        if k in wanted:
            name = f"frame_{k:05d}.jpg"
            write_image_u8(out / name, _resized(rgb, opts.max_side), {"Compression": f"jpeg:{opts.quality}"})
            photos.append({"photo": name, "video_frame_index": k, "time_s": times[k], "sharpness": scores[k]})
            if progress:
                progress("writing", len(photos), len(chosen))
        if k >= chosen[-1]:
            break
    median = float(np.median(scores))
    record = {"video": str(video.resolve()), "video_frames_decoded": len(scores), "count": len(photos), "options": {"count": opts.count,
              "max_side": opts.max_side, "quality": opts.quality}, "median_sharpness": median,
              # the display matrix's rotation (counter-clockwise degrees), applied to every photo
              "display_rotation_deg": sorted(rotations), "photos": photos}
    write_json_atomic(out / "frames.json", record)
    return record
