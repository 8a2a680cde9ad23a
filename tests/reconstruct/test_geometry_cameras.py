"""Scene normalisation and undistortion: closed-form values, round trips, OpenCV as reference."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.capture_folder import Intrinsics, rigid_problem
from damcap.common.errors import DamcapError
from damcap.common.cameras import look_at_world_from_cam
from damcap.reconstruct.normalize import (
    normalization_transform,
    optical_axes_focus,
    rotation_agreement_deg,
    similarity,
    similarity_scale,
    transform_points,
    transform_world_from_cam,
    umeyama_similarity,
    up_direction,
)
from damcap.reconstruct.undistort import (
    PhotoCamera,
    camera_from_colmap,
    distort_normalized,
    pinhole_for,
    resample_to_pinhole,
    undistort_maps,
)


def _orbit(centre: np.ndarray, up: np.ndarray, n: int = 12, radius: float = 5.0, elevation_deg: float = 20.0) -> np.ndarray:
    """Cameras on a tilted ring around ``centre`` with ring normal ``up``, looking at the centre."""
    up = up / np.linalg.norm(up)
    a = np.cross(up, [1.0, 0, 0]) if abs(up[0]) < 0.9 else np.cross(up, [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    e = np.radians(elevation_deg)
    mats = []
    for k in range(n):
        t = 2 * np.pi * k / n
        c = centre + radius * (np.cos(e) * (np.cos(t) * a + np.sin(t) * b) + np.sin(e) * up)
        mats.append(look_at_world_from_cam(c, centre, up))
    return np.stack(mats)


def test_normalization_puts_focus_at_origin_up_on_y():
    centre, up = np.array([3.0, -1.0, 7.0]), np.array([0.3, 0.2, 1.0])
    cams = _orbit(centre, up)
    focus, cond = optical_axes_focus(cams)
    assert np.allclose(focus, centre, atol=1e-9) and cond > 0.01
    assert np.allclose(up_direction(cams), up / np.linalg.norm(up), atol=1e-9)
    t = normalization_transform(cams)
    assert np.allclose(transform_points(t, centre[None])[0], 0, atol=1e-9)
    new = transform_world_from_cam(t, cams)
    assert all(rigid_problem(m) is None for m in new)
    assert np.allclose(up_direction(new), [0, 1, 0], atol=1e-9)
    assert new[0, 0, 3] == pytest.approx(0.0, abs=1e-9) and new[0, 2, 3] > 0  # first camera on +z
    # no points: object radius = 0.35 x camera distance -> 1, so cameras sit at 1 / 0.35
    assert np.linalg.norm(new[:, :3, 3], axis=1) == pytest.approx(np.full(12, 1 / 0.35))
    # cameras still look at the object: the origin projects to the image centre direction (-z)
    to_origin = -new[:, :3, 3] / np.linalg.norm(new[:, :3, 3], axis=1, keepdims=True)
    assert np.allclose(np.einsum("ij,ij->i", to_origin, -new[:, :3, 2]), 1.0, atol=1e-9)


def test_normalization_radius_from_points():
    cams = _orbit(np.zeros(3), np.array([0.0, 1, 0]))
    rng = np.random.default_rng(0)
    d = rng.normal(size=(300, 3))
    pts = 0.5 * d / np.linalg.norm(d, axis=1, keepdims=True)
    t = normalization_transform(cams, pts)
    assert similarity_scale(t) == pytest.approx(2.0, rel=1e-6)


def test_umeyama_and_rotation_agreement():
    cams = _orbit(np.zeros(3), np.array([0.0, 1, 0]))
    a = np.radians(40)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    t = similarity(0.3, rot, np.array([1.0, 2, 3]))
    moved = transform_world_from_cam(t, cams)
    assert np.allclose(umeyama_similarity(cams[:, :3, 3], moved[:, :3, 3]), t, atol=1e-9)
    absolute, relative = rotation_agreement_deg(moved, cams)
    assert absolute.max() < 1e-6 and relative.max() < 1e-6 and len(relative) == 66
    # one camera turned by 1 degree about its optical axis
    bad = moved.copy()
    c, s = np.cos(np.radians(1)), np.sin(np.radians(1))
    bad[3, :3, :3] = bad[3, :3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    absolute, relative = rotation_agreement_deg(bad, cams)
    assert absolute[3] == pytest.approx(1.0, abs=1e-6) and np.median(absolute) < 1e-6


def test_distortion_matches_opencv():
    import cv2

    dist = (0.1, -0.05, 0.002, -0.001, 0.01, 0.0, 0.0, 0.0)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.6, 0.6, (50, 2))
    xd, yd = distort_normalized(xy[:, 0], xy[:, 1], dist)
    k = np.eye(3)
    ref, _ = cv2.projectPoints(np.concatenate([xy, np.ones((50, 1))], 1), np.zeros(3), np.zeros(3), k,
                               np.array([dist[0], dist[1], dist[2], dist[3], dist[4]]))
    assert np.allclose(np.stack([xd, yd], 1), ref[:, 0], atol=1e-12)


def test_colmap_camera_models():
    cam = camera_from_colmap("SIMPLE_RADIAL", 640, 480, [500.0, 320.0, 240.0, 0.03])
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.distortion[0]) == (500.0, 500.0, 320.0, 240.0, 0.03)
    assert camera_from_colmap("PINHOLE", 10, 10, [5, 6, 5, 5]).is_pinhole
    with pytest.raises(DamcapError, match="not supported"):
        camera_from_colmap("OPENCV_FISHEYE", 10, 10, [1] * 8)
    with pytest.raises(DamcapError, match="needs 4 parameters"):
        camera_from_colmap("SIMPLE_RADIAL", 10, 10, [1, 2, 3])


def test_pinhole_for_scales_with_pixel_centres():
    cam = PhotoCamera(1000, 500, 800.0, 810.0, 500.0, 250.0)
    t = pinhole_for(cam, 200)
    assert (t.w, t.h) == (200, 100) and t.fl_x == pytest.approx(160.0) and (t.cx, t.cy) == (100.0, 50.0)
    assert pinhole_for(cam, 2000) == Intrinsics(800.0, 810.0, 500.0, 250.0, 1000, 500)


def test_undistort_round_trip():
    """Distort a smooth pinhole image with a known lens, undistort it back: the same image."""
    import cv2

    w = h = 96
    target = Intrinsics(80.0, 80.0, 48.0, 48.0, w, h)
    cam = PhotoCamera(w, h, 80.0, 80.0, 48.0, 48.0, (0.08, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pinhole_img = (np.sin(j / 9.0) * np.cos(i / 7.0)).astype(np.float32)
    # make the distorted photo by inverting the map numerically: for each photo pixel, find the
    # undistorted point (fixed-point iteration) and sample the pinhole image there
    xd, yd = (j - cam.cx) / cam.fx, (i - cam.cy) / cam.fy
    x, y = xd.copy(), yd.copy()
    for _ in range(30):
        dx, dy = distort_normalized(x, y, cam.distortion)
        x, y = x - (dx - xd), y - (dy - yd)
    photo = cv2.remap(pinhole_img, (x * target.fl_x + target.cx - 0.5).astype(np.float32),
                      (y * target.fl_y + target.cy - 0.5).astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    back = resample_to_pinhole(photo, cam, target)
    inner = np.s_[12:-12, 12:-12]
    assert np.abs(back[inner] - pinhole_img[inner]).max() < 0.02
    mx, my = undistort_maps(PhotoCamera(w, h, 80.0, 80.0, 48.0, 48.0), target)
    assert np.allclose(mx, j - 0.5) and np.allclose(my, i - 0.5)  # identity for a pinhole
