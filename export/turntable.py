"""Rendering DAMs on any mesh along an orbit (Open3D ray casting, then the DAM per pixel)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator, Literal

import numpy as np
import torch

from damcap.appearance.dam import DeepAppearanceMap
from damcap.appearance.spatial import log_albedo_at, albedo_at
from damcap.common.errors import DamcapError
from damcap.common.validate import AZIMUTH_DEG, CAMERA_DISTANCE, ELEVATION_DEG, FOV_DEG, MAX_IMAGE_SIDE, check_ranges, in_range, require_resolution
from damcap.common.cameras import focal_px_from_fov, orbit_world_from_cam
from damcap.common.mesh import Mesh
from damcap.common.raycast import MeshRaycaster, SurfaceBuffers


@dataclass(frozen=True)
class OrbitOptions:
    """Cameras of ``damcap export`` (the mesh is first scaled into the unit sphere)."""

    views: int = field(default=36, metadata=in_range(1, 100_000))
    """frames on the orbit"""
    elevation_deg: float = field(default=20.0, metadata={**ELEVATION_DEG, "cli_flag": "--elevation"})
    """camera elevation above the y = 0 plane, degrees"""
    azimuth0_deg: float = field(default=0.0, metadata=AZIMUTH_DEG)
    """azimuth of the first frame, degrees"""
    resolution: int = field(default=512, metadata=in_range(8, MAX_IMAGE_SIDE))
    """square frame size, pixels"""
    distance: float = field(default=3.0, metadata=CAMERA_DISTANCE)
    """camera distance from the origin (the mesh fits in the unit sphere)"""
    fov_deg: float = field(default=45.0, metadata={**FOV_DEG, "cli_flag": "--fov"})
    """full field of view, degrees"""
    supersample: int = field(default=1, metadata=in_range(1, 16))
    """sub-pixel grid per axis for silhouette coverage (1 = pixel-centre rays only)"""

    def validate(self) -> None:
        check_ranges(self)
        require_resolution(self.resolution, self.resolution, 4 * 32 * self.supersample ** 2, f"--resolution {self.resolution}: a frame")


@dataclass(frozen=True)
class ExportOptions:
    """What ``damcap export`` writes (the orbit's cameras are :class:`OrbitOptions`)."""

    format: Literal["frames", "onnx", "glsl"] = "frames"
    """'frames' (linear EXR + sRGB PNG per orbit view), 'onnx' (the DAM as an ONNX model) or
    'glsl' (the DAM as a fragment-shader function)"""
    video: bool = False
    """frames: also write an MP4 turntable"""
    fps: int = field(default=24, metadata=in_range(1, 1000))
    """frames: video frame rate"""

    def validate(self) -> None:
        check_ranges(self)


def parts_from_vertex_labels(triangles: np.ndarray, vertex_labels: np.ndarray) -> np.ndarray:
    """Per-triangle part: the majority label of its three vertices (ties: the first vertex's).

    Args:
        triangles: (T, 3) vertex indices.
        vertex_labels: (V,) int labels.

    Returns:
        (T,) int64.
    """
    lab = vertex_labels[triangles]
    a, b, c = lab[:, 0], lab[:, 1], lab[:, 2]
    return np.where(b == c, b, a).astype(np.int64)


def shade_buffers(models: list[DeepAppearanceMap], buffers: SurfaceBuffers, camera_centre_world: np.ndarray, triangle_part: np.ndarray,
                  capture_from_render: tuple[np.ndarray, float] | None = None) -> np.ndarray:
    """Evaluate each pixel's DAM: (H, W, 3) float32 linear radiance, 0 on background.

    Args:
        models: the DAMs, indexed by part.
        buffers: ray-cast surface buffers.
        camera_centre_world: (3,).
        triangle_part: (T,) part index per triangle.
        capture_from_render: (centre (3,), radius): a rendered point p lies at
            p * radius + centre in the capture's world, where a model's spatial factor
            (``model.spatial``) is looked up. None: spatial factors are not applied.
    """
    covered = buffers.triangle_id >= 0
    out = np.zeros(covered.shape + (3,), np.float32)
    if not covered.any():
        return out
    part = triangle_part[buffers.triangle_id[covered]]
    pos = buffers.position_world[covered]
    v = camera_centre_world[None].astype(np.float32) - pos
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    n = buffers.normal_world[covered]
    rad = np.zeros((len(part), 3), np.float32)
    with torch.no_grad():
        for k, model in enumerate(models):
            sel = part == k
            if sel.any():
                rad[sel] = model(torch.from_numpy(v[sel]), torch.from_numpy(n[sel])).numpy()
                if model.spatial is not None and capture_from_render is not None:
                    centre, radius = capture_from_render
                    rad[sel] *= albedo_at(model.spatial, pos[sel].astype(np.float64) * radius + centre)
    out[covered] = rad
    return out


SPATIAL_MIN_SURFACE = 0.9
"""a model's spatial factor is applied to a shape only when it has texture at this share of the
shape's vertices (it is the capture's own surface); on any other shape the DAM alone is drawn"""


def spatial_surface_share(model: DeepAppearanceMap, vertices_capture: np.ndarray) -> float | None:
    """Share of the vertices (capture world) at which ``model``'s spatial factor has texture
    (None: the model has none)."""
    if model.spatial is None or len(vertices_capture) == 0:
        return None
    return float(log_albedo_at(model.spatial, np.asarray(vertices_capture, np.float64))[1].mean())


def orbit_intrinsics(opts: OrbitOptions) -> tuple[float, float, float, float, int, int]:
    """(fl_x, fl_y, cx, cy, w, h) of every orbit frame, pixels (the capture-format convention:
    pixel (i, j)'s centre is (j + 0.5, i + 0.5)).

    >>> [round(x, 6) for x in orbit_intrinsics(OrbitOptions(resolution=100, fov_deg=90.0))]
    [50.0, 50.0, 50.0, 50.0, 100, 100]
    """
    f = focal_px_from_fov(opts.fov_deg, opts.resolution)
    c = opts.resolution / 2
    return f, f, c, c, opts.resolution, opts.resolution


def render_orbit(models: list[DeepAppearanceMap], mesh: Mesh, triangle_part: np.ndarray, opts: OrbitOptions,
                 capture_from_render: tuple[np.ndarray, float] | None = None) -> Iterator[tuple[np.ndarray, SurfaceBuffers, np.ndarray]]:
    """Yield (world_from_cam, buffers, radiance_lin) per orbit frame (``capture_from_render``:
    see :func:`shade_buffers`)."""
    opts.validate()
    if triangle_part.shape != (len(mesh.triangles),):
        raise ValueError("one part index per triangle expected")
    if triangle_part.min() < 0 or triangle_part.max() >= len(models):
        raise DamcapError(f"the mesh has parts 0..{int(triangle_part.max())} but {len(models)} model(s) were given; give one .dam per part")
    caster = MeshRaycaster(mesh)
    f, _, c, _ = orbit_intrinsics(opts)[:4]
    for m in orbit_world_from_cam(opts.views, opts.distance, opts.elevation_deg, opts.azimuth0_deg):
        b = caster.buffers(m, f, f, c, c, opts.resolution, opts.resolution, supersample=opts.supersample)
        yield m, b, shade_buffers(models, b, m[:3, 3], triangle_part, capture_from_render)
