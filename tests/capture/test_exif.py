"""Exposure metadata: arithmetic, parsing, EXIF from real files, errors that name --exposures."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.capture.exif import (
    Exposure,
    exposure_factor,
    is_raw_path,
    parse_exposure_list,
    read_exposure,
    resolve_exposure_factors,
)
from damcap.common.errors import DamcapError


def test_exposure_factor_closed_form():
    assert exposure_factor(1 / 50, 200, 2.0) == pytest.approx(0.01)
    # one stop more time == one stop more ISO == one stop wider aperture
    base = exposure_factor(1 / 100, 100, 4.0)
    assert exposure_factor(1 / 50, 100, 4.0) == pytest.approx(2 * base)
    assert exposure_factor(1 / 100, 200, 4.0) == pytest.approx(2 * base)
    assert exposure_factor(1 / 100, 100, 4.0 / np.sqrt(2)) == pytest.approx(2 * base)
    assert exposure_factor(0.5) == 0.5  # missing ISO / aperture count as neutral


def test_parse_exposure_list():
    assert parse_exposure_list("1/30, 0.25,2") == pytest.approx([1 / 30, 0.25, 2.0])
    assert parse_exposure_list("1e-3") == [0.001]
    for bad in ("1/0", "-1", "abc", "1,,2", "0"):
        with pytest.raises(DamcapError, match="--exposures"):
            parse_exposure_list(bad)


def test_read_exposure_from_real_files(shared_data, frobisher):
    assert [read_exposure(p) for p in frobisher] == [
        Exposure(0.125, 100.0, 8.0), Exposure(1.0, 100.0, 8.0), Exposure(8.0, 100.0, 8.0)]
    cape = read_exposure(shared_data / "real" / "mold_gold_cape" / "images" / "IMG_5881.JPG")
    assert cape.time_s == pytest.approx(0.02) and cape.iso == 800 and cape.f_number == 2.5
    # zeroed EXIF counts as missing; PNGs have none
    assert read_exposure(shared_data / "raw" / "tinydng_colorchart.dng") == Exposure(None, None, None)
    assert read_exposure(shared_data / "brackets" / "memorial" / "memorial0061.png").time_s is None
    # RAW that only LibRaw understands
    kdc = read_exposure(shared_data / "raw" / "RAW_KODAK_DC50.KDC")
    assert kdc.time_s == pytest.approx(0.00435) and kdc.iso == 84 and kdc.f_number == pytest.approx(6.2)
    assert is_raw_path("x.KDC") and not is_raw_path("x.png")


def test_resolve_factors_and_errors(tmp_path):
    paths = [tmp_path / "a.jpg", tmp_path / "b.jpg"]
    f = resolve_exposure_factors(paths, [Exposure(0.5, 100, 8), Exposure(2.0, 100, 8)])
    assert f[1] / f[0] == pytest.approx(4.0)
    with pytest.raises(DamcapError, match=r"a.jpg: no exposure time.*--exposures"):
        resolve_exposure_factors(paths, [Exposure(None), Exposure(1.0)])
    with pytest.raises(DamcapError, match=r"b.jpg: metadata has no iso"):
        resolve_exposure_factors(paths, [Exposure(1.0, 100), Exposure(2.0)])
    # --exposures replaces metadata entirely
    f = resolve_exposure_factors(paths, [Exposure(None), Exposure(None)], [0.25, 1.0])
    assert f.tolist() == [0.25, 1.0]
    with pytest.raises(DamcapError, match="--exposures lists 3 value"):
        resolve_exposure_factors(paths, [Exposure(None)] * 2, [1, 2, 3])
    with pytest.raises(DamcapError, match="file not found"):
        read_exposure(tmp_path / "nope.jpg")
