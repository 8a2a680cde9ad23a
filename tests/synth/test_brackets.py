"""The RAW bracket simulator: real DNG files, exact EXIF, the noise model it claims."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.capture.exif import read_exposure
from damcap.capture.raw import read_raw
from damcap.synth.brackets import (
    CameraModel,
    bracket_times,
    camera_rgb_from_rec709,
    cfa_map,
    expose,
    mosaic,
    simulate_raw_bracket,
    write_dng,
)
from damcap.common.errors import DamcapError


def test_dng_round_trip_through_rawpy(tmp_path):
    import rawpy

    model = CameraModel(bits=12, black_level=256, cfa="GRBG")
    rng = np.random.default_rng(0)
    raw = rng.integers(0, model.white_level + 1, (40, 60)).astype(np.uint16)
    path = write_dng(tmp_path / "f.dng", raw, model, exposure_time_s=1 / 250, iso=400, f_number=5.6)
    with rawpy.imread(str(path)) as r:
        assert np.array_equal(r.raw_image_visible, raw)
        assert r.black_level_per_channel == [256] * 4 and r.white_level == 4095
    assert read_exposure(path).time_s == pytest.approx(1 / 250) and read_exposure(path).iso == 400
    assert read_exposure(path).f_number == pytest.approx(5.6)
    m = read_raw(path)
    assert np.array_equal(m.cfa, cfa_map((40, 60), "GRBG"))
    assert m.rgb_from_camera is not None


def test_sensor_noise_model_matches_its_parameters():
    model = CameraModel(full_well_e=20000, read_noise_e=5.0, black_level=512, bits=14)
    rng = np.random.default_rng(1)
    photons = np.full((200, 200), 5000.0)
    raw = expose(photons, 1.0, model, rng).astype(np.float64)
    e = (raw - model.black_level) * model.gain_e_per_adu
    assert e.mean() == pytest.approx(5000, rel=0.005)
    # Poisson + Gaussian read noise + quantisation (gain^2 / 12)
    expected_var = 5000 + 5.0**2 + model.gain_e_per_adu**2 / 12
    assert e.var() == pytest.approx(expected_var, rel=0.05)
    # full-well clipping and the integer range
    raw_sat = expose(photons, 100.0, model, rng)
    assert raw_sat.max() <= model.white_level and np.median(raw_sat) >= model.white_level - 10


def test_bracket_files_and_truth(tmp_path):
    rad = np.exp(np.random.default_rng(2).uniform(-3, 3, (32, 48, 3)))
    times = bracket_times(3, 2.0, 1 / 30)
    sb = simulate_raw_bracket(rad, tmp_path, times, seed=0)
    assert [f.name for f in sb.files] == ["sim_0.dng", "sim_1.dng", "sim_2.dng"]
    assert [read_exposure(f).time_s for f in sb.files] == pytest.approx(times, rel=1e-6)
    assert sb.radiance_rec709.shape == (32, 48, 3)
    # the truth is the radiance up to one factor
    ratio = sb.radiance_rec709 / rad
    assert np.ptp(ratio) < 1e-5 * ratio.mean()
    with pytest.raises(DamcapError, match="3 to 7"):
        simulate_raw_bracket(rad, tmp_path, [1.0, 2.0])
    with pytest.raises(DamcapError, match="finite and >= 0"):
        simulate_raw_bracket(-rad, tmp_path, times)


def test_colour_and_mosaic_helpers():
    white = camera_rgb_from_rec709(np.ones((1, 1, 3)), np.eye(3))
    assert white[0, 0] == pytest.approx([0.950456, 1.0, 1.088754], rel=1e-5)  # D65 white in XYZ
    m = mosaic(np.arange(12.0).reshape(2, 2, 3), "RGGB")
    assert m.tolist() == [[0.0, 4.0], [7.0, 11.0]]
    with pytest.raises(DamcapError, match="unknown CFA"):
        cfa_map((2, 2), "XTRANS")
