"""Bracket alignment with median threshold bitmaps (Ward 2003): known shifts at other exposures."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.capture.align import bitmap_mismatch, chain_shifts, mtb_shift, preview_u8, pyramid_levels, shift_image


def _scene(h: int = 128, w: int = 160, seed: int = 0) -> np.ndarray:
    """Linear radiance with structure at every scale (smoothed noise plus blocks)."""
    import cv2

    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 1, (h, w)).astype(np.float32), (0, 0), 2.0) * 2.0
    img[20:60, 30:90] += 1.0
    img[70:110, 100:140] *= 0.2
    return img + 0.05


def _exposed(radiance: np.ndarray, exposure: float) -> np.ndarray:
    """An 8-bit sRGB-like photo of linear radiance at an exposure, clipped."""
    return np.round(np.clip(radiance * exposure, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)


def test_pyramid_levels_closed_form():
    assert pyramid_levels((512, 768)) == 5  # floor(log2(512 / 16))
    assert pyramid_levels((64, 128)) == 2
    assert pyramid_levels((4000, 6000)) == 6  # capped at `most`
    assert pyramid_levels((8, 8)) == 1 and pyramid_levels((0, 5)) == 1  # at least one level
    assert pyramid_levels((256, 256), smallest=8, most=10) == 5


@pytest.mark.parametrize("dy, dx", [(0, 0), (2, -3), (-5, 4), (7, 0)])
def test_shift_image_moves_content_and_flags_the_border(dy, dx):
    img = np.arange(10 * 12 * 3, dtype=np.float32).reshape(10, 12, 3)
    out, valid = shift_image(img, dy, dx, fill=-1.0)
    assert out.shape == img.shape and out.dtype == img.dtype
    assert valid.sum() == (10 - abs(dy)) * (12 - abs(dx))
    assert np.all(out[~valid] == -1.0)
    ys, xs = np.nonzero(valid)
    np.testing.assert_array_equal(out[ys, xs], img[ys - dy, xs - dx])
    back, back_valid = shift_image(out, -dy, -dx)  # round trip: the original wherever it is defined
    assert back_valid.sum() == valid.sum()
    np.testing.assert_array_equal(back[back_valid], img[back_valid])


def test_bitmap_mismatch_is_zero_at_the_true_shift():
    rad = _scene()
    ref = _exposed(rad, 0.5)
    moved = _exposed(shift_image(rad, 3, -4, fill=0.05)[0], 0.25)  # another exposure, moved
    assert bitmap_mismatch(ref, moved, -3, 4) < 0.01
    assert bitmap_mismatch(ref, moved, 0, 0) > 0.1
    # a flat image has no usable bits
    flat = np.full((32, 32), 128, np.uint8)
    assert bitmap_mismatch(flat, flat, 0, 0) == 1.0


@pytest.mark.parametrize("dy, dx", [(3, -5), (-6, 2), (0, 0)])
def test_mtb_shift_recovers_a_known_shift_across_exposures(dy, dx):
    rad = _scene()
    ref = _exposed(rad, 0.6)
    img = _exposed(shift_image(rad, dy, dx, fill=0.05)[0], 0.15)  # two stops darker
    got = mtb_shift(ref, img)
    assert got == (-dy, -dx)
    # three channels give the same answer
    assert mtb_shift(np.repeat(ref[..., None], 3, -1), np.repeat(img[..., None], 3, -1)) == got


def test_mtb_shift_keeps_zero_for_noise():
    rng = np.random.default_rng(5)
    a = rng.integers(0, 256, (64, 64), dtype=np.uint8)
    b = rng.integers(0, 256, (64, 64), dtype=np.uint8)
    assert mtb_shift(a, b) == (0, 0)


def test_chain_shifts_sums_shifts_along_the_exposure_order():
    rad = _scene()
    truth = {0: (0, 0), 1: (2, -1), 2: (-3, 2)}  # frame k is the scene moved by truth[k]
    exposures = np.array([0.5, 0.25, 1.0])  # order: 1, 0, 2 -> frame 0 is in the middle
    previews = [_exposed(shift_image(rad, *truth[k], fill=0.05)[0], exposures[k]) for k in range(3)]
    shifts = chain_shifts(previews, exposures, reference=0)
    assert shifts == [(0, 0), (-2, 1), (3, -2)]
    assert chain_shifts(previews, exposures, reference=1) == [(2, -1), (0, 0), (5, -3)]


def test_preview_u8_closed_form():
    # the median goes to 0.18, whose sRGB encoding is 0.4613561 -> 118
    assert np.all(preview_u8(np.full((4, 5, 3), 7.0)) == 118)
    img = np.array([[0.0, 0.18, 0.5, 2.0]])
    out = preview_u8(img, normalize=False)
    assert out.dtype == np.uint8 and out.tolist() == [[0, 118, 188, 255]]
    assert preview_u8(np.zeros((2, 2))).tolist() == [[0, 0], [0, 0]]  # median 0: eps floor, no NaN
