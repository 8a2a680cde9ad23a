"""Merge math: closed-form brackets, the Poisson-optimal estimator, clipping, extreme ranges."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.capture.merge import PoissonAccumulator, merge_ldr, merge_poisson
from damcap.capture.response import hat_weights, srgb_log_response
from damcap.common.colour import srgb_to_linear
from damcap.common.errors import DamcapError


def _srgb_bracket(radiance, exposures):
    """8-bit sRGB codes of linear radiance at each exposure (saturating at 1)."""
    from damcap.common.colour import linear_to_srgb

    return np.stack([np.round(linear_to_srgb(np.clip(radiance * h, 0, 1)) * 255).astype(np.uint16) for h in exposures])


def test_ldr_bracket_of_known_radiance_merges_back():
    rng = np.random.default_rng(0)
    radiance = np.exp(rng.uniform(np.log(0.01), np.log(50.0), (40, 50, 3)))
    exposures = np.array([1 / 64, 1 / 16, 1 / 4, 1.0, 4.0])
    codes = _srgb_bracket(radiance, exposures)
    g = srgb_log_response(256)
    w = np.repeat(hat_weights(256)[None], 3, axis=0)
    res = merge_ldr(codes, np.log(exposures), g, w)
    rel = np.abs(res.radiance_lin / radiance - 1)
    # 8-bit quantisation through the curve: well under 1 % typical, 3 % worst over 3.7 decades
    assert np.median(rel) < 0.006 and rel.max() < 0.03
    assert not res.clipped.any()


def test_ldr_clipped_everywhere_is_flagged_with_lower_bound():
    radiance = np.array([[[0.5, 0.5, 0.5], [500.0, 0.5, 0.5]]])
    exposures = np.array([0.5, 2.0])
    codes = _srgb_bracket(radiance, exposures)
    res = merge_ldr(codes, np.log(exposures), srgb_log_response(256), np.repeat(hat_weights(256)[None], 3, axis=0))
    assert res.clipped[0, 1, 0] and not res.clipped[0, 0].any() and not res.clipped[0, 1, 1:].any()
    # lower bound: full scale at the shortest exposure = 1 / 0.5
    assert res.radiance_lin[0, 1, 0] == pytest.approx(2.0, rel=1e-5)
    assert res.radiance_lin[0, 0, 0] == pytest.approx(0.5, rel=0.02)


def test_ldr_zero_and_saturated_frames_do_not_spoil_the_merge():
    rng = np.random.default_rng(1)
    radiance = np.exp(rng.uniform(np.log(0.05), np.log(3.0), (20, 20, 3)))
    exposures = np.array([1e-6, 0.25, 1.0, 1e6])  # an all-black and an all-white frame
    codes = _srgb_bracket(radiance, exposures)
    assert codes[0].max() == 0 and codes[-1].min() == 255
    res = merge_ldr(codes, np.log(exposures), srgb_log_response(256), np.repeat(hat_weights(256)[None], 3, axis=0))
    assert np.median(np.abs(res.radiance_lin / radiance - 1)) < 0.01 and not res.clipped.any()


def test_ldr_all_black_pixels_are_zero_not_flagged():
    codes = np.zeros((2, 2, 2, 3), np.uint16)
    res = merge_ldr(codes, np.log([1.0, 2.0]), srgb_log_response(256), np.repeat(hat_weights(256)[None], 3, axis=0))
    assert res.radiance_lin.max() == 0 and not res.clipped.any()


def test_merge_ldr_rejects_bad_shapes():
    g = srgb_log_response(256)
    w = np.repeat(hat_weights(256)[None], 3, axis=0)
    with pytest.raises(DamcapError, match="at least 2 frames"):
        merge_ldr(np.zeros((1, 4, 4, 3), np.uint16), np.zeros(1), g, w)
    with pytest.raises(DamcapError, match="do not fit"):
        merge_ldr(np.zeros((2, 4, 4, 3), np.uint16), np.zeros(3), g, w)


def test_poisson_estimator_closed_form_and_saturation():
    # c_j = E * H_j without noise; the saturated long frame must be ignored.
    e = np.array([[0.3, 2.0], [0.01, 50.0]])
    h = np.array([0.25, 1.0, 4.0])
    c = np.minimum(e[None] * h[:, None, None], 1.0)
    res = merge_poisson(c, h, c >= 1.0)
    assert np.allclose(res.radiance_lin[..., 0], np.where(e * 0.25 < 1, e, 4.0), rtol=1e-6)
    assert res.clipped[..., 0].tolist() == [[False, False], [False, True]]  # 50 * 0.25 > 1: clipped in all
    assert res.radiance_lin[1, 1, 0] == pytest.approx(4.0)  # lower bound 1 / 0.25


def test_poisson_estimator_is_unbiased_and_beats_hat_weighting():
    rng = np.random.default_rng(2)
    full_well = 2000.0
    e_true = 0.3  # in full wells per unit exposure
    h = np.array([0.25, 1.0, 3.0])
    n = 20000
    lam = e_true * h[:, None] * full_well * np.ones((3, n))
    counts = np.minimum(rng.poisson(lam), full_well) / full_well
    sat = counts >= 1.0
    est = merge_poisson(counts[..., None], h, sat[..., None]).radiance_lin[:, 0, 0]
    assert abs(est.mean() / e_true - 1) < 0.003
    # hat-weighted mean of per-frame estimates (weights on the normalised count)
    w = np.where(sat, 0.0, np.minimum(counts, 1 - counts))
    hat_est = (w * counts / h[:, None]).sum(0) / w.sum(0)
    # Poisson variance bound: E / (sum H * full_well)
    bound = e_true / (h[h * e_true < 1].sum() * full_well)
    assert est.var() == pytest.approx(bound, rel=0.1)
    assert est.var() < 0.8 * hat_est.var()


def test_poisson_accumulator_ignores_invalid_and_rejects_mismatch():
    acc = PoissonAccumulator((2, 2))
    acc.add(np.full((2, 2), 0.5), 1.0, np.zeros((2, 2), bool), valid=np.array([[True, False], [True, True]]))
    acc.add(np.full((2, 2), 0.9), 2.0, np.zeros((2, 2), bool))
    r = acc.result().radiance_lin[..., 0]
    assert r[0, 0] == pytest.approx(1.4 / 3) and r[0, 1] == pytest.approx(0.45)
    with pytest.raises(DamcapError, match="does not match"):
        acc.add(np.zeros((3, 3)), 1.0, np.zeros((3, 3), bool))
    with pytest.raises(DamcapError, match="positive"):
        acc.add(np.zeros((2, 2)), 0.0, np.zeros((2, 2), bool))
    with pytest.raises(DamcapError, match="at least 2 frames"):
        merge_poisson(np.zeros((1, 2, 2)), np.ones(1), np.zeros((1, 2, 2), bool))


def test_dynamic_range_1e_minus4_to_1e5_survives():
    # Nine decades of radiance, a 16-bit sensor, exposures one decade apart.
    radiance = np.logspace(-4, 5, 200)
    h = 10.0 ** np.arange(-6, 5)  # 1e-6 .. 1e4
    white = 65535.0
    raw = np.minimum(np.round(radiance[None] * h[:, None] * white), white)
    counts = raw / white
    res = merge_poisson(counts[..., None], h, (raw >= white)[..., None])  # (P, 200, 1) -> (200, 1, 1)
    rel = np.abs(res.radiance_lin[:, 0, 0] / radiance - 1)
    assert rel.max() < 2e-3 and not res.clipped.any()
    # ... and survives float32 EXR storage bit-exactly
    import tempfile
    from pathlib import Path

    from damcap.common.exr import read_exr, write_exr

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "r.exr"
        write_exr(p, np.repeat(res.radiance_lin.reshape(1, -1, 1), 3, axis=2), ("R", "G", "B"), dtype="float")
        back, _ = read_exr(p)
    assert np.array_equal(back[0, :, 0], res.radiance_lin[:, 0, 0])
    assert srgb_to_linear(np.array(1.0)) == 1.0
