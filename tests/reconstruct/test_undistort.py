"""Undistortion: OpenCV's projections as the closed-form reference, COLMAP camera models, round trips."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.capture_folder import Intrinsics
from damcap.common.errors import DamcapError
from damcap.reconstruct.undistort import (
    PhotoCamera,
    camera_from_colmap,
    pinhole_for,
    resample_to_pinhole,
    undistort_maps,
)


def _distort(x: np.ndarray, y: np.ndarray, dist: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's distortion of normalised coordinates (cv2.projectPoints with K = I)."""
    import cv2

    pts = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], 1)
    out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.array(dist, np.float64))
    return out[:, 0, 0].reshape(x.shape), out[:, 0, 1].reshape(x.shape)


def _maps_at(cam: PhotoCamera, xy: np.ndarray) -> np.ndarray:
    """Where the undistortion maps sample the photo (contract coordinates) for normalised points xy,
    through a 1-pixel target per point (focal 1, principal point at the point)."""
    out = []
    for x, y in xy:
        mx, my = undistort_maps(cam, Intrinsics(1.0, 1.0, 0.5 - x, 0.5 - y, 1, 1))
        out.append([mx[0, 0] + 0.5, my[0, 0] + 0.5])
    return np.array(out)


def test_opencv_family_maps_match_opencv():
    dist = (0.1, -0.05, 0.002, -0.001, 0.01, 0.0, 0.0, 0.0)
    cam = PhotoCamera(640, 480, 500.0, 505.0, 321.0, 239.0, dist)
    xy = np.random.default_rng(0).uniform(-0.6, 0.6, (20, 2))
    xd, yd = _distort(xy[:, 0], xy[:, 1], dist)
    ref = np.stack([500.0 * xd + 321.0, 505.0 * yd + 239.0], 1)
    assert np.allclose(_maps_at(cam, xy), ref, atol=1e-3)  # float32 maps


def test_fisheye_maps_match_opencv_fisheye():
    """COLMAP's OPENCV_FISHEYE is OpenCV's equidistant fisheye model (cv2.fisheye)."""
    import cv2

    k = (0.05, -0.01, 0.002, -0.0005)
    cam = camera_from_colmap("OPENCV_FISHEYE", 800, 600, [300.0, 301.0, 402.0, 298.0, *k])
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.model) == (300.0, 301.0, 402.0, 298.0, "OPENCV_FISHEYE")
    xy = np.random.default_rng(1).uniform(-1.5, 1.5, (20, 2))  # up to ~65 deg off axis
    kmat = np.array([[300.0, 0, 402.0], [0, 301.0, 298.0], [0, 0, 1]])
    ref, _ = cv2.fisheye.projectPoints(np.concatenate([xy, np.ones((20, 1))], 1)[:, None], np.zeros(3), np.zeros(3), kmat, np.array(k))
    assert np.allclose(_maps_at(cam, xy), ref[:, 0], atol=1e-3)
    half = cam.scaled(400, 300)  # resizing scales focal lengths and principal point, not the lens
    assert half.params == (150.0, 150.5, 201.0, 149.0, *k)


def test_colmap_camera_models():
    cam = camera_from_colmap("SIMPLE_RADIAL", 640, 480, [500.0, 320.0, 240.0, 0.03])
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.distortion[0]) == (500.0, 500.0, 320.0, 240.0, 0.03)
    assert camera_from_colmap("PINHOLE", 10, 10, [5, 6, 5, 5]).is_pinhole
    assert not camera_from_colmap("SIMPLE_RADIAL_FISHEYE", 10, 10, [5, 5, 5, 0.0]).is_pinhole
    with pytest.raises(DamcapError, match="no pinhole image"):
        camera_from_colmap("EQUIRECTANGULAR", 10, 10, [])
    with pytest.raises(DamcapError, match="not a COLMAP camera model"):
        camera_from_colmap("NO_SUCH_MODEL", 10, 10, [1, 2, 3])
    with pytest.raises(DamcapError, match="needs 4 parameters"):
        camera_from_colmap("SIMPLE_RADIAL", 10, 10, [1, 2, 3])
    with pytest.raises(DamcapError, match="needs the parameters fx, fy, cx, cy, k1, k2, k3, k4, got 3"):
        camera_from_colmap("OPENCV_FISHEYE", 10, 10, [1, 2, 3])


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
        dx, dy = _distort(x, y, cam.distortion)
        x, y = x - (dx - xd), y - (dy - yd)
    photo = cv2.remap(pinhole_img, (x * target.fl_x + target.cx - 0.5).astype(np.float32),
                      (y * target.fl_y + target.cy - 0.5).astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    back = resample_to_pinhole(photo, cam, target)
    inner = np.s_[12:-12, 12:-12]
    assert np.abs(back[inner] - pinhole_img[inner]).max() < 0.02
    mx, my = undistort_maps(PhotoCamera(w, h, 80.0, 80.0, 48.0, 48.0), target)
    assert np.allclose(mx, j - 0.5) and np.allclose(my, i - 0.5)  # identity for a pinhole
