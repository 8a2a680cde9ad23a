"""Every command: one-line errors (no traceback) on user mistakes, inputs never modified."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest
from damcap.cli.main import main

from tests.conftest import assert_one_line_error as _assert_one_line_error
from tests.conftest import run_cli as run
from tests.conftest import tree_digest


def assert_one_line_error(code, err, *needles):
    _assert_one_line_error(code, err, *needles, exit_code=None)


@pytest.fixture(scope="module")
def fitted(small_capture, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "m.dam"
    assert main(["fit", str(small_capture), "-o", str(out), "--steps", "60"]) == 0
    return out


def test_fit_render_evaluate_end_to_end(small_capture, fitted, tmp_path, capsys):
    before = tree_digest(small_capture)
    code, out, err = run(["render", fitted, small_capture, "-o", tmp_path / "r", "--split", "test"], capsys)
    assert code == 0, err
    names = sorted(p.name for p in (tmp_path / "r").glob("*.exr"))
    assert names == [f"{i:04d}.exr" for i in range(12) if f"images/{i:04d}.exr" in json.loads((small_capture / "transforms.json").read_text())["test_filenames"]]
    code, out, err = run(["evaluate", small_capture, "--model", fitted, "--json", tmp_path / "e.json"], capsys)
    assert code == 0, err
    res = json.loads((tmp_path / "e.json").read_text())["results"]
    assert set(res["test"]) == {"DAM", "RM++", "RM"} and len(res["test"]["DAM"]["per_frame"]) == 8
    assert (tmp_path / "e.png").stat().st_size > 1000
    assert "novel view" in out
    code, out, err = run(["inspect", small_capture], capsys)
    assert code == 0 and "valid capture" in out
    assert tree_digest(small_capture) == before


def test_fit_records_the_normals_it_was_trained_on(small_capture, fitted):
    """The .dam records the histogram of its training pixels' normals, weighted by coverage: the
    train views' covered pixels, all of them."""
    import numpy as np

    from damcap.appearance.coverage import training_normal_histogram
    from damcap.appearance.dam_file import load_dam, recorded_normal_histogram
    from damcap.appearance.views import load_views, samples_of
    from damcap.common.capture_folder import read_capture

    samples = samples_of(load_views(read_capture(small_capture), "train"))
    hist = recorded_normal_histogram(load_dam(fitted)[1])
    np.testing.assert_allclose(hist, training_normal_histogram(samples))
    assert hist.sum() == pytest.approx(float(samples.weight.sum()), rel=1e-6) and (hist > 0).sum() > 10


def test_missing_folder(tmp_path, capsys):
    for cmd in (["inspect", tmp_path / "nope"], ["fit", tmp_path / "nope", "-o", tmp_path / "m.dam"],
                ["evaluate", tmp_path / "nope"]):
        code, _, err = run(cmd, capsys)
        assert_one_line_error(code, err, "nope: capture folder not found")


def test_bad_json(capture_copy, tmp_path, capsys):
    (capture_copy / "transforms.json").write_text('{"frames": [')
    code, _, err = run(["fit", capture_copy, "-o", tmp_path / "m.dam"], capsys)
    assert_one_line_error(code, err, "transforms.json: invalid JSON")


def test_truncated_exr(capture_copy, tmp_path, capsys):
    doc = json.loads((capture_copy / "transforms.json").read_text())
    path = capture_copy / doc["train_filenames"][0]
    path.write_bytes(path.read_bytes()[:300])
    before = tree_digest(capture_copy)
    code, _, err = run(["fit", capture_copy, "-o", tmp_path / "m.dam", "--steps", "5"], capsys)
    assert_one_line_error(code, err, path.name)
    code, _, err = run(["inspect", capture_copy], capsys)
    assert_one_line_error(code, err, "1 problem(s)")
    assert path.name in err
    assert tree_digest(capture_copy) == before


def test_empty_split(capture_copy, fitted, tmp_path, capsys):
    doc = json.loads((capture_copy / "transforms.json").read_text())
    doc["test_filenames"] = []
    (capture_copy / "transforms.json").write_text(json.dumps(doc))
    code, _, err = run(["render", fitted, capture_copy, "-o", tmp_path / "r"], capsys)
    assert_one_line_error(code, err, "'test' split is empty")
    code, _, err = run(["evaluate", capture_copy, "--model", fitted], capsys)
    assert_one_line_error(code, err, "'test' split is empty")


def test_bad_model_and_options(small_capture, tmp_path, capsys):
    (tmp_path / "x.dam").write_bytes(b"\x00" * 100)
    code, _, err = run(["render", tmp_path / "x.dam", small_capture, "-o", tmp_path / "r"], capsys)
    assert_one_line_error(code, err, "x.dam: not a damcap .dam model file")
    code, _, err = run(["fit", small_capture, "-o", tmp_path / "m.dam", "--encoding", "polar"], capsys)
    assert_one_line_error(code, err, "unknown DAM input encoding 'polar'")
    code, _, err = run(["fit", small_capture, "-o", tmp_path / "m.dam", "--steps", "0"], capsys)
    assert_one_line_error(code, err, "--steps must be an integer in [1, 1000000000], got 0")
    code, _, err = run(["fit", small_capture, "-o", tmp_path / "m.dam", "--device", "cuda:7"], capsys)
    assert code != 0 and "Traceback" not in err


def test_outputs_never_overwrite_inputs(capture_copy, fitted, capsys):
    before = tree_digest(capture_copy)
    code, _, err = run(["render", fitted, capture_copy, "-o", capture_copy / "images"], capsys)
    assert_one_line_error(code, err, "would overwrite or write into the input")
    assert tree_digest(capture_copy) == before


def test_console_script_exit_code(tmp_path):
    exe = shutil.which("damcap", path=str(__import__("pathlib").Path(sys.executable).parent))
    assert exe, "the damcap console script is installed next to python"
    p = subprocess.run([exe, "inspect", str(tmp_path / "none")], capture_output=True, text=True)
    assert p.returncode == 2 and p.stderr.strip().startswith("error:") and "Traceback" not in p.stderr
    p = subprocess.run([exe, "fit"], capture_output=True, text=True)
    assert p.returncode == 2 and "Traceback" not in p.stderr
