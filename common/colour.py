"""Colour encodings: the sRGB curve (IEC 61966-2-1) and display encodings of linear radiance.

The one place where damcap encodes or decodes sRGB: capture's response curves, synth's
photos, export's display frames and the paper's preview figure all use these functions. Pure
numpy, elementwise, float64 inside.

References:
    IEC 61966-2-1:1999, Multimedia systems and equipment - Colour measurement and management -
    Part 2-1: Default RGB colour space - sRGB.
"""

from __future__ import annotations

import numpy as np

#: fraction of the display range the exposure reference maps to (headroom for highlights)
DISPLAY_KEY = 0.8

#: exponent of the plain power curve the paper's preview figure uses (not sRGB)
PREVIEW_GAMMA = 2.2


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """The sRGB decoding curve (IEC 61966-2-1), elementwise.

    Args:
        srgb: (...) float, encoded values in [0, 1] (values outside are clipped).

    Returns:
        (...) float64, linear in [0, 1].

    >>> round(float(srgb_to_linear(np.array(0.5))), 7)
    0.2140411
    """
    v = np.clip(np.asarray(srgb, dtype=np.float64), 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(lin: np.ndarray) -> np.ndarray:
    """The sRGB encoding curve (inverse of :func:`srgb_to_linear`), elementwise.

    Args:
        lin: (...) float, linear in [0, 1] (values outside are clipped).

    Returns:
        (...) float64, encoded in [0, 1].

    >>> round(float(linear_to_srgb(np.array(0.18))), 7)
    0.4613561
    """
    v = np.clip(np.asarray(lin, dtype=np.float64), 0.0, 1.0)
    return np.where(v <= 0.0031308, v * 12.92, 1.055 * np.power(v, 1 / 2.4) - 0.055)


def exposure_scale_for(radiance_lin: np.ndarray, mask: np.ndarray, percentile: float = 95.0) -> float:
    """A scale that maps the ``percentile`` of the masked radiance to :data:`DISPLAY_KEY`.

    Args:
        radiance_lin: (..., 3) linear radiance, >= 0.
        mask: (...) bool, pixels that count.
        percentile: which radiance value becomes DISPLAY_KEY, in [0, 100].

    Returns:
        the scale (1 when the masked radiance is black or empty).

    >>> exposure_scale_for(np.full((2, 2, 3), 2.0), np.ones((2, 2), bool))
    0.4
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

    >>> display_srgb8(np.array([[[0.18, 0.0, 2.0]]]), 1.0).tolist()
    [[[118, 0, 255]]]
    """
    x = np.asarray(radiance_lin, np.float64) * exposure_scale
    return np.round(linear_to_srgb(x) * 255).astype(np.uint8)


def preview_gamma(radiance_scaled: np.ndarray, gamma: float = PREVIEW_GAMMA) -> np.ndarray:
    """A quick preview encoding: clip to [0, 1], then the plain power curve ``x ** (1 / gamma)``.

    Not sRGB (no linear toe); the paper's false-colour figure shows its photos with it.

    Args:
        radiance_scaled: (...) linear radiance already divided by a white level.
        gamma: display exponent (> 0).

    Returns:
        (...) encoded values in [0, 1], the input's float dtype.

    >>> round(float(preview_gamma(np.array(0.18))), 7)
    0.4586564
    """
    return np.clip(radiance_scaled, 0, 1) ** (1 / gamma)


_COLOUR_NAMES = {"lin_rec709": "ITU-R BT.709", "acescg": "ACEScg"}


def working_from_rec709(colorspace: str) -> np.ndarray:
    """(3, 3) matrix from linear Rec.709 to a working space (CAT02 adaptation D65 -> ACES white).

    Raises:
        DamcapError: an unknown colour space name.

    >>> working_from_rec709("lin_rec709").tolist() == np.eye(3).tolist()
    True
    >>> bool(np.allclose(working_from_rec709("acescg").sum(axis=1), 1.0, atol=1e-3))
    True
    """
    from damcap.common.capture_folder import COLORSPACES
    from damcap.common.errors import DamcapError

    if colorspace not in COLORSPACES:
        raise DamcapError(f"--colorspace must be one of {', '.join(COLORSPACES)}, got {colorspace!r}")
    if colorspace == "lin_rec709":
        return np.eye(3)
    import colour

    src = colour.RGB_COLOURSPACES[_COLOUR_NAMES["lin_rec709"]]
    dst = colour.RGB_COLOURSPACES[_COLOUR_NAMES[colorspace]]
    return np.asarray(colour.matrix_RGB_to_RGB(src, dst, chromatic_adaptation_transform="CAT02"), dtype=np.float64)
