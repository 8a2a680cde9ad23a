"""Captures whose true appearance is known in closed form.

Analytic shapes (a sphere; a torus, which is non-convex) seen by orbit cameras, lit by a
distant light (one directional light, or an analytic environment map integrated numerically),
with a Lambert + GGX BRDF. Outgoing radiance follows the rendering equation without shadows or
interreflection (Maximov et al. 2019, Eq. 1):

    L_o(x, w_o) = sum_i L_i(w_i) f(w_i, w_o) max(n . w_i, 0) dw_i

so it is a function of (V, N) alone and a perfect deep appearance map could represent it exactly.
Optionally two materials laid out by a smooth function of position, with ground-truth weights.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from damcap.common.capture_folder import Capture, Frame, FrameData, Intrinsics, write_capture
from damcap.common.errors import DamcapError
from damcap.common.validate import ELEVATION_DEG, MAX_IMAGE_SIDE, SEED, check_ranges, in_range, require_resolution
from damcap.common.version import package_version
from damcap.common.numerics import dot, safe_div, safe_normalize

from damcap.common.cameras import focal_px_from_fov, orbit_world_from_cam, pixel_rays_world

# --------------------------------------------------------------------------------------------
# BRDF (pure, torch)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Material:
    """Lambert + GGX (Trowbridge-Reitz) material; all colours linear RGB."""

    albedo: tuple[float, float, float]
    """diffuse reflectance in [0, 1]"""
    roughness: float
    """GGX alpha (= perceptual roughness squared), in (0, 1]"""
    specular: tuple[float, float, float]
    """Fresnel reflectance at normal incidence F0 in [0, 1] (0.04 for dielectrics)"""


def brdf_lambert_ggx(n: torch.Tensor, v: torch.Tensor, l: torch.Tensor, m: Material, eps: float = 1e-6) -> torch.Tensor:
    """Lambert + GGX microfacet BRDF with separable Smith shadowing and Schlick Fresnel.

    Args:
        n, v, l: (..., 3) unit normal, direction to the viewer, direction to the light.
        m: the material.
        eps: floor for cosines in denominators.

    Returns:
        (..., 3) BRDF value, 1/sr, >= 0 (0 where n.l <= 0 or n.v <= 0).
    """
    return brdf_lambert_ggx_t(n, v, l, n.new_tensor(m.albedo), n.new_tensor(m.roughness), n.new_tensor(m.specular), eps)


def brdf_lambert_ggx_t(n: torch.Tensor, v: torch.Tensor, l: torch.Tensor, albedo: torch.Tensor, alpha: torch.Tensor,
                       f0: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """:func:`brdf_lambert_ggx` with the material as tensors that broadcast against the directions
    (one material per scene of a batch).

    Args:
        n, v, l: (..., 3) unit normal, direction to the viewer, direction to the light.
        albedo: (..., 3) diffuse reflectance in [0, 1].
        alpha: (..., 1) or () GGX alpha in (0, 1].
        f0: (..., 3) Fresnel reflectance at normal incidence.

    Returns:
        (..., 3) BRDF value, 1/sr, >= 0 (0 where n.l <= 0 or n.v <= 0).

    At normal incidence with alpha 1 and F0 1 it is 1/pi + D G F / 4 = 1/pi + 1/(4 pi):

    >>> z = torch.tensor([0.0, 0.0, 1.0])
    >>> round(float(brdf_lambert_ggx_t(z, z, z, torch.ones(3), torch.tensor(1.0), torch.ones(3))[0]), 5)
    0.39789
    """
    a2 = alpha**2
    nl = dot(n, l)
    nv = dot(n, v)
    h = safe_normalize(v + l)
    nh = dot(n, h).clamp_min(0)
    vh = dot(v, h).clamp_min(0)
    d = a2 / (math.pi * ((nh * nh) * (a2 - 1) + 1) ** 2)

    def g1(c: torch.Tensor) -> torch.Tensor:
        c = c.clamp_min(eps)
        return 2 * c / (c + torch.sqrt(a2 + (1 - a2) * c * c))

    g = g1(nl) * g1(nv)
    f = f0 + (1 - f0) * (1 - vh) ** 5
    spec = safe_div(d * g * f, 4 * nl.clamp_min(eps) * nv.clamp_min(eps), eps)
    value = albedo / math.pi + spec
    return torch.where((nl > 0) & (nv > 0), value, torch.zeros_like(value))


# --------------------------------------------------------------------------------------------
# Lights (pure)
# --------------------------------------------------------------------------------------------


def analytic_sky(dirs: torch.Tensor) -> torch.Tensor:
    """An HDR environment in closed form: sky gradient, warm sun, a cool fill lobe, dark ground.

    Args:
        dirs: (..., 3) unit world directions (y up).

    Returns:
        (..., 3) radiance, >= 0, ranging over about three orders of magnitude.
    """
    y = dirs[..., 1:2]
    sky = torch.where(y > 0, dirs.new_tensor([0.25, 0.35, 0.6]) * (0.4 + 0.6 * y), dirs.new_tensor([0.08, 0.06, 0.05]) * (1 + y))
    sun_dir = safe_normalize(dirs.new_tensor([0.5, 0.6, 0.3]))
    fill_dir = safe_normalize(dirs.new_tensor([-0.7, 0.2, -0.4]))
    sun = dirs.new_tensor([30.0, 26.0, 20.0]) * torch.exp(40.0 * (dot(dirs, sun_dir) - 1))
    fill = dirs.new_tensor([0.6, 1.0, 2.0]) * torch.exp(6.0 * (dot(dirs, fill_dir) - 1))
    return sky + sun + fill


def equirect_directions(height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell centres and solid angles of an equirectangular grid (height x 2*height cells).

    Returns:
        dirs: (height * 2 * height, 3) unit directions (y up).
        solid_angle_sr: (height * 2 * height,) cell solid angles summing to 4 pi.
    """
    width = 2 * height
    theta = (torch.arange(height, dtype=torch.float64) + 0.5) * math.pi / height  # polar, from +y
    phi = (torch.arange(width, dtype=torch.float64) + 0.5) * 2 * math.pi / width
    t, p = torch.meshgrid(theta, phi, indexing="ij")
    dirs = torch.stack([torch.sin(t) * torch.sin(p), torch.cos(t), torch.sin(t) * torch.cos(p)], -1).reshape(-1, 3)
    band = (torch.cos(theta - 0.5 * math.pi / height) - torch.cos(theta + 0.5 * math.pi / height)) * (2 * math.pi / width)
    solid = band[:, None].expand(height, width).reshape(-1)
    return dirs.float(), solid.float()


@dataclass(frozen=True)
class Lighting:
    """Distant lighting: a list of directions with radiance x solid angle (irradiance-like weights)."""

    dirs: torch.Tensor
    """(K, 3) unit directions toward the light"""
    power: torch.Tensor
    """(K, 3) L_i * d omega_i (W/m^2 per direction, linear RGB)"""


def directional_lighting(direction: tuple[float, float, float] = (0.5, 0.7, 0.4), irradiance: tuple[float, float, float] = (3.0, 3.0, 3.0)) -> Lighting:
    """One directional light: K = 1."""
    d = safe_normalize(torch.tensor([direction], dtype=torch.float32))
    return Lighting(d, torch.tensor([irradiance], dtype=torch.float32))


def environment_lighting(grid_height: int = 24) -> Lighting:
    """:func:`analytic_sky` discretised on an equirectangular grid (the numerical integration)."""
    dirs, solid = equirect_directions(grid_height)
    return Lighting(dirs, analytic_sky(dirs) * solid[:, None])


def shade(normal_world: torch.Tensor, view_dir_world: torch.Tensor, lighting: Lighting, material: Material, chunk: int = 16384) -> torch.Tensor:
    """Outgoing radiance without shadows: sum_k power_k f(l_k, v) max(n . l_k, 0).

    Args:
        normal_world: (P, 3) unit normals.
        view_dir_world: (P, 3) unit directions toward the camera.
        lighting: K distant lights.
        material: the BRDF.
        chunk: pixels per batch (memory: chunk x K x 3 floats).

    Returns:
        (P, 3) radiance, >= 0.
    """
    out = []
    l = lighting.dirs[None]  # (1, K, 3)
    for s in range(0, normal_world.shape[0], chunk):
        n = normal_world[s:s + chunk, None]
        v = view_dir_world[s:s + chunk, None]
        f = brdf_lambert_ggx(n, v, l, material)
        cos = dot(n, l).clamp_min(0)
        out.append((f * cos * lighting.power[None]).sum(1))
    return torch.cat(out) if out else normal_world.new_zeros((0, 3))


# --------------------------------------------------------------------------------------------
# Shapes (pure, numpy): ray intersections with normals
# --------------------------------------------------------------------------------------------


def intersect_sphere(origin: np.ndarray, dirs: np.ndarray, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hit of rays with a sphere at the origin.

    Args:
        origin: (3,) ray origin.
        dirs: (..., 3) unit directions.
        radius: sphere radius.

    Returns:
        hit: (...) bool; position: (..., 3); normal: (..., 3) outward unit normal.
    """
    b = dirs @ origin
    c = origin @ origin - radius**2
    disc = b * b - c
    hit = disc > 0
    t = -b - np.sqrt(np.maximum(disc, 0))
    hit &= t > 0
    p = origin + t[..., None] * dirs
    return hit, p, p / radius


def torus_sdf(p: np.ndarray, major: float, minor: float) -> np.ndarray:
    """Signed distance to a torus around the y axis: (...) for points (..., 3)."""
    q = np.sqrt(p[..., 0] ** 2 + p[..., 2] ** 2) - major
    return np.sqrt(q**2 + p[..., 1] ** 2) - minor


def intersect_torus(origin: np.ndarray, dirs: np.ndarray, major: float = 0.9, minor: float = 0.4, iterations: int = 300, tol: float = 1e-6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hit of rays with a torus (axis y) by sphere tracing its exact SDF; analytic normals.

    Returns:
        hit: (...) bool; position: (..., 3); normal: (..., 3) outward unit normal.
    """
    flat = dirs.reshape(-1, 3)
    t = np.zeros(flat.shape[0])
    idx = np.arange(flat.shape[0])  # rays still marching
    far = np.linalg.norm(origin) + major + minor + 1
    for _ in range(iterations):
        if idx.size == 0:
            break
        dist = torus_sdf(origin + t[idx, None] * flat[idx], major, minor)
        t[idx] += dist
        idx = idx[(dist > tol) & (t[idx] < far)]
    t = t.reshape(dirs.shape[:-1])
    p = origin + t[..., None] * dirs
    hit = np.abs(torus_sdf(p, major, minor)) < 1e-4
    ring = p.copy()
    ring[..., 1] = 0
    ring *= major / np.maximum(np.linalg.norm(ring, axis=-1, keepdims=True), 1e-12)
    normal = p - ring
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    return hit, p, normal


def rand_uniform(gen: torch.Generator, *shape: int, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
    """Uniform draws in [lo, hi) of the given shape, on the generator's device."""
    return lo + (hi - lo) * torch.rand(shape, generator=gen, device=gen.device)


def random_unit(gen: torch.Generator, *shape: int) -> torch.Tensor:
    """(*shape, 3) directions uniform on the sphere."""
    return safe_normalize(torch.randn((*shape, 3), generator=gen, device=gen.device))


@dataclass
class Blobs:
    centres: torch.Tensor
    """(B, M, 3) ball centres (inactive balls coincide with ball 0)"""
    radii: torch.Tensor
    """(B, M) ball radii (inactive balls: 0)"""
    smooth: torch.Tensor
    """(B, 1) smooth-union width, scene units"""


def random_blobs(gen: torch.Generator, b: int, max_balls: int, min_balls: int = 1) -> Blobs:
    """b blobs of ``min_balls`` to ``max_balls`` balls (with min_balls 1, a third of them single
    spheres), scaled to fit the unit sphere."""
    dev = gen.device
    n = torch.randint(min_balls, max_balls + 1, (b, 1), generator=gen, device=dev)
    if min_balls == 1:
        n = torch.where(rand_uniform(gen, b, 1) < 1 / 3, torch.ones_like(n), n)
    active = torch.arange(max_balls, device=dev)[None] < n
    centres = random_unit(gen, b, max_balls) * rand_uniform(gen, b, max_balls, 1, lo=0.2, hi=0.6)
    centres = torch.where(active[..., None], centres, centres[:, :1])
    centres = torch.where((n == 1)[..., None], torch.zeros_like(centres), centres)
    radii = rand_uniform(gen, b, max_balls, lo=0.35, hi=0.7) * active
    smooth = rand_uniform(gen, b, 1, lo=0.05, hi=0.3)
    extent = ((centres.norm(dim=-1) + radii).amax(1, keepdim=True) + smooth / 4).clamp_min(1e-6)  # (B, 1)
    return Blobs(centres / extent[..., None], radii / extent, smooth / extent)


def blob_sdf(p: torch.Tensor, blobs: Blobs) -> torch.Tensor:
    """Smooth-union (polynomial smooth minimum) distance of points to each scene's blob.

    Args:
        p: (B, R, 3) points.

    Returns:
        (B, R) signed distance (negative inside; a bound, not exact, within the blends).

    >>> bl = Blobs(torch.zeros(1, 1, 3), torch.ones(1, 1), torch.full((1, 1), 0.1))
    >>> blob_sdf(torch.tensor([[[2.0, 0, 0]]]), bl).tolist()
    [[1.0]]
    """
    d = (p[:, :, None] - blobs.centres[:, None]).norm(dim=-1) - blobs.radii[:, None]  # (B, R, M)
    d = torch.where(blobs.radii[:, None] > 0, d, torch.full_like(d, 1e3))
    k = blobs.smooth  # (B, 1)
    out = d[..., 0]
    for j in range(1, d.shape[-1]):
        h = (k - (out - d[..., j]).abs()).clamp_min(0) / k
        out = torch.minimum(out, d[..., j]) - h * h * k / 4
    return out


def trace_blobs(origin: torch.Tensor, dirs: torch.Tensor, blobs: Blobs, iterations: int = 80, tol: float = 1e-3
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """First hits of rays with each scene's blob by sphere tracing (from the unit sphere's entry).

    Args:
        origin: (B, R, 3) ray origins outside the unit sphere.
        dirs: (B, R, 3) unit directions.

    Returns:
        hit: (B, R) bool; position: (B, R, 3); normal: (B, R, 3) unit outward normals (the SDF's
        central-difference gradient).
    """
    b_ = dot(origin, dirs)[..., 0]
    c = dot(origin, origin)[..., 0] - 1.0
    disc = b_ * b_ - c
    t = (-b_ - disc.clamp_min(0).sqrt()).clamp_min(0)
    t_far = -b_ + disc.clamp_min(0).sqrt()
    alive = disc > 0
    for _ in range(iterations):
        d = blob_sdf(origin + t[..., None] * dirs, blobs)
        t = torch.where(alive, t + 0.9 * d, t)
        alive = alive & (t < t_far)
    p = origin + t[..., None] * dirs
    hit = (disc > 0) & (t < t_far) & (blob_sdf(p, blobs).abs() < tol)
    e = 1e-3
    grad = torch.stack([blob_sdf(p + e * ax, blobs) - blob_sdf(p - e * ax, blobs)
                        for ax in torch.eye(3, device=p.device)], -1)
    return hit, p, safe_normalize(grad)


def intersect_blob(origin: np.ndarray, dirs: np.ndarray, blobs: Blobs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`trace_blobs` for one blob and one camera, in numpy (the interface of
    :func:`intersect_sphere`).

    Returns:
        hit: (...) bool; position: (..., 3); normal: (..., 3) outward unit normal.
    """
    flat = torch.from_numpy(dirs.reshape(1, -1, 3)).float()
    o = torch.from_numpy(np.asarray(origin, np.float32)).expand_as(flat)
    hit, p, n = trace_blobs(o, flat, blobs)
    shape = dirs.shape[:-1]
    return hit[0].numpy().reshape(shape), p[0].double().numpy().reshape(shape + (3,)), n[0].double().numpy().reshape(shape + (3,))


def two_material_weights(position_world: np.ndarray) -> np.ndarray:
    """Ground-truth weights of two materials laid out by a smooth function of position.

    Args:
        position_world: (..., 3).

    Returns:
        (..., 2) binary weights (material 0, material 1) summing to 1.
    """
    x, y, z = position_world[..., 0], position_world[..., 1], position_world[..., 2]
    field = np.sin(3.1 * x + 0.7) + np.sin(2.3 * y - 0.4 * z + 0.3) + 0.6 * np.sin(4.0 * z)
    m1 = (field > 0.2).astype(np.float32)
    return np.stack([1 - m1, m1], axis=-1)


def silhouette_coverage(hit_centre: np.ndarray, hit_fn, offsets: np.ndarray) -> np.ndarray:
    """Coverage A: 1 inside, 0 outside, the sub-pixel hit fraction on pixels next to a silhouette.

    Args:
        hit_centre: (H, W) bool, the pixel-centre rays that hit.
        hit_fn: maps (S, 2) sub-pixel offsets to (S, H, W) bool hits.
        offsets: (S, 2) sub-pixel offsets.

    Returns:
        (H, W) float32 in [0, 1]; 0 wherever the centre ray misses (the contract's background).
    """
    pad = np.pad(hit_centre, 1, mode="edge")
    h, w = hit_centre.shape
    neigh = [pad[1 + di:1 + di + h, 1 + dj:1 + dj + w] for di in (-1, 0, 1) for dj in (-1, 0, 1)]
    edge = np.any([n != hit_centre for n in neigh], axis=0) & hit_centre
    coverage = hit_centre.astype(np.float32)
    if edge.any():
        frac = hit_fn(offsets).mean(0)
        coverage[edge] = np.maximum(frac[edge], 1.0 / len(offsets))
    return coverage


# --------------------------------------------------------------------------------------------
# The generator
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ClosedFormOptions:
    """Options of ``damcap closed-form``."""

    shape: Literal["sphere", "torus", "blob"] = "sphere"
    """analytic shape. 'sphere' (radius 1), 'torus' (non-convex; radii 0.9 and 0.4) or 'blob' (the
    smooth union of 2 to 4 spheres drawn from --seed, within the unit sphere; concave blends)"""
    light: Literal["directional", "env"] = "directional"
    """'directional' (one distant light) or 'env' (analytic HDR sky, numerically integrated)"""
    materials: int = field(default=1, metadata=in_range(1, 2))
    """1, or 2 (laid out by position, with ground-truth weights/)"""
    views: int = field(default=32, metadata=in_range(3, 100_000))
    """cameras on one circle around the object"""
    resolution: int = field(default=128, metadata=in_range(8, MAX_IMAGE_SIDE, cli_flag="--res"))
    """image width and height, pixels"""
    elevation_deg: float = field(default=25.0, metadata={**ELEVATION_DEG, "cli_flag": "--elevation"})
    """camera elevation above the object's equator, degrees"""
    train_views: int = field(default=10, metadata=in_range(2, 100_000))
    """consecutive views (random start) in the train split; the rest are test"""
    seed: int = field(default=0, metadata=SEED)
    """chooses the train start, the camera start azimuth and the material colours"""
    env_grid: int = field(default=24, metadata=in_range(2, 4096, cli_panel="advanced"))
    """rows of the equirectangular grid that integrates the environment (columns = 2x)"""
    supersample: int = field(default=3, metadata=in_range(1, 64, cli_panel="advanced"))
    """sub-pixel grid (per axis) that measures coverage A at silhouettes"""
    dtype: Literal["half", "float"] = "half"
    """radiance storage in images/"""


def random_materials(seed: int, n: int) -> list[Material]:
    """n plausible materials: random diffuse hue, GGX roughness 0.15..0.45, dielectric or tinted F0."""
    rng = np.random.default_rng(seed + 1000)
    mats = []
    for k in range(n):
        hue = rng.uniform(0, 1)
        rgb = np.clip(np.abs(((hue * 6 + np.array([0, 4, 2])) % 6) - 3) - 1, 0, 1)
        albedo = 0.15 + 0.6 * rgb
        rough = float(rng.uniform(0.15, 0.45))
        spec = (0.04, 0.04, 0.04) if k % 2 == 0 else tuple(float(x) for x in 0.3 + 0.5 * rgb[::-1])
        mats.append(Material(tuple(float(a) for a in albedo), rough, spec))  # type: ignore[arg-type]
    return mats


def render_closed_form(opts: ClosedFormOptions) -> tuple[list[np.ndarray], Intrinsics, list[FrameData], list[Material]]:
    """Render every view of a closed-form capture (pure: no files).

    Returns:
        world_from_cam list, shared intrinsics, per-frame data, the materials used.
    """
    check_ranges(opts)
    if not opts.train_views < opts.views:
        raise DamcapError(f"--train-views must lie in [2, views - 1], got {opts.train_views} of {opts.views} views")
    sub = opts.resolution * opts.supersample
    # per frame: float64 rays and hits (~10 arrays of 3 values) at the sub-pixel grid
    require_resolution(sub, sub, 240, "--res x --supersample", copies=1)
    rng = np.random.default_rng(opts.seed)
    radius = 1.3 if opts.shape == "torus" else 1.0
    distance = 4.0
    fov = 2 * math.degrees(math.asin(min(radius / distance, 0.99))) * 1.12
    focal = focal_px_from_fov(fov, opts.resolution)
    res = opts.resolution
    intr = Intrinsics(focal, focal, res / 2, res / 2, res, res)
    cams = orbit_world_from_cam(opts.views, distance, opts.elevation_deg, azimuth0_deg=float(rng.uniform(0, 360)))
    lighting = directional_lighting() if opts.light == "directional" else environment_lighting(opts.env_grid)
    materials = random_materials(opts.seed, opts.materials)
    ss = opts.supersample
    sub = (np.stack(np.meshgrid(np.arange(ss), np.arange(ss)), -1).reshape(-1, 2) + 0.5) / ss - 0.5
    if opts.shape == "blob":
        gen = torch.Generator().manual_seed(opts.seed + 2000)
        blob = random_blobs(gen, 1, 4, min_balls=2)
        intersect = lambda o, d: intersect_blob(o, d, blob)  # noqa: E731
    else:
        intersect = intersect_sphere if opts.shape == "sphere" else intersect_torus
    frames = []
    for m in cams:
        origin, d = pixel_rays_world(m, intr.fl_x, intr.fl_y, intr.cx, intr.cy, res, res)
        hit, pos, nrm = intersect(origin, d)
        view = origin - pos
        view /= np.maximum(np.linalg.norm(view, axis=-1, keepdims=True), 1e-12)
        hit &= (nrm * view).sum(-1) > 1e-4  # edge-on pixels are background (contract)
        coverage = silhouette_coverage(hit, lambda offs: intersect(origin, pixel_rays_world(
            m, intr.fl_x, intr.fl_y, intr.cx, intr.cy, res, res, offsets=offs)[1])[0], sub)
        weights = two_material_weights(pos) if opts.materials == 2 else np.ones(pos.shape[:-1] + (1,), np.float32)
        n_t = torch.from_numpy(nrm[hit]).float()
        v_t = torch.from_numpy(view[hit]).float()
        radiance = np.zeros(pos.shape, np.float32)
        acc = torch.zeros(n_t.shape)
        for k, mat in enumerate(materials):
            wk = torch.from_numpy(weights[hit][:, k:k + 1]).float()
            if wk.any():
                acc += wk * shade(n_t, v_t, lighting, mat)
        radiance[hit] = acc.numpy()
        frames.append(FrameData(
            radiance_lin=radiance,
            normal_world=np.where(hit[..., None], nrm, 0).astype(np.float32),
            position_world=np.where(hit[..., None], pos, 0).astype(np.float32),
            coverage=coverage.astype(np.float32),
            weights=np.where(hit[..., None], weights, 0).astype(np.float32) if opts.materials == 2 else None,
        ))
    return list(cams), intr, frames, materials


def make_closed_form_capture(out: str | Path, opts: ClosedFormOptions) -> Capture:
    """Render a closed-form capture and write it as a capture folder at ``out``."""
    out = Path(out)
    if (out / "transforms.json").exists():
        raise DamcapError(f"{out}: already holds a capture; choose an empty folder")
    cams, intr, data, materials = render_closed_form(opts)
    rng = np.random.default_rng(opts.seed + 7)
    start = int(rng.integers(0, opts.views))
    train_idx = {(start + k) % opts.views for k in range(opts.train_views)}
    frames = [
        Frame(
            file_path=f"images/{i:04d}.exr",
            geometry_path=f"geometry/{i:04d}.exr",
            weights_path=f"weights/{i:04d}.exr" if opts.materials == 2 else None,
            world_from_cam=m,
            intrinsics=intr,
        )
        for i, m in enumerate(cams)
    ]
    train = [f.file_path for i, f in enumerate(frames) if i in train_idx]
    # consecutive order starting at `start`, so "10 consecutive views" reads naturally
    train = sorted(train, key=lambda p: (int(Path(p).stem) - start) % opts.views)
    capture = Capture(
        root=out,
        frames=frames,
        train_filenames=train,
        test_filenames=[f.file_path for i, f in enumerate(frames) if i not in train_idx],
        materials=opts.materials,
        extra={"damcap_source": {"generator": "closed-form", "damcap_package_version": package_version(), "options": asdict(opts),
                                 "materials": [asdict(m) for m in materials]}},
    )
    write_capture(capture, data, dtype=opts.dtype)
    return capture
