"""The paper's multi-view multi-material data set, re-created with Mitsuba 3 (``damcap synth``).

One capture (Maximov et al. 2019, Sec. 4, "Data"): an object (a mesh normalised into the unit
sphere, or the analytic unit sphere) with one or three layered materials (a diffuse layer plus a
glossy GGX layer; the diffuse hue drawn per seed), lit by an HDR environment map at a rotation or
by a small spherical area light ("point"), path traced with indirect bounces, seen by 32 views
equally spaced on a circle at a random elevation; 10 consecutive views from a random start are
the train split, the other 22 the test split (the paper's protocol).

Materials are laid out by smooth random 3D noise regions (:func:`damcap.synth.regions.material_labels`):
the mesh's faces are split into one sub-mesh per material, each with one BSDF, and the weight
maps record which sub-mesh the pixel's sub-pixel rays hit (:mod:`synth_geometry`). The analytic
sphere with several materials is rendered as an icosphere so it can be split the same way.

Written capture (docs/capture-format.md) plus, per image, the renderer's own coverage as channel
``render.A`` (the fraction of the path tracer's samples that hit the object), kept so validation
can check the geometry's coverage against the renderer. Radiance is un-premultiplied by that
alpha (a silhouette pixel holds the surface's radiance, not a blend with the black background)
and is 0 wherever A = 0. Light units: an environment map is scaled to mean luminance 1, the
point light gives irradiance pi at the origin, so a white Lambertian surface facing either
light has radiance about 1.

Checkpointing: frames are written one by one (each file atomically, the image last); a folder
interrupted mid-way is resumed at the next unfinished frame when the same options are given
again; ``transforms.json`` is written last, after every frame passed validation.
"""

from __future__ import annotations

import colorsys
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from damcap.common.atomic import write_json_atomic
from damcap.common.capture_folder import (
    GEOMETRY_CHANNELS,
    NORMAL_UNIT_TOL,
    RADIANCE_CHANNELS,
    Capture,
    Frame,
    Intrinsics,
    read_capture,
    weight_channels,
    write_transforms,
)
from damcap.common.errors import DamcapError
from damcap.common.exr import read_exr, write_exr
from damcap.common.validate import SEED, check_ranges, in_range

from damcap.common.cameras import focal_px_from_fov, orbit_world_from_cam, pixel_rays_world
from damcap.synth.geometry import GeometryBuffers, RayCaster, SceneGeometry, frame_geometry
from damcap.common.mesh import Mesh, face_normals_area, normalise_to_unit_sphere, read_mesh, vertex_normals_area_weighted
from damcap.common.shapes import icosphere
from damcap.synth.regions import SYNTH_ISOLATED_NORMAL, SYNTH_NORMAL_EPS, material_labels, submesh
from damcap.synth.mitsuba_render import VARIANTS, EnvLight, LayeredMaterial, SphereLight, Variant

#: channel of images/*.exr holding the renderer's alpha (fraction of samples hitting the object)
RENDER_ALPHA_CHANNEL = "render.A"
#: camera distance from the object's centre, scene units (the object lies in the unit sphere)
CAMERA_DISTANCE = 4.0
#: the point light: distance from the origin (beyond the cameras, so it never occludes the
#: object), radius, and the irradiance it gives at the origin (W/m^2)
POINT_LIGHT_DISTANCE = 6.0
POINT_LIGHT_RADIUS = 0.1
POINT_LIGHT_IRRADIANCE = math.pi
#: subdivisions of the icosphere that stands in for the sphere when it has several materials
SPHERE_SUBDIVISIONS = 5
#: largest value half-float images hold; a frame above it is stored as float32
HALF_MAX = 65504.0
#: file that marks a partially rendered capture folder (holds the resolved options)
PARTIAL_MARKER = ".synth_partial.json"
#: most views of one synthetic capture
MAX_SYNTH_VIEWS = 100000

ProgressFn = Callable[[int, int, dict[str, float]], None]


# --------------------------------------------------------------------------------------------
# Options
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SynthOptions:
    """Options of ``damcap synth`` (one capture)."""

    object: str = "sphere"
    """'sphere' (the analytic unit sphere) or a mesh file (.obj, .ply, .off, .glb, .gltf), normalised into the unit sphere"""
    light: str = "point"
    """the light, a small point light or an environment map. 'point[:AZIMUTH_DEG[:ELEVATION_DEG]]'
    (small spherical area light; position from the seed when not given) or
    'env:FILE[:ROTATION_DEG]' (environment map rotated about +y)"""
    materials: int = field(default=1, metadata=in_range(1, 8))
    """number of materials: 1 (whole object) or 3 (noise regions) as in the paper; 1..8 allowed"""
    views: int = field(default=32, metadata=in_range(3, MAX_SYNTH_VIEWS))
    """cameras equally spaced on one circle around the object"""
    resolution: int = field(default=256, metadata=in_range(8, 4096, cli_flag="--res"))
    """image width and height, pixels"""
    spp: int = field(default=64, metadata=in_range(1, 2 ** 20))
    """path-tracing samples per pixel: more lowers the noise floor and costs time. Noise floor
    (bench/synth.md): at 128 px, 512 under environment maps and 256 under the point light keep it
    under 0.02 DSSIM; twice that at 256 px."""
    seed: int = field(default=0, metadata=SEED)
    """chooses camera elevation and start azimuth, material colours and layout, the train start,
    the point light's position (when not given) and the path tracer's random numbers"""
    train_views: int = field(default=10, metadata=in_range(2, MAX_SYNTH_VIEWS))
    """consecutive views (random start) in the train split; the rest are test"""
    elevation_deg: float | None = field(default=None, metadata=in_range(-80, 80, cli_flag="--elevation"))
    """camera elevation above the xz-plane, degrees; None draws it from the seed in [5, 45]"""
    max_depth: int = field(default=6, metadata=in_range(2, 1024, cli_panel="advanced"))
    """path tracer's longest path (2 = direct light only; 6 = up to 4 indirect bounces)"""
    supersample: int = field(default=4, metadata=in_range(1, 16, cli_panel="advanced"))
    """k: coverage A and weights use a k x k grid of sub-pixel rays"""
    variant: Variant = field(default="auto", metadata={"cli_panel": "advanced"})
    """Mitsuba variant: 'auto' (cuda_ad_rgb on a CUDA GPU, else llvm_ad_rgb, else scalar_rgb with a
    warning), 'cuda_ad_rgb', 'llvm_ad_rgb', 'scalar_rgb'"""
    dtype: Literal["half", "float"] = "half"
    """radiance storage in images/ (a frame exceeding the half-float range is stored as float)"""

    def validate(self) -> None:
        """Raise DamcapError naming the first bad value (NaN and inf included)."""
        check_ranges(self)
        if not self.train_views < self.views:
            raise DamcapError(f"--train-views must lie in [2, views - 1], got {self.train_views} of {self.views} views")
        if self.dtype not in ("half", "float"):
            raise DamcapError(f"--dtype must be half or float, got {self.dtype!r}")
        if self.variant not in VARIANTS:
            raise DamcapError(f"--variant must be one of {', '.join(VARIANTS)}, got {self.variant!r}")


# --------------------------------------------------------------------------------------------
# Light specs, materials, cameras (pure)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LightSpec:
    """A parsed ``--light`` value."""

    kind: Literal["env", "point"]
    """'env' or 'point'"""
    path: str | None = None
    """environment map file (env)"""
    rotation_deg: float = 0.0
    """environment rotation about +y, degrees (env)"""
    azimuth_deg: float | None = None
    """point light azimuth about +y from +z, degrees; None = from the seed"""
    elevation_deg: float | None = None
    """point light elevation above the xz-plane, degrees; None = from the seed"""


def _float_or_none(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def parse_light_spec(spec: str) -> LightSpec:
    """Parse ``point[:AZIMUTH[:ELEVATION]]`` or ``env:FILE[:ROTATION]`` (angles in degrees).

    The file is not checked here (see :func:`resolve_light`).

    >>> parse_light_spec("env:maps/studio.hdr:90")
    LightSpec(kind='env', path='maps/studio.hdr', rotation_deg=90.0, azimuth_deg=None, elevation_deg=None)
    >>> parse_light_spec("point:30:45").elevation_deg
    45.0

    Raises:
        DamcapError: the spec matches neither form (the message repeats it).
    """
    usage = "expected 'point', 'point:AZIMUTH[:ELEVATION]' or 'env:FILE[:ROTATION]' (degrees)"
    if not isinstance(spec, str) or not spec:
        raise DamcapError(f"--light {spec!r}: {usage}")
    kind, _, rest = spec.partition(":")
    if kind == "point":
        parts = rest.split(":") if rest else []
        vals = [_float_or_none(p) for p in parts]
        if len(parts) > 2 or any(v is None for v in vals):
            raise DamcapError(f"--light {spec!r}: {usage}")
        if len(vals) == 2 and not -89 <= vals[1] <= 89:  # type: ignore[operator]
            raise DamcapError(f"--light {spec!r}: point light elevation must lie in [-89, 89] degrees")
        return LightSpec("point", azimuth_deg=vals[0] if vals else None, elevation_deg=vals[1] if len(vals) == 2 else None)
    if kind == "env" and rest:
        path, rotation = rest, 0.0
        head, sep, tail = rest.rpartition(":")
        if sep and _float_or_none(tail) is not None:
            path, rotation = head, float(tail)
        if not path:
            raise DamcapError(f"--light {spec!r}: {usage}")
        return LightSpec("env", path=path, rotation_deg=rotation)
    raise DamcapError(f"--light {spec!r}: {usage}")


def env_mean_luminance(radiance_lin: np.ndarray) -> float:
    """Solid-angle-weighted mean luminance (Rec. 709 Y) of an equirectangular map.

    Args:
        radiance_lin: (H, W, >=3) linear radiance; rows span the polar angle 0..pi.

    Returns:
        mean luminance over the sphere of directions, >= 0.

    A constant map has its own value as the mean:

    >>> env_mean_luminance(np.full((8, 16, 3), 2.0))
    2.0
    """
    h = radiance_lin.shape[0]
    theta = (np.arange(h) + 0.5) * math.pi / h
    y = radiance_lin[..., :3].astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    w = np.sin(theta)[:, None] * np.ones(radiance_lin.shape[1])
    return float(round((y * w).sum() / w.sum(), 12))


def point_light(azimuth_deg: float, elevation_deg: float, distance: float = POINT_LIGHT_DISTANCE,
                radius: float = POINT_LIGHT_RADIUS, irradiance: float = POINT_LIGHT_IRRADIANCE) -> SphereLight:
    """A spherical area light at a direction from the origin, giving ``irradiance`` there.

    Radiance L of a sphere of radius r at distance d seen head-on: E = L * pi * r^2 / d^2
    (small-angle), so L = E d^2 / (pi r^2).
    """
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    centre = distance * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    return SphereLight(tuple(float(c) for c in centre), radius, irradiance * distance**2 / (math.pi * radius**2))  # type: ignore[arg-type]


def random_layered_materials(seed: int, n: int) -> list[LayeredMaterial]:
    """n physically plausible diffuse + GGX materials with hues spread around the colour wheel.

    Diffuse: hue random per seed (n materials are about 1/n of the wheel apart), saturation
    0.35..0.9, value 0.3..0.8 (albedo <= 0.8). Glossy layer: weight 0.1..0.4, GGX alpha
    log-uniform 0.03..0.4, white or (1 in 3) tinted by the hue, reflectance 0.9.

    >>> m = random_layered_materials(0, 3)
    >>> len(m), all(max(x.diffuse_rgb) <= 0.8 for x in m)
    (3, True)
    """
    rng = np.random.default_rng([seed, 2])
    h0 = rng.uniform(0, 1)
    out = []
    for k in range(n):
        hue = (h0 + k / n + rng.uniform(-0.25, 0.25) / n) % 1.0
        rgb = np.array(colorsys.hsv_to_rgb(hue, rng.uniform(0.35, 0.9), rng.uniform(0.3, 0.8)))
        weight = rng.uniform(0.1, 0.4)
        alpha = math.exp(rng.uniform(math.log(0.03), math.log(0.4)))
        tint = rng.uniform(0.3, 0.7) if rng.uniform() < 1 / 3 else 0.0
        spec = 0.9 * (1 - tint * (1 - rgb / max(rgb.max(), 1e-6)))
        out.append(LayeredMaterial(tuple(float(x) for x in rgb), float(weight), tuple(float(x) for x in spec), float(alpha)))  # type: ignore[arg-type]
    return out


def camera_setup(opts: SynthOptions) -> tuple[np.ndarray, Intrinsics, float, float]:
    """The capture's cameras: 32 (``views``) on a circle at a seeded (or given) elevation.

    Returns:
        world_from_cam (views, 4, 4), shared intrinsics, elevation_deg, azimuth0_deg.
    """
    rng = np.random.default_rng([opts.seed, 0])
    elevation = float(rng.uniform(5.0, 45.0)) if opts.elevation_deg is None else float(opts.elevation_deg)
    azimuth0 = float(rng.uniform(0.0, 360.0))
    fov = 2 * math.degrees(math.asin(1.0 / CAMERA_DISTANCE)) * 1.12
    res = opts.resolution
    focal = focal_px_from_fov(fov, res)
    intr = Intrinsics(focal, focal, res / 2, res / 2, res, res)
    return orbit_world_from_cam(opts.views, CAMERA_DISTANCE, elevation, azimuth0), intr, elevation, azimuth0


def train_split(seed: int, views: int, train_views: int) -> list[int]:
    """The paper's split: ``train_views`` consecutive view indices from a seeded start (in order).

    >>> len(train_split(0, 32, 10)), len(set(train_split(0, 32, 10)))
    (10, 10)
    """
    start = int(np.random.default_rng([seed, 4]).integers(0, views))
    return [(start + k) % views for k in range(train_views)]


def render_seeds(seed: int, frame: int, passes: int) -> list[int]:
    """Independent 32-bit seeds of a frame's render passes (same inputs, same images)."""
    return [int(s) for s in np.random.SeedSequence([seed, 5, frame]).generate_state(passes)]


# --------------------------------------------------------------------------------------------
# Resolving options against files (the I/O edge of scene set-up)
# --------------------------------------------------------------------------------------------


@dataclass
class ResolvedScene:
    """Everything a capture's rendering needs, resolved from options and files."""

    geometry: SceneGeometry
    parts: list[Any]
    """per material, (mesh, vertex normals), or [None] for the analytic sphere"""
    materials: list[LayeredMaterial]
    light: EnvLight | SphereLight
    record: dict[str, Any]
    """JSON-able description (saved in transforms.json)"""


def resolve_light(opts: SynthOptions) -> tuple[EnvLight | SphereLight, dict[str, Any]]:
    """The light of a capture, with its JSON record.

    Raises:
        DamcapError: bad spec, or the environment map is missing or unreadable.
    """
    spec = parse_light_spec(opts.light)
    if spec.kind == "env":
        path = Path(spec.path)  # type: ignore[arg-type]
        if not path.is_file():
            raise DamcapError(f"{path}: environment map not found (from --light {opts.light!r}); give an existing .hdr or .exr file")
        try:
            pixels, _ = read_exr(path)
        except DamcapError as e:
            raise DamcapError(f"{e} (from --light {opts.light!r})") from None
        if pixels.shape[-1] < 3 or not np.all(np.isfinite(pixels)):
            raise DamcapError(f"{path}: environment map must be finite RGB, got {pixels.shape[-1]} channel(s)")
        mean = env_mean_luminance(pixels)
        if mean <= 0:
            raise DamcapError(f"{path}: environment map is black (mean luminance {mean})")
        light = EnvLight(str(path.resolve()), spec.rotation_deg, 1.0 / mean)
        return light, {"kind": "env", "file": path.name, "rotation_deg": spec.rotation_deg,
                       "scale": light.scale, "mean_luminance_file": mean}
    rng = np.random.default_rng([opts.seed, 1])
    az = spec.azimuth_deg if spec.azimuth_deg is not None else float(rng.uniform(0, 360))
    el = spec.elevation_deg if spec.elevation_deg is not None else float(rng.uniform(20, 60))
    light = point_light(az, el)
    return light, {"kind": "point", "azimuth_deg": az, "elevation_deg": el, "centre_world": list(light.centre_world),
                   "radius": light.radius, "radiance": light.radiance, "irradiance_at_origin": POINT_LIGHT_IRRADIANCE}


def resolve_scene(opts: SynthOptions) -> ResolvedScene:
    """Read and normalise the object, lay out the materials, draw them, resolve the light.

    Raises:
        DamcapError: missing or unreadable mesh or environment map, bad light spec.
    """
    light, light_record = resolve_light(opts)
    n = opts.materials
    materials = random_layered_materials(opts.seed, n)
    if opts.object == "sphere" and n == 1:
        geometry = SceneGeometry(None, None, None, 1)
        parts: list[Any] = [None]
        obj_record: dict[str, Any] = {"kind": "sphere", "analytic": True, "radius": 1.0}
    else:
        if opts.object == "sphere":
            mesh = icosphere(SPHERE_SUBDIVISIONS)
            obj_record = {"kind": "sphere", "analytic": False, "icosphere_subdivisions": SPHERE_SUBDIVISIONS}
        else:
            path = Path(opts.object)
            if not path.is_file():
                raise DamcapError(f"{path}: mesh file not found (from --object {opts.object!r}); give an .obj, .ply, .off, .glb or .gltf file or 'sphere'")
            mesh = normalise_to_unit_sphere(read_mesh(path), clean=True, fix_winding=True)
            obj_record = {"kind": "mesh", "file": path.name}
        normals = vertex_normals_area_weighted(mesh.vertices, mesh.triangles, SYNTH_NORMAL_EPS, SYNTH_ISOLATED_NORMAL)
        labels = material_labels(mesh, n, int(np.random.default_rng([opts.seed, 3]).integers(2**31)))
        geometry = SceneGeometry(mesh, normals, labels, n)
        parts = [submesh(mesh, normals, labels == k) for k in range(n)]
        empty = [k for k, p in enumerate(parts) if len(p[0].triangles) == 0]
        if empty:
            raise DamcapError(f"{opts.object}: material region(s) {empty} got no faces (mesh too coarse?); try another --seed")
        area = np.array([_area(p[0]) for p in parts])
        obj_record.update({"vertices": len(mesh.vertices), "faces": len(mesh.triangles),
                           "material_area_fraction": (area / area.sum()).round(4).tolist()})
    record = {"object": obj_record, "light": light_record, "materials": [asdict(m) for m in materials]}
    return ResolvedScene(geometry, parts, materials, light, record)


def _area(mesh: Mesh) -> float:
    return float(0.5 * np.linalg.norm(face_normals_area(mesh.vertices, mesh.triangles), axis=-1).sum())


# --------------------------------------------------------------------------------------------
# One frame (pure apart from the renderer)
# --------------------------------------------------------------------------------------------


@dataclass
class SynthFrame:
    """One rendered frame, ready to write."""

    radiance_lin: np.ndarray
    """(H, W, 3) float32 linear radiance, un-premultiplied, 0 where A = 0"""
    render_alpha: np.ndarray
    """(H, W) float32 fraction of the path tracer's samples that hit the object"""
    geometry: GeometryBuffers


def compose_frame(radiance_premult: np.ndarray, alpha: np.ndarray, geometry: GeometryBuffers, eps: float = 1e-6) -> SynthFrame:
    """Un-premultiply the renderer's radiance and cut it to the geometry's coverage.

    Args:
        radiance_premult: (H, W, 3) pixel means over all samples (misses count as 0), >= 0.
        alpha: (H, W) fraction of samples that hit.
        geometry: the frame's buffers (A = 0 is background).
        eps: alpha below which a pixel's radiance is unknown and set to 0.

    Returns:
        the frame.
    """
    rad = np.where(alpha[..., None] > eps, radiance_premult / np.maximum(alpha, eps)[..., None], 0.0)
    rad = np.where(geometry.coverage[..., None] > 0, np.maximum(rad, 0.0), 0.0)
    return SynthFrame(rad.astype(np.float32), alpha.astype(np.float32), geometry)


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ValidationTolerances:
    """Thresholds of :func:`frame_problems`."""

    normal_unit: float = NORMAL_UNIT_TOL
    """allowed |norm(N) - 1| on covered pixels"""
    weight_sum: float = 1e-2
    """allowed |sum(W) - 1| on covered pixels (half-float weights)"""
    ray_sin: float = 1e-3
    """allowed sine of the angle between P - camera centre and the pixel-centre ray"""
    fd_cos_median: float = 0.95
    """least median cosine between N and the finite-difference normal of P (measured on every
    mesh in shared/data at 32..128 px: 0.97 and more)"""
    fd_cos_min: float = 0.5
    """cosine below which a finite-difference normal counts as disagreeing ..."""
    fd_fraction: float = 0.85
    """... and the least fraction of checked pixels that must agree (measured: 0.97 and more)"""
    fd_min_pixels: int = 20
    """fewer checkable pixels than this skip the finite-difference check"""
    coverage_mad: float = 0.2
    """largest mean |A - render.A| over pixels where either is > 0 (measured: <= 0.15 at 32 px and
    4 spp, where Monte Carlo alpha is noisy; a mirrored camera gives 0.4 and more)"""
    coverage_shift_px: float = 0.4
    """largest distance between the centroids of A and render.A, pixels (measured: <= 0.24; a
    half-pixel convention error gives 0.5 and more)"""
    coverage_area: float = 0.15
    """largest relative difference between the sums of A and render.A (measured: <= 0.12 at 32 px,
    4 spp; edge-on pixels, background in A, are covered in render.A)"""


def fd_normal_cosines(normal_world: np.ndarray, position_world: np.ndarray, coverage: np.ndarray,
                      camera_centre_world: np.ndarray, max_step_ratio: float = 2.0) -> np.ndarray:
    """Cosines between stored normals and normals from central differences of the positions.

    Checked pixels: fully covered (A = 1) with fully covered 4-neighbours, and no depth
    discontinuity (the forward and backward steps of P differ by at most ``max_step_ratio`` in
    length along both axes). The difference normal is cross(dP/dj, dP/di) turned toward the camera.

    Args:
        normal_world: (H, W, 3) unit normals.
        position_world: (H, W, 3) positions.
        coverage: (H, W) A.
        camera_centre_world: (3,).
        max_step_ratio: largest ratio of forward to backward step lengths.

    Returns:
        (K,) cosines in [-1, 1], one per checked pixel.
    """
    p64 = position_world.astype(np.float64)
    full = coverage >= 1.0
    ok = full[1:-1, 1:-1] & full[1:-1, 2:] & full[1:-1, :-2] & full[2:, 1:-1] & full[:-2, 1:-1]
    c = p64[1:-1, 1:-1]
    steps = [np.linalg.norm(p64[1:-1, 2:] - c, axis=-1), np.linalg.norm(c - p64[1:-1, :-2], axis=-1),
             np.linalg.norm(p64[2:, 1:-1] - c, axis=-1), np.linalg.norm(c - p64[:-2, 1:-1], axis=-1)]
    for a, b in ((steps[0], steps[1]), (steps[2], steps[3])):
        ok &= (a <= max_step_ratio * b) & (b <= max_step_ratio * a)
    n = np.cross(p64[1:-1, 2:] - p64[1:-1, :-2], p64[2:, 1:-1] - p64[:-2, 1:-1])
    length = np.linalg.norm(n, axis=-1)
    ok &= length > 1e-12
    n = n[ok] / length[ok][:, None]
    v = camera_centre_world - c[ok]
    n = np.where(((n * v).sum(-1) < 0)[:, None], -n, n)
    return (n * normal_world[1:-1, 1:-1][ok]).sum(-1)


def coverage_agreement(coverage: np.ndarray, render_alpha: np.ndarray) -> tuple[float, float, float]:
    """How well the geometry's coverage matches the renderer's alpha.

    Args:
        coverage: (H, W) A in [0, 1].
        render_alpha: (H, W) renderer alpha in [0, 1].

    Returns:
        mean |A - alpha| over pixels where either is > 0; distance between their centroids,
        pixels; relative difference of their sums.

    >>> a = np.zeros((8, 8)); a[2:5, 2:6] = 1
    >>> coverage_agreement(a, a)
    (0.0, 0.0, 0.0)
    """
    union = (coverage > 0) | (render_alpha > 0)
    if not union.any():
        return 0.0, 0.0, 0.0
    mad = float(np.abs(coverage - render_alpha)[union].mean())
    ii, jj = np.mgrid[0:coverage.shape[0], 0:coverage.shape[1]]
    sa, sb = float(coverage.sum()), float(render_alpha.sum())
    if sa <= 0 or sb <= 0:
        return mad, float("inf"), 1.0
    ca = np.array([(ii * coverage).sum(), (jj * coverage).sum()]) / sa
    cb = np.array([(ii * render_alpha).sum(), (jj * render_alpha).sum()]) / sb
    return mad, float(np.linalg.norm(ca - cb)), abs(sa - sb) / max(sa, sb)


def frame_problems(name: str, radiance_lin: np.ndarray, render_alpha: np.ndarray | None, normal_world: np.ndarray,
                   position_world: np.ndarray, coverage: np.ndarray, weights: np.ndarray, world_from_cam: np.ndarray,
                   intr: Intrinsics, tol: ValidationTolerances = ValidationTolerances()) -> list[str]:
    """Every way a synthetic frame breaks the capture contract (empty list = valid).

    Checks: no NaN/inf anywhere; A in [0, 1] and not empty; background (A = 0) has RGB 0, N 0
    and W 0; covered pixels have unit normals facing the camera, positions on the pixel-centre
    rays, weights in [0, 1] summing to 1, radiance >= 0; normals agree with finite differences of
    the positions; A agrees with the renderer's alpha (when given).

    Args:
        name: the frame's name (prefixes every message).
        radiance_lin: (H, W, 3).
        render_alpha: (H, W) or None.
        normal_world, position_world: (H, W, 3).
        coverage: (H, W).
        weights: (H, W, n).
        world_from_cam: (4, 4).
        intr: pinhole intrinsics.
        tol: thresholds.
    """
    out: list[str] = []
    arrays = {"radiance": radiance_lin, "normals": normal_world, "positions": position_world, "coverage": coverage,
              "weights": weights, **({"render alpha": render_alpha} if render_alpha is not None else {})}
    for key, arr in arrays.items():
        bad = int((~np.isfinite(arr)).sum())
        if bad:
            out.append(f"{name}: {bad} NaN/inf value(s) in {key}")
    if out:
        return out
    if coverage.min() < 0 or coverage.max() > 1:
        out.append(f"{name}: coverage A outside [0, 1]: {coverage.min():.4g}..{coverage.max():.4g}")
    covered = coverage > 0
    bg = ~covered
    if not covered.any():
        return out + [f"{name}: no covered pixels (the object is not in view)"]
    if np.abs(radiance_lin[bg]).max(initial=0) > 0:
        out.append(f"{name}: {int((np.abs(radiance_lin[bg]).max(-1) > 0).sum())} background pixel(s) with RGB != 0")
    if np.abs(normal_world[bg]).max(initial=0) > 0:
        out.append(f"{name}: {int((np.abs(normal_world[bg]).max(-1) > 0).sum())} background pixel(s) with a non-zero normal")
    if np.abs(weights[bg]).max(initial=0) > 0:
        out.append(f"{name}: {int((np.abs(weights[bg]).max(-1) > 0).sum())} background pixel(s) with non-zero weights")
    if (radiance_lin[covered] < 0).any():
        out.append(f"{name}: negative radiance on covered pixels (min {radiance_lin[covered].min():.4g})")
    dev = np.abs(np.linalg.norm(normal_world[covered], axis=-1) - 1)
    if dev.max() > tol.normal_unit:
        out.append(f"{name}: {int((dev > tol.normal_unit).sum())} covered pixel(s) with non-unit normals (max |len - 1| {dev.max():.3g})")
    centre = world_from_cam[:3, 3]
    _, ray = pixel_rays_world(world_from_cam, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h)
    to_p = position_world[covered].astype(np.float64) - centre
    dist = np.linalg.norm(to_p, axis=-1)
    sin = np.linalg.norm(np.cross(to_p / np.maximum(dist, 1e-12)[:, None], ray[covered]), axis=-1)
    if sin.max() > tol.ray_sin or ((to_p * ray[covered]).sum(-1) <= 0).any():
        out.append(f"{name}: {int((sin > tol.ray_sin).sum())} position(s) off their pixel-centre rays (max sine {sin.max():.3g}): "
                   "positions do not match the camera")
    facing = ((centre - position_world[covered]) * normal_world[covered]).sum(-1)
    if (facing <= 0).any():
        out.append(f"{name}: {int((facing <= 0).sum())} covered pixel(s) whose normal faces away from the camera")
    wsum = weights[covered].sum(-1)
    if np.abs(wsum - 1).max() > tol.weight_sum:
        out.append(f"{name}: weights must sum to 1 on covered pixels, found {wsum.min():.4g}..{wsum.max():.4g}")
    if weights.min() < -1e-3 or weights.max() > 1 + 1e-3:
        out.append(f"{name}: weights outside [0, 1]: {weights.min():.4g}..{weights.max():.4g}")
    cos = fd_normal_cosines(normal_world, position_world, coverage, centre)
    if len(cos) >= tol.fd_min_pixels:
        med, frac = float(np.median(cos)), float((cos >= tol.fd_cos_min).mean())
        if med < tol.fd_cos_median or frac < tol.fd_fraction:
            out.append(f"{name}: normals disagree with the positions' finite differences (median cosine {med:.3f}, "
                       f"{frac:.1%} of {len(cos)} pixels above {tol.fd_cos_min})")
    if render_alpha is not None:
        mad, shift, area = coverage_agreement(coverage, render_alpha)
        if mad > tol.coverage_mad or shift > tol.coverage_shift_px or area > tol.coverage_area:
            out.append(f"{name}: coverage A disagrees with the renderer's alpha (mean |A - render.A| {mad:.3f}, "
                       f"centroids {shift:.2f} px apart, sums differ by {area:.1%}): camera or geometry mismatch")
    return out


def _frame_files_problems(capture: Capture, frame: Frame, tol: ValidationTolerances) -> list[str]:
    n = capture.materials or 0
    try:
        img, img_names = read_exr(capture.root / frame.file_path)
        geo, geo_names = read_exr(capture.root / frame.geometry_path)
        if frame.weights_path is None:
            return [f"{frame.file_path}: no weights_path (a synthetic capture always has weights/)"]
        w, w_names = read_exr(capture.root / frame.weights_path)
    except DamcapError as e:
        return [str(e)]
    missing = [f"{frame.file_path}: missing channel {c}" for c in RADIANCE_CHANNELS if c not in img_names]
    missing += [f"{frame.geometry_path}: missing channel {c}" for c in GEOMETRY_CHANNELS if c not in geo_names]
    missing += [f"{frame.weights_path}: missing channel {c}" for c in weight_channels(n) if c not in w_names]
    if missing:
        return missing
    want = (frame.intrinsics.h, frame.intrinsics.w)
    if img.shape[:2] != want or geo.shape[:2] != want or w.shape[:2] != want:
        return [f"{frame.file_path}: image sizes {img.shape[:2]}, {geo.shape[:2]}, {w.shape[:2]} differ from {want} (H, W)"]
    pick = lambda arr, names, chans: np.stack([arr[..., names.index(c)] for c in chans], -1)  # noqa: E731
    g = pick(geo, geo_names, GEOMETRY_CHANNELS)
    alpha = img[..., img_names.index(RENDER_ALPHA_CHANNEL)] if RENDER_ALPHA_CHANNEL in img_names else None
    return frame_problems(frame.name, pick(img, img_names, RADIANCE_CHANNELS), alpha, g[..., 0:3], g[..., 3:6], g[..., 6],
                          pick(w, w_names, weight_channels(n)), frame.world_from_cam, frame.intrinsics, tol)


def capture_problems(capture: Capture, tol: ValidationTolerances = ValidationTolerances()) -> list[str]:
    """Every problem of a synthetic capture whose frame files exist (transforms.json need not)."""
    out: list[str] = []
    if not capture.materials:
        out.append(f"{capture.root}: 'materials' missing (a synthetic capture always knows its materials)")
    names = [f.file_path for f in capture.frames]
    train, test = set(capture.train_filenames), set(capture.test_filenames)
    if not train or not test or train & test or (train | test) != set(names):
        out.append(f"{capture.root}: train ({len(train)}) and test ({len(test)}) splits must partition the {len(names)} frames")
    for frame in capture.frames:
        out.extend(_frame_files_problems(capture, frame, tol))
    return out


def validate_synthetic_capture(path: str | os.PathLike, tol: ValidationTolerances = ValidationTolerances()) -> list[str]:
    """Validate a rendered synthetic capture folder; returns its problems (empty = valid).

    Every frame: normals unit and facing the camera, normals consistent with the position
    buffer (finite differences), positions on the pixel-centre rays, weights summing to 1 on
    covered pixels and 0 off them, no NaN/inf, background RGB 0, coverage A agreeing with the
    renderer's alpha; plus the splits partitioning the frames.
    """
    try:
        capture = read_capture(path)
    except DamcapError as e:
        return [str(e)]
    return capture_problems(capture, tol)


# --------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------


def _options_record(opts: SynthOptions) -> dict[str, Any]:
    return json.loads(json.dumps(asdict(opts)))


def input_digests(opts: SynthOptions) -> dict[str, str]:
    """SHA-256 of the input files the options name (the mesh of ``--object``, the environment map
    of ``--light env:``): a resumed or finished capture must come from the same file contents,
    not only the same names."""
    from damcap.common.fingerprint import file_digest

    out = {}
    if opts.object != "sphere" and Path(opts.object).is_file():
        out["object"] = file_digest(opts.object)
    light = parse_light_spec(opts.light)
    if light.kind == "env" and light.path and Path(light.path).is_file():
        out["envmap"] = file_digest(light.path)
    return out


def _frames(opts: SynthOptions, cams: np.ndarray, intr: Intrinsics) -> list[Frame]:
    return [Frame(file_path=f"images/{i:04d}.exr", geometry_path=f"geometry/{i:04d}.exr", weights_path=f"weights/{i:04d}.exr",
                  world_from_cam=m, intrinsics=intr) for i, m in enumerate(cams)]


def _frame_done(root: Path, frame: Frame) -> bool:
    return all((root / p).is_file() for p in (frame.weights_path, frame.geometry_path, frame.file_path))  # type: ignore[arg-type]


def finished_with(out: str | os.PathLike, opts: SynthOptions) -> bool:
    """Whether ``out`` holds a finished capture rendered with these options from input files of
    the same contents (:func:`input_digests`)."""
    return _finished_with(Path(out), _options_record(opts), input_digests(opts))


def _finished_with(out: Path, options: dict[str, Any], inputs: dict[str, str]) -> bool:
    try:
        doc = json.loads((out / "transforms.json").read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return False
    src = doc.get("damcap_source", {}) if isinstance(doc, dict) else {}
    return isinstance(src, dict) and src.get("options") == options and src.get("input_sha256", {}) == inputs


def _prepare_folder(out: Path, options: dict[str, Any], inputs: dict[str, str]) -> bool:
    """Check ``out`` for a previous run; True when it already holds this finished capture (same
    options, same input file contents: :func:`input_digests`).

    Raises:
        DamcapError: ``out`` holds something else (another capture, other options or input files,
            other files).
    """
    marker = out / PARTIAL_MARKER
    if (out / "transforms.json").is_file():
        if _finished_with(out, options, inputs):
            return True
        raise DamcapError(f"{out}: already holds a capture made with other options or other input files; "
                          "choose an empty folder")
    if marker.is_file():
        try:
            state = json.loads(marker.read_text(encoding="utf-8"))
            previous = (state.get("options"), state.get("input_sha256", {}))
        except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
            previous = None
        if previous != (options, inputs):
            raise DamcapError(f"{out}: holds a partial capture rendered with other options or other input files "
                              f"({marker.name}); rerun with the same options and files to resume, or choose an empty folder")
        return False
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DamcapError(f"{out}: exists and is not empty; choose an empty or new folder")
    write_json_atomic(marker, {"options": options, "input_sha256": inputs})
    return False


def make_synthetic_capture(out: str | os.PathLike, opts: SynthOptions, *, progress: ProgressFn | None = None,
                           threads: int | None = None) -> Capture:
    """Render one synthetic capture into ``out`` (resuming a partial one made with the same options).

    Args:
        out: capture folder to write (new, empty, or a partial render with the same options).
        opts: options.
        progress: called as progress(frames_done, frames, {"s_per_frame": ...}) after each frame.
        threads: renderer threads (None = all cores).

    Returns:
        the written capture.

    Raises:
        DamcapError: bad options, missing mesh or environment map, a folder holding something
            else, or a rendered frame failing validation (then no transforms.json is written).
    """
    from damcap.common.optional import require
    from damcap.common.version import package_version

    from damcap.synth import mitsuba_render as synth_render

    opts.validate()
    require("mitsuba", "damcap synth")  # before anything is written
    out = Path(out)
    options = _options_record(opts)
    scene_desc = resolve_scene(opts)  # user mistakes (files, specs) surface before anything is written
    inputs = input_digests(opts)
    if _prepare_folder(out, options, inputs):
        return read_capture(out)
    variant = synth_render.select_variant(opts.variant)
    if threads is not None:
        synth_render.set_render_threads(threads)
    import mitsuba as mi

    cams, intr, elevation, azimuth0 = camera_setup(opts)
    frames = _frames(opts, cams, intr)
    train_idx = train_split(opts.seed, opts.views, opts.train_views)
    caster = RayCaster(scene_desc.geometry)
    scene = None
    pass_spp = synth_render.pass_sample_counts(opts.spp, intr.w, intr.h)
    tol = ValidationTolerances()
    done = sum(_frame_done(out, f) for f in frames)
    seconds: list[float] = []
    if progress:
        progress(done, len(frames), {})
    for i, (frame, m) in enumerate(zip(frames, cams)):
        if _frame_done(out, frame):
            continue
        t0 = time.perf_counter()
        if scene is None:
            scene = synth_render.build_scene(scene_desc.parts, scene_desc.materials, scene_desc.light, opts.max_depth)
        geo = frame_geometry(caster, m, intr, opts.supersample)
        rad, alpha = synth_render.render_view(scene, m, intr, pass_spp, render_seeds(opts.seed, i, len(pass_spp)))
        fr = compose_frame(rad, alpha, geo)
        problems = frame_problems(frame.name, fr.radiance_lin, fr.render_alpha, geo.normal_world, geo.position_world,
                                  geo.coverage, geo.weights, m, intr, tol)
        if problems:
            raise DamcapError(f"{out}: rendered frame {frame.name} failed validation: " + "; ".join(problems))
        write_exr(out / frame.weights_path, geo.weights, weight_channels(opts.materials), dtype="half")  # type: ignore[operator]
        write_exr(out / frame.geometry_path,
                  np.concatenate([geo.normal_world, geo.position_world, geo.coverage[..., None]], -1),
                  GEOMETRY_CHANNELS, dtype="float")
        dtype = "float" if opts.dtype == "float" or fr.radiance_lin.max() > HALF_MAX else "half"
        write_exr(out / frame.file_path, np.concatenate([fr.radiance_lin, fr.render_alpha[..., None]], -1),
                  RADIANCE_CHANNELS + (RENDER_ALPHA_CHANNEL,), dtype=dtype, attributes={"damcap:colorspace": "lin_rec709"})
        seconds.append(time.perf_counter() - t0)
        done += 1
        if progress:
            progress(done, len(frames), {"s_per_frame": float(np.mean(seconds))})
    capture = Capture(
        root=out,
        frames=frames,
        train_filenames=[frames[k].file_path for k in train_idx],
        test_filenames=[f.file_path for k, f in enumerate(frames) if k not in set(train_idx)],
        materials=opts.materials,
        extra={"damcap_source": {
            "generator": "synth", "options": options, "input_sha256": inputs, "damcap_package_version": package_version(),
            "renderer": {"name": "mitsuba", "version": mi.__version__, "variant": variant, "integrator": "path",
                         "max_depth": opts.max_depth, "spp": opts.spp, "sampler": synth_render.SAMPLER, "pixel_filter": "box",
                         "pass_spp": pass_spp},
            "cameras": {"distance": CAMERA_DISTANCE, "elevation_deg": elevation, "azimuth0_deg": azimuth0},
            "coverage": f"fraction of a {opts.supersample}x{opts.supersample} sub-pixel ray grid hitting the object; "
                        "0 where the pixel-centre ray misses or sees the surface edge-on",
            "render_alpha_channel": RENDER_ALPHA_CHANNEL,
            **scene_desc.record,
        }},
    )
    problems = capture_problems(capture, tol)
    if problems:
        raise DamcapError(f"{out}: the rendered capture failed validation ({len(problems)} problem(s)): " + "; ".join(problems[:5]))
    write_transforms(capture)
    (out / PARTIAL_MARKER).unlink(missing_ok=True)
    return capture
