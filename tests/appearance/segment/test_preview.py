"""False-colour previews: palette colours for one-hot weights, blends, black background."""

from __future__ import annotations

import numpy as np

from damcap.appearance.segment.preview import PALETTE, false_colour


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
