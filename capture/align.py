"""Translational alignment of hand-held brackets: median threshold bitmaps (Ward 2003) via OpenCV.

The median threshold bitmap of an image does not depend on its exposure, so frames of a bracket
can be compared directly. Shifts are integers; RAW mosaics are aligned on half-resolution
previews and shifted by even amounts so that the colour-filter pattern stays in register.

Reference: Ward. Fast, Robust Image Registration for Compositing High Dynamic Range Photographs
from Hand-Held Exposures. Journal of Graphics Tools 8(2), 2003.
"""

from __future__ import annotations

import numpy as np


def _grey(img: np.ndarray) -> np.ndarray:
    import cv2

    img = np.ascontiguousarray(img)
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def pyramid_levels(shape: tuple[int, ...], smallest: int = 16, most: int = 6) -> int:
    """MTB pyramid depth so the coarsest level keeps at least ``smallest`` pixels per side.

    The largest shift found is ``2**levels - 1`` pixels.

    >>> pyramid_levels((512, 768)), pyramid_levels((64, 128)), pyramid_levels((4000, 6000))
    (5, 2, 6)
    """
    side = min(shape[:2])
    return int(np.clip(np.floor(np.log2(max(side, 1) / smallest)), 1, most))


def bitmap_mismatch(reference_u8: np.ndarray, image_u8: np.ndarray, dy: int, dx: int, exclude_range: int = 4) -> float:
    """Fraction of mismatching median-threshold bits after shifting ``image_u8`` by (dy, dx).

    Bits near the median (noise) and the uncovered border are ignored (Ward 2003, Sec. 3).

    Args:
        reference_u8: (H, W) or (H, W, 3) uint8.
        image_u8: same shape, uint8.
        dy, dx: shift applied to ``image_u8``.
        exclude_range: grey levels around the median ignored as noise.

    Returns:
        Mismatch fraction in [0, 1] (1 when no bit can be compared).
    """
    import cv2

    mtb = cv2.createAlignMTB(1, exclude_range, True)
    tb0, eb0 = mtb.computeBitmaps(_grey(reference_u8))
    tb1, eb1 = mtb.computeBitmaps(_grey(image_u8))
    tb1, valid = shift_image(tb1, dy, dx, 0)
    eb1, _ = shift_image(eb1, dy, dx, 0)
    use = (eb0 > 0) & (eb1 > 0) & valid
    if not use.any():
        return 1.0
    return float(((tb0 > 0) != (tb1 > 0))[use].mean())


def mtb_shift(
    reference_u8: np.ndarray, image_u8: np.ndarray, exclude_range: int = 4, min_gain: float = 0.1
) -> tuple[int, int]:
    """Integer (dy, dx) that moves ``image_u8`` onto ``reference_u8`` (median threshold bitmaps).

    OpenCV's pyramid search can lock onto a wrong optimum at coarse levels, and runs away on
    frames that are mostly clipped or mostly noise. So the search is run at every pyramid depth
    up to :func:`pyramid_levels`, the candidate with the fewest mismatching bits wins, and it is
    kept only when it lowers the mismatch by at least ``min_gain`` (relative) compared with no
    shift; otherwise (0, 0) is returned.

    Args:
        reference_u8: (H, W) or (H, W, 3) uint8, any exposure.
        image_u8: same shape, uint8, any exposure.
        exclude_range: grey levels around the median ignored as noise.
        min_gain: relative mismatch reduction a shift must achieve, in [0, 1).

    Returns:
        (dy, dx); :func:`shift_image` with it aligns the image to the reference.
    """
    import cv2

    ref, img = _grey(reference_u8), _grey(image_u8)
    candidates = {(0, 0)}
    for levels in range(1, pyramid_levels(ref.shape) + 1):
        dx, dy = cv2.createAlignMTB(levels, exclude_range, True).calculateShift(ref, img)  # returns (x, y)
        candidates.add((int(dy), int(dx)))
    mismatch = {c: bitmap_mismatch(ref, img, *c, exclude_range=exclude_range) for c in candidates}
    best = min(sorted(candidates), key=lambda c: mismatch[c])
    return best if mismatch[best] < (1.0 - min_gain) * mismatch[(0, 0)] else (0, 0)


def chain_shifts(previews_u8: list[np.ndarray], exposures: np.ndarray, reference: int) -> list[tuple[int, int]]:
    """Shift of every frame onto the reference, aligning neighbours in exposure order (Ward 2003).

    Adjacent exposures share most unclipped pixels, so each frame is aligned to its neighbour
    one step closer (in exposure) to the reference and the shifts are summed along the chain.

    Args:
        previews_u8: P uint8 previews, (H, W) or (H, W, 3).
        exposures: (P,) exposure factors (only their order matters).
        reference: index of the frame the others are aligned to.

    Returns:
        P (dy, dx) shifts; the reference's is (0, 0).
    """
    order = list(np.argsort(np.asarray(exposures), kind="stable"))
    pos = order.index(reference)
    shifts: list[tuple[int, int]] = [(0, 0)] * len(previews_u8)
    for direction in (-1, 1):
        total = (0, 0)
        k = pos + direction
        while 0 <= k < len(order):
            near, far = order[k - direction], order[k]
            dy, dx = mtb_shift(previews_u8[near], previews_u8[far])
            total = (total[0] + dy, total[1] + dx)
            shifts[far] = total
            k += direction
    return shifts


def preview_u8(linear: np.ndarray, normalize: bool = True, eps: float = 1e-12) -> np.ndarray:
    """An 8-bit sRGB-encoded preview of a linear image for alignment.

    Args:
        linear: (H, W) or (H, W, C) float, linear.
        normalize: scale so the median maps to mid-grey (0.18); False: values are used as given
            (1 = white), e.g. frames already brought to one exposure.
        eps: floor of the median.

    Returns:
        (H, W) uint8.
    """
    from damcap.common.colour import linear_to_srgb

    img = np.asarray(linear, dtype=np.float32)
    if img.ndim == 3:
        img = img.mean(axis=-1)
    if normalize:
        img = img * (0.18 / max(float(np.median(img)), eps))
    return np.round(linear_to_srgb(np.clip(img, 0.0, 1.0)) * 255).astype(np.uint8)


def shift_image(image: np.ndarray, dy: int, dx: int, fill: float | int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Translate an image by whole pixels; uncovered pixels get ``fill``.

    Args:
        image: (H, W, ...) array.
        dy, dx: shift in pixels (positive moves content down / right).
        fill: value of the uncovered border.

    Returns:
        shifted: same shape and dtype (a new array).
        valid: (H, W) bool, False on the uncovered border.

    >>> s, v = shift_image(np.arange(4).reshape(1, 4), 0, 1)
    >>> s.tolist(), v.tolist()
    ([[0, 0, 1, 2]], [[False, True, True, True]])
    """
    h, w = image.shape[:2]
    out = np.full_like(image, fill)
    valid = np.zeros((h, w), dtype=bool)
    ys_dst = slice(max(dy, 0), h + min(dy, 0))
    xs_dst = slice(max(dx, 0), w + min(dx, 0))
    ys_src = slice(max(-dy, 0), h + min(-dy, 0))
    xs_src = slice(max(-dx, 0), w + min(-dx, 0))
    out[ys_dst, xs_dst] = image[ys_src, xs_src]
    valid[ys_dst, xs_dst] = True
    return out, valid
