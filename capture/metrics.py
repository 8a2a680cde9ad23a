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
