"""From linear radiance to display pixels (pure)."""

from __future__ import annotations

import colour
import numpy as np

#: fraction of the display range the exposure reference maps to (headroom for highlights)
DISPLAY_KEY = 0.8


def exposure_scale_for(radiance_lin: np.ndarray, mask: np.ndarray, percentile: float = 95.0) -> float:
    """A scale that maps the ``percentile`` of the masked radiance to :data:`DISPLAY_KEY`.

    Args:
        radiance_lin: (..., 3) linear radiance.
        mask: (...) bool, pixels that count.
        percentile: which radiance value becomes DISPLAY_KEY.

    Returns:
        the scale (1 when the masked radiance is black or empty).
    """
    vals = radiance_lin[mask]
    p = float(np.percentile(vals, percentile)) if vals.size else 0.0
    return DISPLAY_KEY / p if p > 0 and np.isfinite(p) else 1.0


def display_srgb8(radiance_lin: np.ndarray, exposure_scale: float) -> np.ndarray:
    """Linear radiance -> 8-bit sRGB: scale, clip to [0, 1], sRGB encoding (IEC 61966-2-1).

    Args:
        radiance_lin: (H, W, 3) linear Rec.709 radiance, >= 0.
        exposure_scale: multiplier applied before clipping.

    Returns:
        (H, W, 3) uint8.
    """
    x = np.clip(np.asarray(radiance_lin, np.float64) * exposure_scale, 0, 1)
    srgb = colour.cctf_encoding(x, function="sRGB")
    return np.round(np.clip(srgb, 0, 1) * 255).astype(np.uint8)
