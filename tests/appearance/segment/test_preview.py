"""False-colour previews: palette colours for one-hot weights, blends, black background; the legend."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.appearance.segment.preview import PALETTE, false_colour, legend_entries, legend_image


def test_one_hot_weights_give_the_palette_colours():
    w = np.eye(3, dtype=np.float32)[[0, 1, 2, 1]].reshape(2, 2, 3)
    out = false_colour(w, np.ones((2, 2)))
    assert out.shape == (2, 2, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out.reshape(4, 3), np.round(PALETTE[[0, 1, 2, 1]] * 255).astype(np.uint8))
    assert out[0, 0].tolist() == [230, 76, 64]  # 0.90, 0.30, 0.25


def test_blends_background_and_palette_wrap():
    w = np.array([[[0.5, 0.5], [1.0, 0.0]]], np.float32)
    out = false_colour(w, np.array([[1.0, 0.0]]))
    np.testing.assert_array_equal(out[0, 0], np.round((0.5 * PALETTE[0] + 0.5 * PALETTE[1]) * 255).astype(np.uint8))
    assert out[0, 1].tolist() == [0, 0, 0]  # coverage 0
    # more materials than palette colours: material 8 looks like material 0
    w10 = np.zeros((1, 2, 10), np.float32)
    w10[0, 0, 0] = w10[0, 1, 8] = 1
    out10 = false_colour(w10, np.ones((1, 2)))
    np.testing.assert_array_equal(out10[0, 0], out10[0, 1])
    # weights above 1 saturate instead of wrapping around uint8
    assert false_colour(np.full((1, 1, 1), 3.0, np.float32), np.ones((1, 1))).tolist() == [[[255, 230, 191]]]  # 3 x (0.9, 0.3, 0.25), clipped


def test_legend_colours_are_the_previews_colours():
    n = 10  # past the palette's 8 colours: materials 8 and 9 share 0's and 1's, and the legend says so
    entries = legend_entries(n)
    assert list(entries) == [str(k) for k in range(n)]
    one_hot = false_colour(np.eye(n, dtype=np.float32)[None], np.ones((1, n)))[0]  # pixel k: wholly material k
    for k in range(n):
        assert entries[str(k)] == {"rgb": one_hot[k].tolist(), "dam": f"material_{k}.dam"}
    assert entries["0"]["rgb"] == [230, 76, 64] and entries["8"]["rgb"] == entries["0"]["rgb"]


def test_legend_image_has_a_swatch_of_each_colour():
    n = 3
    img = legend_image(n)
    assert img.dtype == np.uint8 and img.shape[2] == 3
    assert img.shape[1] == 300 and 28 * n <= img.shape[0] <= 28 * n + 20  # one row per material
    rows = np.array_split(np.arange(img.shape[0] - 12) + 6, n)  # the rows' centres, inside the margins
    for k in range(n):
        colour = np.array(legend_entries(n)[str(k)]["rgb"])
        row = img[rows[k][len(rows[k]) // 2], :60].astype(int)
        assert (np.abs(row - colour).max(-1) <= 2).sum() >= 20  # a swatch at least 20 px wide in the row's colour
    text = img[:, 60:]
    assert (text.max(-1) < 100).mean() > 0.01  # dark text drawn right of the swatches
    with pytest.raises(ValueError, match="materials >= 1, got 0"):
        legend_image(0)
