"""The predictor's light orientation: the brightness gradient, the terminator fit, the rotation to +y,
turned images."""

from __future__ import annotations

import math

import pytest
import torch

from damcap.appearance.hyper.orientation import (MIN_GRADIENT, brightness_gradient, light_rotation, light_up_world, rotate_images,
                                                 rotation_to_up, terminator_fit)


def _sphere_images(brightness, side: int = 48, views: int = 1, cap=None) -> torch.Tensor:
    """(1, V, 9, side, side) images whose covered pixels hold normals spread over the whole sphere
    (Fibonacci), RGB = brightness(normal) in each channel, view directions = the normals; the
    last row of each view is uncovered (zeros). With ``cap`` = (axis, cos_max): the normals of the
    spherical cap about the unit axis within that angle instead (the part of an object some views see)."""
    m = (side - 1) * side
    i = torch.arange(m, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / m if cap is None else 1 - (1 - cap[1]) * i / m
    phi = math.pi * (3 - math.sqrt(5)) * i
    n = torch.stack([torch.sqrt(1 - z * z) * torch.cos(phi), torch.sqrt(1 - z * z) * torch.sin(phi), z], -1)
    if cap is not None:  # the cap about +z turned onto the axis
        n = n @ rotation_to_up(torch.tensor([[0.0, 0, 1]]))[0].double().T @ rotation_to_up(cap[0][None])[0].double()
    n = n.float()
    y = brightness(n)
    img = torch.zeros(9, side * side)
    img[0:3, :m] = y[None]
    img[3:6, :m] = n.T
    img[6:9, :m] = n.T
    return img.reshape(9, side, side)[None, None].repeat(1, views, 1, 1, 1)


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, float((a / a.norm()) @ (b / b.norm()))))))


def test_a_linear_brightness_is_recovered_exactly():
    b_true = torch.tensor([0.1, -0.2, 0.4])
    img = _sphere_images(lambda n: 0.3 + n @ b_true)
    assert torch.allclose(brightness_gradient(img)[0], b_true, atol=1e-4)
    radiance = _sphere_images(lambda n: torch.log1p(0.8 + n @ b_true))  # the images hold log1p(radiance / scale)
    assert torch.allclose(brightness_gradient(radiance, linear=True)[0], b_true, atol=1e-4)


def test_one_distant_light_is_found_and_absent_views_do_not_count():
    light = torch.tensor([0.5, 0.7, 0.4])
    light = light / light.norm()
    lit = _sphere_images(lambda n: torch.log1p((n @ light).clamp_min(0) * 3), views=2)
    assert _angle_deg(brightness_gradient(lit)[0], light) < 1.0  # symmetric normals: exactly the light, up to sampling
    other = _sphere_images(lambda n: torch.log1p((-n @ light).clamp_min(0)))
    both = torch.cat([lit[:, :1], other], 1)
    only_first = brightness_gradient(both, torch.tensor([[True, False]]))[0]
    assert _angle_deg(only_first, light) < 1.0
    assert torch.equal(brightness_gradient(torch.zeros(2, 3, 9, 8, 8)), torch.zeros(2, 3))  # nothing covered: no direction
    up = light_up_world(torch.cat([lit[:, :1], torch.zeros_like(lit[:, :1])]))
    assert math.isclose(float(up[0].norm()), 1.0, rel_tol=1e-5) and _angle_deg(up[0], light) < 1.0
    assert torch.equal(up[1], torch.zeros(3))  # no direction: no light named


@pytest.mark.parametrize("direction", [[1.0, 0, 0], [0.0, 1, 0], [0.0, -1, 0], [1e-7, -1, 0], [-0.3, 0.2, -0.9], [0.0, -0.999, 0.045]])
def test_rotation_to_up_is_a_rotation_taking_the_direction_to_up(direction):
    d = torch.tensor([direction])
    r = rotation_to_up(d)[0]
    assert torch.allclose(r @ r.T, torch.eye(3), atol=1e-5) and math.isclose(float(torch.linalg.det(r)), 1.0, abs_tol=1e-5)
    assert torch.allclose(r @ (d[0] / d[0].norm()), torch.tensor([0.0, 1, 0]), atol=1e-5)


def test_rotation_to_up_keeps_the_world_for_light_from_above_or_no_direction():
    assert torch.allclose(rotation_to_up(torch.tensor([[0.0, 2.0, 0.0], [0.0, 0.0, 0.0], [1e-6, 0, 0]])), torch.eye(3).expand(3, 3, 3))
    # near +y the rotation is near the identity (smallest rotation: continuous there)
    r = rotation_to_up(torch.tensor([[0.01, 1.0, 0.0]]))[0]
    assert (r - torch.eye(3)).abs().max() < 0.011


def test_in_its_light_orientation_an_image_is_lit_from_up():
    light = torch.tensor([-0.6, -0.2, 0.77])
    img = _sphere_images(lambda n: torch.log1p((n @ light).clamp_min(0)))
    r = light_rotation(img)
    turned = rotate_images(img, r)
    assert torch.equal(turned[:, :, 0:3], img[:, :, 0:3])  # RGB as it was
    assert _angle_deg(brightness_gradient(turned)[0], torch.tensor([0.0, 1, 0])) < 1.0
    assert torch.allclose(turned[0, 0, 3:6].flatten(1).T, img[0, 0, 3:6].flatten(1).T @ r[0].T, atol=1e-6)


def test_the_terminator_fit_finds_one_light_where_the_views_saw_part_of_the_object():
    """Clamped-cosine brightness over a cap of normals 70 deg around an axis 60 deg from the light
    (a capture's views see one side): the linear fit is pulled toward the seen normals, the
    terminator fit is not; a highlight's few bright pixels do not move it."""
    light = torch.nn.functional.normalize(torch.tensor([0.5, 0.7, 0.4]), dim=0)
    axis = torch.nn.functional.normalize(torch.tensor([0.9, 0.1, -0.3]), dim=0)
    assert 50 < _angle_deg(axis, light) < 70
    cap = (axis, math.cos(math.radians(70)))
    img = _sphere_images(lambda n: torch.log1p(0.05 + 2 * (n @ light).clamp_min(0)), cap=cap)
    assert _angle_deg(brightness_gradient(img)[0], light) > 5  # the linear fit, biased (9.5 deg)
    assert _angle_deg(terminator_fit(img)[0], light) < 0.5
    spec = torch.nn.functional.normalize(axis + light, dim=0)
    shiny = _sphere_images(lambda n: torch.log1p(0.05 + 2 * (n @ light).clamp_min(0) + 20 * (n @ spec).clamp_min(0) ** 200), cap=cap)
    assert 0.001 < float((shiny[0, 0, 0] > img[0, 0, 0] + 0.1).float().mean()) < 0.1  # some pixels are highlight
    assert _angle_deg(terminator_fit(shiny)[0], light) < 1.0
    assert _angle_deg(light_up_world(shiny)[0], light) < 1.0 and _angle_deg(light_rotation(shiny)[0] @ light, torch.tensor([0.0, 1, 0])) < 1.0


def test_the_terminator_fit_without_light_or_pixels_names_no_direction():
    flat = _sphere_images(lambda n: torch.full_like(n[:, 0], 0.3))
    assert float(terminator_fit(flat)[0].norm()) < MIN_GRADIENT
    assert torch.equal(light_rotation(flat)[0], torch.eye(3))
    assert torch.equal(terminator_fit(torch.zeros(1, 2, 9, 8, 8)), torch.zeros(1, 3))  # a single set, nothing covered
    assert torch.equal(terminator_fit(torch.zeros(3, 2, 9, 8, 8)), torch.zeros(3, 3))
    light = torch.tensor([0.0, 0.0, 1.0])
    lit = _sphere_images(lambda n: torch.log1p((n @ light).clamp_min(0)), views=2)
    # a batch: each set's own answer; the second set's only view is absent
    both = terminator_fit(torch.cat([lit, lit]), torch.tensor([[True, True], [False, False]]))
    assert _angle_deg(both[0], light) < 0.5 and torch.equal(both[1], torch.zeros(3))
