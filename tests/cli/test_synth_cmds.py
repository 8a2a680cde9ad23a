"""``damcap synth`` and ``damcap synth-set``: exit codes and one-line errors naming the value."""

from __future__ import annotations

import json

from damcap.common.capture_folder import read_capture

from tests.conftest import assert_one_line_error
from tests.conftest import run_cli as run


def test_synth_command_writes_a_capture(tmp_path, capsys):
    out = tmp_path / "cap"
    code, stdout, err = run(["synth", out, "--object", "sphere", "--light", "point:20:30", "--materials", "3",
                             "--views", "5", "--res", "16", "--spp", "2", "--seed", "4", "--train-views", "2"], capsys)
    assert code == 0, err
    assert "wrote 5 frames" in stdout and "validated" in stdout
    cap = read_capture(out)
    opts = cap.extra["damcap_source"]["options"]
    assert (opts["seed"], opts["materials"], opts["resolution"], opts["light"]) == (4, 3, 16, "point:20:30")


def test_synth_errors_name_the_value(tmp_path, capsys):
    code, _, err = run(["synth", tmp_path / "a", "--object", tmp_path / "nope.obj"], capsys)
    assert_one_line_error(code, err, "nope.obj", "mesh file not found")
    code, _, err = run(["synth", tmp_path / "b", "--light", "sun"], capsys)
    assert_one_line_error(code, err, "--light 'sun'")
    code, _, err = run(["synth", tmp_path / "c", "--light", f"env:{tmp_path / 'gone.exr'}:90"], capsys)
    assert_one_line_error(code, err, "gone.exr", "environment map not found")
    code, _, err = run(["synth", tmp_path / "d", "--materials", "0"], capsys)
    assert_one_line_error(code, err, "--materials")
    code, _, err = run(["synth-set", tmp_path / "e", "--preset", "huge"], capsys)
    assert_one_line_error(code, err, "--preset", "huge")
    code, _, err = run(["synth-set", tmp_path / "e", "--data", tmp_path], capsys)
    assert_one_line_error(code, err, str(tmp_path), "--data")


def test_synth_set_dry_run_writes_the_plan(tmp_path, capsys, shared_data):
    code, stdout, err = run(["synth-set", tmp_path / "corpus", "--preset", "paper", "--data", shared_data, "--dry-run"], capsys)
    assert code == 0, err
    doc = json.loads((tmp_path / "corpus" / "corpus.json").read_text())
    assert len(doc["captures"]) == 720 and doc["counts"]["train"] + doc["counts"]["heldout"] == 720
    assert {"split", "object", "light", "materials", "seed"} <= set(doc["captures"][0])
    assert "not rendered 720" in stdout
