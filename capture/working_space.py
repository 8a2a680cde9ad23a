"""Working colour spaces of damcap's linear images and the conversions between them (colour-science)."""

from __future__ import annotations

from typing import Literal

import numpy as np

from damcap.common.capture_folder import COLORSPACES  # noqa: F401  (the names --colorspace accepts: the capture format's)
from damcap.common.colour import working_from_rec709

ColorSpace = Literal["lin_rec709", "acescg"]
#: the label of unconverted camera RGB (a RAW file without a colour matrix)
CAMERA_RGB = "camera_rgb"

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
