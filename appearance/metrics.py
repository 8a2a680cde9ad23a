"""DSSIM exactly as docs/capture-format.md defines it (the number every result in damcap reports)."""

from __future__ import annotations

import warnings

import kornia
import numpy as np
import torch

from damcap.appearance.pixels import FOREGROUND_COVERAGE

#: percentile of the reference's foreground values that maps to 1 before SSIM
NORMALISE_PERCENTILE = 95.0
#: SSIM window (kornia's defaults: Gaussian sigma 1.5, reflect borders, C1 = 0.01^2, C2 = 0.03^2)
SSIM_WINDOW = 11


def normalise_pair(reference_lin: np.ndarray, prediction_lin: np.ndarray, foreground: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scale both images by the factor mapping the reference's 95th foreground percentile to 1.

    Args:
        reference_lin: (H, W, 3) linear radiance, finite.
        prediction_lin: (H, W, 3) linear radiance, finite.
        foreground: (H, W) bool.

    Returns:
        (H, W, 3) float32 pair in [0, 1]; background 0 in both. A black reference foreground
        (95th percentile 0) keeps scale 1.
    """
    fg = foreground[..., None]
    ref = np.where(fg, reference_lin, 0).astype(np.float64)
    pred = np.where(fg, prediction_lin, 0).astype(np.float64)
    p = float(np.percentile(ref[foreground], NORMALISE_PERCENTILE)) if foreground.any() else 0.0
    scale = 1.0 / p if p > 0 else 1.0
    return np.clip(ref * scale, 0, 1).astype(np.float32), np.clip(pred * scale, 0, 1).astype(np.float32)


def dssim(reference_lin: np.ndarray, prediction_lin: np.ndarray, coverage: np.ndarray, threshold: float = FOREGROUND_COVERAGE) -> float | None:
    """DSSIM = (1 - SSIM) / 2 over the foreground of one frame (docs/capture-format.md).

    SSIM per channel with an 11x11 Gaussian window (kornia.metrics.ssim), averaged over the
    channels and over the pixels whose window centre is foreground.

    Args:
        reference_lin: (H, W, 3) reference radiance.
        prediction_lin: (H, W, 3) predicted radiance.
        coverage: (H, W) coverage A; foreground is A > threshold.
        threshold: foreground coverage threshold.

    Returns:
        DSSIM in [0, 1], or None (with a warning) for a frame without foreground.

    Identical images give 0:

    >>> img = np.random.default_rng(0).random((16, 16, 3))
    >>> round(dssim(img, img, np.ones((16, 16))), 6)
    0.0
    """
    if reference_lin.shape != prediction_lin.shape or reference_lin.shape[:2] != coverage.shape:
        raise ValueError(f"shape mismatch: reference {reference_lin.shape}, prediction {prediction_lin.shape}, coverage {coverage.shape}")
    fg = coverage > threshold
    if not fg.any():
        warnings.warn("frame without foreground skipped in DSSIM", stacklevel=2)
        return None
    ref, pred = normalise_pair(reference_lin, prediction_lin, fg)
    # contiguous float32 NCHW: channels-last strides or float64 make CPU conv2d 100x slower
    to_t = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None].contiguous()  # noqa: E731
    ssim = kornia.metrics.ssim(to_t(ref), to_t(pred), SSIM_WINDOW)  # (1, 3, H, W)
    ssim_px = ssim[0].double().mean(0).numpy()
    return float((1.0 - ssim_px[fg].mean()) / 2.0)
