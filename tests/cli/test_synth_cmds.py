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


def test_synth_set_finds_the_shared_data_by_option_environment_or_current_folder(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DAMCAP_SHARED_DATA", str(tmp_path / "from-env"))
    code, _, err = run(["synth-set", tmp_path / "e", "--dry-run"], capsys)
    assert_one_line_error(code, err, str(tmp_path / "from-env"), "--data-dir", "DAMCAP_SHARED_DATA")
    code, _, err = run(["synth-set", tmp_path / "e", "--data-dir", tmp_path / "from-option", "--dry-run"], capsys)
    assert_one_line_error(code, err, str(tmp_path / "from-option"))
    monkeypatch.delenv("DAMCAP_SHARED_DATA")
    monkeypatch.chdir(tmp_path)
    code, _, err = run(["synth-set", tmp_path / "e", "--dry-run"], capsys)
    assert_one_line_error(code, err, "../shared/data: no meshes/")


def test_synth_photos_command_is_the_library_photo_set(tmp_path, capsys):
    from damcap.synth.photos import PhotoSetOptions, make_photo_set

    code, stdout, err = run(["synth-photos", tmp_path / "cli", "--views", "2", "--size", "32", "--elevation", "30",
                             "--jitter", "2", "--seed", "3"], capsys)
    assert code == 0, err
    assert "wrote 2 photos" in stdout
    make_photo_set(tmp_path / "lib", PhotoSetOptions(views=2, size=32, elevation_deg=30.0, jitter_deg=2.0, seed=3))
    files = sorted(p.relative_to(tmp_path / "lib") for p in (tmp_path / "lib").rglob("*") if p.is_file())
    assert [str(f) for f in files] == ["images/IMG_0000.jpg", "images/IMG_0001.jpg", "masks/IMG_0000.png", "masks/IMG_0001.png",
                                       "transforms.json"]
    for f in files:
        assert (tmp_path / "cli" / f).read_bytes() == (tmp_path / "lib" / f).read_bytes(), f
    code, _, err = run(["synth-photos", tmp_path / "cli"], capsys)
    assert_one_line_error(code, err, "images exists")
    code, _, err = run(["synth-photos", tmp_path / "x", "--distance", "0.5"], capsys)
    assert_one_line_error(code, err, "--distance")


def test_synth_photos_turntable_room_and_principal_point_flags(tmp_path, capsys):
    from damcap.synth.photos import PhotoSetOptions, make_photo_set

    code, stdout, err = run(["synth-photos", tmp_path / "cli", "--views", "2", "--size", "32", "--motion", "turntable", "--room",
                             "--principal-dx", "2.5", "--principal-dy", "-1", "--jitter", "0"], capsys)
    assert code == 0, err
    assert "wrote 2 photos (turntable in a textured room)" in stdout
    make_photo_set(tmp_path / "lib", PhotoSetOptions(views=2, size=32, motion="turntable", room=True, principal_dx_px=2.5,
                                                     principal_dy_px=-1.0, jitter_deg=0.0))
    files = sorted(p.relative_to(tmp_path / "lib") for p in (tmp_path / "lib").rglob("*") if p.is_file())
    assert len(files) == 5
    for f in files:
        assert (tmp_path / "cli" / f).read_bytes() == (tmp_path / "lib" / f).read_bytes(), f
    doc = json.loads((tmp_path / "cli" / "transforms.json").read_text())
    assert (doc["cx"], doc["cy"]) == (18.5, 15.0)
    code, _, err = run(["synth-photos", tmp_path / "x", "--size", "32", "--principal-dx", "8.5"], capsys)
    assert_one_line_error(code, err, "--principal-dx 8.5", "quarter of --size 32")
    code, _, err = run(["synth-photos", tmp_path / "y", "--motion", "spin"], capsys)
    assert_one_line_error(code, err, "--motion", "spin")
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_synth_set_shard_values_are_checked(tmp_path, capsys):
    for bad in ("0/2", "3/2", "x", "1/0", "2", "1/2/3"):
        code, _, err = run(["synth-set", tmp_path / "e", "--shard", bad, "--dry-run", "--data-dir", tmp_path], capsys)
        assert_one_line_error(code, err, "--shard must be I/N with 1 <= I <= N", repr(bad))
    assert not (tmp_path / "e").exists()


def test_synth_set_shard_dry_run_lists_its_share_and_writes_nothing(tmp_path, capsys, shared_data):
    counts = []
    for i in (1, 2, 3):
        code, stdout, err = run(["synth-set", tmp_path / "corpus", "--preset", "paper", "--data", shared_data, "--dry-run",
                                 "--shard", f"{i}/3"], capsys)
        assert code == 0, err
        assert f"shard {i}/3: 240 captures" in stdout and "run the same command without --shard: it writes corpus.json" in stdout
        counts.append(int(stdout.split("not rendered ")[1].split(";")[0]))
    assert counts == [240, 240, 240] and not (tmp_path / "corpus").exists()


CLOSED_FORM = ["--views", "4", "--train-views", "2", "--res", "8", "--env-grid", "4", "--supersample", "1"]


def test_closed_form_is_staged_and_replaces_only_its_own_earlier_output(tmp_path, capsys, monkeypatch):
    """Interrupted or failed: nothing at OUT and the line says so truly; a rerun then writes it; a
    rerun over its own earlier output replaces it whole; a folder of other files is refused."""
    import damcap.synth.closed_form as closed_form

    out = tmp_path / "cap"
    real = closed_form.write_capture
    for failure, code_expected in ((KeyboardInterrupt(), 130), (OSError(28, "No space left on device"), 2)):
        def failing(capture, *args, **kwargs):
            (capture.root / "images").mkdir(parents=True)
            (capture.root / "images" / "0000.exr").write_bytes(b"half a frame")
            raise failure
        monkeypatch.setattr(closed_form, "write_capture", failing)
        code, _, err = run(["closed-form", out, *CLOSED_FORM], capsys)
        assert code == code_expected and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert sorted(p.name for p in tmp_path.iterdir()) == [], "a partial capture or a staging folder was left"
        if code == 130:
            assert err.startswith("interrupted: no output was completed (staged files were removed)"), err
        else:
            assert err.strip() == f"error: {out}: No space left on device; free disk space or write to another disk", err
    monkeypatch.setattr(closed_form, "write_capture", real)
    code, stdout, err = run(["closed-form", out, *CLOSED_FORM], capsys)
    assert code == 0 and "wrote 4 frames" in stdout, err
    (out / "images" / "9999.exr").write_bytes(b"stale")
    code, _, err = run(["closed-form", out, *CLOSED_FORM, "--seed", "3"], capsys)
    assert code == 0, err
    assert not (out / "images" / "9999.exr").exists() and read_capture(out).extra["damcap_source"]["options"]["seed"] == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap"]
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    code, _, err = run(["closed-form", other, *CLOSED_FORM], capsys)
    assert_one_line_error(code, err, str(other), "was not written by this command")
