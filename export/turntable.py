"""Rendering DAMs on any mesh along an orbit (Open3D ray casting, then the DAM per pixel)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator, Literal

import numpy as np
import torch

from damcap.appearance.dam import DeepAppearanceMap
from damcap.appearance.normal_field import field_share, refined_normals
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
    """camera elevation above the plane normal to the up axis (``up``), degrees"""
    azimuth0_deg: float = field(default=0.0, metadata=AZIMUTH_DEG)
    """azimuth of the first frame, degrees"""
    resolution: int = field(default=512, metadata=in_range(8, MAX_IMAGE_SIDE))
    """square frame size, pixels"""
    distance: float = field(default=3.0, metadata=CAMERA_DISTANCE)
    """camera distance from the origin (the mesh fits in the unit sphere)"""
    fov_deg: float = field(default=45.0, metadata={**FOV_DEG, "cli_flag": "--fov"})
    """full field of view, degrees"""
    supersample: int = field(default=1, metadata=in_range(1, 16, cli_panel="advanced"))
    """sub-pixel grid per axis for silhouette coverage (1 = pixel-centre rays only)"""
    up: str = "model"
    """the axis the orbit turns about: 'model' (the up direction the first model's capture
    recorded, +y for a model that records none), an axis ('+x', '-x', '+y', '-y', '+z', '-z') or
    three numbers 'x,y,z'. Elevation is measured from the plane normal to it"""

    def validate(self) -> None:
        check_ranges(self)
        parse_up(self.up)
        require_resolution(self.resolution, self.resolution, 4 * 32 * self.supersample ** 2, f"--resolution {self.resolution}: a frame")


@dataclass(frozen=True)
class ExportOptions:
    """What ``damcap export`` writes (the orbit's cameras are :class:`OrbitOptions`)."""

    format: Literal["frames", "onnx", "glsl", "matcap", "glb", "threejs", "blender"] = "frames"
    """what to write. 'frames' (linear EXR + sRGB PNG per orbit view), 'onnx' (the DAM as an ONNX
    model), 'glsl' (the DAM as a fragment-shader function), 'matcap' (the DAM on a sphere seen from the
    orbit's first view, orthographic: EXR + PNG for any matcap shader), 'glb' (binary glTF: the
    mesh with the radiance of the orbit's first view baked per vertex, unlit, that view as its
    camera), 'threejs' (an ES module making three.js ShaderMaterials that evaluate the DAMs, one
    per part; with --mesh the mesh in parts too) or
    'blender' (an OSL shader per model and a script making Blender materials of them, with --mesh
    the mesh too)"""
    video: bool = False
    """frames: also write an MP4 turntable"""
    fps: int = field(default=24, metadata=in_range(1, 1000))
    """frames: the video's highest frame rate. An orbit of few views plays slower (views / 3 s, down
    to 8 fps) and, below 24 views, whole orbits repeat, so that the video lasts at least 3 s"""
    glb_min_triangles: int = field(default=40_000, metadata=in_range(0, 10_000_000, cli_panel="advanced"))
    """glb: the mesh is subdivided (each triangle into four at its edges' midpoints) until it has at
    least this many triangles, so that the colours baked per vertex follow the DAM across each
    triangle (0 = as given)"""

    def validate(self) -> None:
        check_ranges(self)


AXES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
        "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}
UP_DISAGREE_DEG = 1.0
"""models whose recorded up directions differ by more than this get a note (the first one's is used)"""


def parse_up(text: str) -> np.ndarray | None:
    """``OrbitOptions.up`` as a unit vector, or None for 'model'.

    Raises:
        DamcapError: neither 'model', an axis nor three finite numbers of non-zero length.

    >>> parse_up("-z").tolist(), parse_up("0,2,0").tolist(), parse_up("model")
    ([0.0, 0.0, -1.0], [0.0, 1.0, 0.0], None)
    """
    t = text.strip().lower()
    if t == "model":
        return None
    if t in AXES or t in ("x", "y", "z"):
        return np.array(AXES[t if t[0] in "+-" else "+" + t])
    try:
        v = np.array([float(x) for x in t.split(",")], np.float64)
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) < 1e-12:
        raise DamcapError(f"--up must be 'model', one of {', '.join(AXES)} or three numbers x,y,z of non-zero length, got {text!r}")
    return v / np.linalg.norm(v)


def orbit_up(up_option: str, model_ups: list[np.ndarray | None]) -> tuple[np.ndarray, str, str | None]:
    """The orbit's axis: (unit vector, where it came from, a note or None).

    Args:
        up_option: ``OrbitOptions.up``.
        model_ups: each model's recorded up direction (None where it records none).

    >>> up, source, _ = orbit_up("model", [np.array([0.0, 0.0, 1.0]), None]); up.tolist(), source
    ([0.0, 0.0, 1.0], 'model')
    >>> up, source, _ = orbit_up("model", [None]); up.tolist(), source
    ([0.0, 1.0, 0.0], 'default')
    """
    given = parse_up(up_option)
    if given is not None:
        return given, "--up", None
    first = model_ups[0] if model_ups else None
    if first is None:
        return np.array(AXES["+y"]), "default", None
    note = None
    for k, u in enumerate(model_ups[1:], 1):
        if u is not None and float(np.degrees(np.arccos(np.clip(u @ first, -1, 1)))) > UP_DISAGREE_DEG:
            note = (f"the models' captures disagree about up (model {k + 1}: {np.round(u, 3).tolist()}, the first: "
                    f"{np.round(first, 3).tolist()}); the orbit turns about the first's (--up overrides)")
            break
    return first, "model", note


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


def shape_and_parts(mesh_path, labels_path, models: int) -> tuple:
    """The shape ``damcap export`` renders and each triangle's part (model index).

    Args:
        mesh_path: the mesh file.
        labels_path: per-vertex labels in the file's vertex order (:func:`.labels.read_vertex_labels`),
            or None: one part with one model, else the OBJ material groups.
        models: how many models there are.

    Returns:
        (the mesh as read, the mesh in the unit sphere, (T,) int64 part per triangle).

    Raises:
        DamcapError: a part has no model (the labels or the OBJ groups name more parts than ``models``).
    """
    from damcap.common.mesh import file_vertex_order, load_mesh, normalise_to_unit_sphere
    from damcap.export.labels import read_vertex_labels

    raw = load_mesh(mesh_path)
    shape = normalise_to_unit_sphere(raw)
    if labels_path is not None:  # labels follow the file's vertex order, which load_mesh does not keep for every format
        order, n_file = file_vertex_order(mesh_path, raw.vertices)
        part = parts_from_vertex_labels(shape.triangles, read_vertex_labels(labels_path, n_file, models)[order])
    elif models == 1:
        part = np.zeros(len(shape.triangles), np.int64)
    else:
        part = shape.triangle_groups.astype(np.int64)
    if len(part) and part.max() >= models:
        raise DamcapError(f"{labels_path or mesh_path}: part {int(part.max())} has no model; give {int(part.max()) + 1} .dam files (one per part)")
    return raw, shape, part


def shade_buffers(models: list[DeepAppearanceMap], buffers: SurfaceBuffers, camera_centre_world: np.ndarray, triangle_part: np.ndarray,
                  capture_from_render: tuple[np.ndarray, float] | None = None) -> np.ndarray:
    """Evaluate each pixel's DAM: (H, W, 3) float32 linear radiance, 0 on background.

    Args:
        models: the DAMs, indexed by part.
        buffers: ray-cast surface buffers.
        camera_centre_world: (3,).
        triangle_part: (T,) part index per triangle.
        capture_from_render: (centre (3,), radius): a rendered point p lies at
            p * radius + centre in the capture's world, where a model's normal field
            (``model.normal_field``) and spatial factor (``model.spatial``) are looked up (the
            transform has no rotation: normals are the same in both). None: neither is applied.
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
                n_sel, pos_capture = n[sel], None
                if capture_from_render is not None and model.has_surface_factors:
                    centre, radius = capture_from_render
                    pos_capture = pos[sel].astype(np.float64) * radius + centre
                    if model.normal_field is not None:
                        n_sel = refined_normals(model.normal_field, n_sel, pos_capture)
                rad[sel] = model(torch.from_numpy(v[sel]), torch.from_numpy(n_sel)).numpy()
                if model.spatial is not None and pos_capture is not None:
                    rad[sel] *= albedo_at(model.spatial, pos_capture)
    out[covered] = rad
    return out


SURFACE_MIN_SHARE = 0.9
"""a model's surface factors (spatial factor, normal field) are applied to a shape only when they
cover this share of the shape's vertices (it is the capture's own surface); on any other shape
the DAM alone is drawn"""


def surface_share(model: DeepAppearanceMap, vertices_capture: np.ndarray) -> float | None:
    """Share of the vertices (capture world) that ``model``'s surface factors cover: the smaller of
    the spatial factor's and the normal field's (None: the model has neither)."""
    if not model.has_surface_factors or len(vertices_capture) == 0:
        return None
    v = np.asarray(vertices_capture, np.float64)
    shares = []
    if model.spatial is not None:
        shares.append(float(log_albedo_at(model.spatial, v)[1].mean()))
    if model.normal_field is not None:
        shares.append(field_share(model.normal_field, v))
    return min(shares)


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
                 capture_from_render: tuple[np.ndarray, float] | None = None,
                 up_world: np.ndarray | None = None) -> Iterator[tuple[np.ndarray, SurfaceBuffers, np.ndarray]]:
    """Yield (world_from_cam, buffers, radiance_lin) per orbit frame (``capture_from_render``:
    see :func:`shade_buffers`; ``up_world``: the orbit's axis, :func:`orbit_up`, default +y)."""
    opts.validate()
    if triangle_part.shape != (len(mesh.triangles),):
        raise ValueError("one part index per triangle expected")
    if triangle_part.min() < 0 or triangle_part.max() >= len(models):
        raise DamcapError(f"the mesh has parts 0..{int(triangle_part.max())} but {len(models)} model(s) were given; give one .dam per part")
    caster = MeshRaycaster(mesh)
    f, _, c, _ = orbit_intrinsics(opts)[:4]
    for m in orbit_world_from_cam(opts.views, opts.distance, opts.elevation_deg, opts.azimuth0_deg, up_world):
        b = caster.buffers(m, f, f, c, c, opts.resolution, opts.resolution, supersample=opts.supersample)
        yield m, b, shade_buffers(models, b, m[:3, 3], triangle_part, capture_from_render)
