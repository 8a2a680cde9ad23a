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
  start from. Its points are COLMAP's own with their tracks (``damcap reconstruct`` keeps the
  registration's model, or the points it triangulated at known poses, in ``CAPTURE/reconstruction/``):
  each observation moved into the capture's undistorted, resized frame (undistorted with the
  registration's camera, projected with the frame's), kept where it lands in the frame, its error
  the distance to the point's projection (:func:`tracked_points`). A capture without such a model
  (known poses where none were triangulated, synthetic captures) gets ``--points`` surface samples
  without tracks (error -1), as in the nerfstudio layout; ``damcap_export.json`` says which.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from damcap.common.atomic import write_json_atomic
from damcap.common.capture_folder import Capture, FrameData, Intrinsics, read_frame
from damcap.common.colour import display_srgb8, exposure_scale_for, working_from_rec709
from damcap.common.errors import DamcapError
from damcap.common.exr import write_png
from damcap.common.validate import SEED, check_ranges, in_range
from damcap.common.version import package_version

MASK_COVERAGE = 0.5
"""a pixel is in the mask when its coverage is above this"""
SCALE_SAMPLES_PER_FRAME = 20_000
"""covered pixels per frame pooled for the capture's one display exposure"""
OPENCV_FROM_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
"""camera axes: OpenGL (x right, y up, looking down -z) to OpenCV (x right, y down, looking down +z)"""
REGISTRATION_MODELS = ("sfm/model", "sfm/upsampled/model", "sfm-masked/model", "sfm-masked/upsampled/model", "sfm/triangulated")
"""COLMAP models ``damcap reconstruct`` may leave in ``CAPTURE/reconstruction/``, tried in this order"""
CENTRE_TOL = 1e-4
"""a registration model is the capture's when every frame's camera centre is its image's (mapped
by ``norm_from_input_world``) within this, in capture units (the object's radius is ~1)"""


@dataclass(frozen=True)
class CaptureExportOptions:
    """Options of ``damcap export-capture``."""

    format: Literal["nerfstudio", "colmap"] = "nerfstudio"
    """the target tool's layout: 'nerfstudio' (its dataset layout: PNG frames, masks,
    transforms.json, points.ply) or 'colmap' (a COLMAP text model of the undistorted capture and its PNG frames)"""
    points: int = field(default=100_000, metadata=in_range(0, 100_000_000))
    """surface points written as the point cloud (samples of the frames' covered pixels; 0 = none); for
    'colmap', only where the capture has no registration points with tracks"""
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


@dataclass(frozen=True)
class TrackedPoints:
    """The registration's points in the capture's world, each with its observations in the capture's frames."""

    xyz_world: np.ndarray
    """(P, 3) float64 positions in the capture's world"""
    rgb_u8: np.ndarray
    """(P, 3) uint8 colours (the registration's)"""
    frame_index: list[np.ndarray]
    """per point, (L,) int64 indices into ``capture.frames`` of its observations, L >= 2"""
    xy_px: list[np.ndarray]
    """per point, (L, 2) float64 observations in the frames' pixels (x right, y down, pixel centres at +0.5)"""
    model: str
    """the model they came from, relative to the capture folder"""


def _frame_of_image(capture: Capture, image_names: dict[int, str]) -> dict[int, int]:
    """image id -> frame index, by the photo's base name (the registration may have read a proxy of it)."""
    by_stem = {Path(str(f.extra.get("photo", f.file_path))).stem: k for k, f in enumerate(capture.frames)}
    return {i: by_stem[Path(n).stem] for i, n in image_names.items() if Path(n).stem in by_stem}


def tracked_points(rec: Any, capture: Capture, norm_from_input_world: np.ndarray, model: str) -> TrackedPoints | None:
    """The points of the registration ``rec`` (a ``pycolmap.Reconstruction``) with their tracks
    moved into the capture's frames, or None when its cameras are not the capture's.

    Each observation is undistorted with the registration's camera (``cam_from_img``), turned
    into the frame's camera axes and projected with the frame's pinhole intrinsics (the frames
    are the photos resampled onto those cameras); it is kept where it lands inside the frame and
    in front of it. Observations in photos the capture dropped are dropped; a point keeps only
    with 2 or more observations left.

    Args:
        rec: the registration's model (its world is the input world).
        capture: the capture made from it.
        norm_from_input_world: (4, 4) similarity from the registration's world to the capture's.
        model: where ``rec`` was read, for the record.
    """
    norm = np.asarray(norm_from_input_world, np.float64)
    scale = float(np.cbrt(np.linalg.det(norm[:3, :3])))
    rot_norm = norm[:3, :3] / scale
    frame_of = _frame_of_image(capture, {int(i): rec.image(i).name for i in rec.reg_image_ids()})
    if len(frame_of) < 2:
        return None
    capcam_from_regcam: dict[int, np.ndarray] = {}
    for image_id, k in frame_of.items():
        img, f = rec.image(image_id), capture.frames[k]
        centre = norm[:3, :3] @ np.asarray(img.projection_center(), np.float64) + norm[:3, 3]
        if not np.linalg.norm(centre - np.asarray(f.world_from_cam)[:3, 3]) <= CENTRE_TOL:
            return None  # another registration than the one this capture was made from
        regcam_from_world = np.asarray(img.cam_from_world().matrix(), np.float64)[:3, :3]
        capcam_from_world = cam_from_world_opencv(f.world_from_cam)[:3, :3]
        capcam_from_regcam[image_id] = capcam_from_world @ rot_norm @ regcam_from_world.T
    # every observation of a matched image: (point, image, registration pixel)
    pids, iids, xy_reg = [], [], []
    for pid, p3d in rec.points3D.items():
        for el in p3d.track.elements:
            if el.image_id in frame_of:
                pids.append(pid)
                iids.append(el.image_id)
                xy_reg.append(rec.image(el.image_id).points2D[el.point2D_idx].xy)
    pids_a, iids_a = np.asarray(pids, np.int64), np.asarray(iids, np.int64)
    xy_reg_a = np.asarray(xy_reg, np.float64).reshape(-1, 2)
    xy_cap = np.full((len(pids_a), 2), np.nan)
    for image_id, m in capcam_from_regcam.items():
        sel = iids_a == image_id
        if not sel.any():
            continue
        ray = np.concatenate([rec.camera(rec.image(image_id).camera_id).cam_from_img(xy_reg_a[sel]), np.ones((sel.sum(), 1))], 1)
        xy_cap[sel] = pinhole_px(ray @ m.T, capture.frames[frame_of[image_id]].intrinsics)
    points = {pid: rec.points3D[pid] for pid in dict.fromkeys(pids)}
    cams = np.stack([cam_from_world_opencv(f.world_from_cam) for f in capture.frames])
    xyz, rgb, frames_out, xy_out = [], [], [], []
    for pid, p3d in points.items():
        sel = pids_a == pid
        x = norm[:3, :3] @ np.asarray(p3d.xyz, np.float64) + norm[:3, 3]
        ks = np.array([frame_of[int(i)] for i in iids_a[sel]], np.int64)
        depth = np.einsum("lj,j->l", cams[ks, 2, :3], x) + cams[ks, 2, 3]
        ok = np.isfinite(xy_cap[sel]).all(1) & (depth > 0)
        ok &= _first_of_each(ks)
        if ok.sum() >= 2:
            xyz.append(x)
            rgb.append(np.asarray(p3d.color, np.uint8))
            frames_out.append(ks[ok])
            xy_out.append(xy_cap[sel][ok])
    return TrackedPoints(np.asarray(xyz, np.float64).reshape(-1, 3), np.asarray(rgb, np.uint8).reshape(-1, 3), frames_out, xy_out, model)


def _first_of_each(ks: np.ndarray) -> np.ndarray:
    """(L,) bool: True at the first observation of each frame (a point observed twice in one photo keeps one)."""
    first = np.zeros(len(ks), bool)
    first[np.unique(ks, return_index=True)[1]] = True
    return first


def pinhole_px(x_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(N, 2) pixels (x right, y down, pixel centres at +0.5) of (N, 3) OpenCV-axes camera points;
    NaN where a point is not in front of the camera or lands outside the ``w`` x ``h`` image.

    >>> pinhole_px(np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -1.0]]), Intrinsics(fl_x=10, fl_y=10, cx=4, cy=3, w=8, h=6)).tolist()
    [[4.0, 3.0], [nan, nan]]
    """
    z = x_cam[:, 2]
    front = z > 0
    zs = np.where(front, z, 1.0)
    uv = np.stack([intr.fl_x * x_cam[:, 0] / zs + intr.cx, intr.fl_y * x_cam[:, 1] / zs + intr.cy], 1)
    inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < intr.w) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.h)
    uv[~inside] = np.nan
    return uv


def registration_points(capture: Capture) -> TrackedPoints | None:
    """The registration's points with tracks of a capture ``damcap reconstruct`` made from photos
    (the first of :data:`REGISTRATION_MODELS` whose cameras are the capture's), or None."""
    source = capture.extra.get("damcap_source")
    if not isinstance(source, dict) or source.get("norm_from_input_world") is None:
        return None
    from damcap.common.native_stderr import load_pycolmap

    pycolmap = load_pycolmap()

    for rel in REGISTRATION_MODELS:
        folder = capture.root / "reconstruction" / rel
        if not (folder / "points3D.bin").is_file() and not (folder / "points3D.txt").is_file():
            continue
        found = tracked_points(pycolmap.Reconstruction(str(folder)), capture, np.asarray(source["norm_from_input_world"]),
                               f"reconstruction/{rel}")
        if found is not None and len(found.xyz_world):
            return found
    return None


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
        a summary: format, frames, points, ``points_source`` ('registration' with ``model``,
        ``mean_track_length`` and ``mean_reprojection_error_px``, or 'surface samples'), display exposure scale.

    Raises:
        DamcapError: a capture without covered pixels.
    """
    opts.validate()
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    if opts.format == "nerfstudio":
        (out / "masks").mkdir(exist_ok=True)
    tracked = registration_points(capture) if opts.format == "colmap" else None
    scale = capture_display_scale(capture, opts.seed)
    rng = np.random.default_rng(opts.seed)
    per_frame = -(-opts.points // len(capture.frames)) if opts.points and tracked is None else 0
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
    summary: dict[str, Any] = {"format": opts.format, "frames": len(capture.frames), "points": len(points),
                               "points_source": "surface samples", "exposure_scale": scale}
    if opts.format == "nerfstudio":
        _write_nerfstudio(capture, out, points, colours)
        return summary
    summary.update(_write_colmap(capture, out / "sparse" / "0", points, colours, tracked))
    write_json_atomic(out / "damcap_export.json", {
        "tool": "damcap export-capture", "damcap_package_version": package_version(), "options": asdict(opts),
        "exported_from": str(capture.root.resolve()), **{k: v for k, v in summary.items() if k != "format"}})
    return summary


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


def _write_colmap(capture: Capture, sparse: Path, points: np.ndarray, colours: np.ndarray,
                  tracked: TrackedPoints | None) -> dict[str, Any]:
    """Write the model; with ``tracked``, its points and their observations instead of ``points``.
    Returns what the summary says about the points."""
    from damcap.common.native_stderr import load_pycolmap

    pycolmap = load_pycolmap()

    observations: list[list[tuple[int, np.ndarray]]] = [[] for _ in capture.frames]  # per frame: (point, xy)
    if tracked is not None:
        for j, (ks, xy) in enumerate(zip(tracked.frame_index, tracked.xy_px)):
            for k, uv in zip(ks, xy):
                observations[k].append((j, uv))
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
        keypoints = np.array([uv for _, uv in observations[image_id - 1]], np.float64).reshape(-1, 2)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=_png_name(f.file_path), keypoints=keypoints, camera_id=cam_ids[key],
                                                        image_id=image_id),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:3, :3]), pose[:3, 3]))
    if tracked is not None:
        elements: list[list[Any]] = [[] for _ in tracked.frame_index]
        for k, obs in enumerate(observations):
            for idx, (j, _) in enumerate(obs):
                elements[j].append(pycolmap.TrackElement(k + 1, idx))
        for x, c, el in zip(tracked.xyz_world, tracked.rgb_u8, elements):
            rec.add_point3D(x, pycolmap.Track(el), c)
        rec.update_point_3d_errors()  # distance between each observation and the point's projection, through the frame's camera
    else:
        for p, c in zip(points, colours):
            rec.add_point3D(p, pycolmap.Track(), np.round(c * 255).astype(np.uint8))
    sparse.mkdir(parents=True, exist_ok=True)
    rec.write_text(str(sparse))
    if tracked is None:
        return {"points": len(points), "points_source": "surface samples"}
    return {"points": int(rec.num_points3D()), "points_source": "registration", "model": tracked.model,
            "mean_track_length": float(np.mean([len(k) for k in tracked.frame_index])),
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error())}
