"""False-colour previews of material weights."""

from __future__ import annotations


import numpy as np




#: false colours of the preview images (material k -> RGB in [0, 1])
PALETTE = np.array([[0.90, 0.30, 0.25], [0.25, 0.60, 0.95], [0.95, 0.80, 0.20], [0.40, 0.80, 0.40],
                    [0.70, 0.40, 0.85], [0.95, 0.55, 0.10], [0.30, 0.85, 0.85], [0.85, 0.85, 0.85]], np.float32)


def false_colour(weights: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 preview: each pixel the weight-blend of its materials' palette colours."""
    pal = PALETTE[np.arange(weights.shape[-1]) % len(PALETTE)]
    rgb = weights @ pal * (coverage > 0)[..., None]
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
