"""False-colour previews of material weights, and their legend (which colour is which material's DAM)."""

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


def material_colours8(materials: int) -> np.ndarray:
    """(materials, 3) uint8: the colour a pixel wholly of material k has in the previews.

    >>> material_colours8(2).tolist()
    [[230, 76, 64], [64, 153, 242]]
    """
    return np.round(PALETTE[np.arange(materials) % len(PALETTE)] * 255).astype(np.uint8)


def legend_entries(materials: int) -> dict[str, dict]:
    """The legend as JSON: ``{"k": {"rgb": [r, g, b] (0-255, the previews' colour), "dam": "material_k.dam"}}``."""
    return {str(k): {"rgb": [int(c) for c in rgb], "dam": f"material_{k}.dam"} for k, rgb in enumerate(material_colours8(materials))}


def legend_image(materials: int, dpi: int = 100) -> np.ndarray:
    """(H, W, 3) uint8 legend: one row per material, a swatch of its preview colour, "material k" and its DAM file.

    Rendered with matplotlib's Agg canvas (no window, no global pyplot state); about 300 px wide
    and 28 px per row at ``dpi`` 100.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    if materials < 1:
        raise ValueError(f"legend_image: expected materials >= 1, got {materials}")
    row_in = 0.28
    fig = Figure(figsize=(3.0, row_in * materials + 0.12), dpi=dpi, facecolor="white")
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, 3.0)
    ax.set_ylim(row_in * materials + 0.06, -0.06)
    ax.axis("off")
    for k, rgb in enumerate(material_colours8(materials)):
        y = k * row_in
        ax.add_patch(Rectangle((0.08, y + 0.04), 0.34, row_in - 0.08, facecolor=rgb / 255.0, edgecolor="black", linewidth=0.5))
        ax.text(0.52, y + row_in / 2, f"material {k}   material_{k}.dam", va="center", ha="left", fontsize=9, color="black")
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()
