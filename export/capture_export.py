"""A capture folder for the tools people already use: nerfstudio's dataset layout and a COLMAP model.

``damcap export-capture CAPTURE --format nerfstudio|colmap -o DIR``. The capture's frames are
linear radiance on undistorted pinhole cameras (docs/capture-format.md); both formats get them as
8-bit sRGB PNGs under one exposure for the whole capture (so frames keep their relative
brightness), and the surface the capture was ray cast against as a coloured point cloud (samples
of the frames' covered pixels: every capture has them, measured or synthetic).

- ``nerfstudio``: ``images/*.png``, ``masks/*.png`` (255 where the frame's coverage is above
  :data:`MASK_COVERAGE`), ``points.ply`` and ``transforms.json`` as nerfstudio's dataparser
  reads it: shared pinhole intrinsics (``camera_model`` PINHOLE) or per-frame ones, per-frame
  ``file_path``, ``mask_path`` and OpenGL ``transform_matrix``, ``train_filenames`` /
  ``val_filenames`` / ``test_filenames`` (val = the capture's test split: nerfstudio stops when a
  split list is missing) and ``ply_file_path``. The points are in the frames' world, so no
  ``applied_transform`` is written (nerfstudio would apply it to the points a second time); the
  similarity ``damcap reconstruct`` applied to its registration is kept as
  ``damcap_norm_from_input_world`` (4x4).
- ``colmap``: a COLMAP text model (``sparse/0/cameras.txt``, ``images.txt``, ``points3D.txt``,
  ``rigs.txt``, ``frames.txt``, written by pycolmap) of the undistorted capture, PINHOLE cameras
  and the OpenCV-axes poses COLMAP uses, plus ``images/*.png``: what 3D Gaussian splatting tools
  start from. The points have no tracks (the capture keeps no feature observations).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from damcap.common.atomic import write_json_atomic
from damcap.common.capture_folder import Capture, FrameData, Intrinsics, read_frame
from damcap.common.colour import display_srgb8, exposure_scale_for, working_from_rec709
from damcap.common.errors import DamcapError
from damcap.common.exr import write_png
from damcap.common.validate import SEED, check_ranges, in_range

MASK_COVERAGE = 0.5
"""a pixel is in the mask when its coverage is above this"""
SCALE_SAMPLES_PER_FRAME = 20_000
"""covered pixels per frame pooled for the capture's one display exposure"""
OPENCV_FROM_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
"""camera axes: OpenGL (x right, y up, looking down -z) to OpenCV (x right, y down, looking down +z)"""


@dataclass(frozen=True)
class CaptureExportOptions:
    """Options of ``damcap export-capture``."""

    format: Literal["nerfstudio", "colmap"] = "nerfstudio"
    """the target tool's layout: 'nerfstudio' (its dataset layout: PNG frames, masks,
    transforms.json, points.ply) or 'colmap' (a COLMAP text model of the undistorted capture and its PNG frames)"""
    points: int = field(default=100_000, metadata=in_range(0, 100_000_000))
    """surface points written as the point cloud (samples of the frames' covered pixels; 0 = none)"""
    seed: int = field(default=0, metadata=SEED)
    """seeds which pixels become points"""

    def validate(self) -> None:
        check_ranges(self)


def rec709_of(radiance_lin: np.ndarray, colorspace: str) -> np.ndarray:
    """(..., 3) linear radiance in ``colorspace`` (``lin_rec709`` or ``acescg``) as linear Rec.709
    (the inverse of the conversion the capture stage applied, :func:`~damcap.common.colour.working_from_rec709`)."""
    if colorspace == "lin_rec709":
        return radiance_lin
    return (radiance_lin @ np.linalg.inv(working_from_rec709(colorspace)).T).astype(np.float32)


def mask_u8(coverage: np.ndarray) -> np.ndarray:
    """(H, W) uint8 mask: 255 where ``coverage`` > :data:`MASK_COVERAGE`, else 0.

    >>> mask_u8(np.array([[0.0, 0.5, 0.51, 1.0]])).tolist()
    [[0, 0, 255, 255]]
    """
    return np.where(coverage > MASK_COVERAGE, 255, 0).astype(np.uint8)


def cam_from_world_opencv(world_from_cam_gl: np.ndarray) -> np.ndarray:
    """(4, 4) COLMAP's pose (world to camera, OpenCV axes) of a capture camera (camera to world, OpenGL axes).

    >>> m = np.eye(4); m[:3, 3] = [0, 0, 2]  # at z = 2, looking down -z at the origin
    >>> (cam_from_world_opencv(m)[:3, 3] + 0.0).tolist()  # the origin lies 2 ahead of the camera
    [0.0, 0.0, 2.0]
    """
    return np.linalg.inv(np.asarray(world_from_cam_gl, np.float64) @ OPENCV_FROM_OPENGL)


def _png_name(frame_path: str) -> str:
    return Path(frame_path).stem + ".png"


def _frames(capture: Capture, progress: Callable[[int, int], None] | None):
    """Yield (k, frame, data), reading the frames one at a time (an export reads them twice: once
    for the one display exposure, once to write them, rather than holding every frame in memory)."""
    for k, f in enumerate(capture.frames):
        if progress:
            progress(k, len(capture.frames))
        yield k, f, read_frame(capture, f, with_weights=False)
    if progress:
        progress(len(capture.frames), len(capture.frames))


def capture_display_scale(capture: Capture, seed: int = 0) -> float:
    """One display exposure for every frame of the capture: its covered pixels' 95th percentile
    (pooled over up to :data:`SCALE_SAMPLES_PER_FRAME` pixels a frame) maps to the display key."""
    rng = np.random.default_rng(seed)
    pooled = []
    for _, _, d in _frames(capture, None):
        px = rec709_of(d.radiance_lin, capture.colorspace)[d.coverage > MASK_COVERAGE]
        if len(px):
            pooled.append(px[rng.permutation(len(px))[:SCALE_SAMPLES_PER_FRAME]])
    if not pooled:
        raise DamcapError(f"{capture.root}: no frame has covered pixels; nothing to export")
    px = np.concatenate(pooled)
    return exposure_scale_for(px, np.ones(len(px), bool))


def surface_samples(data: FrameData, colorspace: str, scale: float, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``n`` covered pixels of one frame as points: ((n, 3) world positions, (n, 3) sRGB colours in [0, 1])."""
    cov = data.coverage > MASK_COVERAGE
    pos = data.position_world[cov]
    rgb = display_srgb8(rec709_of(data.radiance_lin, colorspace)[cov][None], scale)[0].astype(np.float64) / 255.0
    keep = rng.permutation(len(pos))[:n]
    return pos[keep].astype(np.float64), rgb[keep]


def _write_points(path: Path, points: np.ndarray, colours: np.ndarray) -> None:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.colors = o3d.utility.Vector3dVector(colours)
    if not o3d.io.write_point_cloud(str(path), pcd):
        raise DamcapError(f"{path}: cannot write the point cloud")


def _shared_intrinsics(capture: Capture) -> Intrinsics | None:
    first = capture.frames[0].intrinsics
    return first if all(f.intrinsics == first for f in capture.frames) else None


def _intrinsics_json(i: Intrinsics) -> dict[str, Any]:
    return {"fl_x": i.fl_x, "fl_y": i.fl_y, "cx": i.cx, "cy": i.cy, "w": i.w, "h": i.h}


def export_capture(capture: Capture, out: str | os.PathLike, opts: CaptureExportOptions,
                   progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Write ``capture`` into the folder ``out`` in ``opts.format`` (see the module docstring).

    Returns:
        a summary: format, frames, points, display exposure scale.

    Raises:
        DamcapError: a capture without covered pixels.
    """
    opts.validate()
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    if opts.format == "nerfstudio":
        (out / "masks").mkdir(exist_ok=True)
    scale = capture_display_scale(capture, opts.seed)
    rng = np.random.default_rng(opts.seed)
    per_frame = -(-opts.points // len(capture.frames)) if opts.points else 0
    pts, cols = [], []
    for _, f, d in _frames(capture, progress):
        name = _png_name(f.file_path)
        write_png(out / "images" / name, display_srgb8(rec709_of(d.radiance_lin, capture.colorspace), scale))
        if opts.format == "nerfstudio":
            write_png(out / "masks" / name, mask_u8(d.coverage))
        if per_frame:
            p, c = surface_samples(d, capture.colorspace, scale, per_frame, rng)
            pts.append(p)
            cols.append(c)
    points = np.concatenate(pts)[: opts.points] if pts else np.zeros((0, 3))
    colours = np.concatenate(cols)[: opts.points] if cols else np.zeros((0, 3))
    if opts.format == "nerfstudio":
        _write_nerfstudio(capture, out, points, colours)
    else:
        _write_colmap(capture, out / "sparse" / "0", points, colours)
    return {"format": opts.format, "frames": len(capture.frames), "points": len(points), "exposure_scale": scale}


def _write_nerfstudio(capture: Capture, out: Path, points: np.ndarray, colours: np.ndarray) -> None:
    shared = _shared_intrinsics(capture)
    frames = []
    for f in capture.frames:
        name = _png_name(f.file_path)
        frame = {"file_path": f"images/{name}", "mask_path": f"masks/{name}", "transform_matrix": np.asarray(f.world_from_cam).tolist()}
        if shared is None:
            frame.update(_intrinsics_json(f.intrinsics))
        frames.append(frame)
    by_name = {f.file_path: f"images/{_png_name(f.file_path)}" for f in capture.frames}
    doc: dict[str, Any] = {"camera_model": "PINHOLE", **(_intrinsics_json(shared) if shared is not None else {}), "frames": frames,
                           "train_filenames": [by_name[n] for n in capture.train_filenames],
                           "val_filenames": [by_name[n] for n in capture.test_filenames],
                           "test_filenames": [by_name[n] for n in capture.test_filenames]}
    if len(points):
        _write_points(out / "points.ply", points, colours)
        doc["ply_file_path"] = "points.ply"
    source = capture.extra.get("damcap_source")
    norm = source.get("norm_from_input_world") if isinstance(source, dict) else None
    if norm is not None:
        doc["damcap_norm_from_input_world"] = norm
    doc["damcap_exported_from"] = str(capture.root.resolve())
    write_json_atomic(out / "transforms.json", doc)


def _write_colmap(capture: Capture, sparse: Path, points: np.ndarray, colours: np.ndarray) -> None:
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam_ids: dict[tuple[float, ...], int] = {}
    for image_id, f in enumerate(capture.frames, start=1):
        i = f.intrinsics
        key = (i.fl_x, i.fl_y, i.cx, i.cy, float(i.w), float(i.h))
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=i.w, height=i.h, params=[i.fl_x, i.fl_y, i.cx, i.cy],
                                                            camera_id=cam_ids[key]))
        pose = cam_from_world_opencv(f.world_from_cam)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=_png_name(f.file_path), camera_id=cam_ids[key], image_id=image_id),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:3, :3]), pose[:3, 3]))
    for p, c in zip(points, colours):
        rec.add_point3D(p, pycolmap.Track(), np.round(c * 255).astype(np.uint8))
    sparse.mkdir(parents=True, exist_ok=True)
    rec.write_text(str(sparse))
