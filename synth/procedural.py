"""Random closed-form scenes, rendered in batches on any torch device: the predictor's training
distribution (``damcap train-hyper --procedural``).

A scene is an object (a blob: the smooth union of 1 to ``blob_balls`` spheres; one ball is a
sphere), one Lambert + GGX material (diffuse to mirror-like, dielectric or coloured metal), distant
illumination (an environment of a sky gradient and 0 to 3 spherical-Gaussian lobes under a random
rotation, 1 to 3 directional lights, or both), an exposure scale drawn over decades, and 5 to 30
cameras around it. Radiance follows the rendering equation without shadows or interreflection,
as :mod:`.closed_form` does, so every scene is exactly what a deep appearance map can represent.

For each scene the batch holds the views a predictor reads (what ``damcap predict`` would crop from
a capture: radiance, normal, view direction and coverage) and target samples (view direction,
normal, radiance) from pixels of *all* the scene's cameras, as a capture's train views give them.
Everything is vectorised over the batch (no per-scene Python loop): on a GPU a batch of 32 scenes
renders in a fraction of the training step it feeds.

Pure: tensors in, tensors out; random draws come from one ``torch.Generator`` so a batch depends
only on its seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from damcap.common.errors import DamcapError
from damcap.common.numerics import dot, safe_normalize
from damcap.common.validate import check_ranges, in_range

from damcap.synth.closed_form import rand_uniform, brdf_lambert_ggx_t, equirect_directions, random_blobs, random_unit, trace_blobs


@dataclass(frozen=True)
class ProceduralOptions:
    """The distribution of random closed-form scenes (each option one knob of the recipe)."""

    scene_px: int = field(default=128, metadata=in_range(8, 1024, cli_panel="advanced"))
    """side of each rendered input view, pixels"""
    scene_views_min: int = field(default=5, metadata=in_range(1, 1000, cli_panel="advanced"))
    """fewest cameras of a scene"""
    scene_views_max: int = field(default=30, metadata=in_range(1, 1000, cli_panel="advanced"))
    """most cameras of a scene"""
    scene_env_grid: int = field(default=8, metadata=in_range(2, 64, cli_panel="advanced"))
    """rows of the equirectangular grid that integrates an environment (columns = 2x)"""
    scene_exposure_decades: float = field(default=2.0, metadata=in_range(0, 6, cli_panel="advanced"))
    """exposure scale drawn log-uniformly in 10^[-d, d]"""
    scene_blob_balls: int = field(default=4, metadata=in_range(1, 16, cli_panel="advanced"))
    """most spheres in a blob (one = a sphere)"""
    scene_min_alpha: float = field(default=0.03, metadata=in_range(1e-3, 1, cli_panel="advanced"))
    """smallest GGX alpha drawn (log-uniform up to 1): how mirror-like a material may be"""
    scene_env_only: float = field(default=0.4, metadata=in_range(0, 1, cli_panel="advanced"))
    """fraction of scenes lit by an environment alone (:func:`random_lighting`)"""
    scene_lights_only: float = field(default=0.35, metadata=in_range(0, 1, cli_panel="advanced"))
    """fraction lit by 1 to 3 directional lights and a dim environment; the rest of the scenes have
    both at comparable power"""

    def validate(self) -> None:
        check_ranges(self)
        if self.scene_views_min > self.scene_views_max:
            raise DamcapError(f"--scene-views-min {self.scene_views_min} is above --scene-views-max {self.scene_views_max}")
        if self.scene_env_only + self.scene_lights_only > 1:
            raise DamcapError(f"--scene-env-only {self.scene_env_only} and --scene-lights-only {self.scene_lights_only} "
                              "add up to more than 1 (they are fractions of the scenes); lower one")


@dataclass
class SceneBatch:
    """B random scenes: input views and target samples (all on one device, float32)."""

    views: torch.Tensor
    """(B, V, 10, S, S) radiance (linear), normal_world, view_dir_world, coverage per input view"""
    view_mask: torch.Tensor
    """(B, V) bool: which input views a scene has (1 to V)"""
    view_dir_world: torch.Tensor
    """(B, T, 3) target samples: unit directions from the surface toward the camera"""
    normal_world: torch.Tensor
    """(B, T, 3) unit normals"""
    radiance_lin: torch.Tensor
    """(B, T, 3) linear radiance"""
    sample_mask: torch.Tensor
    """(B, T) bool: the sample's ray hit the object"""


# --------------------------------------------------------------------------------------------
# Random draws
# --------------------------------------------------------------------------------------------


def hue_rgb(hue: torch.Tensor) -> torch.Tensor:
    """(..., 3) fully saturated RGB of hues in [0, 1).

    >>> hue_rgb(torch.tensor([0.0, 1 / 3])).tolist()
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    """
    k = torch.tensor([0.0, 4.0, 2.0], device=hue.device)
    return (((hue[..., None] * 6 + k) % 6 - 3).abs() - 1).clamp(0, 1)


def random_colour(gen: torch.Generator, b: int, value_lo: float, value_hi: float) -> torch.Tensor:
    """(b, 3) colours: random hue, saturation in [0, 1], value in [value_lo, value_hi]."""
    sat = rand_uniform(gen, b, 1)
    value = rand_uniform(gen, b, 1, lo=value_lo, hi=value_hi)
    return value * ((1 - sat) + sat * hue_rgb(rand_uniform(gen, b)))


@dataclass
class Materials:
    albedo: torch.Tensor
    """(B, 3) diffuse reflectance"""
    alpha: torch.Tensor
    """(B, 1) GGX alpha"""
    f0: torch.Tensor
    """(B, 3) Fresnel reflectance at normal incidence"""


def random_materials(gen: torch.Generator, b: int, min_alpha: float) -> Materials:
    """One Lambert + GGX material per scene: 60% dielectric (grey F0 0.02-0.08), 30% metal (dark
    diffuse, coloured F0 0.5-1), 10% diffuse only; alpha log-uniform in [min_alpha, 1]."""
    kind = rand_uniform(gen, b, 1)
    albedo = random_colour(gen, b, 0.02, 0.9)
    metal = kind < 0.3
    diffuse_only = kind > 0.9
    f0_dielectric = rand_uniform(gen, b, 1, lo=0.02, hi=0.08).expand(b, 3)
    f0_metal = 0.5 + 0.5 * random_colour(gen, b, 0.6, 1.0)
    f0 = torch.where(metal, f0_metal, torch.where(diffuse_only, torch.zeros_like(f0_dielectric), f0_dielectric))
    albedo = torch.where(metal, albedo * rand_uniform(gen, b, 1, hi=0.1), albedo)
    alpha = torch.exp(rand_uniform(gen, b, 1, lo=math.log(min_alpha), hi=0.0))
    return Materials(albedo, alpha, f0)


def random_lighting(gen: torch.Generator, b: int, env_grid: int, exposure_decades: float, max_lights: int = 3,
                    env_only: float = 0.4, lights_only: float = 0.35) -> tuple[torch.Tensor, torch.Tensor]:
    """Distant illumination of b scenes as directions with radiance x solid angle.

    A fraction ``env_only`` of scenes (default 40%) is lit by an environment only (sky gradient
    about a random up direction plus 0-3 spherical-Gaussian lobes, sharpness 2-300), ``lights_only``
    (35%) by 1-3 directional lights and a dim environment (0-10% of one light's power), the rest
    (25%) by both at comparable power. Then every scene's power is multiplied by an exposure scale
    10^U(-d, d). The draws do not depend on the fractions, so two mixes differ only in which
    scenes change mode.

    Returns:
        dirs: (B, K + max_lights, 3) unit directions toward the light (the environment grid, then
            the directional lights' slots).
        power: (B, K + max_lights, 3) radiance x solid angle, W/m^2 per direction, >= 0.
    """
    dev = gen.device
    grid_dirs, solid = equirect_directions(env_grid)
    grid_dirs, solid = grid_dirs.to(dev), solid.to(dev)
    k = grid_dirs.shape[0]
    up = random_unit(gen, b)
    top, bottom = random_colour(gen, b, 0.2, 1.0), random_colour(gen, b, 0.0, 0.5)
    t = (1 + grid_dirs[None] @ up[..., None]) / 2  # (B, K, 1)
    env = bottom[:, None] * (1 - t) + top[:, None] * t
    n_lobes = torch.randint(0, 4, (b, 1), generator=gen, device=dev)
    for j in range(3):
        mu = random_unit(gen, b)
        sharp = torch.exp(rand_uniform(gen, b, 1, lo=math.log(2.0), hi=math.log(300.0)))
        # a lobe's integral is ~ 2 pi / sharpness: scale its peak so lobes carry comparable energy
        peak = rand_uniform(gen, b, 1, lo=0.5, hi=3.0) * sharp / 4
        lobe = random_colour(gen, b, 0.5, 1.0)[:, None] * peak[:, None] * torch.exp(sharp[:, None] * (grid_dirs[None] @ mu[..., None] - 1))
        env = env + lobe * (j < n_lobes)[:, None].float()
    env_power = env * solid[None, :, None]  # (B, K, 3)

    light_dirs = random_unit(gen, b, max_lights)
    n_lights = torch.randint(1, max_lights + 1, (b, 1), generator=gen, device=dev)
    on = (torch.arange(max_lights, device=dev)[None] < n_lights).float()[..., None]  # (B, L, 1)
    light_power = on * (0.5 + 0.5 * random_colour(gen, b * max_lights, 0.7, 1.0).reshape(b, max_lights, 3)) * 3.0

    mode = rand_uniform(gen, b, 1, 1)
    env_total = env_power.sum(1, keepdim=True).mean(-1, keepdim=True).clamp_min(1e-12)  # (B, 1, 1)
    is_env_only = mode < env_only
    is_lights_only = mode > 1 - lights_only
    # environment only: as drawn; lights only: a dim environment (0-10% of one light's power);
    # both: the environment rescaled to one light's power
    dim = rand_uniform(gen, b, 1, 1, hi=0.1) * 3.0 / env_total
    env_weight = torch.where(is_env_only, torch.ones_like(dim), torch.where(is_lights_only, dim, 3.0 / env_total))
    light_weight = (~is_env_only).float()
    exposure = 10 ** rand_uniform(gen, b, 1, 1, lo=-exposure_decades, hi=exposure_decades)
    dirs = torch.cat([grid_dirs[None].expand(b, k, 3), light_dirs], 1)
    power = torch.cat([env_power * env_weight, light_power * light_weight], 1) * exposure
    return dirs, power


def random_cameras(gen: torch.Generator, b: int, v: int, distance: float = 3.5) -> torch.Tensor:
    """(b, v, 3) camera centres at ``distance``, azimuth uniform, elevation uniform in [-30, 80] deg."""
    az = rand_uniform(gen, b, v, hi=2 * math.pi)
    el = torch.deg2rad(rand_uniform(gen, b, v, lo=-30.0, hi=80.0))
    return distance * torch.stack([el.cos() * az.sin(), el.sin(), el.cos() * az.cos()], -1)


def camera_rays(centres: torch.Tensor, uv: torch.Tensor, half_fov_tan: float) -> torch.Tensor:
    """Unit ray directions of pinhole cameras looking at the origin (y up).

    Args:
        centres: (..., 3) camera centres.
        uv: (..., 2) image-plane coordinates in [-1, 1] (x right, y down).
        half_fov_tan: tan of half the field of view.

    Returns:
        (..., 3) unit directions.
    """
    fwd = safe_normalize(-centres)
    up = torch.zeros_like(fwd)
    up[..., 1] = 1.0
    right = safe_normalize(torch.cross(fwd, up, dim=-1))
    down = torch.cross(fwd, right, dim=-1)
    return safe_normalize(fwd + half_fov_tan * (uv[..., :1] * right + uv[..., 1:] * down))


def shade_batch(normal: torch.Tensor, view: torch.Tensor, dirs: torch.Tensor, power: torch.Tensor, mats: Materials,
                mask: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
    """Outgoing radiance without shadows, per scene: sum_k power_k f(l_k, v) max(n . l_k, 0),
    computed at the masked samples only (0 elsewhere).

    Args:
        normal, view: (B, P, 3) unit normals and directions toward the camera.
        dirs, power: (B, K, 3) each scene's lights (:func:`random_lighting`).
        mats: each scene's material.
        mask: (B, P) bool, the samples to shade (rays that hit).
        chunk: samples per pass (memory: chunk x K x 3 floats, a few times over).

    Returns:
        (B, P, 3) radiance, >= 0.
    """
    out = torch.zeros_like(normal)
    scene, sample = mask.nonzero(as_tuple=True)
    for s in range(0, scene.numel(), chunk):
        b, p = scene[s:s + chunk], sample[s:s + chunk]
        n, v, l = normal[b, p][:, None], view[b, p][:, None], dirs[b]
        f = brdf_lambert_ggx_t(n, v, l, mats.albedo[b][:, None], mats.alpha[b][:, None], mats.f0[b][:, None])
        out[b, p] = (f * dot(n, l).clamp_min(0) * power[b]).sum(1)
    return out


def render_scenes(gen: torch.Generator, b: int, input_views: int, target_samples: int, opts: ProceduralOptions) -> SceneBatch:
    """b random scenes: up to ``input_views`` input views each and ``target_samples`` target rays
    spread over all the scene's cameras (see the module docstring).

    Args:
        gen: the generator (its device is where everything is computed).
        b: scenes.
        input_views: most input views per scene (each scene gets 1 to this many).
        target_samples: target rays per scene (those that miss are masked out).
        opts: the distribution.
    """
    opts.validate()
    dev = gen.device
    s = opts.scene_px
    mats = random_materials(gen, b, opts.scene_min_alpha)
    dirs, power = random_lighting(gen, b, opts.scene_env_grid, opts.scene_exposure_decades,
                                  env_only=opts.scene_env_only, lights_only=opts.scene_lights_only)
    blobs = random_blobs(gen, b, opts.scene_blob_balls)
    n_cams = torch.randint(opts.scene_views_min, opts.scene_views_max + 1, (b, 1), generator=gen, device=dev)
    cams = random_cameras(gen, b, opts.scene_views_max)
    half_fov_tan = 1.08 / math.sqrt(3.5**2 - 1.0)  # the unit sphere fills the frame with 8% margin

    n_in = torch.randint(1, input_views + 1, (b, 1), generator=gen, device=dev)
    view_mask = torch.arange(input_views, device=dev)[None] < torch.minimum(n_in, n_cams)
    pick = (rand_uniform(gen, b, input_views) * n_cams).long()  # input views are cameras of the scene
    in_cams = torch.gather(cams, 1, pick[..., None].expand(b, input_views, 3))
    g = (torch.arange(s, device=dev) + 0.5) / s * 2 - 1
    yy, xx = torch.meshgrid(g, g, indexing="ij")
    uv = torch.stack([xx, yy], -1).reshape(1, 1, s * s, 2)
    origin = in_cams[:, :, None].expand(b, input_views, s * s, 3)
    ray = camera_rays(origin, uv.expand(b, input_views, s * s, 2), half_fov_tan)
    flat = lambda x: x.reshape(b, input_views * s * s, 3)  # noqa: E731
    hit, pos, nrm = trace_blobs(flat(origin), flat(ray), blobs)
    vdir = safe_normalize(flat(origin) - pos)
    hit = hit & (dot(nrm, vdir)[..., 0] > 1e-4)
    rad = shade_batch(nrm, vdir, dirs, power, mats, hit)
    img = torch.cat([rad, nrm * hit[..., None], vdir * hit[..., None], hit[..., None].float()], -1)
    views = img.reshape(b, input_views, s, s, 10).permute(0, 1, 4, 2, 3).contiguous()

    t_cam = (rand_uniform(gen, b, target_samples) * n_cams).long()
    t_origin = torch.gather(cams, 1, t_cam[..., None].expand(b, target_samples, 3))
    t_ray = camera_rays(t_origin, rand_uniform(gen, b, target_samples, 2, lo=-1.0, hi=1.0), half_fov_tan)
    t_hit, t_pos, t_nrm = trace_blobs(t_origin, t_ray, blobs)
    t_view = safe_normalize(t_origin - t_pos)
    t_hit = t_hit & (dot(t_nrm, t_view)[..., 0] > 1e-4)
    t_rad = shade_batch(t_nrm, t_view, dirs, power, mats, t_hit)
    return SceneBatch(views, view_mask, t_view, t_nrm, t_rad, t_hit)
