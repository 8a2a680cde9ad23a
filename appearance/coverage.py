"""Which world normals a capture showed a material at (pure).

A DAM is a function of (view, normal) in world space, learnt from the normals its training
photos show. Drawn on a new shape, it is an interpolation where the shape's normals are among
those and a guess where they are not. A ``.dam`` file records the histogram of its training
normals over a fixed set of directions (:func:`normal_histogram`); ``damcap export`` reports
the share of each material's pixels whose normal falls in a direction the capture did not show
(:func:`unobserved_share`) and warns when it is large.

Measured on ``make demo``'s segmentation (16 train views, 256 directions, each training pixel
counted for the material it is assigned to) against the path-traced truth of its torus
(bench/export_truth.md, *normals the capture did not show*): 15 % of the torus's aluminium pixels
face directions the capture did not show aluminium at, and their mean absolute error is 2.8x
that of the others (0.42 against 0.15; a third of the region's error); gold's and red plastic's
shares are 2 % and 1 %. With ``segment --seed 1`` aluminium's share was 15 % again and its error
3.1x (a throwaway script, 2026-11-27).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from damcap.appearance.pixels import PixelSamples

#: directions of the histogram (a Fibonacci lattice: bins of about 12.7 deg)
NORMAL_BINS = 256

OBSERVED_SHARE = 0.05
"""a direction counts as observed when it holds at least this fraction of a uniform share of
the training pixels (1 / bins of them): fewer is a handful of stray pixels"""

UNOBSERVED_WARNING = 0.05
"""``damcap export`` warns when more than this share of a material's pixels face unobserved
directions"""


def fibonacci_directions(k: int) -> np.ndarray:
    """(k, 3) float64 unit vectors spread almost evenly over the sphere (a Fibonacci lattice,
    +y is the lattice's pole).

    >>> d = fibonacci_directions(4)
    >>> d.shape, bool(np.allclose(np.linalg.norm(d, axis=1), 1))
    ((4, 3), True)
    """
    i = np.arange(k) + 0.5
    polar = np.arccos(1 - 2 * i / k)
    azimuth = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.cos(polar), np.sin(azimuth) * np.sin(polar)], 1)


def direction_bins(direction_world: np.ndarray, k: int = NORMAL_BINS, chunk: int = 1 << 15) -> np.ndarray:
    """(...,) int64 index of the lattice direction nearest to each of (..., 3) unit vectors.

    >>> direction_bins(fibonacci_directions(16)[[3, 7]], 16).tolist()
    [3, 7]
    """
    d = np.asarray(direction_world, np.float64)
    flat, lattice = d.reshape(-1, 3), fibonacci_directions(k).T
    out = np.empty(len(flat), np.int64)
    for s in range(0, len(flat), chunk):  # (chunk, k) scores at a time: a capture's pixels would need gigabytes at once
        out[s:s + chunk] = np.argmax(flat[s:s + chunk] @ lattice, 1)
    return out.reshape(d.shape[:-1])


def normal_histogram(normal_world: np.ndarray, weight: np.ndarray | None = None, k: int = NORMAL_BINS) -> np.ndarray:
    """(k,) float64 summed weight of the training pixels per lattice direction.

    Args:
        normal_world: (N, 3) unit normals of the training pixels.
        weight: (N,) their weights (coverage, a material's share), None = 1 each.
        k: directions.

    >>> float(normal_histogram(np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]]), k=8).sum())
    2.0
    """
    w = np.ones(len(normal_world)) if weight is None else np.asarray(weight, np.float64).reshape(-1)
    return np.bincount(direction_bins(np.asarray(normal_world).reshape(-1, 3), k), weights=w, minlength=k).astype(np.float64)


def training_normal_histogram(samples: PixelSamples, k: int = NORMAL_BINS) -> np.ndarray:
    """(k,) :func:`normal_histogram` of a fit's training samples, weighted by their weights."""
    return normal_histogram(samples.normal_world.numpy(), samples.weight.numpy(), k)


def observed_directions(histogram: np.ndarray) -> np.ndarray:
    """(k,) bool: the directions holding at least ``OBSERVED_SHARE`` of a uniform share of the
    histogram's total (all False for an empty histogram).

    >>> observed_directions(np.array([100.0, 1.0, 0.0, 99.0])).tolist()
    [True, False, False, True]
    """
    h = np.asarray(histogram, np.float64)
    total = h.sum()
    return h >= OBSERVED_SHARE * total / len(h) if total > 0 else np.zeros(len(h), bool)


def observed_at(histogram: np.ndarray, normal_world: np.ndarray) -> np.ndarray:
    """(...,) bool: whether each of (..., 3) unit normals falls in a direction the histogram observed.

    >>> observed_at(normal_histogram(np.array([[0.0, 1.0, 0.0]]), k=64), np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])).tolist()
    [True, False]
    """
    return observed_directions(histogram)[direction_bins(normal_world, len(histogram))]


def unobserved_share(histogram: np.ndarray, shown: np.ndarray) -> float | None:
    """Share of a new shape's pixels whose normals fall in directions the model's training
    normals did not observe.

    Args:
        histogram: (k,) the model's training-normal histogram (:func:`normal_histogram`).
        shown: (k,) the histogram of the normals the new shape shows of that model (same k).

    Returns:
        a share in [0, 1], or None when ``shown`` is empty.

    >>> h = normal_histogram(np.array([[0.0, 1.0, 0.0]]), k=64)
    >>> unobserved_share(h, normal_histogram(np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]), k=64))
    0.5
    """
    shown = np.asarray(shown, np.float64)
    if len(shown) != len(histogram):
        raise ValueError(f"histograms of {len(histogram)} and {len(shown)} directions")
    total = shown.sum()
    return float(shown[~observed_directions(histogram)].sum() / total) if total > 0 else None
