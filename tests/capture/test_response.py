"""Response curves: the sRGB response table, Debevec recovery of a known curve (sRGB itself: tests/common/test_colour.py)."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.capture.response import (
    hat_weights,
    level_weights_from_residuals,
    linear_hat_weights,
    recover_response,
    sample_pixels_for_response,
    solve_response_Debevec1997,
    srgb_log_response,
)
from damcap.common.errors import DamcapError


def test_hat_and_linear_hat_weights():
    w = hat_weights(256)
    assert w[0] == w[255] == 0 and w.max() == pytest.approx(127 / 127.5) and np.allclose(w, w[::-1])
    assert hat_weights(5).tolist() == [0.0, 0.5, 1.0, 0.5, 0.0]
    lw = linear_hat_weights(srgb_log_response(256, 3))
    assert lw.shape == (3, 256) and lw[:, 0].max() == 0 and lw[:, -1].max() == 0
    # linear values below 1 % of full scale (sRGB code < 25) get no weight
    assert lw[0, 24] == 0 and lw[0, 30] > 0


def _synthetic_stack(n_pix=400, frames=6, seed=0, noise=0.0):
    """Codes of random radiances through a known non-sRGB curve (gamma 2.6 with an offset)."""
    rng = np.random.default_rng(seed)
    ln_e = rng.uniform(np.log(1e-3), np.log(2.0), n_pix)
    lnh = np.log(2.0) * np.arange(frames) - 3.0
    x = np.exp(ln_e[:, None] + lnh[None, :])  # linear exposure
    x = x * np.exp(noise * rng.standard_normal(x.shape))
    true_curve = lambda v: 0.03 + 0.97 * np.clip(v, 0, 1) ** (1 / 2.6)  # noqa: E731
    codes = np.clip(np.round(true_curve(x) * 255), 0, 255).astype(np.int64)
    return codes, lnh, true_curve


def test_debevec_recovers_a_known_curve():
    codes, lnh, true_curve = _synthetic_stack()
    g, ln_e = solve_response_Debevec1997(codes, lnh, 256, hat_weights(256), smoothness=2.0)
    # Compare with the true inverse curve up to the global constant, over well-exposed codes.
    z = np.arange(40, 240)
    inv = np.log(((z / 255 - 0.03) / 0.97) ** 2.6)
    d = g[z] - inv
    assert np.abs(d - np.median(d)).max() < 0.03
    assert g[128] == pytest.approx(0.0, abs=1e-9)  # anchored at the middle code
    assert ln_e.shape == (codes.shape[0],)


def test_recover_response_weights_and_errors():
    codes, lnh, _ = _synthetic_stack(noise=0.01)
    curve = recover_response(codes[:, :, None].repeat(3, axis=2), lnh, 256, "debevec", smoothness=4.0)
    assert curve.log_response.shape == (3, 256) and curve.levels == 256
    assert curve.level_weight[:, 0].max() == 0 and curve.level_weight[:, -1].max() == 0
    assert np.all(np.diff(curve.log_response[0, 60:230]) > 0)  # monotone where data exist
    with pytest.raises(DamcapError, match="--response must be debevec or srgb"):
        recover_response(codes[:, :, None], lnh, 256, "gamma")
    with pytest.raises(DamcapError, match="at least 2"):
        recover_response(codes[:, :1, None], lnh[:1], 256, "srgb")


def test_level_weights_follow_residual_variance():
    codes = np.repeat(np.arange(256), 50)
    rng = np.random.default_rng(1)
    sd = np.where(codes < 128, 0.3, 0.03)
    w = level_weights_from_residuals(codes, sd * rng.standard_normal(codes.size), 256)
    assert w[200] > 20 * w[60]  # 10x smaller noise -> ~100x larger weight
    assert w[0] == w[255] == 0


def test_sample_pixels_prefers_flat_regions():
    img = np.zeros((2, 64, 64, 3), np.uint16)
    img[:, :, :32] = 50
    img[:, :, 32:] = 200
    img[:, ::2, 31:33] = 0  # a jagged edge
    rows, cols = sample_pixels_for_response(img, 100, 0.5)
    assert len(rows) == 100
    assert not np.any((cols >= 30) & (cols <= 33))  # the Sobel footprint of the edge
    assert (cols < 30).sum() > 30 and (cols > 33).sum() > 30  # both brightness levels represented


def test_sample_phases_are_other_samples_of_the_same_pixels():
    rng = np.random.default_rng(0)
    img = np.repeat(rng.integers(1, 255, (1, 40, 40, 1)), 3, axis=-1).repeat(2, axis=0).astype(np.uint16)
    base = set(zip(*sample_pixels_for_response(img, 50, 1.0)))
    shifted = set(zip(*sample_pixels_for_response(img, 50, 1.0, phase=0.5)))
    assert len(base) == len(shifted) == 50
    assert base != shifted  # another sample
    again = set(zip(*sample_pixels_for_response(img, 50, 1.0, phase=0.0)))
    assert again == base  # phase 0 is the default sample

