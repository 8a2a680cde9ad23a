"""EXR and 8-bit image I/O: exact float round trips, half precision, channel selection, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.common.exr import (image_header, read_exr, read_exr_channels, read_image_u8, upright, upright_size, write_exr,
                               write_image_u8, write_png)


def _ramp(h: int = 5, w: int = 7, c: int = 3) -> np.ndarray:
    return (np.arange(h * w * c, dtype=np.float32).reshape(h, w, c) * 0.37 - 3.1).astype(np.float32)


def test_float_round_trip_is_exact(tmp_path):
    px = _ramp()
    write_exr(tmp_path / "a.exr", px, ("R", "G", "B"), dtype="float")
    back, names = read_exr(tmp_path / "a.exr")
    assert names == ("R", "G", "B") and back.dtype == np.float32 and back.shape == (5, 7, 3)
    np.testing.assert_array_equal(back, px)


def test_half_round_trip_within_half_precision(tmp_path):
    px = np.abs(_ramp()) + 1e-2
    write_exr(tmp_path / "h.exr", px, ("R", "G", "B"))  # half is the default
    back, _ = read_exr(tmp_path / "h.exr")
    np.testing.assert_array_equal(back, px.astype(np.float16).astype(np.float32))
    assert np.max(np.abs(back - px) / px) <= 2.0 ** -11


def test_half_keeps_65504_nan_and_inf_and_overflows_above(tmp_path):
    px = np.array([[[65504.0, np.nan, np.inf], [70000.0, -np.inf, -2.5]]], np.float32)
    write_exr(tmp_path / "x.exr", px, ("R", "G", "B"))
    back, _ = read_exr(tmp_path / "x.exr")
    assert back[0, 0, 0] == 65504.0 and np.isnan(back[0, 0, 1]) and back[0, 0, 2] == np.inf
    assert back[0, 1, 0] == np.inf and back[0, 1, 1] == -np.inf and back[0, 1, 2] == -2.5


def test_a_2d_image_is_one_channel_and_names_are_kept(tmp_path):
    write_exr(tmp_path / "a.exr", np.full((3, 4), 0.5, np.float32), ("A",))
    back, names = read_exr(tmp_path / "a.exr")
    assert names == ("A",) and back.shape == (3, 4, 1) and np.all(back == 0.5)
    px = _ramp(2, 2, 3)
    write_exr(tmp_path / "n.exr", px, ("N.X", "N.Y", "N.Z"), dtype="float")
    assert read_exr(tmp_path / "n.exr")[1] == ("N.X", "N.Y", "N.Z")


def test_channels_in_the_order_asked(tmp_path):
    px = _ramp(2, 3, 4)
    write_exr(tmp_path / "a.exr", px, ("R", "G", "B", "A"), dtype="float")
    got = read_exr_channels(tmp_path / "a.exr", ["A", "R"])
    assert got.shape == (2, 3, 2)
    np.testing.assert_array_equal(got[..., 0], px[..., 3])
    np.testing.assert_array_equal(got[..., 1], px[..., 0])
    with pytest.raises(DamcapError, match=r"a\.exr: missing channel\(s\) W\.0, Z; the file has R, G, B, A"):
        read_exr_channels(tmp_path / "a.exr", ["R", "W.0", "Z"])


def test_shape_that_does_not_match_the_channels():
    with pytest.raises(ValueError, match=r"pixels shape \(2, 2, 3\) does not match channels \['R', 'G'\]"):
        write_exr("unused.exr", np.zeros((2, 2, 3)), ("R", "G"))


def test_missing_damaged_and_truncated_files(tmp_path):
    with pytest.raises(DamcapError, match=r"nope\.exr: file not found"):
        read_exr(tmp_path / "nope.exr")
    (tmp_path / "junk.exr").write_bytes(b"junk" * 16)
    with pytest.raises(DamcapError, match=r"junk\.exr: named \.exr but its content is unknown, not OpenEXR"):
        read_exr(tmp_path / "junk.exr")
    write_exr(tmp_path / "ok.exr", _ramp(16, 16), ("R", "G", "B"))
    data = (tmp_path / "ok.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(DamcapError, match=r"cut\.exr: cannot read (image|pixels)"):
        read_exr(tmp_path / "cut.exr")


def test_no_temporary_file_is_left_behind(tmp_path):
    write_exr(tmp_path / "a.exr", _ramp(), ("R", "G", "B"))
    assert [p.name for p in tmp_path.iterdir()] == ["a.exr"]


def test_u8_png_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (6, 5, 3), dtype=np.uint8)
    write_png(tmp_path / "a.png", rgb)
    np.testing.assert_array_equal(read_image_u8(tmp_path / "a.png"), rgb)
    rgba = rng.integers(0, 256, (4, 3, 4), dtype=np.uint8)
    rgba[..., 3] = 255  # opaque (partial alpha: below)
    write_png(tmp_path / "b.png", rgba)
    np.testing.assert_array_equal(read_image_u8(tmp_path / "b.png"), rgba)
    grey = rng.integers(0, 256, (4, 3, 1), dtype=np.uint8)
    write_image_u8(tmp_path / "g.png", grey)
    np.testing.assert_array_equal(read_image_u8(tmp_path / "g.png"), grey)


def test_u8_unreadable_file(tmp_path):
    (tmp_path / "x.png").write_bytes(b"not a png")
    with pytest.raises(DamcapError, match=r"x\.png: cannot read image"):
        read_image_u8(tmp_path / "x.png")


def test_u8_png_round_trip_with_partial_alpha(tmp_path):
    rgba = np.array([[[240, 245, 230, 100], [104, 120, 179, 0]]], np.uint8)
    write_png(tmp_path / "a.png", rgba)
    np.testing.assert_array_equal(read_image_u8(tmp_path / "a.png"), rgba)


@pytest.mark.parametrize("shape", [(4, 4), (3, 5)])
def test_u8_png_round_trip_of_a_2d_image(tmp_path, shape):
    grey = (np.arange(np.prod(shape)).reshape(shape) * 11).astype(np.uint8)
    write_png(tmp_path / "g.png", grey)
    np.testing.assert_array_equal(read_image_u8(tmp_path / "g.png")[..., 0], grey)


def stored_turned(upright_px: np.ndarray, orientation: int) -> np.ndarray:
    """The (H, W, ...) pixels a camera stores for an upright picture with this EXIF Orientation,
    written out from the EXIF definitions (not from :func:`upright`, which they check)."""
    a = upright_px
    return np.ascontiguousarray({1: a, 2: a[:, ::-1], 3: a[::-1, ::-1], 4: a[::-1], 5: a.swapaxes(0, 1),
                                 6: np.rot90(a, 1),  # shown turned 90 degrees clockwise: stored counter-clockwise
                                 7: a[::-1, ::-1].swapaxes(0, 1), 8: np.rot90(a, -1)}[orientation])


@pytest.mark.parametrize("orientation", range(1, 9))
def test_upright_turns_as_openimageio_reorients(orientation):
    """Every EXIF Orientation, mirrored ones included, against OpenImageIO's own ImageBufAlgo.reorient."""
    import OpenImageIO as oiio

    stored = np.random.default_rng(orientation).integers(0, 256, (3, 5, 2), dtype=np.uint8)
    spec = oiio.ImageSpec(5, 3, 2, "uint8")
    spec.attribute("Orientation", orientation)
    buf = oiio.ImageBuf(spec)
    buf.set_pixels(oiio.ROI(), stored)
    want = oiio.ImageBufAlgo.reorient(buf).get_pixels(oiio.UINT8)
    got = upright(stored, orientation)
    np.testing.assert_array_equal(got, want)
    assert (got.shape[1], got.shape[0]) == upright_size(5, 3, orientation)
    np.testing.assert_array_equal(upright(stored_turned(got, orientation), orientation), got)


@pytest.mark.parametrize("orientation, suffix", [(6, ".png"), (5, ".png"), (7, ".tif"), (8, ".png"), (3, ".png"), (2, ".tif")])
def test_an_image_stored_turned_reads_as_the_upright_original(tmp_path, orientation, suffix):
    """A portrait picture stored sideways (6, as phones do), mirrored (5, 7, 2) or turned 180 degrees:
    the reader gives the upright original's pixels exactly; the header still says how it is stored."""
    original = np.random.default_rng(0).integers(0, 256, (6, 4, 3), dtype=np.uint8)  # 4 wide, 6 high
    path = tmp_path / f"turned{suffix}"
    write_image_u8(path, stored_turned(original, orientation), {"Orientation": orientation})
    np.testing.assert_array_equal(read_image_u8(path), original)
    w, h, _, tag = image_header(path)
    assert tag == orientation and upright_size(w, h, tag) == (4, 6)
    write_image_u8(tmp_path / "odd.png", original, {"Orientation": 9})  # not an orientation: as stored
    np.testing.assert_array_equal(read_image_u8(tmp_path / "odd.png"), original)


_WRITE_CUT_SHORT = r"""
import os, resource, signal, sys
import numpy as np
from damcap.common.errors import DamcapError
import damcap.common.exr as exr
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (20000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
if sys.argv[2] == "full":
    real = os.statvfs
    class Full:
        f_bavail, f_frsize = 1, 4096
    exr.os.statvfs = lambda p: Full()
try:
    exr.write_exr(sys.argv[1], np.random.default_rng(0).random((256, 256, 3), dtype=np.float32), ("R", "G", "B"), dtype="float")
except (OSError, DamcapError) as e:
    print(type(e).__name__, getattr(e, "errno", None), getattr(e, "filename", None), str(e).replace("\n", " "))
"""


@pytest.mark.parametrize("disk", ["full", "limit"])
def test_a_write_cut_short_names_the_file_asked_for(tmp_path, disk):
    """A write the disk cuts short is one error naming the .exr asked for (never OpenImageIO's hidden
    temporary file): ENOSPC when the disk has no room for the pixels, EFBIG at the file size limit."""
    import subprocess
    import sys

    out = tmp_path / "a.exr"
    got = subprocess.run([sys.executable, "-c", _WRITE_CUT_SHORT, str(out), disk], capture_output=True, text=True, timeout=60)
    line = got.stdout.strip()
    assert got.returncode == 0 and line, got.stderr[-500:]
    assert ".tmp" not in line and str(out) in line, line
    if disk == "full":
        assert line.startswith(f"OSError 28 {out} ") and "No space left on device" in line, line
    else:
        assert line.startswith(f"OSError 27 {out} ") and "File too large (the file size limit, ulimit -f, is 20000 bytes)" in line, line
    assert list(tmp_path.iterdir()) == []


def test_oiio_error_escapes_a_message_that_is_not_utf8():
    """OpenImageIO's binding raises when its error quotes a damaged file's bytes; the text comes
    back escaped, and a plain message as it is."""
    from damcap.common.exr import oiio_error

    class Damaged:
        def geterror(self):
            raise UnicodeDecodeError("utf-8", b"Attribute 'compression\x80compression'", 22, 23, "invalid start byte")

    class Plain:
        def geterror(self):
            return "Could not open file"

    assert oiio_error(Damaged()) == "Attribute 'compression\\x80compression'"
    assert oiio_error(Plain()) == "Could not open file"
