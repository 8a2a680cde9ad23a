"""Error of a radiance map against a reference: absolute log ratio after one global scale.

The measure of the capture issue and bench: for every pixel and channel the reference resolves
(reference > 0, finite, not masked out), ``|ln(estimate * s) - ln(reference)|`` with the one
global scale ``s`` that makes the median log ratio zero (radiance maps are only defined up to a
scale). Reported as the median and the 90th percentile.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from damcap.common.errors import DamcapError


@dataclass(frozen=True)
class LogRatioError:
    """Summary of absolute log ratios (natural log; 0.01 is about 1 %)."""

    median: float
    p90: float
    scale: float
    """The global factor applied to the estimate."""
    pixels: int
    """Number of values (pixel-channels) compared."""


def centred_log_ratio(
    estimate: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None, eps: float = 1e-30
) -> tuple[np.ndarray, np.ndarray, float]:
    """Per value ``ln(estimate) - ln(reference)`` minus its median over the resolved values.

    Args: as :func:`abs_log_ratio_error`.

    Returns:
        log_ratio: (H, W, C) float64, centred (meaningless where not resolved);
        resolved: (H, W, C) bool, the values compared;
        offset: the median removed (the global scale is ``exp(-offset)``).

    Raises:
        DamcapError: shapes differ or nothing is resolved.
    """
    est = np.asarray(estimate, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if est.shape != ref.shape:
        raise DamcapError(f"estimate {est.shape} and reference {ref.shape} differ in shape")
    use = np.isfinite(ref) & (ref > 0) & np.isfinite(est)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        use &= m[..., None] if m.ndim == est.ndim - 1 else m
    if not use.any():
        raise DamcapError("no resolved reference values to compare")
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(np.maximum(est, eps)) - np.log(np.where(use, ref, 1.0))
    offset = float(np.median(lr[use]))
    return lr - offset, use, offset


def abs_log_ratio_error(
    estimate: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None, eps: float = 1e-30
) -> LogRatioError:
    """Median and 90th percentile of ``|ln(s * estimate / reference)|`` over resolved values.

    Args:
        estimate: (H, W, C) float, linear, >= 0.
        reference: (H, W, C) float, linear; values <= 0 or non-finite are not resolved.
        mask: (H, W) or (H, W, C) bool, True where compared (default: everywhere resolved).
        eps: floor on the estimate before the log (a zero estimate of a resolved value counts
            as a large error rather than being skipped).

    Returns:
        :class:`LogRatioError`.

    Raises:
        DamcapError: shapes differ or nothing is resolved.

    >>> ref = np.array([[[1.0, 2.0, 4.0]]]); e = abs_log_ratio_error(3 * ref, ref)
    >>> e.median, round(e.scale, 6)
    (0.0, 0.333333)
    """
    lr, use, offset = centred_log_ratio(estimate, reference, mask, eps)
    a = np.abs(lr[use])
    return LogRatioError(median=float(np.median(a)), p90=float(np.percentile(a, 90)), scale=float(np.exp(-offset)),
                         pixels=int(use.sum()))


def rgbe_step(rgb: np.ndarray) -> np.ndarray:
    """Quantisation step of each value of an image stored as Radiance RGBE (``.hdr``).

    RGBE (Ward 1991) keeps one 8-bit exponent per pixel, that of its largest channel, and an
    8-bit mantissa per channel: a pixel whose largest value is ``f 2^e`` (``f`` in [0.5, 1))
    stores every channel in steps of ``2^(e-8)``. The largest channel is known to within 1/128
    to 1/256 of its value; a channel 20x smaller only to within 1/6 to 1/13. Writers in
    Radiance's lineage truncate (Ward's ``setcolr``, Walter's ``float2rgbe``), so a stored
    mantissa ``m`` stands for values in ``[m, m + 1)`` steps; OpenImageIO reads it back as
    ``m`` steps.

    Args:
        rgb: (..., C) float, linear, >= 0, as read from the file.

    Returns:
        (..., 1) float64, the step of each pixel (0 where the pixel is 0).

    >>> rgbe_step(np.array([[1.0, 0.1, 0.0]])).tolist()
    [[0.0078125]]
    >>> rgbe_step(np.array([[0.0, 0.0, 0.0]])).tolist()
    [[0.0]]
    """
    top = np.max(np.asarray(rgb, dtype=np.float64), axis=-1, keepdims=True)
    _, e = np.frexp(top)
    return np.where(top > 0, np.ldexp(1.0, e - 8), 0.0)
