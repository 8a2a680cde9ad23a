"""Undistortion: OpenCV as reference, COLMAP camera models, round trips."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.capture_folder import Intrinsics
from damcap.common.errors import DamcapError
from damcap.reconstruct.undistort import (
    PhotoCamera,
    camera_from_colmap,
    distort_normalized,
    pinhole_for,
    resample_to_pinhole,
    undistort_maps,
)


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
