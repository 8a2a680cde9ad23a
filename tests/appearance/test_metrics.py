"""DSSIM against hand-computed values (docs/capture-format.md convention)."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.appearance.metrics import dssim, normalise_pair

C1, C2 = 0.01**2, 0.03**2


def test_constant_images_match_closed_form():
    # Constant reference a and prediction b: sigma terms vanish, SSIM = (2 mu1 mu2 + C1) / (mu1^2 + mu2^2 + C1)
    # after both are scaled so the reference's 95th percentile is 1: mu1 = 1, mu2 = b / a.
    a, b = 3.0, 1.5
    ref = np.full((20, 20, 3), a)
    pred = np.full((20, 20, 3), b)
    r = b / a
    ssim = (2 * r + C1) / (1 + r * r + C1)
    assert dssim(ref, pred, np.ones((20, 20))) == pytest.approx((1 - ssim) / 2, rel=1e-6)  # images are float32 after normalisation


def test_clipping_makes_overshoot_free():
    ref = np.full((16, 16, 3), 2.0)
    assert dssim(ref, ref * 5, np.ones((16, 16))) == pytest.approx(0.0, abs=1e-8)


def test_only_foreground_centres_count():
    # Reference and prediction agree on the foreground; the background differs wildly but is
    # zeroed in both. The centre-foreground average must be 0.
    ref = np.zeros((24, 24, 3))
    pred = np.full((24, 24, 3), 7.0)
    cov = np.zeros((24, 24))
    cov[6:18, 6:18] = 1.0
    ref[cov > 0.5] = 1.0
    pred[cov > 0.5] = 1.0
    assert dssim(ref, pred, cov) == pytest.approx(0.0, abs=1e-8)


def test_window_sees_the_neighbourhood():
    # A single wrong pixel affects SSIM within the 11x11 window only.
    rng = np.random.default_rng(1)
    ref = rng.random((32, 32, 3)) + 0.5
    pred = ref.copy()
    pred[16, 16] *= 0.2
    d = dssim(ref, pred, np.ones((32, 32)))
    assert 1e-4 < d < 0.05


def test_normalisation_uses_reference_95th_percentile():
    ref = np.arange(100, dtype=float).reshape(10, 10, 1).repeat(3, -1)
    fg = np.ones((10, 10), bool)
    r, p = normalise_pair(ref, ref * 0.5, fg)
    p95 = np.percentile(ref, 95)
    np.testing.assert_allclose(r, np.clip(ref / p95, 0, 1), rtol=1e-6)
    np.testing.assert_allclose(p, np.clip(ref * 0.5 / p95, 0, 1), rtol=1e-6)


def test_empty_foreground_is_skipped_with_warning():
    with pytest.warns(UserWarning, match="without foreground"):
        assert dssim(np.ones((8, 8, 3)), np.ones((8, 8, 3)), np.zeros((8, 8))) is None


def test_black_reference_keeps_scale_one():
    ref = np.zeros((16, 16, 3))
    # kornia's eps = 1e-12 in the denominator gives 1 - C1 C2 / (C1 C2 + eps) ~ 1e-5
    assert dssim(ref, ref, np.ones((16, 16))) == pytest.approx(0.0, abs=2e-5)
