"""Working colour spaces: Rec.709 -> ACEScg against the matrix built from the primaries (CAT02)."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.capture.working_space import COLORSPACES, rec709_to_working, working_from_rec709
from damcap.common.errors import DamcapError

#: CAT02 cone response matrix (CIE 159:2004)
M_CAT02 = np.array([[0.7328, 0.4296, -0.1624], [-0.7036, 1.6975, 0.0061], [0.0030, 0.0136, 0.9834]])


def _xyz_from_rgb(primaries_xy: list[tuple[float, float]], white_xy: tuple[float, float]) -> np.ndarray:
    """RGB -> XYZ of a colour space from its chromaticities (SMPTE RP 177)."""
    xyz = lambda x, y: np.array([x / y, 1.0, (1 - x - y) / y])  # noqa: E731
    p = np.stack([xyz(*c) for c in primaries_xy], axis=1)
    s = np.linalg.solve(p, xyz(*white_xy))
    return p * s


def _rec709_to_acescg_reference() -> np.ndarray:
    d65, aces_white = (0.3127, 0.3290), (0.32168, 0.33767)
    rec709 = _xyz_from_rgb([(0.64, 0.33), (0.30, 0.60), (0.15, 0.06)], d65)
    ap1 = _xyz_from_rgb([(0.713, 0.293), (0.165, 0.830), (0.128, 0.044)], aces_white)
    w_src = M_CAT02 @ np.array([d65[0] / d65[1], 1.0, (1 - sum(d65)) / d65[1]])
    w_dst = M_CAT02 @ np.array([aces_white[0] / aces_white[1], 1.0, (1 - sum(aces_white)) / aces_white[1]])
    cat = np.linalg.inv(M_CAT02) @ np.diag(w_dst / w_src) @ M_CAT02
    return np.linalg.inv(ap1) @ cat @ rec709


def test_rec709_is_the_identity_and_a_copy():
    assert COLORSPACES == ("lin_rec709", "acescg")
    np.testing.assert_array_equal(working_from_rec709("lin_rec709"), np.eye(3))
    img = np.random.default_rng(0).uniform(0, 4, (3, 4, 3)).astype(np.float32)
    out = rec709_to_working(img, "lin_rec709")
    np.testing.assert_array_equal(out, img)
    out[0, 0, 0] = -1.0
    assert img[0, 0, 0] >= 0  # the input is not modified


def test_acescg_matrix_matches_the_primaries():
    m = working_from_rec709("acescg")
    np.testing.assert_allclose(m, _rec709_to_acescg_reference(), atol=1e-4)
    np.testing.assert_allclose(m.sum(axis=1), 1.0, atol=1e-4)  # white stays white (adapted)


def test_acescg_conversion_of_images_and_round_trip():
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 10, (5, 6, 3)).astype(np.float32)
    out = rec709_to_working(img, "acescg")
    assert out.dtype == np.float32 and out.shape == img.shape
    m = working_from_rec709("acescg")
    np.testing.assert_allclose(out, img @ m.T, rtol=1e-5)
    np.testing.assert_allclose(out @ np.linalg.inv(m).T.astype(np.float32), img, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(rec709_to_working(np.ones((1, 1, 3)), "acescg"), 1.0, atol=1e-4)
    # NaN is carried, not hidden
    bad = img.copy()
    bad[0, 0, 1] = np.nan
    assert np.isnan(rec709_to_working(bad, "acescg")[0, 0]).all() and np.isfinite(rec709_to_working(bad, "acescg")[1:]).all()


@pytest.mark.parametrize("name", ["srgb", "ACEScg", ""])
def test_unknown_colour_space(name):
    with pytest.raises(DamcapError, match=rf"--colorspace must be one of lin_rec709, acescg, got {name!r}"):
        working_from_rec709(name)
    with pytest.raises(DamcapError, match="--colorspace"):
        rec709_to_working(np.zeros((1, 1, 3)), name)
