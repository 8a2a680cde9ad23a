"""Pinhole cameras in the OpenGL convention: look-at, orbits, focal length from FOV, pixel rays."""

from __future__ import annotations

import math

import numpy as np
import pytest

from damcap.common.cameras import focal_px_from_fov, look_at_world_from_cam, orbit_world_from_cam, pixel_rays_world


def _is_rotation(r: np.ndarray) -> bool:
    return np.allclose(r.T @ r, np.eye(3), atol=1e-12) and math.isclose(np.linalg.det(r), 1.0, abs_tol=1e-12)


def test_look_at_closed_form():
    # a camera on +z looking at the origin with y up: the identity rotation
    m = look_at_world_from_cam(np.array([0.0, 0.0, 5.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(m, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]], atol=1e-15)
    # on +x: right is -z, backwards is +x
    m = look_at_world_from_cam(np.array([2.0, 0.0, 0.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(m[:3, :3], [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-15)


def test_look_at_rotation_is_proper_and_points_at_the_target():
    rng = np.random.default_rng(0)
    for _ in range(10):
        c, t = rng.normal(size=3) * 4, rng.normal(size=3)
        m = look_at_world_from_cam(c, t, np.array([0.0, 1.0, 0.3]))
        assert _is_rotation(m[:3, :3]) and np.array_equal(m[3], [0, 0, 0, 1])
        np.testing.assert_allclose(m[:3, 3], c)
        forward = -m[:3, 2]
        np.testing.assert_allclose(forward, (t - c) / np.linalg.norm(t - c), atol=1e-12)
        assert m[:3, 1] @ np.array([0.0, 1.0, 0.3]) > 0  # image up leans toward the up hint


def test_look_at_with_up_along_the_view_is_refused():
    with pytest.raises(ValueError, match="up_world is parallel to the viewing direction"):
        look_at_world_from_cam(np.array([0.0, 3.0, 0.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))


def test_orbit_closed_form():
    m = orbit_world_from_cam(4, 2.0, 30.0)
    assert m.shape == (4, 4, 4)
    el = math.radians(30)
    expected = 2.0 * np.array([[0, math.sin(el), math.cos(el)], [math.cos(el), math.sin(el), 0],
                               [0, math.sin(el), -math.cos(el)], [-math.cos(el), math.sin(el), 0]])
    np.testing.assert_allclose(m[:, :3, 3], expected, atol=1e-12)
    for w in m:
        assert _is_rotation(w[:3, :3])
        np.testing.assert_allclose(-w[:3, 2], -w[:3, 3] / np.linalg.norm(w[:3, 3]), atol=1e-12)  # looks at the origin
    shifted = orbit_world_from_cam(4, 2.0, 30.0, azimuth0_deg=90.0)
    np.testing.assert_allclose(shifted[0], m[1], atol=1e-12)


@pytest.mark.parametrize("fov, size, focal", [(90.0, 256, 128.0), (60.0, 100, 50 / math.tan(math.radians(30))),
                                              (2 * math.degrees(math.atan(0.25)), 64, 128.0)])
def test_focal_px_from_fov(fov, size, focal):
    assert focal_px_from_fov(fov, size) == pytest.approx(focal, rel=1e-12)


def _project(d_world: np.ndarray, world_from_cam: np.ndarray, fl_x, fl_y, cx, cy) -> np.ndarray:
    d_cam = d_world @ world_from_cam[:3, :3]
    return np.stack([cx + fl_x * d_cam[..., 0] / -d_cam[..., 2], cy - fl_y * d_cam[..., 1] / -d_cam[..., 2]], axis=-1)


def test_pixel_rays_pass_through_the_pixel_centres():
    wfc = look_at_world_from_cam(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.5, 0.0]), np.array([0.0, 1.0, 0.0]))
    fl_x, fl_y, cx, cy, w, h = 40.0, 42.0, 9.5, 6.0, 20, 13
    origin, d = pixel_rays_world(wfc, fl_x, fl_y, cx, cy, w, h)
    assert d.shape == (13, 20, 3)
    np.testing.assert_allclose(origin, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    np.testing.assert_allclose(_project(d, wfc, fl_x, fl_y, cx, cy), np.stack([j, i], -1), atol=1e-9)
    # the ray through the principal point is the optical axis (-z of the camera)
    _, d_c = pixel_rays_world(wfc, fl_x, fl_y, 1.5, 1.5, 3, 3)
    np.testing.assert_allclose(d_c[1, 1], -wfc[:3, 2], atol=1e-12)


def test_pixel_rays_with_subpixel_offsets():
    wfc = orbit_world_from_cam(3, 4.0, 10.0)[1]
    args = (30.0, 30.0, 8.0, 6.0, 16, 12)
    _, centres = pixel_rays_world(wfc, *args)
    offs = np.array([[0.0, 0.0], [0.25, -0.25], [-0.5, 0.5]])
    _, d = pixel_rays_world(wfc, *args, offsets=offs)
    assert d.shape == (3, 12, 16, 3)
    np.testing.assert_allclose(d[0], centres, atol=1e-12)
    j, i = np.meshgrid(np.arange(16) + 0.5, np.arange(12) + 0.5)
    for k, (dx, dy) in enumerate(offs):
        np.testing.assert_allclose(_project(d[k], wfc, *args[:4]), np.stack([j + dx, i + dy], -1), atol=1e-9)


def test_pixel_rays_cache_is_read_only():
    _, d = pixel_rays_world(np.eye(4), 10.0, 10.0, 2.0, 2.0, 4, 4)
    d2 = d.copy()
    d2[...] = 0  # a caller's copy can be changed
    _, again = pixel_rays_world(np.eye(4), 10.0, 10.0, 2.0, 2.0, 4, 4)
    np.testing.assert_allclose(np.linalg.norm(again, axis=-1), 1.0, atol=1e-12)


def test_orbit_about_another_up_axis():
    """Turned to orbit about +z: every centre sits at the elevation above the xy-plane, the ring's
    normal is +z, each camera still looks at the origin, and its image up leans toward +z."""
    from damcap.common.cameras import up_direction

    el = 25.0
    m = orbit_world_from_cam(12, 3.0, el, up_world=np.array([0.0, 0.0, 2.0]))
    centres = m[:, :3, 3]
    np.testing.assert_allclose(centres[:, 2], 3.0 * math.sin(math.radians(el)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), 3.0, atol=1e-12)
    np.testing.assert_allclose(up_direction(m), [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(np.einsum("ij,ij->i", -m[:, :3, 2], -centres / 3.0), 1.0, atol=1e-12)
    assert (m[:, 2, 1] > 0.5).all()  # camera y (image up) has a large +z component
    # the default and an explicit +y are the same orbit
    np.testing.assert_allclose(orbit_world_from_cam(5, 2.0, 10.0, 30.0, np.array([0.0, 1.0, 0.0])), orbit_world_from_cam(5, 2.0, 10.0, 30.0),
                               atol=1e-12)


def test_up_direction_of_a_ring_and_of_scattered_cameras():
    from damcap.common.cameras import rotation_between, up_direction

    up = np.array([0.3, -0.4, 0.8]) / np.linalg.norm([0.3, -0.4, 0.8])
    ring = orbit_world_from_cam(10, 4.0, 15.0, up_world=up)
    np.testing.assert_allclose(up_direction(ring), up, atol=1e-9)
    # two cameras (no ring): the mean of their image-up axes
    two = ring[:2]
    mean_up = two[:, :3, 1].sum(0)
    np.testing.assert_allclose(up_direction(two), mean_up / np.linalg.norm(mean_up), atol=1e-12)
    np.testing.assert_allclose(rotation_between(np.array([0.0, 1.0, 0.0]), up) @ [0, 1, 0], up, atol=1e-12)
    np.testing.assert_allclose(rotation_between(up, -up) @ up, -up, atol=1e-12)
