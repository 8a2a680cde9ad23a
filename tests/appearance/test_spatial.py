"""The spatial factor's sparse voxel texture against closed-form references."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.appearance.spatial import (
    LOG_ALBEDO_RANGE, SpatialAlbedo, albedo_at, corner_lookup, estimate_spatial_albedo, log_albedo_at, log_ratio, pack_keys,
    pixel_footprint_world, trilinear_corners,
)
from damcap.common.errors import DamcapError


def _plane_points(n: int = 200, size: float = 1.0, seed: int = 0) -> np.ndarray:
    """(n*n, 3) jittered points on the z = 0.3 plane."""
    rng = np.random.default_rng(seed)
    u = (np.arange(n) + 0.5) / n * size
    x, y = np.meshgrid(u, u)
    p = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.3)], -1)
    return p + rng.uniform(-0.2, 0.2, size=p.shape) * size / n * np.array([1, 1, 0])


def test_trilinear_weights_sum_to_one_and_reproduce_a_linear_function():
    rng = np.random.default_rng(1)
    p = rng.uniform(0.1, 0.9, size=(500, 3))
    origin, h = np.zeros(3), 0.125
    keys, w = trilinear_corners(p, origin, h)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-12)
    # unpack the keys to corner positions: the weighted corners are the point itself
    mask = (1 << 21) - 1
    ijk = np.stack([keys >> 42, (keys >> 21) & mask, keys & mask], -1)
    np.testing.assert_allclose(np.einsum("nk,nkc->nc", w, ijk * h), p, atol=1e-12)


def test_pack_keys_orders_like_the_index_triples():
    ijk = np.array([[0, 0, 0], [0, 0, 5], [0, 3, 0], [2, 0, 0], [2, 0, 1]])
    assert (np.diff(pack_keys(ijk)) > 0).all()


def test_estimate_recovers_a_smooth_pattern_on_a_surface():
    """Log ratios that vary slowly over a plane: the texture gives them back (less their median)."""
    p = _plane_points()
    pattern = lambda q: np.stack([0.4 * np.sin(2 * np.pi * q[:, 0]), 0.2 * np.cos(2 * np.pi * q[:, 1]), 0.1 * q[:, 0]], -1)  # noqa: E731
    sa = estimate_spatial_albedo(p, pattern(p), np.ones(len(p)), voxel_size=0.02, prior=0.0)
    assert sa.problem() is None
    q = _plane_points(n=37, seed=5)
    la, found = log_albedo_at(sa, q)
    assert found.all()
    shift = np.median(pattern(p), axis=0)  # the texture is centred on the median corner
    np.testing.assert_allclose(la, pattern(q) - shift, atol=0.02)
    np.testing.assert_allclose(albedo_at(sa, q), np.exp(la), rtol=1e-6)


def test_ridge_prior_shrinks_a_corner_by_its_weight():
    """Two pixels exactly on two corners (weight 1 each), log ratios +1 and -1: l = r / (1 + prior)."""
    p = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    r = np.array([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]])
    for prior in (0.0, 0.5, 3.0):
        sa = estimate_spatial_albedo(p, r, np.ones(2), voxel_size=1.0, prior=prior)
        la, found = log_albedo_at(sa, p)
        assert found.all()
        np.testing.assert_allclose(la[:, 0], [1 / (1 + prior), -1 / (1 + prior)], atol=1e-6)


def test_points_without_texture_get_albedo_one_and_missing_corners_are_dropped():
    sa = SpatialAlbedo(np.zeros(3), 1.0, pack_keys(np.array([[1, 1, 1]])), np.array([[0.5, 0.5, 0.5]], np.float32))
    far = np.array([[10.5, 10.5, 10.5]])
    assert (albedo_at(sa, far) == 1).all()
    # a point inside the voxel (0..1)^3 sees only corner (1, 1, 1): its value, whatever the weight
    idx, w, found = corner_lookup(sa, np.array([[0.2, 0.3, 0.9]]))
    assert found[0] and w.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(log_albedo_at(sa, np.array([[0.2, 0.3, 0.9]]))[0], [[0.5, 0.5, 0.5]], atol=1e-6)


def test_pixel_footprint_of_a_plane_seen_head_on():
    h, w, step = 20, 30, 0.01
    i, j = np.mgrid[0:h, 0:w]
    pos = np.stack([j * step, i * step, np.ones((h, w))], -1).astype(np.float32)
    cov = np.ones((h, w), np.float32)
    assert pixel_footprint_world(pos, cov) == pytest.approx(step, rel=1e-5)
    assert pixel_footprint_world(pos, np.zeros((h, w))) is None


def test_log_ratio_floors_black_pixels():
    r = log_ratio(np.array([[0.0, 1.0, 4.0]]), np.array([[1.0, 1.0, 1.0]]), floor=0.01)
    np.testing.assert_allclose(r, [[np.log(0.01), 0.0, np.log(4.0)]])


def test_estimate_clips_to_the_stored_range_and_refuses_bad_input():
    p = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    r = np.array([[50.0] * 3, [0.0] * 3, [-50.0] * 3])
    sa = estimate_spatial_albedo(p, r, np.ones(3), voxel_size=1.0, prior=0.0)
    lo, hi = LOG_ALBEDO_RANGE
    assert sa.log_albedo.min() >= lo and sa.log_albedo.max() <= hi
    with pytest.raises(DamcapError, match="too small"):
        estimate_spatial_albedo(np.array([[0.0, 0, 0], [1e3, 0, 0]]), np.zeros((2, 3)), np.ones(2), voxel_size=1e-6, prior=0.0)
    with pytest.raises(DamcapError, match="no training pixels"):
        estimate_spatial_albedo(np.zeros((0, 3)), np.zeros((0, 3)), np.ones(0), voxel_size=1.0, prior=0.0)


@pytest.mark.parametrize("change, needle", [
    (dict(keys=np.array([5, 3], np.int64)), "sorted"),
    (dict(log_albedo=np.array([[0, 0, 0], [99, 0, 0]], np.float32)), "outside"),
    (dict(log_albedo=np.array([[0, 0, 0], [np.nan, 0, 0]], np.float32)), "NaN"),
    (dict(voxel_size=0.0), "voxel size"),
    (dict(origin_world=np.zeros(2)), "origin"),
])
def test_problem_names_what_is_wrong(change, needle):
    base = dict(origin_world=np.zeros(3), voxel_size=1.0, keys=np.array([3, 5], np.int64), log_albedo=np.zeros((2, 3), np.float32))
    assert needle in SpatialAlbedo(**{**base, **change}).problem()
    assert SpatialAlbedo(**base).problem() is None
