"""Camera RAW files to linear camera counts, and a RAW bracket to one linear radiance map.

The RAW path never lets LibRaw apply gamma, auto-brightness, white balance or highlight
recovery. It reads the sensor values (rawpy ``raw_image_visible``), subtracts the black level and
divides by the white level given by the file, detects saturation on those raw values (before
any interpolation), merges the bracket per photosite with the Poisson-optimal estimator
(:func:`damcap.capture.merge.merge_poisson`), demosaics the merged HDR mosaic once (Menon 2007
on log values, i.e. interpolating colour ratios; bilinear for non-Bayer layouts) and converts
camera RGB to linear Rec.709 with the file's colour matrix as LibRaw resolves it
(``rgb_from_camera = color_matrix @ diag(daylight_whitebalance)``, i.e.
``inverse(ColorMatrix @ XYZ_from_Rec709)`` for a DNG).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damcap.common.errors import DamcapError

#: a raw value at or above ``black + SATURATION_FRACTION * (white - black)`` counts as clipped
SATURATION_FRACTION = 0.99


class CaptureWarning(UserWarning):
    """Something the user should know about a capture (e.g. a RAW file without a colour matrix)."""


@dataclass
class RawMosaic:
    """One RAW frame as normalised linear counts, before demosaicing."""

    counts: np.ndarray
    """(H, W) float32 for a colour-filter mosaic or (H, W, 3) for 3-channel RAWs: (raw - black) / (white - black);
    1 is the white level; slightly negative from noise."""
    saturated: np.ndarray
    """Same shape as ``counts``, bool: raw value at or above the saturation threshold."""
    cfa: np.ndarray | None
    """(H, W) uint8 colour of each photosite, 0 = R, 1 = G, 2 = B; None for 3-channel RAWs."""
    rgb_from_camera: np.ndarray | None
    """(3, 3) float64, camera RGB to linear Rec.709; None when the file has no colour matrix."""
    flip: int
    """LibRaw orientation code: 0 none, 3 rotate 180, 5 rotate 90 counter-clockwise, 6 rotate 90 clockwise."""
    black_level: tuple[float, ...]
    """Black level per LibRaw colour index (ADU)."""
    white_level: float
    """White level (ADU), the largest valid raw value."""


# --------------------------------------------------------------------------------------------
# Pure functions
# --------------------------------------------------------------------------------------------

def cfa_channels(raw_colors: np.ndarray, color_desc: bytes | str) -> np.ndarray:
    """Map LibRaw's colour indices (0..3 into ``color_desc``, e.g. ``RGBG``) to 0 = R, 1 = G, 2 = B.

    Args:
        raw_colors: (H, W) int, LibRaw's ``raw_colors_visible``.
        color_desc: LibRaw's colour description, e.g. ``b"RGBG"``.

    Returns:
        (H, W) uint8 in {0, 1, 2}.

    Raises:
        DamcapError: a sensor whose filters are not R, G, B (e.g. CMYG).

    >>> cfa_channels(np.array([[0, 1], [3, 2]]), b"RGBG").tolist()
    [[0, 1], [1, 2]]
    """
    desc = color_desc.decode("ascii", "replace") if isinstance(color_desc, bytes) else color_desc
    lut = np.zeros(max(4, len(desc)), np.uint8)
    for i, ch in enumerate(desc):
        if ch not in "RGB":
            raise DamcapError(f"colour filter {desc!r} is not an RGB mosaic; damcap reads RGB sensors only")
        lut[i] = "RGB".index(ch)
    return lut[np.asarray(raw_colors)]


def normalize_raw(
    raw: np.ndarray, black: np.ndarray, white: float | np.ndarray, saturation_fraction: float = SATURATION_FRACTION
) -> tuple[np.ndarray, np.ndarray]:
    """Black-subtract and scale raw values; detect saturation on the raw values themselves.

    Args:
        raw: (H, W) or (H, W, C) uint16 sensor values.
        black: black level, broadcastable to ``raw`` (per photosite or per channel).
        white: white level (the largest valid value), broadcastable to ``raw``.
        saturation_fraction: fraction of the black-to-white range above which a value is clipped,
            in (0, 1].

    Returns:
        counts: float32, ``(raw - black) / (white - black)``.
        saturated: bool, ``raw >= black + saturation_fraction * (white - black)``.

    >>> c, s = normalize_raw(np.array([[100, 1100, 4095]], np.uint16), 100.0, 4095.0)
    >>> [round(float(v), 4) for v in c[0]], s.tolist()
    ([0.0, 0.2503, 1.0], [[False, False, True]])
    """
    raw_f = np.asarray(raw, dtype=np.float32)
    black = np.asarray(black, dtype=np.float32)
    span = np.asarray(white, dtype=np.float32) - black
    if np.any(span <= 0):
        raise DamcapError(f"white level {white} is not above black level {black.max()}")
    counts = (raw_f - black) / span
    saturated = raw_f >= black + saturation_fraction * span
    return counts, saturated


def demosaic_bilinear(mosaic: np.ndarray, cfa: np.ndarray) -> np.ndarray:
    """Bilinear demosaicing of any RGB colour-filter pattern by normalised convolution.

    Each channel at a photosite of another colour is the weighted mean of that channel's
    photosites in the 3x3 neighbourhood (weights 4 centre, 2 edge, 1 corner; the Bayer bilinear
    interpolator), or in the 5x5 neighbourhood where the 3x3 has none (X-Trans); measured values
    are kept. A convex combination: linear in the data, never negative for non-negative data.

    Args:
        mosaic: (H, W) float, linear values.
        cfa: (H, W) int in {0, 1, 2}, the colour of each photosite.

    Returns:
        (H, W, 3) float32.

    >>> m = np.array([[1.0, 2.0], [2.0, 3.0]]); cfa = np.array([[0, 1], [1, 2]])
    >>> demosaic_bilinear(np.tile(m, (2, 2)), np.tile(cfa, (2, 2)))[1, 1].tolist()
    [1.0, 2.0, 3.0]
    """
    import cv2

    mosaic = np.asarray(mosaic, dtype=np.float32)
    if mosaic.shape != np.shape(cfa):
        raise DamcapError(f"mosaic {mosaic.shape} and colour pattern {np.shape(cfa)} differ in shape")
    k3 = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], np.float32)
    k5 = np.outer([1, 2, 3, 2, 1], [1, 2, 3, 2, 1]).astype(np.float32)
    out = np.empty(mosaic.shape + (3,), np.float32)
    for c in range(3):
        mask = (cfa == c).astype(np.float32)
        vals = mosaic * mask
        num = cv2.filter2D(vals, -1, k3, borderType=cv2.BORDER_REFLECT_101)
        den = cv2.filter2D(mask, -1, k3, borderType=cv2.BORDER_REFLECT_101)
        missing = den <= 0
        if missing.any():
            num5 = cv2.filter2D(vals, -1, k5, borderType=cv2.BORDER_REFLECT_101)
            den5 = cv2.filter2D(mask, -1, k5, borderType=cv2.BORDER_REFLECT_101)
            num = np.where(missing, num5, num)
            den = np.where(missing, den5, den)
        est = num / np.maximum(den, 1e-12)
        out[..., c] = np.where(mask > 0, mosaic, est)
    return out


def bayer_masks(cfa: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Red, green and blue masks of a Bayer pattern, or None when ``cfa`` is not a 2x2 Bayer layout.

    Args:
        cfa: (H, W) int in {0, 1, 2}.

    Returns:
        Three (H, W) float32 masks (1 where the photosite has that colour), or None.
    """
    cfa = np.asarray(cfa)
    if cfa.ndim != 2 or min(cfa.shape) < 2:
        return None
    quad = cfa[:2, :2]
    tiled = np.tile(quad, ((cfa.shape[0] + 1) // 2, (cfa.shape[1] + 1) // 2))[: cfa.shape[0], : cfa.shape[1]]
    if not np.array_equal(tiled, cfa) or sorted(quad.ravel().tolist()) != [0, 1, 1, 2] or quad[0, 0] == quad[0, 1]:
        return None
    return tuple((cfa == c).astype(np.float32) for c in range(3))  # type: ignore[return-value]


def demosaic_Menon2007(mosaic: np.ndarray, cfa: np.ndarray) -> np.ndarray:
    """Bayer demosaicing by directional filtering and a posteriori decision (Menon et al. 2007).

    Green is interpolated horizontally and vertically (Eq. 3-4), the direction with the smaller
    gradient of colour differences is kept (Eq. 6-8), red and blue follow by interpolating colour
    differences along the chosen direction, then the refining step (Sec. IV) updates all three.
    float32, OpenCV filters with mirrored borders.

    Reference: Menon, Andriani, Calvagno. Demosaicing With Directional Filtering and a
    posteriori Decision. IEEE Transactions on Image Processing 16(1), 2007.

    Args:
        mosaic: (H, W) float, one value per photosite (damcap applies it to log values).
        cfa: (H, W) int in {0, 1, 2}, a 2x2 Bayer layout.

    Returns:
        (H, W, 3) float32.

    Raises:
        DamcapError: ``cfa`` is not a Bayer layout.

    >>> cfa = np.tile(np.array([[0, 1], [1, 2]]), (4, 4))
    >>> rgb = demosaic_Menon2007(np.where(cfa == 0, 1.0, np.where(cfa == 1, 2.0, 3.0)), cfa)
    >>> bool(np.abs(rgb - [1.0, 2.0, 3.0]).max() < 1e-5)
    True
    """
    import cv2

    masks = bayer_masks(cfa)
    if masks is None:
        raise DamcapError("Menon demosaicing needs a 2x2 Bayer colour-filter layout")
    r_m, g_m, b_m = masks
    cfa_v = np.asarray(mosaic, dtype=np.float32)
    border = cv2.BORDER_REFLECT_101

    def cnv_h(x: np.ndarray, k: np.ndarray) -> np.ndarray:
        return cv2.filter2D(x, -1, np.asarray(k, np.float32)[None, :], borderType=border)

    def cnv_v(x: np.ndarray, k: np.ndarray) -> np.ndarray:
        return cv2.filter2D(x, -1, np.asarray(k, np.float32)[:, None], borderType=border)

    h_0 = np.array([0.0, 0.5, 0.0, 0.5, 0.0])
    h_1 = np.array([-0.25, 0.0, 0.5, 0.0, -0.25])
    k_b = np.array([0.5, 0.0, 0.5])
    fir = np.ones(3) / 3
    r = cfa_v * r_m
    g = cfa_v * g_m
    b = cfa_v * b_m
    g_h = np.where(g_m == 0, cnv_h(cfa_v, h_0) + cnv_h(cfa_v, h_1), g)
    g_v = np.where(g_m == 0, cnv_v(cfa_v, h_0) + cnv_v(cfa_v, h_1), g)
    c_h = np.where(r_m == 1, r - g_h, np.where(b_m == 1, b - g_h, 0.0)).astype(np.float32)
    c_v = np.where(r_m == 1, r - g_v, np.where(b_m == 1, b - g_v, 0.0)).astype(np.float32)
    d_h = np.abs(c_h - cv2.copyMakeBorder(c_h, 0, 0, 0, 2, border)[:, 2:])
    d_v = np.abs(c_v - cv2.copyMakeBorder(c_v, 0, 2, 0, 0, border)[2:, :])
    k = np.array([[0, 0, 1, 0, 1], [0, 0, 0, 1, 0], [0, 0, 3, 0, 3], [0, 0, 0, 1, 0], [0, 0, 1, 0, 1]], np.float32)
    # scipy's convolve flips the kernel; cv2.filter2D correlates: flip explicitly.
    dd_h = cv2.filter2D(d_h, -1, k[::-1, ::-1].copy(), borderType=cv2.BORDER_CONSTANT)
    dd_v = cv2.filter2D(d_v, -1, k.T[::-1, ::-1].copy(), borderType=cv2.BORDER_CONSTANT)
    horizontal = dd_v >= dd_h
    g = np.where(horizontal, g_h, g_v).astype(np.float32)
    del g_h, g_v, c_h, c_v, d_h, d_v, dd_h, dd_v
    red_rows = np.broadcast_to((r_m.any(axis=1))[:, None], r_m.shape)
    blue_rows = np.broadcast_to((b_m.any(axis=1))[:, None], b_m.shape)
    red_cols = np.broadcast_to((r_m.any(axis=0))[None, :], r_m.shape)
    blue_cols = np.broadcast_to((b_m.any(axis=0))[None, :], b_m.shape)
    g_site = g_m == 1
    r = np.where(g_site & red_rows, g + cnv_h(r, k_b) - cnv_h(g, k_b), r)
    r = np.where(g_site & blue_rows, g + cnv_v(r, k_b) - cnv_v(g, k_b), r)
    b = np.where(g_site & blue_rows, g + cnv_h(b, k_b) - cnv_h(g, k_b), b)
    b = np.where(g_site & red_rows, g + cnv_v(b, k_b) - cnv_v(g, k_b), b)
    r = np.where(blue_rows & (b_m == 1),
                 np.where(horizontal, b + cnv_h(r, k_b) - cnv_h(b, k_b), b + cnv_v(r, k_b) - cnv_v(b, k_b)), r)
    b = np.where(red_rows & (r_m == 1),
                 np.where(horizontal, r + cnv_h(b, k_b) - cnv_h(r, k_b), r + cnv_v(b, k_b) - cnv_v(r, k_b)), b)
    r, g, b = (np.asarray(x, np.float32) for x in (r, g, b))
    # Refining step (Sec. IV): green from smoothed colour differences, then red and blue.
    r_g = r - g
    b_g = b - g
    b_g_m = np.where(b_m == 1, np.where(horizontal, cnv_h(b_g, fir), cnv_v(b_g, fir)), 0.0)
    r_g_m = np.where(r_m == 1, np.where(horizontal, cnv_h(r_g, fir), cnv_v(r_g, fir)), 0.0)
    g = np.where(r_m == 1, r - r_g_m, g)
    g = np.where(b_m == 1, b - b_g_m, g).astype(np.float32)
    r_g = (r - g).astype(np.float32)
    b_g = (b - g).astype(np.float32)
    sel = g_site & blue_rows
    r_g_m = np.where(sel, cnv_v(r_g, k_b), r_g_m)
    r = np.where(sel, g + r_g_m, r)
    sel = g_site & blue_cols
    r_g_m = np.where(sel, cnv_h(r_g, k_b), r_g_m)
    r = np.where(sel, g + r_g_m, r)
    sel = g_site & red_rows
    b_g_m = np.where(sel, cnv_v(b_g, k_b), b_g_m)
    b = np.where(sel, g + b_g_m, b)
    sel = g_site & red_cols
    b_g_m = np.where(sel, cnv_h(b_g, k_b), b_g_m)
    b = np.where(sel, g + b_g_m, b)
    r_b = (r - b).astype(np.float32)
    r_b_m = np.where(b_m == 1, np.where(horizontal, cnv_h(r_b, fir), cnv_v(r_b, fir)), 0.0)
    r = np.where(b_m == 1, b + r_b_m, r)
    r_b_m = np.where(r_m == 1, np.where(horizontal, cnv_h(r_b, fir), cnv_v(r_b, fir)), 0.0)
    b = np.where(r_m == 1, r - r_b_m, b)
    return np.stack([r, g, b], axis=-1).astype(np.float32)


def demosaic_log(mosaic: np.ndarray, cfa: np.ndarray, floor: float) -> np.ndarray:
    """Demosaic HDR values in the log domain (colour ratios instead of colour differences).

    Across the huge contrasts of an HDR mosaic, interpolating ``log`` values keeps estimates
    positive and interpolates hue as a ratio; Bayer layouts use :func:`demosaic_Menon2007`, other
    layouts :func:`demosaic_bilinear`.

    Args:
        mosaic: (H, W) float, linear, >= 0 up to noise.
        cfa: (H, W) int in {0, 1, 2}.
        floor: values below are raised to it before the log (the smallest resolvable signal), > 0.

    Returns:
        (H, W, 3) float32, linear, > 0.
    """
    if not floor > 0:
        raise DamcapError(f"log-domain demosaicing needs a positive floor, got {floor}")
    log_m = np.log(np.maximum(np.asarray(mosaic, dtype=np.float32), np.float32(floor)))
    rgb = demosaic_Menon2007(log_m, cfa) if bayer_masks(cfa) is not None else demosaic_bilinear(log_m, cfa)
    return np.exp(rgb)


def dilate_mask(mask: np.ndarray, radius: int = 1) -> np.ndarray:
    """True where any pixel within ``radius`` (square neighbourhood) is True.

    >>> dilate_mask(np.eye(3, dtype=bool)[0:1]).tolist()
    [[True, True, False]]
    """
    import cv2

    m = np.asarray(mask).astype(np.uint8)
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    return cv2.dilate(m, k, borderType=cv2.BORDER_REFLECT_101).astype(bool)


def rgb_from_camera_matrix(color_matrix: np.ndarray, daylight_whitebalance: np.ndarray) -> np.ndarray | None:
    """Camera RGB to linear Rec.709 from LibRaw's ``rgb_cam`` and daylight multipliers.

    LibRaw's ``color_matrix`` maps white-balanced camera RGB to sRGB primaries (rows sum to 1);
    the daylight multipliers ``pre_mul`` come from the same file matrix. Their product is the
    colorimetric transform ``inverse(camera_from_XYZ @ XYZ_from_Rec709)``, scaled so that the green
    multiplier is 1.

    Args:
        color_matrix: (3, 3) or (3, 4) float, rawpy's ``color_matrix``.
        daylight_whitebalance: (3,) or (4,) float, rawpy's ``daylight_whitebalance``.

    Returns:
        (3, 3) float64, or None when the file gives no matrix (all zeros) or no usable multipliers.
    """
    m = np.asarray(color_matrix, dtype=np.float64)[:3, :3]
    wb = np.asarray(daylight_whitebalance, dtype=np.float64)[:3]
    if not np.any(m) or not np.all(np.isfinite(m)) or not np.all(wb > 0) or not np.all(np.isfinite(wb)):
        return None
    return m @ np.diag(wb / wb[1])


def apply_flip(image: np.ndarray, flip: int) -> np.ndarray:
    """Apply LibRaw's orientation code (``sizes.flip``) to an (H, W, ...) image.

    >>> apply_flip(np.arange(6).reshape(2, 3), 6).tolist()
    [[3, 0], [4, 1], [5, 2]]
    """
    if flip == 3:
        return np.rot90(image, 2).copy()
    if flip == 5:
        return np.rot90(image, 1).copy()
    if flip == 6:
        return np.rot90(image, -1).copy()
    return image


# --------------------------------------------------------------------------------------------
# Reader
# --------------------------------------------------------------------------------------------

#: bytes per photosite that reading a RAW photo makes (normalised float64 counts, its saturation
#: mask, the demosaiced and converted float32 RGB, the flipped copies)
RAW_WORKING_BYTES = 48


def read_raw(path: str | os.PathLike, saturation_fraction: float = SATURATION_FRACTION) -> RawMosaic:
    """Read one RAW file as normalised linear counts (no demosaicing, no colour processing).

    Args:
        path: any file LibRaw reads (DNG, CR2, NEF, ARW, ...).
        saturation_fraction: see :func:`normalize_raw`.

    Raises:
        DamcapError: the file is missing, not a RAW LibRaw can read, damaged, not an RGB sensor,
            or (from its header, before decoding) more pixels than this machine's memory holds.
    """
    import rawpy

    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: file not found")
    from damcap.common.exr import check_header_size

    try:
        with rawpy.RawPy() as raw:
            raw.open_file(str(path))  # the header: sizes are known before anything is decoded
            check_header_size(path, raw.sizes.raw_width, raw.sizes.raw_height, 1, 2, RAW_WORKING_BYTES)
            raw.unpack()
            values = np.array(raw.raw_image_visible, copy=True)
            blacks = np.asarray(raw.black_level_per_channel, dtype=np.float64)
            white = float(raw.white_level)
            per_white = raw.camera_white_level_per_channel
            matrix = rgb_from_camera_matrix(raw.color_matrix, raw.daylight_whitebalance)
            flip = int(raw.sizes.flip)
            if values.ndim == 2:
                colors = np.array(raw.raw_colors_visible, copy=True)
                cfa = cfa_channels(colors, raw.color_desc)
            else:
                colors = None
                cfa = None
    except (rawpy.LibRawError, OSError, ValueError) as e:
        raise DamcapError(f"{path}: cannot read as a camera RAW file ({type(e).__name__}: {e}); "
                          "is the file complete and a RAW format?") from None
    if colors is not None:
        black = blacks[colors]
        white_site = np.asarray(per_white, dtype=np.float64)[colors] if per_white is not None and min(per_white) > 0 else white
    else:
        black = blacks[: values.shape[-1]]
        white_site = white
    counts, saturated = normalize_raw(values, black, white_site, saturation_fraction)
    return RawMosaic(counts=counts, saturated=saturated, cfa=cfa, rgb_from_camera=matrix, flip=flip,
                     black_level=tuple(float(b) for b in blacks), white_level=white)


def camera_rgb_from_mosaic(counts: np.ndarray, cfa: np.ndarray | None, floor: float) -> np.ndarray:
    """Camera RGB of merged counts: (H, W) mosaics are demosaiced (:func:`demosaic_log`), (H, W, 3) passes.

    Args:
        counts: (H, W) or (H, W, 3) float, linear.
        cfa: (H, W) colour of each photosite, or None for (H, W, 3) input.
        floor: see :func:`demosaic_log`.

    Returns:
        (H, W, 3) float32, linear camera RGB.
    """
    counts = np.asarray(counts)
    if counts.ndim == 3:
        return counts.astype(np.float32)
    if cfa is None:
        raise DamcapError("a single-channel RAW needs its colour-filter pattern")
    return demosaic_log(counts, cfa, floor)


def to_rec709(camera_rgb: np.ndarray, rgb_from_camera: np.ndarray | None, source: str = "") -> tuple[np.ndarray, bool]:
    """Camera RGB to linear Rec.709; without a matrix, warn and keep camera RGB.

    Args:
        camera_rgb: (H, W, 3) float, linear camera RGB.
        rgb_from_camera: (3, 3) or None.
        source: file name for the warning.

    Returns:
        (H, W, 3) float32 and whether a colour matrix was applied.
    """
    if rgb_from_camera is None:
        warnings.warn(
            f"{source}: the RAW file has no colour matrix; output stays in the camera's own RGB "
            "(colour space recorded as camera_rgb)", CaptureWarning, stacklevel=2)
        return np.asarray(camera_rgb, np.float32), False
    out = np.asarray(camera_rgb, np.float32) @ np.asarray(rgb_from_camera, np.float32).T
    return out, True


def read_raw_rgb(path: str | os.PathLike, saturation_fraction: float = SATURATION_FRACTION) -> tuple[np.ndarray, np.ndarray, bool]:
    """One RAW photo as linear RGB (``damcap linearize`` and ``damcap reconstruct`` read RAW files with it).

    The sensor values as :func:`read_raw` gives them (black subtracted, 1 = white level),
    demosaiced once (:func:`camera_rgb_from_mosaic`), converted with the file's colour matrix
    (:func:`to_rec709`, which warns when there is none) and turned upright (:func:`apply_flip`).
    The exposure is not divided out here.

    Args:
        path: any file LibRaw reads.
        saturation_fraction: see :func:`normalize_raw`.

    Returns:
        rgb: (H, W, 3) float32, linear Rec.709 (camera RGB when the file has no colour matrix), >= 0.
        clipped: (H, W) bool, some photosite saturated (dilated by the demosaicing footprint for mosaics).
        converted: whether a colour matrix was applied.

    Raises:
        DamcapError: see :func:`read_raw`.
    """
    m = read_raw(path, saturation_fraction)
    floor = 1.0 / (m.white_level - max(m.black_level))
    cam = camera_rgb_from_mosaic(np.maximum(m.counts, 0.0), m.cfa, floor)
    rgb, converted = to_rec709(cam, m.rgb_from_camera, Path(path).name)
    sat = m.saturated if m.saturated.ndim == 2 else m.saturated.any(axis=-1)
    clipped = dilate_mask(sat, 2) if m.cfa is not None else sat
    return np.maximum(apply_flip(rgb, m.flip), 0.0), apply_flip(clipped, m.flip), converted
