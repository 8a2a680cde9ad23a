"""The closed-form capture generator against analytic references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from damcap.common.capture_folder import inspect_capture, read_capture, read_frame
from damcap.common.cameras import orbit_world_from_cam, pixel_rays_world
from damcap.synth.closed_form import (
    ClosedFormOptions, Material, brdf_lambert_ggx, directional_lighting, equirect_directions,
    intersect_sphere, intersect_torus, make_closed_form_capture, render_closed_form, shade, torus_sdf,
)


def test_lambert_only_matches_closed_form():
    m = Material((0.5, 0.25, 0.8), 0.3, (0.0, 0.0, 0.0))
    n = torch.tensor([[0.0, 0.0, 1.0]])
    light = directional_lighting((0.0, 0.6, 0.8), (2.0, 2.0, 2.0))
    v = torch.tensor([[0.0, 0.6, 0.8]])  # v = l, so h = l and v.h = 1
    out = shade(n, v, light, m)
    expected = torch.tensor(m.albedo) / math.pi * 2.0 * 0.8
    # Schlick with F0 = 0 gives F = (1 - v.h)^5 = 0 at v.h = 1: only the Lambert term remains
    torch.testing.assert_close(out[0], expected, rtol=1e-5, atol=1e-6)


def test_ggx_conserves_energy():
    # white-furnace style check: the specular lobe's directional albedo is <= 1 at every angle
    dirs, solid = equirect_directions(256)
    m = Material((0.0, 0.0, 0.0), 0.3, (1.0, 1.0, 1.0))
    n = torch.tensor([0.0, 1.0, 0.0])
    for theta in (0.0, 0.6, 1.2, 1.5):
        v = torch.tensor([math.sin(theta), math.cos(theta), 0.0])
        f = brdf_lambert_ggx(n.expand_as(dirs), v.expand_as(dirs), dirs, m)[:, 0]
        albedo = float((f * dirs[:, 1].clamp_min(0) * solid).sum())
        assert 0.5 < albedo <= 1.01, (theta, albedo)


def test_equirect_solid_angles_sum_to_4pi():
    _, solid = equirect_directions(32)
    assert float(solid.sum()) == pytest.approx(4 * math.pi, rel=1e-5)


def test_sphere_and_torus_intersections():
    o = np.array([0.0, 0.0, 4.0])
    hit, p, n = intersect_sphere(o, np.array([[0.0, 0.0, -1.0]]))
    assert hit[0] and np.allclose(p[0], [0, 0, 1]) and np.allclose(n[0], [0, 0, 1])
    d = np.array([[0.0, -1.0, 0.0]])  # straight down (the torus axis is y)
    assert not intersect_torus(np.array([0.0, 4.0, 0.0]), d)[0][0]  # through the hole
    hit, p, n = intersect_torus(np.array([0.9, 4.0, 0.0]), np.repeat(d, 2, 0))
    np.testing.assert_allclose(p[1], [0.9, 0.4, 0.0], atol=1e-4)  # top of the tube
    np.testing.assert_allclose(n[1], [0.0, 1.0, 0.0], atol=1e-4)
    assert hit[1] and abs(torus_sdf(p[1:], 0.9, 0.4)[0]) < 1e-4
    assert np.allclose(np.linalg.norm(n[1]), 1)


def test_rendered_capture_is_valid_and_self_consistent(small_capture):
    s = inspect_capture(small_capture)
    assert s.problems == []
    cap = read_capture(small_capture)
    assert len(cap.train_filenames) == 4
    idx = [int(p[-8:-4]) for p in cap.train_filenames]
    assert all((b - a) % 12 == 1 for a, b in zip(idx, idx[1:]))  # consecutive (mod the circle)
    f = cap.frames[0]
    d = read_frame(cap, f)
    fg = d.coverage > 0
    v = f.camera_centre_world - d.position_world[fg]
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    assert ((d.normal_world[fg] * v).sum(-1) > 0).all()  # normals face the camera
    np.testing.assert_allclose(np.linalg.norm(d.position_world[fg], axis=-1), 1.0, atol=1e-5)  # on the sphere


def test_two_materials_have_weights_that_partition_the_surface(tmp_path):
    cap = make_closed_form_capture(tmp_path / "c", ClosedFormOptions(shape="torus", materials=2, views=4, resolution=24, train_views=2))
    d = read_frame(cap, cap.frames[0])
    fg = d.coverage > 0
    assert d.weights is not None and d.weights.shape[-1] == 2
    np.testing.assert_allclose(d.weights[fg].sum(-1), 1.0)
    assert 0.1 < d.weights[fg][:, 1].mean() < 0.9
    assert (d.weights[~fg] == 0).all()


def test_radiance_depends_on_view_and_normal_only():
    # the same (V, N) pair seen from two different cameras gets the same radiance
    cams, intr, data, mats = render_closed_form(ClosedFormOptions(views=4, resolution=16, train_views=2, light="env", env_grid=8))
    n = torch.tensor([[0.0, 1.0, 0.0]])
    v = torch.tensor([[0.0, 0.6, 0.8]])
    from damcap.synth.closed_form import environment_lighting
    a = shade(n, v, environment_lighting(8), mats[0])
    b = shade(n.repeat(3, 1), v.repeat(3, 1), environment_lighting(8), mats[0])
    torch.testing.assert_close(b, a.repeat(3, 1))
    assert (data[0].radiance_lin >= 0).all()


def test_orbit_cameras_look_at_the_origin():
    cams = orbit_world_from_cam(5, 3.0, 30.0)
    for m in cams:
        o, d = pixel_rays_world(m, 10, 10, 8, 8, 16, 16)
        centre_ray = d[8, 8] if False else -m[:3, 2]
        assert np.allclose(np.cross(centre_ray, -o / np.linalg.norm(o)), 0, atol=1e-9)
        assert np.linalg.norm(o) == pytest.approx(3.0)
