"""Textured photo sets' building blocks: exposures, camera rings, intrinsics, albedo, JPEG EXIF.

Whole photo sets (render_textured, write_photo_set) are registered end to end in
tests/reconstruct/test_reconstruct.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from damcap.capture.exif import read_exposure
from damcap.common.exr import read_image_u8
from damcap.synth.photos import PhotoExposure, default_intrinsics, exposure_series, orbit_cameras, procedural_albedo, write_jpeg


def test_exposure_factor_closed_form():
    assert PhotoExposure(1 / 50, 200.0, 4.0).factor == pytest.approx(0.25)
    assert PhotoExposure(2.0, 100.0, 8.0).factor == pytest.approx(3.125)


def test_exposure_series_stays_near_the_target_factor():
    series = exposure_series(200, seed=3, target_factor=0.25)
    assert len(series) == 200 and series == exposure_series(200, seed=3, target_factor=0.25)
    assert {e.iso for e in series} == {100.0, 200.0, 400.0} and all(e.f_number == 4.0 for e in series)
    for e in series:
        assert 1 / e.time_s == pytest.approx(round(1 / e.time_s))  # 1/N s, as cameras show it
        assert 0.25 * 0.7 < e.factor < 0.25 * 1.4
    assert exposure_series(5, seed=4) != exposure_series(5, seed=3)


def test_default_intrinsics_closed_form():
    intr = default_intrinsics(256, fov_deg=90.0)
    assert (intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h) == (pytest.approx(128.0), pytest.approx(128.0), 128.0, 128.0, 256, 256)
    assert default_intrinsics(100).fl_x == pytest.approx(50 / math.tan(math.radians(22.5)))


def test_orbit_cameras_on_rings_looking_at_the_origin():
    cams = orbit_cameras(12, 3.0, elevations_deg=(10.0, 40.0))
    assert cams.shape == (12, 4, 4)
    centres = cams[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), 3.0, atol=1e-12)
    el = np.degrees(np.arcsin(centres[:, 1] / 3.0))
    np.testing.assert_allclose(el, [10.0] * 6 + [40.0] * 6, atol=1e-9)
    np.testing.assert_allclose(-cams[:, :3, 2], -centres / 3.0, atol=1e-12)  # optical axis through the origin
    az = np.degrees(np.arctan2(centres[:6, 0], centres[:6, 2])) % 360
    np.testing.assert_allclose(az, np.arange(6) * 60.0, atol=1e-9)
    jittered = orbit_cameras(12, 3.0, elevations_deg=(10.0, 40.0), jitter_deg=4.0, seed=1)
    el_j = np.degrees(np.arcsin(jittered[:, 1, 3] / 3.0))
    assert np.all(np.abs(el_j - el) <= 4.0 + 1e-9) and np.abs(el_j - el).max() > 0.1


def test_procedural_albedo_is_a_bounded_function_of_the_point():
    p = np.random.default_rng(0).uniform(-1, 1, (5000, 3))
    a = procedural_albedo(p, seed=2)
    assert a.shape == (5000, 3) and a.dtype == np.float32
    assert a.min() >= 0.05 - 1e-6 and a.max() <= 0.9 + 1e-6
    assert a.std(axis=0).min() > 0.1  # texture, not a flat colour
    np.testing.assert_array_equal(procedural_albedo(p[::-1], seed=2), a[::-1])  # per point, order-free
    assert np.abs(procedural_albedo(p, seed=3) - a).mean() > 0.05


def test_write_jpeg_carries_the_exposure_in_exif(tmp_path):
    j, i = np.meshgrid(np.arange(32), np.arange(24))
    img = np.stack([j * 8, i * 10, 255 - j * 4], -1).astype(np.uint8)  # smooth: JPEG keeps it within a few levels
    write_jpeg(tmp_path / "a.jpg", img, PhotoExposure(1 / 60, 400.0, 4.0), quality=95)
    ex = read_exposure(tmp_path / "a.jpg")
    assert ex.time_s == pytest.approx(1 / 60, rel=1e-4) and ex.iso == 400 and ex.f_number == pytest.approx(4.0)
    back = read_image_u8(tmp_path / "a.jpg")
    assert back.shape == (24, 32, 3) and np.abs(back.astype(int) - img).mean() < 3
    write_jpeg(tmp_path / "b.jpg", img, None)
    assert read_exposure(tmp_path / "b.jpg").time_s is None
