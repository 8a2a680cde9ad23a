"""Merging a bracket into one radiance map: pure array math, no files.

Two estimators:

- LDR frames (8/16-bit codes through a response curve): the weighted mean of the per-frame log
  radiance estimates ``g(z_ij) - ln H_j`` (Debevec & Malik 1997, Eq. 6), with per-code
  reliabilities as weights (:mod:`damcap.capture.response`).
- RAW frames (counts proportional to light): the Poisson maximum-likelihood estimate
  ``E = sum_j c_j / sum_j H_j`` over the frames where the photosite is not saturated. For photon
  counts ``c_j ~ Poisson(E H_j)`` this is the minimum-variance unbiased estimator, and it needs
  no weighting function.

A pixel that is saturated in every frame cannot be measured: it gets the lower bound from the
shortest exposure and is flagged in ``clipped`` (never silently invented).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from damcap.common.errors import DamcapError


@dataclass
class MergeResult:
    """A merged radiance map and where it could not be measured."""

    radiance_lin: np.ndarray
    """(H, W, C) float32, linear, relative to the reference exposure, >= 0 where measured."""
    clipped: np.ndarray
    """(H, W, C) bool: saturated in every frame (value is a lower bound)."""


def merge_ldr(
    level_codes: np.ndarray,
    log_exposures: np.ndarray,
    log_response: np.ndarray,
    level_weight: np.ndarray,
) -> MergeResult:
    """Merge LDR frames through a response curve (Debevec & Malik 1997, Eq. 6).

    ``ln E = sum_j w(z_j) (g(z_j) - ln H_j) / sum_j w(z_j)``. Where every frame has weight 0: if
    some frame is at the top code the pixel is clipped (value ``exp(g(top)) / H_shortest``, a lower
    bound); otherwise it is black in every frame and gets 0.

    Args:
        level_codes: (P, H, W, C) int code values in [0, L), P >= 2 frames.
        log_exposures: (P,) float, ln H_j of each frame relative to the reference exposure.
        log_response: (C, L) float, g(z) per channel.
        level_weight: (C, L) float >= 0, reliability per code.

    Returns:
        :class:`MergeResult` with (H, W, C) arrays.

    Raises:
        DamcapError: fewer than 2 frames, or shapes that do not match.
    """
    codes = np.asarray(level_codes)
    if codes.ndim != 4 or codes.shape[0] < 2:
        raise DamcapError(f"merging needs a (P, H, W, C) stack of at least 2 frames, got shape {codes.shape}")
    p, h, w, c = codes.shape
    g = np.asarray(log_response, dtype=np.float64)
    wt = np.asarray(level_weight, dtype=np.float64)
    lnh = np.asarray(log_exposures, dtype=np.float64)
    if g.shape != wt.shape or g.shape[0] != c or lnh.shape != (p,):
        raise DamcapError(f"response {g.shape}, weights {wt.shape} and exposures {lnh.shape} do not fit a stack {codes.shape}")
    levels = g.shape[1]
    top = levels - 1
    offsets = (np.arange(c, dtype=np.int64) * levels)[None, None, :]
    g_flat = g.astype(np.float32).ravel()
    w_flat = wt.astype(np.float32).ravel()
    num = np.zeros((h, w, c), np.float32)
    den = np.zeros((h, w, c), np.float32)
    short = np.full((h, w, c), np.inf, np.float32)
    for j in range(p):
        z = codes[j]
        idx = z.astype(np.int64) + offsets
        wj = w_flat[idx]
        num += wj * (g_flat[idx] - np.float32(lnh[j]))
        den += wj
        np.minimum(short, np.where(z >= top, np.float32(lnh[j]), np.float32(np.inf)), out=short)
    at_top = np.isfinite(short)
    measured = den > 0
    ln_e = np.where(measured, num / np.where(measured, den, 1.0), 0.0)
    radiance = np.where(measured, np.exp(ln_e), 0.0)
    clipped = ~measured & at_top
    bound = np.exp(g[:, top][None, None, :] - np.where(at_top, short, 0.0))
    radiance = np.where(clipped, bound, radiance)
    return MergeResult(radiance_lin=radiance.astype(np.float32), clipped=clipped)


@dataclass
class PoissonAccumulator:
    """Running sums of the Poisson-optimal merge, one frame at a time (bounded memory).

    ``add`` each frame's counts; ``result`` gives ``sum c_j / sum H_j`` over unsaturated samples.
    """

    shape: tuple[int, ...]
    counts_sum: np.ndarray = field(init=False)
    exposure_sum: np.ndarray = field(init=False)
    bound: np.ndarray = field(init=False)
    shortest_saturated: np.ndarray = field(init=False)
    frames: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self.counts_sum = np.zeros(self.shape, np.float64)
        self.exposure_sum = np.zeros(self.shape, np.float64)
        self.bound = np.zeros(self.shape, np.float64)
        self.shortest_saturated = np.full(self.shape, np.inf)

    def add(self, counts: np.ndarray, exposure: float, saturated: np.ndarray, valid: np.ndarray | None = None) -> None:
        """Add one frame.

        Args:
            counts: (...) float, signal proportional to light (black level removed), any scale
                shared by all frames; may be slightly negative from noise.
            exposure: H_j > 0 of the frame.
            saturated: (...) bool, True where the sample is clipped.
            valid: (...) bool, False where the frame has no data (e.g. shifted-in borders).
        """
        if counts.shape != self.shape or saturated.shape != self.shape:
            raise DamcapError(f"frame of shape {counts.shape} does not match the bracket's {self.shape}")
        if not (np.isfinite(exposure) and exposure > 0):
            raise DamcapError(f"exposure must be a positive number, got {exposure!r}")
        use = ~saturated if valid is None else (~saturated & valid)
        self.counts_sum += np.where(use, counts, 0.0)
        self.exposure_sum += np.where(use, exposure, 0.0)
        sat = saturated if valid is None else (saturated & valid)
        newer = sat & (exposure < self.shortest_saturated)
        self.bound = np.where(newer, counts / exposure, self.bound)
        self.shortest_saturated = np.where(newer, exposure, self.shortest_saturated)
        self.frames += 1

    def result(self) -> MergeResult:
        """The merged map (float32) and the clipped flags (saturated wherever a frame had data)."""
        measured = self.exposure_sum > 0
        radiance = np.where(measured, self.counts_sum / np.where(measured, self.exposure_sum, 1.0), 0.0)
        clipped = ~measured & np.isfinite(self.shortest_saturated)
        radiance = np.where(clipped, self.bound, radiance)
        if radiance.ndim == 2:
            return MergeResult(radiance_lin=radiance.astype(np.float32)[..., None], clipped=clipped[..., None])
        return MergeResult(radiance_lin=radiance.astype(np.float32), clipped=clipped)


def merge_poisson(counts: np.ndarray, exposures: np.ndarray, saturated: np.ndarray) -> MergeResult:
    """Poisson-optimal merge of linear frames: ``sum_j c_j / sum_j H_j`` over unsaturated samples.

    Args:
        counts: (P, H, W) or (P, H, W, C) float, linear signal with the black level removed.
        exposures: (P,) float, H_j > 0.
        saturated: same shape as ``counts``, bool.

    Returns:
        :class:`MergeResult` with (H, W, C) arrays (C = 1 for mosaics).

    Raises:
        DamcapError: fewer than 2 frames or mismatched shapes.

    >>> c = np.array([[[0.2]], [[0.8]], [[1.0]]]); t = np.array([1.0, 4.0, 16.0])
    >>> r = merge_poisson(c, t, c >= 1.0)
    >>> round(float(r.radiance_lin[0, 0, 0]), 4), bool(r.clipped.any())
    (0.2, False)
    """
    counts = np.asarray(counts)
    exposures = np.asarray(exposures, dtype=np.float64)
    if counts.shape[0] < 2 or exposures.shape != (counts.shape[0],):
        raise DamcapError(f"merging needs at least 2 frames with one exposure each; got {counts.shape[0]} frame(s), "
                          f"{exposures.shape[0]} exposure(s)")
    acc = PoissonAccumulator(counts.shape[1:])
    for j in range(counts.shape[0]):
        acc.add(counts[j], float(exposures[j]), np.asarray(saturated[j], dtype=bool))
    return acc.result()
