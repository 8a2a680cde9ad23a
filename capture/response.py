"""Camera response curves: the sRGB curve as a response table and Debevec & Malik's recovery from a bracket.

The sRGB curve itself lives in :mod:`damcap.common.colour`.

A response curve here is a table ``log_response[c, z]``: the natural log of the (relative) linear
exposure ``X = E * H`` that produces code value ``z`` in channel ``c`` (Debevec & Malik 1997 call
it ``g(z) = ln f^-1(z)``). A companion table ``level_weight[c, z]`` is the reliability of a code
value, the inverse of the variance of ``g(z)`` as measured on the bracket itself, normalised to a
maximum of 1 (0 for the lowest and highest code: no information).

References:
    Debevec, Malik. Recovering High Dynamic Range Radiance Maps from Photographs. SIGGRAPH 1997.
    IEC 61966-2-1:1999 (sRGB).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from damcap.common.colour import srgb_to_linear
from damcap.common.errors import DamcapError

#: floor for linear values before ``log`` (the sRGB curve reaches 0 at code 0)
LOG_EPS = 1e-6


def srgb_log_response(levels: int, channels: int = 3, eps: float = LOG_EPS) -> np.ndarray:
    """The sRGB curve as a response table ``g(z) = ln(srgb_to_linear(z / (levels - 1)))``.

    Args:
        levels: number of code values (256 for 8-bit images).
        channels: number of channels C.
        eps: floor on the linear value before the log (code 0 has linear value 0).

    Returns:
        (C, levels) float64 log linear exposure; code levels-1 maps to 0 (linear 1).

    >>> float(srgb_log_response(256, 1)[0, 255])
    0.0
    """
    z = np.arange(levels) / (levels - 1)
    g = np.log(np.maximum(srgb_to_linear(z), eps))
    return np.repeat(g[None], channels, axis=0)


# --------------------------------------------------------------------------------------------
# Weights
# --------------------------------------------------------------------------------------------

def hat_weights(levels: int) -> np.ndarray:
    """Debevec & Malik's hat weighting on code values (1997, Eq. 4), scaled so the middle is 1.

    Args:
        levels: number of code values L.

    Returns:
        (L,) float64, 0 at the first and last code, 1 at the middle (1 - 1/(L-1) for even L).

    >>> hat_weights(5).tolist()
    [0.0, 0.5, 1.0, 0.5, 0.0]
    """
    z = np.arange(levels, dtype=np.float64)
    mid = (levels - 1) / 2
    return np.where(z <= mid, z, (levels - 1) - z) / mid


def linear_hat_weights(log_response: np.ndarray, low: float = 0.01, high: float = 0.99) -> np.ndarray:
    """Hat weighting applied to the linearised value (as colour-hdri's ``weighting_function_Debevec1997``).

    The linear value ``X = exp(g(z))`` is scaled so that the top usable code is 1; the weight rises
    from 0 at ``low`` to 1 at the middle of [low, high] and falls to 0 at ``high``. Codes whose
    linear value is below ``low`` (sensor floor, film fog) get no weight.

    Args:
        log_response: (C, L) response table.
        low: linear value with zero weight at the dark end, in [0, 0.5).
        high: linear value with zero weight at the bright end, in (0.5, 1].

    Returns:
        (C, L) float64 in [0, 1]; 0 at the first and last code.
    """
    g = np.asarray(log_response, dtype=np.float64)
    x = np.exp(g - g[:, -2:-1])
    mid = (low + high) / 2
    w = np.where(x <= mid, (x - low) / (mid - low), (high - x) / (high - mid))
    w = np.clip(w, 0.0, 1.0)
    w[:, 0] = 0.0
    w[:, -1] = 0.0
    return w


def level_weights_from_residuals(
    codes: np.ndarray,
    residuals: np.ndarray,
    levels: int,
    window: int = 9,
    prior_variance: float = 1e-2,
    min_variance: float = 1e-4,
) -> np.ndarray:
    """Reliability of each code value: inverse residual variance, smoothed over nearby codes.

    Iteratively reweighted least squares for the noise of ``g(z)``: the residual of an
    observation is ``g(z_ij) - ln E_i - ln H_j``; its variance per code is a local average over
    ``window`` codes, pulled toward ``prior_variance`` where few observations exist.

    Args:
        codes: (M,) int, code value of each observation, in [0, levels).
        residuals: (M,) float, log residual of each observation.
        levels: number of code values L.
        window: codes averaged together (odd, >= 1).
        prior_variance: variance assumed for a code with one observation's worth of prior.
        min_variance: floor on the variance (caps the weight of a code).

    Returns:
        (L,) float64 in [0, 1], peak 1; 0 at the first and last code.
    """
    codes = np.asarray(codes).reshape(-1)
    r2 = np.asarray(residuals, dtype=np.float64).reshape(-1) ** 2
    s2 = np.bincount(codes, r2, minlength=levels)[:levels]
    cnt = np.bincount(codes, minlength=levels)[:levels].astype(np.float64)
    k = np.ones(window)
    var = (np.convolve(s2, k, "same") + prior_variance) / (np.convolve(cnt, k, "same") + 1.0)
    w = 1.0 / np.maximum(var, min_variance)
    w[0] = 0.0
    w[-1] = 0.0
    return w / w.max()


# --------------------------------------------------------------------------------------------
# Debevec & Malik 1997
# --------------------------------------------------------------------------------------------

def solve_response_Debevec1997(
    codes: np.ndarray,
    log_exposures: np.ndarray,
    levels: int,
    data_weight: np.ndarray,
    smoothness: float = 12.0,
    anchor: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares response recovery of one channel (Debevec & Malik 1997, Eq. 3).

    Minimises ``sum_ij w(z_ij) (g(z_ij) - ln E_i - ln H_j)^2 + lam^2 sum_z (h(z) g''(z))^2`` with
    ``g(anchor) = 0``, where ``h`` is the hat weighting. The per-pixel unknowns ``ln E_i`` are
    eliminated exactly (Schur complement), so the linear system has only L unknowns and many
    sample pixels stay cheap. ``lam = smoothness * sqrt(M / L)`` for M observations, so the
    balance of data and smoothness does not depend on the number of samples.

    Args:
        codes: (N, P) int, code values of N sample pixels in P frames, in [0, levels).
        log_exposures: (P,) float, ln H of each frame.
        levels: number of code values L.
        data_weight: (L,) float >= 0, weight of an observation by its code.
        smoothness: lam before scaling, >= 0.
        anchor: code fixed at g = 0 (default: the middle code).

    Returns:
        log_response: (L,) float64, g(z).
        log_irradiance: (N,) float64, ln E of the sample pixels.

    Raises:
        DamcapError: the samples do not constrain the curve (fewer than 2 frames).
    """
    codes = np.asarray(codes)
    n, p = codes.shape
    if p < 2:
        raise DamcapError(f"response recovery needs at least 2 exposures, got {p}")
    lnh = np.asarray(log_exposures, dtype=np.float64)
    anchor = (levels - 1) // 2 + 1 if anchor is None else anchor
    z = codes.astype(np.int64)  # (N, P)
    w = np.asarray(data_weight, dtype=np.float64)[z]  # (N, P)
    y = np.broadcast_to(lnh, (n, p))
    # Normal equations of the data term in blocks [g | lnE]; lnE is eliminated per pixel:
    # S = A_gg - A_ge A_ee^-1 A_eg, built from the pairs of observations of each pixel.
    a_ee = w.sum(axis=1)  # (N,)
    inv_ee = np.where(a_ee > 0, 1.0 / np.maximum(a_ee, 1e-300), 0.0)
    b_e = -(w * y).sum(axis=1)
    a_gg = np.bincount(z.ravel(), w.ravel(), minlength=levels)
    b_g = np.bincount(z.ravel(), (w * y).ravel(), minlength=levels)
    pair_index = (z[:, :, None] * levels + z[:, None, :]).ravel()
    pair_weight = (w[:, :, None] * w[:, None, :] * inv_ee[:, None, None]).ravel()
    s = np.diag(a_gg) - np.bincount(pair_index, pair_weight, minlength=levels * levels).reshape(levels, levels)
    # rhs = b_g - A_ge A_ee^-1 b_e, with A_ge[z_ij, i] = -w_ij
    rhs = b_g + np.bincount(z.ravel(), (w * (inv_ee * b_e)[:, None]).ravel(), minlength=levels)
    # Smoothness on the second difference, weighted by the hat (Eq. 3, second term).
    lam = smoothness * np.sqrt(max(z.size, 1) / levels)
    k = np.arange(1, levels - 1)
    d = np.zeros((levels - 2, levels))
    h = hat_weights(levels)[k] * lam
    d[k - 1, k - 1] = h
    d[k - 1, k] = -2 * h
    d[k - 1, k + 1] = h
    s += d.T @ d
    # The data and smoothness terms do not change when g and every ln E shift by one constant;
    # a penalty on g(anchor) picks the solution with g(anchor) = 0 exactly.
    s[anchor, anchor] += max(1.0, float(np.diag(s).mean()))
    g = np.linalg.solve(s, rhs)
    ln_e = inv_ee * (b_e + (w * g[z]).sum(axis=1))
    return g, ln_e


def sample_pixels_for_response(
    codes: np.ndarray,
    n_samples: int = 2000,
    flat_fraction: float = 0.1,
    phase: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels to recover a response from: flat regions, spread over the brightness range.

    Debevec & Malik pick pixels "with sufficiently small intensity variance" and a good spread of
    brightness (1997, Sec. 2.1). Flatness here is the largest Sobel gradient of a pixel over all
    frames (edges suffer from blur, misregistration and demosaicing); of the flattest
    ``flat_fraction`` of pixels, ``n_samples`` are taken evenly spaced in rank of brightness.
    ``phase`` shifts those ranks by a fraction of their spacing: each phase is an equally valid
    sample, so comparing phases shows how much a result owes to which pixels were picked.

    Args:
        codes: (P, H, W, C) int code values of the bracket.
        n_samples: pixels wanted (fewer when the image is small).
        flat_fraction: fraction of the flattest pixels to choose from, in (0, 1].
        phase: shift of the evenly spaced ranks, in units of their spacing, in [0, 1).

    Returns:
        rows, cols: (n,) int arrays.
    """
    import cv2

    p, hgt, wid = codes.shape[:3]
    grad = np.zeros((hgt, wid), np.float32)
    luma_sum = np.zeros((hgt, wid), np.float32)
    for j in range(p):
        luma = codes[j].astype(np.float32).mean(axis=-1)
        gx = cv2.Sobel(luma, cv2.CV_32F, 1, 0)
        gy = cv2.Sobel(luma, cv2.CV_32F, 0, 1)
        np.maximum(grad, np.hypot(gx, gy), out=grad)
        luma_sum += np.log1p(luma)
    flat = np.flatnonzero(grad.ravel() <= np.quantile(grad, flat_fraction))
    order = flat[np.argsort(luma_sum.ravel()[flat], kind="stable")]
    take = min(n_samples, len(order))
    ranks = np.linspace(0, len(order) - 1, take) + phase * (len(order) - 1) / max(take - 1, 1)
    idx = order[np.minimum(ranks.round().astype(np.int64), len(order) - 1)]
    return idx // wid, idx % wid


@dataclass
class ResponseCurve:
    """A camera response with per-code reliability (see the module docstring)."""

    log_response: np.ndarray
    """(C, L) float64, ln of linear exposure per code value; the top code is the saturation level."""
    level_weight: np.ndarray
    """(C, L) float64 in [0, 1], reliability of each code value (0 at the first and last code)."""
    method: str
    """``debevec`` or ``srgb``."""

    @property
    def levels(self) -> int:
        return int(self.log_response.shape[1])


def _residuals(codes_c: np.ndarray, g: np.ndarray, lnh: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Residuals g(z_ij) - ln E_i - ln H_j, with ln E_i the weighted mean estimate."""
    obs = g[codes_c] - lnh[None, :]
    wij = w[codes_c]
    ln_e = (wij * obs).sum(axis=1) / np.maximum(wij.sum(axis=1), 1e-300)
    return obs - ln_e[:, None]


def recover_response(
    sample_codes: np.ndarray,
    log_exposures: np.ndarray,
    levels: int,
    method: str = "debevec",
    smoothness: float = 12.0,
    iterations: int = 2,
    low: float = 0.01,
    high: float = 0.99,
) -> ResponseCurve:
    """Response curve and code reliabilities from sample pixels of a bracket.

    Debevec: solve with the hat weighting on codes, then ``iterations`` rounds of re-solving with
    reliabilities (first the hat on linearised values, :func:`linear_hat_weights`, then inverse
    residual variance, :func:`level_weights_from_residuals`). sRGB: the curve is fixed and only the
    reliabilities are estimated the same way.

    Args:
        sample_codes: (N, P, C) int code values of N sample pixels in P frames.
        log_exposures: (P,) float, ln H per frame.
        levels: number of code values L.
        method: ``debevec`` or ``srgb``.
        smoothness: see :func:`solve_response_Debevec1997`.
        iterations: reweighting rounds, >= 0.
        low, high: see :func:`linear_hat_weights`.

    Returns:
        The recovered :class:`ResponseCurve`; each channel's curve has g(middle code) = 0 for
        Debevec (as in the paper, which fixes each channel's scale at mid-grey).

    Raises:
        DamcapError: unknown method, or fewer than 2 frames.
    """
    if method not in ("debevec", "srgb"):
        raise DamcapError(f"--response must be debevec or srgb, got {method!r}")
    sample_codes = np.asarray(sample_codes)
    n, p, c = sample_codes.shape
    if p < 2:
        raise DamcapError(f"merging needs at least 2 exposures, got {p}")
    lnh = np.asarray(log_exposures, dtype=np.float64)
    curves = np.zeros((c, levels))
    weights = np.zeros((c, levels))
    srgb = srgb_log_response(levels, 1)[0]
    for ch in range(c):
        zc = sample_codes[:, :, ch].astype(np.int64)
        if method == "debevec":
            g, _ = solve_response_Debevec1997(zc, lnh, levels, hat_weights(levels), smoothness)
        else:
            g = srgb
        w = linear_hat_weights(g[None], low, high)[0]
        for _ in range(iterations):
            if method == "debevec":
                g, ln_e = solve_response_Debevec1997(zc, lnh, levels, w, smoothness)
                res = g[zc] - ln_e[:, None] - lnh[None, :]
            else:
                res = _residuals(zc, g, lnh, w)
            w = level_weights_from_residuals(zc, res, levels)
        curves[ch] = g
        weights[ch] = w
    return ResponseCurve(log_response=curves, level_weight=weights, method=method)
