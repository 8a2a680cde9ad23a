"""Mitsuba 3 scenes and renders of the synthetic data set (the only module that imports mitsuba).

The Mitsuba variant is process-wide state; :func:`select_variant` is the one place that sets it.
``llvm_ad_rgb`` is preferred; without libLLVM the renderer falls back to ``scalar_rgb`` (same
images, much slower) with a warning.

Radiance is path traced (``path`` integrator, indirect bounces on, emitters hidden from camera
rays so the background is black) with stratified samples (:data:`SAMPLER`) and a box pixel
filter, so every pixel is the plain mean of its own samples; passes with independent seeds are
averaged (each pass stratified on its own). Mitsuba's alpha (the fraction of a pixel's samples that hit a visible surface) is
returned with the radiance so the caller can un-premultiply it and cross-check its coverage.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from damcap.common.capture_folder import Intrinsics
from damcap.common.errors import DamcapError

from damcap.common.mesh import Mesh

Variant = Literal["auto", "cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb"]
VARIANTS = ("auto", "cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
#: most camera samples (pixels x samples) traced per Mitsuba call; more passes above it
MAX_LANES_PER_PASS = 1 << 22
#: Mitsuba sampler: correlated multi-jittered (stratified) samples. Measured on the bunny under an
#: environment map at 128 px, 256 spp: DSSIM to a 4096-spp reference 0.008 vs 0.029 with the
#: 'independent' sampler (the same error needs about 4x fewer samples); renders with different
#: seeds stay independent (their DSSIM is about twice the error to the reference, as for
#: 'independent').
SAMPLER = "multijitter"


def select_variant(requested: Variant = "auto") -> str:
    """Set Mitsuba's variant for this process and return it.

    Args:
        requested: 'auto' (cuda_ad_rgb where Dr.Jit finds a CUDA GPU, else llvm_ad_rgb when
            libLLVM loads, else scalar_rgb with a warning), 'cuda_ad_rgb', 'llvm_ad_rgb' or
            'scalar_rgb'.

    Raises:
        DamcapError: an unknown variant, 'cuda_ad_rgb' asked for without a CUDA GPU, or
            'llvm_ad_rgb' without libLLVM.
    """
    from damcap.common.optional import require

    mi = require("mitsuba", "Mitsuba renders (damcap synth, synth-set)")
    dr = require("drjit", "Mitsuba renders (damcap synth, synth-set)")

    if requested not in VARIANTS:
        raise DamcapError(f"unknown Mitsuba variant {requested!r}: use {', '.join(VARIANTS)}")
    needs = (("cuda_ad_rgb", dr.JitBackend.CUDA, "a CUDA GPU and driver, which Dr.Jit did not find; use auto or llvm_ad_rgb"),
             ("llvm_ad_rgb", dr.JitBackend.LLVM, "libLLVM (apt-get install libllvm19), which did not load"))
    for variant, backend, need in needs:
        if requested in ("auto", variant):
            if dr.has_backend(backend):
                if mi.variant() != variant:
                    mi.set_variant(variant)
                return variant
            if requested == variant:
                raise DamcapError(f"Mitsuba variant {variant} needs {need}")
    if requested == "auto":
        warnings.warn("libLLVM not found: rendering with Mitsuba's scalar_rgb variant (much slower); "
                      "install libllvm19 for llvm_ad_rgb", RuntimeWarning, stacklevel=2)
    if mi.variant() != "scalar_rgb":
        mi.set_variant("scalar_rgb")
    return "scalar_rgb"


def set_render_threads(n: int) -> None:
    """Threads Mitsuba/Dr.Jit may use in this process (at least 2).

    Measured (Mitsuba 3.9.1): with a pool of ONE thread, loading an OpenEXR environment map
    (``museum.exr``) never returns (no CPU use; .hdr maps load fine), so the pool never shrinks
    below 2 threads.
    """
    import drjit as dr

    dr.set_thread_count(max(2, int(n)))


@dataclass(frozen=True)
class LayeredMaterial:
    """A diffuse layer plus a glossy GGX layer (Maximov et al. 2019, Sec. 4), linear RGB.

    Rendered as Mitsuba's ``blendbsdf`` of ``diffuse`` and ``roughconductor`` (GGX), wrapped in
    ``twosided``: f = (1 - specular_weight) * f_diffuse + specular_weight * f_GGX, energy
    conserving because both layers are.
    """

    diffuse_rgb: tuple[float, float, float]
    """diffuse reflectance (albedo), linear, in [0, 1)"""
    specular_weight: float
    """blend weight of the glossy layer, in [0, 1]"""
    specular_rgb: tuple[float, float, float]
    """glossy layer's reflectance (conductor with Fresnel 1 scaled by this), linear, in [0, 1]"""
    roughness_alpha: float
    """GGX alpha (perceptual roughness squared), in (0, 1]"""


def material_dict(m: LayeredMaterial) -> dict[str, Any]:
    """The Mitsuba BSDF description of a :class:`LayeredMaterial`."""
    return {"type": "twosided", "bsdf": {
        "type": "blendbsdf", "weight": float(m.specular_weight),
        "bsdf_0": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(m.diffuse_rgb)}},
        "bsdf_1": {"type": "roughconductor", "distribution": "ggx", "alpha": float(m.roughness_alpha),
                   "material": "none", "specular_reflectance": {"type": "rgb", "value": list(m.specular_rgb)}},
    }}


@dataclass(frozen=True)
class EnvLight:
    """An equirectangular HDR environment map, rotated about the world y axis."""

    path: str
    """image file Mitsuba can read (.hdr, .exr)"""
    rotation_deg: float
    """rotation about +y, degrees"""
    scale: float
    """radiance multiplier (normalises the map's mean luminance)"""


@dataclass(frozen=True)
class SphereLight:
    """A small spherical area light ("point" light)."""

    centre_world: tuple[float, float, float]
    """centre, scene units"""
    radius: float
    """radius, scene units"""
    radiance: float
    """emitted radiance (white), W / (m^2 sr)"""


@dataclass(frozen=True)
class Board:
    """A textured square the object stands on (a turntable board or a printed mat), diffuse."""

    y: float
    """height of the board's plane (world y), scene units"""
    half_size: float
    """half its edge, scene units"""
    albedo: np.ndarray
    """(R, R, 3) float32 linear albedo texture in [0, 1) over the square, row 0 at -z"""


def mesh_part(mi: Any, name: str, mesh: Mesh, normals: np.ndarray, bsdf: Any) -> Any:
    """A Mitsuba mesh built from arrays (works in every variant).

    Args:
        mi: the mitsuba module (variant set).
        name: the shape's name.
        mesh: triangles.
        normals: (V, 3) unit vertex normals (the shading normals).
        bsdf: an instantiated Mitsuba BSDF.
    """
    props = mi.Properties()
    props["bsdf"] = bsdf
    shape = mi.Mesh(name, len(mesh.vertices), len(mesh.triangles), props, has_vertex_normals=True)
    params = mi.traverse(shape)
    float_t, index_t = type(params["vertex_positions"]), type(params["faces"])
    params["vertex_positions"] = float_t(mesh.vertices.astype(np.float32).ravel())
    params["faces"] = index_t(mesh.triangles.astype(np.uint32).ravel())
    params["vertex_normals"] = float_t(normals.astype(np.float32).ravel())
    params.update()
    return shape


def build_scene(parts: list[tuple[Mesh, np.ndarray] | None], materials: list[LayeredMaterial | dict[str, Any]],
                light: EnvLight | SphereLight, max_depth: int, board: Board | None = None) -> Any:
    """The Mitsuba scene: one shape per material, the light, a path tracer.

    Args:
        parts: per material, its (mesh, vertex normals), or a single ``None`` for the analytic
            unit sphere; shape ids are ``material_0``, ``material_1``, ...
        materials: one per part: a :class:`LayeredMaterial`, or a Mitsuba BSDF description
            (wrapped in ``twosided``).
        light: environment map or spherical area light.
        max_depth: the path tracer's longest path (2 = direct light only).
        board: a textured square under the object (shape id ``board``), or None.

    Returns:
        a ``mitsuba.Scene``.
    """
    import mitsuba as mi

    scene: dict[str, Any] = {"type": "scene",
                             "integrator": {"type": "path", "max_depth": int(max_depth), "hide_emitters": True}}
    for k, (part, mat) in enumerate(zip(parts, materials, strict=True)):
        bsdf = material_dict(mat) if isinstance(mat, LayeredMaterial) else {"type": "twosided", "bsdf": mat}
        if part is None:
            scene[f"material_{k}"] = {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0, "bsdf": bsdf}
        else:
            scene[f"material_{k}"] = mesh_part(mi, f"material_{k}", part[0], part[1], mi.load_dict(bsdf))
    if board is not None:
        scene["board"] = {"type": "rectangle",
                          "to_world": mi.ScalarTransform4f().translate([0.0, float(board.y), 0.0]).rotate([1, 0, 0], -90)
                          .scale(float(board.half_size)),
                          "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "raw": True,
                                                                      "bitmap": mi.Bitmap(np.ascontiguousarray(board.albedo, np.float32))}}}
    if isinstance(light, EnvLight):
        scene["light"] = {"type": "envmap", "filename": light.path, "scale": float(light.scale),
                          "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], float(light.rotation_deg))}
    else:
        scene["light"] = {"type": "sphere", "center": list(light.centre_world), "radius": float(light.radius),
                          "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [light.radiance] * 3}}}
    return mi.load_dict(scene)


def sensor_for(world_from_cam: np.ndarray, intr: Intrinsics) -> Any:
    """A Mitsuba perspective sensor with exactly the capture's pinhole and camera pose.

    Args:
        world_from_cam: (4, 4) camera-to-world, OpenGL axes (x right, y up, looking down -z).
        intr: pinhole intrinsics; fl_x must equal fl_y (square pixels).
    """
    import mitsuba as mi

    if abs(intr.fl_x - intr.fl_y) > 1e-6 * intr.fl_x:
        raise ValueError(f"square pixels required, got fl_x={intr.fl_x}, fl_y={intr.fl_y}")
    centre = world_from_cam[:3, 3]
    fov_x = math.degrees(2 * math.atan(0.5 * intr.w / intr.fl_x))
    return mi.load_dict({
        "type": "perspective", "fov": fov_x, "fov_axis": "x",
        # measured: Mitsuba shifts the image the other way from the principal point
        "principal_point_offset_x": -(intr.cx - intr.w / 2) / intr.w,
        "principal_point_offset_y": -(intr.cy - intr.h / 2) / intr.h,
        "to_world": mi.ScalarTransform4f().look_at(origin=centre.tolist(), target=(centre - world_from_cam[:3, 2]).tolist(),
                                                   up=world_from_cam[:3, 1].tolist()),
        "sampler": {"type": SAMPLER},
        "film": {"type": "hdrfilm", "width": intr.w, "height": intr.h, "rfilter": {"type": "box"},
                 "pixel_format": "rgba"},
    })


def render_view(scene: Any, world_from_cam: np.ndarray, intr: Intrinsics, pass_spp: list[int],
                seeds: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Path-trace one view in passes and average them, each weighted by its sample count.

    Args:
        scene: from :func:`build_scene`.
        world_from_cam: (4, 4) camera-to-world.
        intr: pinhole intrinsics.
        pass_spp: samples per pixel of each pass, each one the sampler takes exactly
            (:func:`pass_sample_counts`).
        seeds: one 32-bit seed per pass.

    Returns:
        radiance_premult: (H, W, 3) float32, linear, the pixel mean over all samples (0 where a
            sample hits nothing), >= 0.
        alpha: (H, W) float32, the fraction of samples that hit a visible surface.
    """
    import mitsuba as mi

    if len(pass_spp) != len(seeds) or not pass_spp:
        raise ValueError(f"one seed per pass: {len(pass_spp)} passes, {len(seeds)} seeds")
    bad = [n for n in pass_spp if not sampler_count_ok(n)]
    if bad:
        raise ValueError(f"{SAMPLER} would round these sample counts: {bad}")
    sensor = sensor_for(world_from_cam, intr)
    total = sum(pass_spp)
    acc = np.zeros((intr.h, intr.w, 4), np.float64)
    for n, seed in zip(pass_spp, seeds):
        img = np.asarray(mi.render(scene, sensor=sensor, spp=int(n), seed=int(seed)), dtype=np.float64)
        acc += img * (n / total)
    return acc[..., :3].astype(np.float32), acc[..., 3].astype(np.float32)


def sampler_count_ok(n: int) -> bool:
    """Whether Mitsuba's multijitter sampler takes n samples per pixel as they are: n = k^2,
    k (k + 1) or k (k + 2) (it rounds other counts up, e.g. 128 to 132).

    >>> [n for n in range(1, 17) if sampler_count_ok(n)]
    [1, 2, 3, 4, 6, 8, 9, 12, 15, 16]
    """
    k = math.isqrt(n)
    return n >= 1 and n in (k * k, k * (k + 1), k * (k + 2))


def _largest_ok(n: int) -> int:
    while not sampler_count_ok(n):
        n -= 1
    return n


def pass_sample_counts(spp: int, width: int, height: int, max_lanes: int = MAX_LANES_PER_PASS) -> list[int]:
    """Split ``spp`` samples per pixel into as few passes as possible, of nearly equal counts that
    the sampler takes exactly, each tracing at most ``max_lanes`` camera samples.

    >>> pass_sample_counts(1024, 128, 128)
    [256, 256, 256, 256]
    >>> pass_sample_counts(128, 128, 128)  # 128 is not a multijitter count; 64 is
    [64, 64]
    """
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    cap = max(1, max_lanes // (width * height))
    first = math.ceil(spp / cap)
    for passes in range(first, first + 16):
        counts, left = [], spp
        for j in range(passes):
            n = _largest_ok(min(math.ceil(left / (passes - j)), cap, left))
            counts.append(n)
            left -= n
            if left == 0:
                return counts
    counts, left = [], spp  # greedy fallback (1 is always a valid count)
    while left > 0:
        counts.append(_largest_ok(min(left, cap)))
        left -= counts[-1]
    return counts
