"""The spatial factor of a DAM: an RGB albedo texture on the object's surface (pure).

A DAM maps (view, normal) to radiance, so it cannot place a dark tarnish patch, print or an
embossed dot: on a real object those are what the photos are made of (on the real cape a
2-pixel blur of the photo itself already scores DSSIM 0.34; bench/reconstruct.md). The spatial
factor multiplies the DAM's radiance by a per-surface-point albedo a(p) = exp(l(p)) (RGB):

    radiance(p, v, n) = D(v, n) * exp(l(p))

Storage: l is kept at the corners of the voxels that training pixels touch (a sparse grid in
world units; the voxel edge is a fraction of a pixel's footprint on the surface, so the texture
has the photos' own resolution) and interpolated trilinearly over the corners that exist (the
weights of missing corners are dropped and the rest renormalised; a point with no stored corner
gets l = 0, albedo 1). Corners are addressed by one int64 key, 21 bits per axis.

Estimation (closed form, given the DAM D): each corner's l is the ridge-regularised weighted
mean of the log ratios r_i = log(y_i / D(v_i, n_i)) of the training pixels around it,

    l_k = sum_i w_ik r_i / (sum_i w_ik + prior),

the minimiser of sum_i w_ik (r_i - l_k)^2 + prior l_k^2 (w_ik: pixel i's trilinear weight at
corner k; the prior pulls sparsely observed corners toward albedo 1), then shifted so that the
median over observed corners is 0 per channel (the DAM keeps the object's overall colour).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from damcap.common.errors import DamcapError

KEY_BITS = 21
"""bits per axis of a corner key (three axes in one int64)"""
MAX_CELLS = (1 << KEY_BITS) - 2
"""most voxels along an axis"""
LOG_ALBEDO_RANGE = (-12.0, 6.0)
"""the log albedo a fit may store (albedo e^-12 .. e^6); a file outside it is refused"""
_CORNER_OFFSETS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.int64)


@dataclass(frozen=True)
class SpatialAlbedo:
    """A sparse voxel texture of log albedo (see the module docstring)."""

    origin_world: np.ndarray
    """(3,) float64 world position of corner (0, 0, 0)"""
    voxel_size: float
    """voxel edge, world units"""
    keys: np.ndarray
    """(M,) int64 sorted, unique corner keys (:func:`pack_keys`)"""
    log_albedo: np.ndarray
    """(M, 3) float32 natural log of the RGB albedo at each corner"""

    def problem(self) -> str | None:
        """Why these arrays cannot be a spatial factor (None when they can)."""
        la = self.log_albedo
        grid = grid_problem(self.origin_world, self.voxel_size, self.keys, la, "log albedo")
        if grid:
            return grid
        lo, hi = LOG_ALBEDO_RANGE
        if la.size and (la.min() < lo or la.max() > hi):
            return f"log albedo {float(la.min()):.3g}..{float(la.max()):.3g} lies outside [{lo}, {hi}]"
        return None


def grid_problem(origin_world: np.ndarray, voxel_size: float, keys: np.ndarray, values: np.ndarray, what: str) -> str | None:
    """Why arrays cannot be a sparse corner grid (this module's, or :class:`.normal_field.NormalField`'s):
    origin, voxel size, (M,) keys sorted, unique and in range, (M, 3) finite ``values`` (named
    ``what`` in the message). None when they can."""
    o, k = origin_world, keys
    if o.shape != (3,) or not np.isfinite(o).all():
        return f"origin must be 3 finite numbers, got shape {o.shape}"
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        return f"voxel size must be positive and finite, got {voxel_size!r}"
    if k.ndim != 1 or values.shape != (k.shape[0], 3):
        return f"keys {k.shape} and {what} {values.shape} must be (M,) and (M, 3)"
    if k.size and (k.min() < 0 or k.max() >= 1 << (3 * KEY_BITS) or (np.diff(k) <= 0).any()):
        return "corner keys must be sorted, unique and within 63 bits"
    if not np.isfinite(values).all():
        return f"{what} contains NaN or inf"
    return None


def pack_keys(ijk: np.ndarray) -> np.ndarray:
    """(..., 3) non-negative int64 corner indices -> (...,) int64 keys (i, j, k in 21 bits each).

    >>> pack_keys(np.array([[0, 0, 1], [1, 0, 0]])).tolist()
    [1, 4398046511104]
    """
    ijk = np.asarray(ijk, np.int64)
    return (ijk[..., 0] << (2 * KEY_BITS)) | (ijk[..., 1] << KEY_BITS) | ijk[..., 2]


def trilinear_corners(points_world: np.ndarray, origin_world: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """The 8 voxel corners around each point and their trilinear weights.

    Args:
        points_world: (N, 3) positions.
        origin_world: (3,) corner (0, 0, 0).
        voxel_size: voxel edge, world units.

    Returns:
        keys (N, 8) int64 (-1 where a corner lies outside the key range) and weights (N, 8)
        float64 summing to 1 per point.

    >>> k, w = trilinear_corners(np.array([[0.25, 0.0, 0.0]]), np.zeros(3), 1.0)
    >>> w[0][w[0] > 0].round(2).tolist()
    [0.75, 0.25]
    """
    g = (np.asarray(points_world, np.float64) - origin_world) / voxel_size
    i0 = np.floor(g).astype(np.int64)
    f = g - i0
    ijk = i0[:, None, :] + _CORNER_OFFSETS[None]
    w = np.prod(np.where(_CORNER_OFFSETS[None] == 1, f[:, None, :], 1.0 - f[:, None, :]), axis=-1)
    inside = ((ijk >= 0) & (ijk <= MAX_CELLS + 1)).all(-1)
    return np.where(inside, pack_keys(np.clip(ijk, 0, MAX_CELLS + 1)), -1), w


def corner_lookup(sa: SpatialAlbedo, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which stored corners each point interpolates, with renormalised weights.

    Returns:
        index (N, 8) into ``sa.keys`` (0 where missing), weight (N, 8) float64 (0 where missing,
        rows summing to 1 where any corner exists) and found (N,) bool (some corner exists).
    """
    keys, w = trilinear_corners(points_world, sa.origin_world, sa.voxel_size)
    if sa.keys.size == 0:
        return np.zeros(keys.shape, np.int64), np.zeros_like(w), np.zeros(len(keys), bool)
    idx = np.clip(np.searchsorted(sa.keys, keys), 0, sa.keys.size - 1)
    present = (sa.keys[idx] == keys) & (keys >= 0)
    w = np.where(present, w, 0.0)
    total = w.sum(1, keepdims=True)
    found = total[:, 0] > 0
    return np.where(present, idx, 0), np.where(found[:, None], w / np.maximum(total, 1e-300), 0.0), found


def log_albedo_at(sa: SpatialAlbedo, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interpolated log albedo (N, 3) float32 (0 where no corner is stored) and found (N,) bool."""
    idx, w, found = corner_lookup(sa, points_world)
    la = np.einsum("nk,nkc->nc", w, sa.log_albedo[idx].astype(np.float64))
    return la.astype(np.float32), found


def albedo_at(sa: SpatialAlbedo, points_world: np.ndarray) -> np.ndarray:
    """(N, 3) float32 RGB albedo factor exp(l(p)) (1 where no corner is stored)."""
    return np.exp(log_albedo_at(sa, points_world)[0])


def pixel_footprint_world(position_world: np.ndarray, coverage: np.ndarray, threshold: float = 0.5) -> float | None:
    """Median distance between the surface points of horizontally or vertically adjacent
    foreground pixels: the size of one pixel on the surface, world units.

    Args:
        position_world: (H, W, 3) per-pixel surface points.
        coverage: (H, W) coverage; both pixels of a pair above ``threshold``.

    Returns:
        the median spacing, or None when no two adjacent pixels are foreground.
    """
    fg = coverage > threshold
    gaps = []
    for axis in (0, 1):
        both = np.logical_and(np.delete(fg, -1, axis), np.delete(fg, 0, axis))
        d = np.linalg.norm(np.diff(position_world, axis=axis), axis=-1)
        gaps.append(d[both])
    gaps_all = np.concatenate(gaps)
    gaps_all = gaps_all[np.isfinite(gaps_all) & (gaps_all > 0)]
    return float(np.median(gaps_all)) if gaps_all.size else None


def log_ratio(radiance_lin: np.ndarray, predicted_lin: np.ndarray, floor: float) -> np.ndarray:
    """r = log(max(y, floor) / max(D, floor)), (N, 3) float64: what the albedo must explain.

    >>> log_ratio(np.array([[2.0, 1.0, 0.0]]), np.array([[1.0, 1.0, 1.0]]), 0.5).round(3).tolist()
    [[0.693, 0.0, -0.693]]
    """
    y = np.maximum(np.asarray(radiance_lin, np.float64), floor)
    d = np.maximum(np.asarray(predicted_lin, np.float64), floor)
    return np.log(y) - np.log(d)


def estimate_spatial_albedo(points_world: np.ndarray, log_ratio_rgb: np.ndarray, weight: np.ndarray, voxel_size: float,
                            prior: float) -> SpatialAlbedo:
    """The closed-form spatial factor of the module docstring.

    Args:
        points_world: (N, 3) training pixels' surface points.
        log_ratio_rgb: (N, 3) log(radiance / DAM) per pixel (:func:`log_ratio`).
        weight: (N,) per-pixel data weights (>= 0).
        voxel_size: voxel edge, world units.
        prior: ridge strength (in units of one pixel's total weight) pulling l toward 0.

    Raises:
        DamcapError: no pixels, or a voxel too small for the points' extent.
    """
    p = np.asarray(points_world, np.float64)
    if len(p) == 0:
        raise DamcapError("no training pixels to estimate the spatial factor from")
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise DamcapError(f"the spatial factor's voxel size must be positive, got {voxel_size!r}")
    lo, hi = p.min(0), p.max(0)
    if float(((hi - lo) / voxel_size).max()) > MAX_CELLS - 4:
        raise DamcapError(f"a spatial voxel of {voxel_size:.3g} world units is too small for an object {float((hi - lo).max()):.3g} "
                          f"across (at most {MAX_CELLS - 4} voxels per axis); raise --spatial-voxel-px")
    origin = lo - voxel_size
    keys8, w8 = trilinear_corners(p, origin, voxel_size)
    w8 = w8 * np.asarray(weight, np.float64)[:, None]
    keys, inverse = np.unique(keys8.ravel(), return_inverse=True)
    den = np.bincount(inverse, weights=w8.ravel(), minlength=keys.size)
    r = np.asarray(log_ratio_rgb, np.float64)
    num = np.stack([np.bincount(inverse, weights=(w8 * r[:, c:c + 1]).ravel(), minlength=keys.size) for c in range(3)], -1)
    keep = den > 0
    la = num[keep] / (den[keep, None] + prior)
    if la.size:
        la -= np.median(la, axis=0)
    la = np.clip(la, *LOG_ALBEDO_RANGE).astype(np.float32)
    return SpatialAlbedo(origin, float(voxel_size), keys[keep].astype(np.int64), la)
