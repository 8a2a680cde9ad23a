"""bench.demo_picture's composition on synthetic panels: the strip's size, each panel where its
order puts it, white gaps, and the palette capped (no Blender, no Chromium)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.demo_picture import compose_strip

COLOURS = [(220, 30, 30), (30, 200, 40), (20, 40, 230), (240, 220, 20)]


def solid(side: int, rgb: tuple[int, int, int], alpha: bool = False) -> np.ndarray:
    px = np.empty((side, side, 4 if alpha else 3), np.uint8)
    px[...] = (*rgb, 255) if alpha else rgb
    return px


def test_panels_sit_in_order_with_white_gaps_between():
    panels = [solid(10, COLOURS[0]), solid(24, COLOURS[1]), solid(7, COLOURS[2], alpha=True), solid(16, COLOURS[3])]
    picture = compose_strip(panels, panel_px=12, gap_px=3, colours=8)
    assert picture.mode == "P" and picture.size == (4 * 12 + 3 * 3, 12)
    rgb = np.asarray(picture.convert("RGB")).astype(int)
    for k, colour in enumerate(COLOURS):
        x = k * 15
        assert np.abs(rgb[:, x:x + 12] - colour).max() <= 2, k  # the whole panel is its colour, nothing bleeds in
    for x in (12, 27, 42):
        assert (rgb[:, x:x + 3] == 255).all(), x


def test_the_palette_is_capped_and_used():
    yy, xx = np.mgrid[0:32, 0:32]
    ramp = np.stack([xx * 8, yy * 8, (xx + yy) * 4], -1).astype(np.uint8)  # 1024 colours
    picture = compose_strip([ramp, ramp[::-1]], panel_px=32, gap_px=2, colours=16)
    assert len(picture.getcolors(256)) == 16


@pytest.mark.parametrize("bad", [[], [np.zeros((4, 5, 3), np.uint8)], [np.zeros((4, 4, 3), np.float32)]],
                         ids=["none", "not square", "float"])
def test_panels_it_cannot_place_are_refused(bad):
    with pytest.raises(ValueError, match="compose_strip"):
        compose_strip(bad)
