"""appearance.coverage: the training normals' histogram and the share of a new shape it does not cover."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.appearance.coverage import (NORMAL_BINS, OBSERVED_SHARE, direction_bins, fibonacci_directions, normal_histogram,
                                        observed_directions, unobserved_share)


def _uniform_sphere(n: int, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_lattice_directions_fall_in_their_own_bins_and_bins_are_about_equal_area():
    d = fibonacci_directions(NORMAL_BINS)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    assert direction_bins(d).tolist() == list(range(NORMAL_BINS))
    many = _uniform_sphere(1000).reshape(10, 100, 3)
    np.testing.assert_array_equal(direction_bins(many, chunk=7), np.argmax(many @ d.T, -1))  # in chunks as at once, any shape
    # uniform normals land about evenly: each bin within 40 % of the uniform share (4 * pi / k of solid angle each)
    counts = normal_histogram(_uniform_sphere(200_000))
    assert counts.sum() == 200_000 and 0.6 < counts.min() / counts.mean() and counts.max() / counts.mean() < 1.4


def test_a_hemisphere_of_training_normals_leaves_half_a_sphere_unobserved():
    """Training normals on the upper hemisphere (y > 0) only: up to half of a sphere's pixels (the
    lower hemisphere less the bins straddling the equator, which the upper half observes) face
    unobserved directions; an upper cap none; the sphere's own normals none."""
    sphere = _uniform_sphere(100_000, seed=1)
    upper = sphere[sphere[:, 1] > 0]
    hist = normal_histogram(upper)
    assert 0.4 < unobserved_share(hist, normal_histogram(sphere)) <= 0.5  # measured 0.442
    assert unobserved_share(hist, normal_histogram(sphere[sphere[:, 1] > 0.3])) == 0.0
    assert unobserved_share(normal_histogram(sphere), normal_histogram(sphere)) == 0.0
    assert unobserved_share(hist, np.zeros(NORMAL_BINS)) is None
    with pytest.raises(ValueError):
        unobserved_share(hist, np.zeros(NORMAL_BINS // 2))


def test_a_handful_of_stray_pixels_does_not_make_a_direction_observed():
    """A direction counts as observed from OBSERVED_SHARE of an even share of the pixels on: a few
    mislabelled pixels facing down do not vouch for the material's look there."""
    up = np.tile([0.0, 1.0, 0.0], (100_000, 1))
    down = np.tile([0.0, -1.0, 0.0], (3, 1))
    hist = normal_histogram(np.concatenate([up, down]))
    down_bin = direction_bins(down[0])
    assert hist[down_bin] == 3 < OBSERVED_SHARE * hist.sum() / NORMAL_BINS
    assert not observed_directions(hist)[down_bin] and observed_directions(hist)[direction_bins(up[0])]
    assert unobserved_share(hist, normal_histogram(down)) == 1.0
    # weights count as pixels: the same down pixels weighted up become observed
    heavy = normal_histogram(np.concatenate([up, down]), np.concatenate([np.ones(100_000), np.full(3, 100.0)]))
    assert observed_directions(heavy)[down_bin]
    assert not observed_directions(np.zeros(8)).any()
