"""RAW decoding: the two real files, levels, colour matrices, demosaicing, orientation."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from damcap.capture.raw import (
    CaptureWarning,
    apply_flip,
    bayer_masks,
    cfa_channels,
    demosaic_bilinear,
    demosaic_log,
    demosaic_Menon2007,
    normalize_raw,
    read_raw,
    rgb_from_camera_matrix,
    to_rec709,
)
from damcap.synth.brackets import CANON_550D_CAMERA_FROM_XYZ, XYZ_FROM_REC709, cfa_map, mosaic
from damcap.common.errors import DamcapError


def test_real_dng_levels_size_and_colour_matrix(shared_data):
    m = read_raw(shared_data / "raw" / "tinydng_colorchart.dng")
    # DefaultCropSize 1734x1156, BlackLevel 2056, WhiteLevel 15000 (from the file's tags)
    assert m.counts.shape == (1156, 1734) and m.cfa.shape == (1156, 1734)
    assert m.black_level == (2056.0,) * 4 and m.white_level == 15000.0
    assert m.cfa[:2, :2].tolist() == [[0, 1], [1, 2]]  # RGGB
    # counts are (raw - black) / (white - black): the chart's darkest patch sits near 0
    assert -0.02 < float(m.counts.min()) < 0.01 and 0.5 < float(m.counts.max()) < 1.0
    assert not m.saturated.any()
    # The matrix is the colorimetric inverse of the file's ColorMatrix1 (XYZ -> camera):
    # rgb_from_camera @ camera_from_xyz @ xyz_from_rec709 = identity up to the green scale.
    prod = m.rgb_from_camera @ np.asarray(CANON_550D_CAMERA_FROM_XYZ) @ np.asarray(XYZ_FROM_REC709)
    assert np.allclose(prod / prod[1, 1], np.eye(3), atol=2e-3)


def test_real_kdc_without_colour_matrix_warns(shared_data):
    m = read_raw(shared_data / "raw" / "RAW_KODAK_DC50.KDC")
    assert m.counts.shape == (512, 768) and m.white_level == 16383.0 and m.black_level == (0.0,) * 4
    assert m.rgb_from_camera is None
    assert 0 < m.saturated.mean() < 1e-3  # a few photosites at the white level
    with pytest.warns(CaptureWarning, match="no colour matrix"):
        rgb, converted = to_rec709(np.ones((2, 2, 3)), m.rgb_from_camera, "RAW_KODAK_DC50.KDC")
    assert not converted and rgb.shape == (2, 2, 3)


def test_corrupt_and_non_raw_files(tmp_path, shared_data):
    bad = tmp_path / "broken.dng"
    bad.write_bytes((shared_data / "raw" / "tinydng_colorchart.dng").read_bytes()[:4000])
    with pytest.raises(DamcapError, match="broken.dng: cannot read as a camera RAW"):
        read_raw(bad)
    text = tmp_path / "notes.cr2"
    text.write_text("not an image")
    with pytest.raises(DamcapError, match="notes.cr2"):
        read_raw(text)
    with pytest.raises(DamcapError, match="file not found"):
        read_raw(tmp_path / "missing.nef")


def test_a_raw_file_beyond_memory_is_refused_from_its_header(shared_data, monkeypatch):
    """The sensor size is read from the header and checked against memory (with what reading makes
    of each photosite) before LibRaw decodes anything."""
    from damcap.common import validate

    monkeypatch.setattr(validate, "machine_memory_bytes", lambda: 64 * 2 ** 20)
    # 1888x1182 photosites (the sensor's whole raw size), 2 bytes each decoded and copied, 48 made of each
    with pytest.raises(DamcapError, match=r"tinydng_colorchart.dng: an image of 1888x1182 pixels, 1 channels would need 0.108 GiB "
                                          r"of memory; this machine allows 0.0312 GiB"):
        read_raw(shared_data / "raw" / "tinydng_colorchart.dng")


def test_normalize_and_saturation_on_raw_values():
    raw = np.array([[512, 8448, 16190, 16383]], np.uint16)
    counts, sat = normalize_raw(raw, 512.0, 16383.0, 0.99)
    assert counts[0].tolist() == pytest.approx([0.0, 0.5000315, 0.98784, 1.0], abs=1e-5)
    assert sat[0].tolist() == [False, False, False, True]
    with pytest.raises(DamcapError, match="white level"):
        normalize_raw(raw, 600.0, 500.0)


def test_cfa_mapping_and_bayer_detection():
    assert cfa_channels(np.array([[0, 1], [3, 2]]), b"RGBG").tolist() == [[0, 1], [1, 2]]
    with pytest.raises(DamcapError, match="not an RGB mosaic"):
        cfa_channels(np.zeros((2, 2), int), b"CMYG")
    assert bayer_masks(cfa_map((4, 6), "GBRG")) is not None
    assert bayer_masks(np.zeros((4, 4), int)) is None


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_demosaic_reproduces_smooth_colour_fields(cfa):
    h, w = 32, 48
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    rgb = np.stack([1 + 0.01 * xx, 2 + 0.02 * yy, 0.5 + 0.005 * (xx + yy)], axis=-1)
    colors = cfa_map((h, w), cfa)
    mos = mosaic(rgb, cfa)
    inner = (slice(3, -3), slice(3, -3))
    # bilinear is exact on linear ramps; Menon's directional choice costs a fraction of a percent
    for out, tol in ((demosaic_bilinear(mos, colors), 1e-6), (demosaic_Menon2007(mos, colors), 4e-3),
                     (demosaic_log(mos, colors, 1e-6), 4e-3)):
        assert np.abs(out[inner] / rgb[inner] - 1).max() < tol


def test_log_domain_demosaic_handles_hdr_edges_better():
    # A sharp HDR edge (1 : 1000) with a coloured bright side: linear interpolation smears
    # the bright side into the dark one by orders of magnitude; log-domain Menon does not.
    h, w = 32, 32
    rgb = np.full((h, w, 3), [0.001, 0.001, 0.001])
    rgb[:, 16:] = [2.0, 1.0, 0.5]
    colors = cfa_map((h, w), "RGGB")
    mos = mosaic(rgb, "RGGB")
    err = {name: np.abs(np.log(np.maximum(f(), 1e-9)) - np.log(rgb))[4:-4, 4:-4]
           for name, f in {"bilinear": lambda: demosaic_bilinear(mos, colors),
                           "log": lambda: demosaic_log(mos, colors, 1e-6)}.items()}
    assert np.median(err["log"]) < 1e-3
    assert err["log"].max() < 0.5 * err["bilinear"].max()


def test_colour_matrix_from_libraw_values():
    assert rgb_from_camera_matrix(np.zeros((3, 4)), np.ones(4)) is None
    m = rgb_from_camera_matrix(np.eye(3), np.array([2.0, 1.0, 1.5, 0.0]))
    assert m.tolist() == [[2.0, 0, 0], [0, 1.0, 0], [0, 0, 1.5]]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out, converted = to_rec709(np.ones((1, 1, 3)), m)
    assert converted and out[0, 0].tolist() == [2.0, 1.0, 1.5]


def test_flip_codes():
    img = np.arange(6).reshape(2, 3)
    assert apply_flip(img, 0) is img
    assert apply_flip(img, 3).tolist() == [[5, 4, 3], [2, 1, 0]]
    assert apply_flip(img, 5).tolist() == [[2, 5], [1, 4], [0, 3]]
    assert apply_flip(img, 6).tolist() == [[3, 0], [4, 1], [5, 2]]
