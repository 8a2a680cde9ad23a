"""Working colour spaces of damcap's linear images and the conversions between them (colour-science)."""

from __future__ import annotations

from typing import Literal

import numpy as np

from damcap.common.capture_folder import COLORSPACES  # noqa: F401  (the names --colorspace accepts: the capture format's)
from damcap.common.errors import DamcapError

ColorSpace = Literal["lin_rec709", "acescg"]
#: the label of unconverted camera RGB (a RAW file without a colour matrix)
CAMERA_RGB = "camera_rgb"

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
    if colorspace not in COLORSPACES:
        raise DamcapError(f"--colorspace must be one of {', '.join(COLORSPACES)}, got {colorspace!r}")
    if colorspace == "lin_rec709":
        return np.eye(3)
    import colour

    src = colour.RGB_COLOURSPACES[_COLOUR_NAMES["lin_rec709"]]
    dst = colour.RGB_COLOURSPACES[_COLOUR_NAMES[colorspace]]
    return np.asarray(colour.matrix_RGB_to_RGB(src, dst, chromatic_adaptation_transform="CAT02"), dtype=np.float64)


def rec709_to_working(radiance_rec709: np.ndarray, colorspace: str) -> np.ndarray:
    """Convert (H, W, 3) linear Rec.709 to the working space (a copy; the input is not modified).

    Args:
        radiance_rec709: (H, W, 3) float, linear.
        colorspace: one of :data:`COLORSPACES`.

    Returns:
        (H, W, 3) float32, linear, in the working space.
    """
    m = working_from_rec709(colorspace)
    img = np.asarray(radiance_rec709, dtype=np.float32)
    if colorspace == "lin_rec709":
        return img.copy()
    return img @ m.astype(np.float32).T
