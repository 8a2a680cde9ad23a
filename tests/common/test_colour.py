"""sRGB encode/decode, display encoding and the preview curve (common/colour.py)."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.colour import (
    DISPLAY_KEY,
    display_srgb8,
    exposure_scale_for,
    linear_to_srgb,
    preview_gamma,
    srgb_to_linear,
)


def test_srgb_closed_form_values():
    # IEC 61966-2-1 values: the linear segment, the knee, mid-grey, the ends.
    assert srgb_to_linear(np.array(0.04045)) == pytest.approx(0.04045 / 12.92, rel=1e-12)
    assert srgb_to_linear(np.array(0.5)) == pytest.approx(0.21404114, abs=1e-8)
    assert linear_to_srgb(np.array(0.18)) == pytest.approx(0.46135612, abs=1e-8)
    assert srgb_to_linear(np.array([0.0, 1.0])).tolist() == [0.0, 1.0]


def test_srgb_round_trip_and_monotone():
    x = np.linspace(0, 1, 10001)
    assert np.abs(linear_to_srgb(srgb_to_linear(x)) - x).max() < 1e-12
    assert np.all(np.diff(srgb_to_linear(x)) > 0)
    # continuity at the knee (the two segments meet within 1e-7)
    knee = 0.0031308
    assert abs(knee * 12.92 - (1.055 * knee ** (1 / 2.4) - 0.055)) < 1e-7


def test_srgb_clips_and_keeps_batch_shape():
    x = np.array([[-0.5, 0.0], [1.0, 7.0]])
    assert linear_to_srgb(x).shape == (2, 2)
    np.testing.assert_allclose(linear_to_srgb(x), [[0.0, 0.0], [1.0, 1.0]], rtol=0, atol=1e-15)
    assert srgb_to_linear(x).tolist() == [[0.0, 0.0], [1.0, 1.0]]
    assert linear_to_srgb(np.float32(0.18)).dtype == np.float64


def test_srgb_matches_colour_science():
    colour = pytest.importorskip("colour")
    x = np.linspace(0, 1, 257)
    assert np.abs(srgb_to_linear(x) - colour.cctf_decoding(x, "sRGB")).max() < 1e-12
    # the encoding is bit-identical to colour's (display frames keep their pixels)
    y = np.random.default_rng(0).uniform(0, 1, 100_000)
    np.testing.assert_array_equal(linear_to_srgb(y), colour.cctf_encoding(y, function="sRGB"))


def test_exposure_scale_rule():
    rad = np.ones((4, 4, 3)) * 2.0
    assert exposure_scale_for(rad, np.ones((4, 4), bool)) == pytest.approx(0.4)
    assert exposure_scale_for(rad * 0, np.ones((4, 4), bool)) == 1.0
    assert exposure_scale_for(rad, np.zeros((4, 4), bool)) == 1.0  # nothing masked
    assert exposure_scale_for(rad * 5, np.ones((4, 4), bool)) * 10.0 == pytest.approx(DISPLAY_KEY)


def test_display_srgb8_values():
    # 0.18 -> 0.4613561 -> 117.64 -> 118; clipped above 1 and below 0
    rad = np.array([[[0.18, 0.0, 2.0], [-1.0, 0.5, 1.0]]])
    np.testing.assert_array_equal(display_srgb8(rad, 1.0), [[[118, 0, 255], [0, 188, 255]]])
    np.testing.assert_array_equal(display_srgb8(rad, 2.0)[0, 0], [162, 0, 255])  # 0.36 -> 0.6342 -> 161.7
    assert display_srgb8(rad, 1.0).dtype == np.uint8


def test_preview_gamma_is_a_plain_power_curve():
    x = np.array([-0.2, 0.0, 0.18, 0.5, 1.0, 3.0])
    np.testing.assert_array_equal(preview_gamma(x), np.clip(x, 0, 1) ** (1 / 2.2))
    assert preview_gamma(np.array(0.18)) == pytest.approx(0.18 ** (1 / 2.2), rel=1e-15)
    assert preview_gamma(np.array(0.5), gamma=1.0) == 0.5
    assert preview_gamma(np.float32(0.25)).dtype == np.float32
