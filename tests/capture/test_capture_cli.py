"""``damcap hdr`` and ``damcap linearize``: outputs, one-line errors (exit 2), inputs untouched."""

from __future__ import annotations

import json
import shutil

import numpy as np
from damcap.common.exr import read_exr

from tests.conftest import assert_one_line_error, tree_digest
from tests.conftest import run_cli as run


def test_hdr_raw_bracket(sim_bracket, tmp_path, capsys):
    before = tree_digest(sim_bracket.files[0].parent)
    out = tmp_path / "merged.exr"
    code, stdout, err = run(["hdr", *sim_bracket.files, "-o", out, "--dtype", "half"], capsys)
    assert code == 0, err
    assert "5 raw frames" in stdout and "lin_rec709" in stdout
    pixels, names = read_exr(out)
    assert names == ("R", "G", "B", "clipped") and pixels.shape == (128, 256, 4)
    record = json.loads((tmp_path / "merged.exr.json").read_text())
    assert record["kind"] == "raw" and record["options"]["dtype"] == "half"
    assert tree_digest(sim_bracket.files[0].parent) == before


def test_hdr_ldr_with_exposures_and_srgb(memorial, tmp_path, capsys):
    files, times, _ = memorial
    out = tmp_path / "m.exr"
    sel = [0, 5, 10]
    code, stdout, err = run(["hdr", *[files[i] for i in sel], "-o", out, "--exposures",
                             ",".join(str(times[i]) for i in sel), "--response", "srgb"], capsys)
    assert code == 0, err
    pixels, _ = read_exr(out)
    assert pixels[..., :3].min() >= 0 and np.isfinite(pixels).all()
    assert json.loads((tmp_path / "m.exr.json").read_text())["response"]["method"] == "srgb"


def test_hdr_errors(memorial, frobisher, tmp_path, capsys):
    files, _, _ = memorial
    code, _, err = run(["hdr", *files[:2], "-o", tmp_path / "a.exr"], capsys)
    assert_one_line_error(code, err, "no exposure time", "--exposures")
    code, _, err = run(["hdr", files[0], "-o", tmp_path / "a.exr", "--exposures", "1"], capsys)
    assert_one_line_error(code, err, "at least 2 exposures")
    code, _, err = run(["hdr", *files[:2], "-o", tmp_path / "a.exr", "--exposures", "1,x"], capsys)
    assert_one_line_error(code, err, "--exposures", "'x'")
    code, _, err = run(["hdr", *frobisher, "-o", tmp_path / "a.exr", "--colorspace", "p3"], capsys)
    assert_one_line_error(code, err, "--colorspace must be one of lin_rec709, acescg")
    code, _, err = run(["hdr", *frobisher, "-o", tmp_path / "a.png"], capsys)
    assert_one_line_error(code, err, "must be an .exr")
    code, _, err = run(["hdr", *frobisher, "-o", frobisher[0]], capsys)
    assert_one_line_error(code, err, "would overwrite")
    assert not (tmp_path / "a.exr").exists()


def test_linearize_command(shared_data, tmp_path, capsys):
    src = tmp_path / "photos"
    src.mkdir()
    for name in ("IMG_5881.JPG", "IMG_5890.JPG"):
        shutil.copy(shared_data / "real" / "mold_gold_cape" / "images" / name, src / name)
    before = tree_digest(src)
    code, stdout, err = run(["linearize", src, "-o", tmp_path / "lin"], capsys)
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "lin").iterdir()) == ["IMG_5881.exr", "IMG_5890.exr", "linearize.json"]
    doc = json.loads((tmp_path / "lin" / "linearize.json").read_text())
    assert doc["damcap_package_version"] and [p["exposure"]["iso"] for p in doc["photos"]]
    assert tree_digest(src) == before
    code, _, err = run(["linearize", src, "-o", src / "out"], capsys)
    assert_one_line_error(code, err, "would overwrite or write into the input")
    code, _, err = run(["linearize", tmp_path / "nothing", "-o", tmp_path / "x"], capsys)
    assert_one_line_error(code, err, "not a folder of photos")


def test_linearize_replaces_its_earlier_output_whole(shared_data, tmp_path, capsys):
    """A rerun into its own earlier output replaces it (no EXR of the earlier photos stays); a
    failed rerun leaves the earlier output as it was; a folder of other files is refused."""
    import damcap.capture.linearize as linearize

    src = tmp_path / "photos"
    src.mkdir()
    for name in ("IMG_5881.JPG", "IMG_5890.JPG"):
        shutil.copy(shared_data / "real" / "mold_gold_cape" / "images" / name, src / name)
    out = tmp_path / "lin"
    code, _, err = run(["linearize", src, "-o", out, "--ignore-exposure"], capsys)
    assert code == 0, err
    first = tree_digest(out)
    (src / "IMG_5890.JPG").rename(tmp_path / "IMG_5890.JPG")
    real = linearize._linearize_into

    def failing(*args, **kwargs):
        real(*args, **kwargs)
        raise OSError(28, "No space left on device")
    linearize._linearize_into = failing
    try:
        code, _, err = run(["linearize", src, "-o", out, "--ignore-exposure"], capsys)
    finally:
        linearize._linearize_into = real
    assert code == 2 and "No space left on device" in err and tree_digest(out) == first
    code, _, err = run(["linearize", src, "-o", out, "--ignore-exposure"], capsys)
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["IMG_5881.exr", "linearize.json"]
    assert [p["file"] for p in json.loads((out / "linearize.json").read_text())["photos"]] == ["IMG_5881.JPG"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["IMG_5890.JPG", "lin", "photos"]
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    code, _, err = run(["linearize", src, "-o", other, "--ignore-exposure"], capsys)
    assert_one_line_error(code, err, str(other), "was not written by this command")
