"""Single-exposure photos: undo the curve, divide out exposure; folders of real auto-exposed photos."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from damcap.capture.exif import Exposure, read_exposure
from damcap.capture.linearize import LinearizeOptions, clipped_mask, linearize_files, linearize_photo, list_photos
from damcap.capture.response import srgb_log_response
from damcap.common.colour import linear_to_srgb
from damcap.common.errors import DamcapError
from damcap.common.exr import read_exr


def test_exposure_division_closed_form():
    radiance = np.array([[[0.02, 0.1, 0.3]]])
    for exp in (Exposure(1 / 60, 800, 2.5), Exposure(1 / 40, 500, 2.5), Exposure(1 / 125, 100, 1.4)):
        h = exp.time_s * exp.iso / 100 / exp.f_number**2
        photo = linear_to_srgb(np.clip(radiance * h / 0.01, 0, 1))  # what the camera records at H
        back = linearize_photo(photo, exp, reference_exposure=0.01)
        assert np.allclose(back, radiance, rtol=1e-5)
    # two photos of one scene at different exposures agree after linearisation
    a = linearize_photo(linear_to_srgb(radiance * 0.5), 0.5, 1.0)
    b = linearize_photo(linear_to_srgb(radiance * 2.0), 2.0, 1.0)
    assert np.allclose(a, b, rtol=1e-6) and np.allclose(a, radiance, rtol=1e-6)


def test_codes_and_response_tables():
    codes = np.array([[[0, 128, 255]]], np.uint8)
    lin = linearize_photo(codes, 1.0)
    assert lin[0, 0].tolist() == pytest.approx([0.0, 0.2158605, 1.0], abs=1e-6)
    table = linearize_photo(codes, 1.0, log_response=srgb_log_response(256))
    assert np.allclose(table[0, 0, 1:], lin[0, 0, 1:], rtol=1e-6)
    c16 = linearize_photo(np.array([[[0, 32768, 65535]]], np.uint16), 2.0)
    assert c16[0, 0, 2] == pytest.approx(0.5)
    assert clipped_mask(codes[..., [2, 0, 0]]).tolist() == [[True]]


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_integer_codes_give_the_values_of_their_float_encoding(dtype):
    """8/16-bit codes go through a table of the sRGB curve: bit for bit the values of the codes
    as floats in [0, 1]."""
    top = np.iinfo(dtype).max
    codes = np.random.default_rng(0).integers(0, top + 1, (7, 5, 3)).astype(dtype)
    codes[0, 0] = [0, 1, top]
    exp = Exposure(time_s=0.01, iso=200, f_number=4.0)
    assert np.array_equal(linearize_photo(codes, exp, 0.003), linearize_photo(codes / float(top), exp, 0.003))


def test_linearize_photo_errors():
    with pytest.raises(DamcapError, match="no exposure time"):
        linearize_photo(np.zeros((2, 2, 3)), Exposure(None))
    with pytest.raises(DamcapError, match="positive"):
        linearize_photo(np.zeros((2, 2, 3)), 0.0)
    with pytest.raises(DamcapError, match=r"\(H, W, 3\)"):
        linearize_photo(np.zeros((2, 2)), 1.0)
    with pytest.raises(DamcapError, match=r"\(3, L\)"):
        linearize_photo(np.zeros((2, 2, 3)), 1.0, log_response=np.zeros(256))


def test_auto_exposed_real_photos(shared_data, tmp_path):
    """mold_gold_cape: auto exposure varies; outputs carry the inverse exposure as their scale."""
    src = shared_data / "real" / "mold_gold_cape" / "images"
    names = sorted(p.name for p in src.glob("*.JPG"))
    exps = {n: read_exposure(src / n) for n in names}
    factors = {n: e.time_s * e.iso / 100 / e.f_number**2 for n, e in exps.items()}
    lo, hi = min(factors, key=factors.get), max(factors, key=factors.get)
    assert factors[hi] / factors[lo] > 1.5  # the camera really changed exposure
    folder = tmp_path / "photos"
    folder.mkdir()
    for n in (lo, hi):
        shutil.copy(src / n, folder / n)
    out = tmp_path / "out"
    record = linearize_files(list_photos(folder), out, LinearizeOptions())
    ref = record["reference_exposure"]
    assert ref == pytest.approx(np.median([factors[lo], factors[hi]]))
    for r in record["photos"]:
        assert r["scale"] == pytest.approx(ref / factors[r["file"]], rel=1e-6)
        pixels, names_ = read_exr(out / r["output"])
        assert names_ == ("R", "G", "B", "clipped") and pixels.shape == (912, 912, 4)
        photo = read_exr(src / r["file"])[0]  # OpenImageIO decodes the JPEG to [0, 1]
        expected = linearize_photo(photo, factors[r["file"]], ref)
        assert np.abs(pixels[..., :3] - expected).max() < 2e-3 * max(1.0, float(expected.max()))  # half storage
        assert 0 < pixels[..., 3].mean() < 0.05  # a few specular highlights clip


def test_folder_errors(tmp_path, shared_data):
    with pytest.raises(DamcapError, match="not a folder"):
        list_photos(tmp_path / "none")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DamcapError, match="no photos found"):
        list_photos(tmp_path / "empty")
    pngs = tmp_path / "pngs"
    pngs.mkdir()
    shutil.copy(shared_data / "brackets" / "memorial" / "memorial0066.png", pngs)
    with pytest.raises(DamcapError, match="memorial0066.png: no exposure time.*--ignore-exposure"):
        linearize_files(list_photos(pngs), tmp_path / "o", LinearizeOptions())
    record = linearize_files(list_photos(pngs), tmp_path / "o", LinearizeOptions(ignore_exposure=True))
    assert record["photos"][0]["scale"] == 1.0
    assert json.dumps(record)  # serialisable


def test_a_bad_later_input_leaves_no_output_file(tmp_path):
    from damcap.common.exr import write_image_u8

    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        write_image_u8(photos / f"p{k}.jpg", (rng.random((32, 32, 3)) * 255).astype(np.uint8))
    data = (photos / "p2.jpg").read_bytes()
    (photos / "p2.jpg").write_bytes(data[: len(data) // 2])  # the last photo is truncated
    out = tmp_path / "out"
    with pytest.raises(DamcapError, match=r"p2\.jpg: cannot read pixels, the file is damaged or truncated"):
        linearize_files(list_photos(photos), out, LinearizeOptions(ignore_exposure=True))
    assert not out.exists()  # nothing written, not even the folder this call made
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(DamcapError):
        linearize_files(list_photos(photos), out, LinearizeOptions(ignore_exposure=True))
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]  # no EXR, no staging folder
    (photos / "p2.jpg").unlink()
    record = linearize_files(list_photos(photos), out, LinearizeOptions(ignore_exposure=True))
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt", "p0.exr", "p1.exr"]
    assert [r["output"] for r in record["photos"]] == ["p0.exr", "p1.exr"]


@pytest.mark.parametrize("field, value", [("clip_level", float("nan")), ("reference_exposure", float("inf")),
                                          ("reference_exposure", float("nan")), ("clip_level", float("inf"))])
def test_options_refuse_nan_and_inf(field, value):
    with pytest.raises(DamcapError, match="--" + field.replace("_", "-")):
        LinearizeOptions(**{field: value}).validate()
