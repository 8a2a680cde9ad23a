"""Per-frame buffers of ``damcap reconstruct`` (step 6): each photo linearised and resampled once
into its pinhole target, the geometry ray cast into normals, positions and coverage (limited to the
mask when given, and to the pixels not flagged clipped), written as one frame of the capture
folder. Frames the geometry misses are dropped with a reason."""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from damcap.common.capture_folder import Capture, Frame, FrameData, Intrinsics, write_frame
from damcap.common.errors import DamcapError
from damcap.common.mesh import Mesh
from damcap.common.raycast import MeshRaycaster

from damcap.reconstruct.photos import photo_kind, read_photo_radiance
from damcap.reconstruct.undistort import PhotoCamera, resample_to_pinhole


@dataclass
class FramePhoto:
    """One registered photo and what its frame needs."""

    name: str
    """the photo's name in the photo folder"""
    path: Path
    """the photo file"""
    camera: PhotoCamera
    """its (possibly distorted) camera"""
    target: Intrinsics
    """the pinhole camera of its frame"""
    exposure_factor: float
    """what its pixel values are divided by to be comparable across photos (exposure time x ISO / N^2)"""
    exposure: dict[str, Any] | None
    """its EXIF exposure, as written into the frame (None when unknown)"""
    mask: np.ndarray | None
    """(H, W) object mask in [0, 1] in the target camera, when coverage is limited to the mask"""


def frame_data_from_buffers(radiance_lin: np.ndarray, normal_world: np.ndarray, position_world: np.ndarray,
                            coverage: np.ndarray, mask: np.ndarray | None = None) -> FrameData:
    """Compose one frame: coverage (limited to the mask when given), background zeroed.

    Args:
        radiance_lin: (H, W, 3) float32 linear radiance of the whole photo.
        normal_world, position_world: (H, W, 3) ray-cast buffers.
        coverage: (H, W) ray-cast coverage in [0, 1].
        mask: optional (H, W) object mask in [0, 1].
    """
    a = coverage if mask is None else np.minimum(coverage, np.clip(mask, 0, 1))
    a = np.where(a > 1e-3, a, 0).astype(np.float32)
    on = a[..., None] > 0
    return FrameData(
        radiance_lin=np.where(on, np.maximum(radiance_lin, 0), 0).astype(np.float32),
        normal_world=np.where(on, normal_world, 0).astype(np.float32),
        position_world=np.where(on, position_world, 0).astype(np.float32),
        coverage=a,
    )


def unclipped_fraction(clipped: np.ndarray, camera: PhotoCamera, target: Intrinsics) -> np.ndarray:
    """Where a photo's clipped pixels land in its pinhole target: 1 where no clipped pixel
    contributes, 0 where any does (a conservative mask: resampling spreads a clipped pixel).

    Args:
        clipped: (H, W) bool of the photo's size.
        camera, target: as for :func:`damcap.reconstruct.undistort.resample_to_pinhole`.

    Returns:
        (target.h, target.w) float32 in {0, 1}.
    """
    c = resample_to_pinhole(np.asarray(clipped, np.float32), camera, target)
    return (c <= 0).astype(np.float32)


def write_frames(out: Path, photos: list[FramePhoto], world_from_cams: np.ndarray, mesh: Mesh,
                 sphere: tuple[np.ndarray, float] | None, reference: float, supersample: int, dtype: str,
                 progress: Callable[[str, int, int], None], log: Callable[[str], None],
                 log_response: np.ndarray | None = None, clipped: str = "auto") -> tuple[list[Frame], dict[str, str]]:
    """Write one frame per photo that sees the geometry (each file atomically).

    Args:
        out: the capture folder.
        photos: the registered photos, in order.
        world_from_cams: (N, 4, 4) their cameras in the capture's world.
        mesh: the geometry in the capture's world.
        sphere: (centre, radius) of an analytic sphere, whose exact normals replace the mesh's.
        reference: the exposure factor that maps to radiance scale 1.
        supersample: sub-pixel grid per axis for coverage at silhouettes.
        dtype: 'half' or 'float' EXR channels.
        progress, log: progress(stage, done, total) and one-line messages.
        log_response: (3, L) response curve undone for 8-bit photos instead of sRGB, or None.
        clipped: pixels the photo flags clipped (:class:`.photos.PhotoRadiance`): 'drop' (coverage
            0), 'keep', or 'auto' (keep a display photo's, drop the others'; ``ReconstructOptions.clipped``).
            Either way one line of ``log`` says how many of the object's pixels were clipped, and
            each frame records its count.

    Returns:
        the frames written, and the dropped photos with their reasons.
    """
    with ThreadPoolExecutor(max_workers=1) as writer:  # writes one frame while the next is ray cast
        return _write_frames(out, photos, world_from_cams, mesh, sphere, reference, supersample, dtype, progress, log,
                             log_response, clipped, writer)


def _write_frames(out: Path, photos: list[FramePhoto], world_from_cams: np.ndarray, mesh: Mesh,
                  sphere: tuple[np.ndarray, float] | None, reference: float, supersample: int, dtype: str,
                  progress: Callable[[str, int, int], None], log: Callable[[str], None], log_response: np.ndarray | None,
                  clipped: str, writer: ThreadPoolExecutor) -> tuple[list[Frame], dict[str, str]]:
    """:func:`write_frames`' loop; each frame's files go to ``writer`` (at most two pending)."""
    rc = MeshRaycaster(mesh)
    frames: list[Frame] = []
    # a photo folder holds one kind of file (reconstruct.photos refuses a mix): one decision for all
    keep_flagged = bool(photos) and keeps_clipped(clipped, photo_kind(photos[0].path))
    clipped_object_total = object_total = photos_clipped = 0
    dropped: dict[str, str] = {}
    pending: list[Future] = []
    for k, p in enumerate(photos):
        progress("frames", k, len(photos))
        tgt = p.target
        photo = read_photo_radiance(p.path, p.exposure_factor, reference, log_response)
        if (photo.radiance_lin.shape[1], photo.radiance_lin.shape[0]) != (p.camera.width, p.camera.height):
            raise DamcapError(f"{p.path}: the photo is {photo.radiance_lin.shape[1]}x{photo.radiance_lin.shape[0]} but its "
                              f"camera is {p.camera.width}x{p.camera.height}")
        radiance = resample_to_pinhole(photo.radiance_lin, p.camera, tgt)
        mask = p.mask
        clipped_px = 0
        keep = None
        if photo.clipped is not None and photo.clipped.any():
            keep = unclipped_fraction(photo.clipped, p.camera, tgt)
            clipped_px = int((keep == 0).sum())
            if not keep_flagged:
                mask = keep if mask is None else np.minimum(mask, keep)
        b = rc.buffers(world_from_cams[k], tgt.fl_x, tgt.fl_y, tgt.cx, tgt.cy, tgt.w, tgt.h, supersample=supersample)
        on_object = (b.coverage > 0.5) if p.mask is None else (b.coverage > 0.5) & (p.mask > 0.5)
        clipped_object_px = int(((keep == 0) & on_object).sum()) if keep is not None else 0
        clipped_object_total += clipped_object_px
        object_total += int(on_object.sum())
        photos_clipped += clipped_object_px > 0
        normal = b.normal_world
        if sphere is not None:  # analytic normals of the analytic sphere
            hit = b.coverage > 0
            d = b.position_world[hit] - sphere[0]
            normal = normal.copy()
            normal[hit] = d / np.linalg.norm(d, axis=1, keepdims=True)
        data = frame_data_from_buffers(radiance, normal, b.position_world, b.coverage, mask)
        if not (data.coverage > 0.5).any():
            dropped[p.name] = "the geometry is not seen from this camera (no covered pixel)"
            log(f"dropped: {p.name}: {dropped[p.name]}")
            continue
        stem = Path(p.name).stem
        frame = Frame(file_path=f"images/{stem}.exr", geometry_path=f"geometry/{stem}.exr", world_from_cam=world_from_cams[k],
                      intrinsics=tgt, exposure=p.exposure,
                      extra={"photo": p.name, "exposure_relative": float(p.exposure_factor / reference),
                             **({"clipped_pixels": clipped_px, "clipped_object_pixels": clipped_object_px} if clipped_px else {})})
        while len(pending) >= 2:
            pending.pop(0).result()  # raises the writer's error here
        pending.append(writer.submit(write_frame, Capture(out, [frame], [], []), frame, data, dtype=dtype))
        frames.append(frame)
    for f in pending:
        f.result()
    progress("frames", len(photos), len(photos))
    if clipped_object_total:
        log(clipped_note(clipped_object_total, object_total, photos_clipped, len(photos), keep_flagged))
    return frames, dropped


def keeps_clipped(policy: str, kind: str) -> bool:
    """Whether a photo's clipped pixels stay in the coverage (``ReconstructOptions.clipped``, which
    ``ReconstructOptions.validate`` checks).

    >>> keeps_clipped("auto", "display"), keeps_clipped("auto", "raw"), keeps_clipped("drop", "display")
    (True, False, False)
    """
    return policy == "keep" or (policy == "auto" and kind == "display")


def clipped_note(clipped_px: int, object_px: int, photos_with: int, photos: int, kept: bool) -> str:
    """The one line reconstruct prints when photos have clipped pixels on the object.

    >>> print(clipped_note(30, 1000, 2, 5, False))
    clipped: 30 of the object's 1000 pixels (3.0 %) in 2 of 5 photos are saturated (their radiance is only a lower bound): left out of the coverage (--clipped keep keeps them)
    """
    share = f"{clipped_px} of the object's {object_px} pixels ({100 * clipped_px / max(object_px, 1):.1f} %) in {photos_with} of {photos} photos are saturated"
    if kept:
        return (f"clipped: {share} (their radiance is only a lower bound): kept in the coverage, so what is fitted there is that "
                "bound (--clipped drop leaves them out; an exposure bracket, damcap hdr, records them)")
    return f"clipped: {share} (their radiance is only a lower bound): left out of the coverage (--clipped keep keeps them)"
