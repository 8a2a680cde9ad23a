"""Random closed-form scenes: the tracer and the shading against closed forms, determinism, ranges."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from damcap.common.errors import DamcapError
from damcap.synth.closed_form import (Blobs, Material, blob_sdf, directional_lighting, intersect_sphere, shade, trace_blobs)
from damcap.synth.procedural import (Materials, ProceduralOptions, camera_rays, random_lighting, random_materials, render_scenes,
                                     shade_batch)

SMALL = ProceduralOptions(scene_px=16, scene_views_min=3, scene_views_max=6)


def _sphere(radius: float = 1.0) -> Blobs:
    return Blobs(torch.zeros(1, 2, 3), torch.tensor([[radius, 0.0]]), torch.full((1, 1), 0.1))


def test_a_one_ball_blob_is_the_exact_sphere():
    p = torch.randn(1, 100, 3) * 2
    assert torch.allclose(blob_sdf(p, _sphere(0.8)), p.norm(dim=-1) - 0.8, atol=1e-6)
    origin = np.array([0.3, 0.4, 3.0])
    dirs = -origin + np.random.default_rng(0).normal(0, 0.2, (200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hit_ref, pos_ref, nrm_ref = intersect_sphere(origin, dirs)
    o = torch.tensor(origin, dtype=torch.float32).expand(1, 200, 3)
    hit, pos, nrm = trace_blobs(o, torch.from_numpy(dirs).float()[None], _sphere())
    assert hit[0].numpy().tolist() == hit_ref.tolist() and hit_ref.sum() > 50
    assert np.abs(pos[0].numpy()[hit_ref] - pos_ref[hit_ref]).max() < 2e-3
    assert np.abs(nrm[0].numpy()[hit_ref] - nrm_ref[hit_ref]).max() < 2e-3


def test_two_overlapping_balls_blend_smoothly():
    blobs = Blobs(torch.tensor([[[-0.4, 0, 0], [0.4, 0, 0]]]), torch.tensor([[0.5, 0.5]]), torch.full((1, 1), 0.2))
    # on the axis between the balls the smooth union lies below both distances (the blend bulges out)
    p = torch.tensor([[[0.0, 0.45, 0.0]]])
    d_min = min(float((p - c).norm()) - 0.5 for c in blobs.centres[0])
    assert float(blob_sdf(p, blobs)) < d_min
    # far away the union is the nearer ball's distance
    assert math.isclose(float(blob_sdf(torch.tensor([[[3.0, 0, 0]]]), blobs)), 2.1, abs_tol=1e-6)


def test_batched_shading_is_the_closed_form_shading():
    n = torch.nn.functional.normalize(torch.randn(1, 300, 3), dim=-1)
    v = torch.nn.functional.normalize(torch.randn(1, 300, 3) + n * 1.5, dim=-1)
    mat = Material((0.6, 0.3, 0.2), 0.25, (0.04, 0.04, 0.04))
    light = directional_lighting()
    ref = shade(n[0], v[0], light, mat)
    mats = Materials(torch.tensor([mat.albedo]), torch.tensor([[mat.roughness]]), torch.tensor([mat.specular]))
    mask = torch.ones(1, 300, dtype=torch.bool)
    mask[0, ::7] = False
    out = shade_batch(n, v, light.dirs[None], light.power[None], mats, mask, chunk=64)
    assert torch.allclose(out[0][mask[0]], ref[mask[0]], rtol=1e-5, atol=1e-6)
    assert (out[0][~mask[0]] == 0).all()


def test_camera_rays_look_at_the_origin():
    c = torch.tensor([[0.0, 0.0, 3.5], [2.0, 1.0, -1.0]])
    d = camera_rays(c, torch.zeros(2, 2), 0.3)
    assert torch.allclose(d, torch.nn.functional.normalize(-c, dim=-1), atol=1e-6)
    right = camera_rays(c[:1], torch.tensor([[1.0, 0.0]]), 0.3)  # x = +1 is the image's right edge
    assert math.isclose(float(torch.rad2deg(torch.acos((right * d[:1]).sum()))), math.degrees(math.atan(0.3)), rel_tol=1e-4)


def test_materials_and_lights_are_physical_and_varied():
    g = torch.Generator().manual_seed(0)
    m = random_materials(g, 400, 0.03)
    assert ((m.albedo >= 0) & (m.albedo <= 1)).all() and ((m.f0 >= 0) & (m.f0 <= 1)).all()
    assert m.alpha.min() >= 0.03 and m.alpha.max() <= 1 and m.alpha.min() < 0.05 and m.alpha.max() > 0.8
    assert (m.f0.mean(1) > 0.45).float().mean() > 0.2  # metals
    assert (m.f0.amax(1) == 0).float().mean() > 0.03  # diffuse only
    dirs, power = random_lighting(g, 400, 6, 2.0)
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(()), atol=1e-5)
    assert (power >= 0).all() and torch.isfinite(power).all()
    directional = power[:, -3:].sum((1, 2))
    assert (directional == 0).float().mean() > 0.25 and (directional > 0).float().mean() > 0.4  # environment only / with lights
    total = power.sum((1, 2))
    assert total.max() / total.min() > 100  # exposures over decades


def test_the_lighting_mix_sets_each_modes_share():
    draw = lambda **mix: random_lighting(torch.Generator().manual_seed(1), 2000, 6, 0.0, **mix)[1]  # noqa: E731
    directional = lambda p: p[:, -3:].sum((1, 2))  # noqa: E731
    env = lambda p: p[:, :-3].sum((1, 2))  # noqa: E731
    default = draw()
    assert torch.equal(default, draw(env_only=0.4, lights_only=0.35))
    assert abs(float((directional(default) == 0).float().mean()) - 0.4) < 0.03  # binomial sd 0.011
    lights = draw(env_only=0.0, lights_only=1.0)
    assert (directional(lights) > 0).all()
    # the dim environment: at most 10% of one light's power (3 W/m^2 per channel before exposure)
    assert (env(lights) <= 0.1 * 3.0 * 3 + 1e-4).all()
    assert (directional(draw(env_only=1.0, lights_only=0.0)) == 0).all()
    shifted = draw(env_only=0.3, lights_only=0.55)
    assert abs(float((directional(shifted) == 0).float().mean()) - 0.3) < 0.03
    assert abs(float((env(shifted) <= 0.9 + 1e-4).float().mean()) - 0.55) < 0.03


def test_options_refuse_a_lighting_mix_above_one():
    with pytest.raises(DamcapError, match="--scene-env-only 0.7 and --scene-lights-only 0.4 add up to more than 1"):
        ProceduralOptions(scene_env_only=0.7, scene_lights_only=0.4).validate()


def test_scenes_are_deterministic_and_consistent():
    a = render_scenes(torch.Generator().manual_seed(3), 3, 2, 200, SMALL)
    b = render_scenes(torch.Generator().manual_seed(3), 3, 2, 200, SMALL)
    assert torch.equal(a.views, b.views) and torch.equal(a.radiance_lin, b.radiance_lin)
    assert a.views.shape == (3, 2, 10, 16, 16) and a.view_mask[:, 0].all()
    fg = a.views[:, :, 9] > 0.5
    assert fg.flatten(1).any(1).all()
    normals = a.views[:, :, 3:6].permute(0, 1, 3, 4, 2)[fg]
    assert torch.allclose(normals.norm(dim=-1), torch.ones(()), atol=1e-4)
    assert (a.views[:, :, :9].permute(0, 1, 3, 4, 2)[~fg] == 0).all()
    assert a.sample_mask.float().mean() > 0.2 and (a.radiance_lin[~a.sample_mask] == 0).all()
    assert (a.radiance_lin >= 0).all() and torch.isfinite(a.radiance_lin).all()


def test_options_refuse_an_empty_view_range():
    with pytest.raises(DamcapError, match="--scene-views-min 9 is above --scene-views-max 5"):
        ProceduralOptions(scene_views_min=9, scene_views_max=5).validate()
