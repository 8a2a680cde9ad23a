"""cli/paths.py: every writing command checks its outputs against its inputs before touching
anything, stages folder outputs, turns OS errors and interrupts into one line."""

from __future__ import annotations

import errno
import json
import os
import shutil
import threading
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from damcap.cli.paths import (Interrupted, Terminated, check_paths, command_locks, file_out, folder_out, frame_output_names, holds,
                              on_interrupt, os_error_line, staged_folder)
from damcap.common.errors import DamcapError

from tests.conftest import assert_one_line_error, run_cli, tree_digest


def _inputs(root: Path) -> Path:
    """A folder of stand-in inputs: the checks run before any input is read."""
    inp = root / "inp"
    (inp / "cap").mkdir(parents=True)
    (inp / "cap" / "transforms.json").write_text("{}")
    (inp / "photos").mkdir()
    (inp / "photos" / "a.jpg").write_bytes(b"jpg")
    (inp / "seg").mkdir()
    (inp / "seg" / "segment.json").write_text("{}")
    (inp / "data" / "meshes").mkdir(parents=True)
    (inp / "data" / "envmaps").mkdir(parents=True)
    for name in ("m.dam", "mesh.obj", "a.jpg", "b.jpg", "labels.npy"):
        (inp / name).write_bytes(name.encode())
    return inp


# command -> (argument builder, output kind, output suffix, the input folder used for "inside" cases)
COMMANDS = {
    "fit": (lambda i, o: ["fit", i / "cap", "-o", o], "file", ".dam", "cap"),
    "render": (lambda i, o: ["render", i / "m.dam", i / "cap", "-o", o], "folder", "", "cap"),
    "evaluate": (lambda i, o: ["evaluate", i / "cap", "--model", i / "m.dam", "--json", o], "file", ".json", "cap"),
    "evaluate-plot": (lambda i, o: ["evaluate", i / "cap", "--model", i / "m.dam", "--plot", o], "file", ".png", "cap"),
    "evaluate-table": (lambda i, o: ["evaluate", "--table2", i / "cap", "--out", o], "folder", "", "cap"),
    "tables": (lambda i, o: ["tables", "--table2", i / "cap", "--out", o], "folder", "", "cap"),
    "predict": (lambda i, o: ["predict", i / "cap", "--predictor", i / "m.dam", "-o", o], "file", ".dam", "cap"),
    "train-hyper": (lambda i, o: ["train-hyper", i / "cap", "-o", o], "file", ".safetensors", "cap"),
    "hdr": (lambda i, o: ["hdr", i / "a.jpg", i / "b.jpg", "-o", o], "file", ".exr", None),
    "linearize": (lambda i, o: ["linearize", i / "photos", "-o", o], "folder", "", "photos"),
    "reconstruct": (lambda i, o: ["reconstruct", i / "photos", "-o", o], "folder", "", "photos"),
    "closed-form": (lambda i, o: ["closed-form", o], "folder", "", None),
    "synth": (lambda i, o: ["synth", o, "--object", i / "mesh.obj"], "folder", "", None),
    "synth-set": (lambda i, o: ["synth-set", o, "--data-dir", i / "data"], "folder", "", "data"),
    "synth-photos": (lambda i, o: ["synth-photos", o], "folder", "", None),
    "shape": (lambda i, o: ["shape", "sphere", o], "file", ".obj", None),
    "export": (lambda i, o: ["export", i / "m.dam", "--mesh", i / "mesh.obj", "-o", o], "folder", "", None),
    "export-onnx": (lambda i, o: ["export", i / "m.dam", "--format", "onnx", "-o", o], "file", ".onnx", None),
    "export-capture": (lambda i, o: ["export-capture", i / "cap", "-o", o], "folder", "", "cap"),
    "view": (lambda i, o: ["view", i / "m.dam", "-o", o], "file", ".html", None),
    "segment": (lambda i, o: ["segment", i / "cap", "-o", o], "folder", "", "cap"),
    "segment-labels": (lambda i, o: ["segment-labels", i / "seg", "--mesh", i / "mesh.obj", "-o", o], "file", ".npy", "seg"),
}
WITH_INPUTS = [c for c in COMMANDS if c not in ("closed-form", "synth-photos", "shape")]


def _listing(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _refused(capsys, tmp_path: Path, inp: Path, args: list, *needles: str) -> None:
    before, listing = tree_digest(inp), _listing(tmp_path)
    code, _, err = run_cli(args, capsys)
    assert_one_line_error(code, err, *needles)
    assert tree_digest(inp) == before, "an input was modified"
    assert _listing(tmp_path) == listing, "something was left behind"


class TestCollisions:
    @pytest.mark.parametrize("name", WITH_INPUTS)
    def test_output_is_an_input(self, name, tmp_path, capsys):
        inp = _inputs(tmp_path)
        build, kind, suffix, folder = COMMANDS[name]
        target = inp / (folder or "m.dam") if kind == "folder" or folder else inp / "m.dam"
        if name == "hdr":
            target = inp / "a.jpg"
        if name == "synth":
            target = inp / "mesh.obj"
        _refused(capsys, tmp_path, inp, build(inp, target), "would overwrite or write into the input")

    @pytest.mark.parametrize("name", [c for c in WITH_INPUTS if COMMANDS[c][3]])
    def test_output_inside_an_input(self, name, tmp_path, capsys):
        inp = _inputs(tmp_path)
        build, _, suffix, folder = COMMANDS[name]
        out = inp / folder / f"out{suffix}"
        _refused(capsys, tmp_path, inp, build(inp, out), str(out), "would overwrite or write into the input")

    @pytest.mark.parametrize("name", [c for c in WITH_INPUTS if COMMANDS[c][1] == "folder"])
    def test_input_inside_the_output_folder(self, name, tmp_path, capsys):
        inp = _inputs(tmp_path)
        build, *_ = COMMANDS[name]
        _refused(capsys, tmp_path, inp, build(inp, inp), str(inp), "would overwrite or write into the input")

    def test_reconstruct_keeps_a_pose_file_inside_its_output(self, tmp_path, capsys):
        """The issue's case: --poses CAP/transforms.json with -o CAP deleted the pose file."""
        inp = _inputs(tmp_path)
        cap = tmp_path / "cap"
        (cap / "reconstruction").mkdir(parents=True)
        (cap / "transforms.json").write_text('{"frames": []}')
        before = tree_digest(cap)
        code, _, err = run_cli(["reconstruct", inp / "photos", "-o", cap, "--poses", cap / "transforms.json"], capsys)
        assert_one_line_error(code, err, str(cap), "transforms.json")
        assert tree_digest(cap) == before

    def test_export_labels_inside_the_output_folder(self, tmp_path, capsys):
        inp = _inputs(tmp_path)
        out = tmp_path / "out"
        out.mkdir()
        (out / "labels.npy").write_bytes(b"labels")
        before = tree_digest(out)
        code, _, err = run_cli(["export", inp / "m.dam", "--mesh", inp / "mesh.obj", "--labels", out / "labels.npy", "-o", out], capsys)
        assert_one_line_error(code, err, "labels.npy", "would overwrite")
        assert tree_digest(out) == before

    def test_two_outputs_on_one_path(self, tmp_path, capsys):
        inp = _inputs(tmp_path)
        out = tmp_path / "w.npy"
        _refused(capsys, tmp_path, inp, ["segment-labels", inp / "seg", "--mesh", inp / "mesh.obj", "-o", out, "--weights", out],
                 str(out), "two outputs")


class TestWrongKind:
    @pytest.mark.parametrize("name", list(COMMANDS))
    def test_existing_output_of_the_wrong_kind(self, name, tmp_path, capsys):
        inp = _inputs(tmp_path)
        build, kind, suffix, _ = COMMANDS[name]
        out = tmp_path / f"out{suffix}"
        if kind == "file":
            (out / "keep").mkdir(parents=True)  # a folder where a file is written
            needle = "is a folder"
        else:
            out.write_text("keep")  # a file where a folder is written
            needle = "is not a folder"
        _refused(capsys, tmp_path, inp, build(inp, out), needle)

    def test_fit_into_an_existing_folder_is_refused_before_fitting(self, small_capture, tmp_path, capsys):
        """The issue's case: fit -o DIR ran the whole fit, deleted the checkpoint, then failed."""
        (tmp_path / "dir").mkdir()
        code, _, err = run_cli(["fit", small_capture, "-o", tmp_path / "dir", "--steps", "5000"], capsys)
        assert_one_line_error(code, err, str(tmp_path / "dir"), "is a folder")
        assert list((tmp_path / "dir").iterdir()) == []


class TestUnwritable:
    @pytest.mark.parametrize("name", list(COMMANDS))
    def test_parent_is_a_file(self, name, tmp_path, capsys):
        """Fails for root too (chmod does not deny root): the output's parent is a regular file."""
        inp = _inputs(tmp_path)
        build, _, suffix, _ = COMMANDS[name]
        blocker = tmp_path / "blocker"
        blocker.write_text("x")
        _refused(capsys, tmp_path, inp, build(inp, blocker / "sub" / f"out{suffix}"), str(blocker), "is not a folder")

    @pytest.mark.parametrize("name", ["fit", "render", "shape", "closed-form", "view", "segment-labels"])
    def test_not_writable_folder(self, name, tmp_path, capsys):
        """/proc/sys is read-only even for root."""
        if os.access("/proc/sys", os.W_OK):
            pytest.skip("/proc/sys is writable here")
        inp = _inputs(tmp_path)
        build, _, suffix, _ = COMMANDS[name]
        _refused(capsys, tmp_path, inp, build(inp, Path("/proc/sys/damcap-test") / f"out{suffix}"), "/proc/sys", "not writable")


class TestOSErrors:
    def test_disk_full_while_rendering_is_one_line_and_leaves_nothing(self, fitted_model, small_capture, tmp_path, capsys, monkeypatch):
        import damcap.common.exr as exr

        real, calls = exr.write_exr, []

        def full(path, *a, **k):
            calls.append(path)
            if len(calls) == 3:
                raise OSError(errno.ENOSPC, "No space left on device", str(path))
            return real(path, *a, **k)

        monkeypatch.setattr(exr, "write_exr", full)
        before = tree_digest(small_capture)
        code, _, err = run_cli(["render", fitted_model, small_capture, "-o", tmp_path / "r", "--split", "all"], capsys)
        assert_one_line_error(code, err, "No space left on device", "free disk space")
        assert not (tmp_path / "r").exists()
        assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".r.")] == []
        assert tree_digest(small_capture) == before

    def test_disk_full_at_a_mid_run_checkpoint_is_one_line_and_keeps_the_earlier_checkpoint(self, small_capture, tmp_path, capsys,
                                                                                            monkeypatch):
        """The disk fills while the fit writes its second checkpoint (as a Python file write does:
        ENOSPC naming no file): one line naming the checkpoint and the full disk, exit 2, the first
        checkpoint intact and no temporary file left."""
        import torch

        import damcap.appearance.fit as fit

        real, saves = torch.save, []

        class Filling:  # a file on a disk that fills after 1000 bytes, as torch's zip writer meets it
            def __init__(self, f):
                self.f, self.written = f, 0

            def write(self, data):
                self.written += len(data)
                if self.written > 1000:
                    raise OSError(errno.ENOSPC, "No space left on device")
                return self.f.write(data)

            def flush(self):
                return self.f.flush()

        def filling(obj, f, *a, **k):
            saves.append(1)
            # the disk stays full from the second checkpoint on: the fit's last try to checkpoint fails too
            return real(obj, Filling(f) if len(saves) >= 2 else f, *a, **k)

        monkeypatch.setattr(fit.torch, "save", filling)
        out = tmp_path / "m.dam"
        code, _, err = run_cli(["fit", small_capture, "-o", out, "--steps", "60", "--checkpoint-every", "10"], capsys)
        ckpt = tmp_path / "m.dam.ckpt"
        assert_one_line_error(code, err, f"{ckpt}: No space left on device", "free disk space")
        assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["m.dam.ckpt"]
        assert torch.load(ckpt, weights_only=True)["step"] == 10

    def test_memory_running_out_under_an_address_space_limit_is_one_line(self, tmp_path):
        """A real MemoryError (the address space limited with setrlimit, then an allocation beyond it
        inside a command) ends in one line, exit 2, nothing written."""
        import subprocess
        import sys

        code = (
            "import resource, sys\n"
            "import numpy as np\n"
            "import damcap.common.shapes as shapes\n"
            "from damcap.cli.main import main\n"
            "shapes.write_shape = lambda name, path: np.ones(2 ** 34, dtype=np.uint8)\n"
            "resource.setrlimit(resource.RLIMIT_AS, (8 * 2 ** 30, resource.getrlimit(resource.RLIMIT_AS)[1]))\n"
            "sys.exit(main(['shape', 'sphere', sys.argv[1]]))\n")
        got = subprocess.run([sys.executable, "-c", code, str(tmp_path / "s.obj")], capture_output=True, text=True, timeout=120)
        assert got.returncode == 2 and "Traceback" not in got.stderr, got.stderr[-800:]
        assert got.stderr.strip().startswith("error: out of memory (MemoryError: Unable to allocate 16.0 GiB"), got.stderr
        assert len(got.stderr.strip().splitlines()) == 1 and not (tmp_path / "s.obj").exists()

    @pytest.mark.parametrize("message", ["[enforce fail at alloc_cpu.cpp:117] data. DefaultCPUAllocator: can't allocate memory: "
                                         "you tried to allocate 107374182400 bytes. Error code 12 (Cannot allocate memory)",
                                         "CUDA out of memory. Tried to allocate 20.00 GiB"])
    def test_an_allocators_runtime_error_is_one_line(self, message, tmp_path, capsys, monkeypatch):
        import damcap.common.shapes as shapes

        def oom(name, path):
            raise RuntimeError(message)

        monkeypatch.setattr(shapes, "write_shape", oom)
        code, _, err = run_cli(["shape", "sphere", tmp_path / "s.obj"], capsys)
        assert_one_line_error(code, err, "out of memory (RuntimeError: ", "make the work smaller")

    def test_permission_denied_on_a_single_file(self, tmp_path, capsys, monkeypatch):
        import damcap.common.shapes as shapes

        def denied(name, path):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))

        monkeypatch.setattr(shapes, "write_shape", denied)
        code, _, err = run_cli(["shape", "sphere", tmp_path / "s.obj"], capsys)
        assert_one_line_error(code, err, str(tmp_path / "s.obj"), "Permission denied", "permissions")

    @pytest.mark.parametrize("e, needle", [
        (OSError(errno.EROFS, "Read-only file system", "/x"), "/x: Read-only file system; the filesystem is read-only"),
        (OSError(errno.ENOSPC, "No space left on device"), "No space left on device; free disk space"),
        (OSError(errno.EACCES, "Permission denied", "/a", None, "/b"), "/a -> /b: Permission denied"),
    ])
    def test_os_error_line(self, e, needle):
        assert needle in os_error_line(e) and "\n" not in os_error_line(e)


class TestFrameNames:
    def test_one_folder_keeps_base_names(self):
        assert frame_output_names(["images/0000.exr", "images/0001.exr"]) == ["0000.exr", "0001.exr"]
        assert frame_output_names(["images/IMG_1.exr"], "") == ["IMG_1"]

    def test_several_folders_use_relative_paths(self):
        assert frame_output_names(["images/0004.exr", "images2/0004.exr"], ".exr") == ["images/0004.exr", "images2/0004.exr"]

    def test_a_duplicate_or_escaping_frame_is_refused(self):
        with pytest.raises(DamcapError, match="'images/0000.exr' and 'images/0000.exr'"):
            frame_output_names(["images/0000.exr", "images/0000.exr"])
        with pytest.raises(DamcapError, match="leaves the capture folder"):
            frame_output_names(["../0000.exr"])

    def test_render_frames_of_one_name_in_two_folders(self, fitted_model, capture_copy, tmp_path, capsys):
        doc = json.loads((capture_copy / "transforms.json").read_text())
        frame = doc["frames"][1]
        old = frame["file_path"]
        (capture_copy / "images2").mkdir()
        shutil.move(capture_copy / old, capture_copy / "images2" / Path(doc["frames"][0]["file_path"]).name)
        frame["file_path"] = "images2/" + Path(doc["frames"][0]["file_path"]).name
        for key in ("train_filenames", "test_filenames"):
            if key in doc:
                doc[key] = [frame["file_path"] if f == old else f for f in doc[key]]
        (capture_copy / "transforms.json").write_text(json.dumps(doc))
        code, out, err = run_cli(["render", fitted_model, capture_copy, "-o", tmp_path / "r", "--split", "all"], capsys)
        assert code == 0, err
        written = sorted(str(p.relative_to(tmp_path / "r")) for p in (tmp_path / "r").rglob("*.exr"))
        assert len(written) == len(doc["frames"]) == 12
        assert "images2/" + Path(doc["frames"][0]["file_path"]).name in written
        assert f"wrote {len(written)} frames" in out


class TestStaging:
    def test_a_new_folder_appears_only_on_success(self, tmp_path):
        with staged_folder(tmp_path / "out") as stage:
            (stage / "a").mkdir()
            (stage / "a" / "x.txt").write_text("x")
            assert not (tmp_path / "out").exists()
        assert (tmp_path / "out" / "a" / "x.txt").read_text() == "x"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]

    def test_an_existing_folder_keeps_its_other_files(self, tmp_path):
        (tmp_path / "out").mkdir()
        (tmp_path / "out" / "old.txt").write_text("old")
        (tmp_path / "out" / "x.txt").write_text("before")
        with staged_folder(tmp_path / "out") as stage:
            (stage / "x.txt").write_text("after")
        assert (tmp_path / "out" / "old.txt").read_text() == "old" and (tmp_path / "out" / "x.txt").read_text() == "after"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]

    def test_an_error_removes_the_staged_files(self, tmp_path):
        with pytest.raises(RuntimeError):
            with staged_folder(tmp_path / "out") as stage:
                (stage / "x.txt").write_text("x")
                raise RuntimeError("boom")
        assert list(tmp_path.iterdir()) == []

    def test_a_staged_folder_gets_the_users_umask(self, tmp_path):
        old = os.umask(0o027)
        try:
            with staged_folder(tmp_path / "out") as stage:
                (stage / "x.txt").write_text("x")
        finally:
            os.umask(old)
        assert (tmp_path / "out").stat().st_mode & 0o777 == 0o750

    def test_replace_swaps_the_earlier_output_whole(self, tmp_path):
        (tmp_path / "out").mkdir()
        (tmp_path / "out" / "stale.txt").write_text("old")
        with staged_folder(tmp_path / "out", replace=True) as stage:
            (stage / "x.txt").write_text("new")
            assert (tmp_path / "out" / "stale.txt").exists()  # the earlier output stays until the end
        assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["x.txt"]
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]

    def test_leftovers_of_killed_runs_are_removed_by_the_next_run(self, tmp_path):
        """What kill -9 leaves (staging folders, atomic writers' temporary files) goes when the next
        run locks the same output, with one warning line; other files and other outputs' stay."""
        leftovers = [".out.staging-ab12cd_3", ".out.replaced-zz99yy00", ".m.q1w2e3r4.tmp.dam", ".m.dam.a1b2c3d4.tmp.ckpt",
                     "out/images/.0000.k3j_x0ab.tmp.exr"]
        kept = ["out/images/0000.exr", "out/.0001.exr", ".other.ab12cd_3.tmp.dam", ".out2.staging-ab12cd_3", "m.dam",
                ".m.tmp.dam", ".mx.q1w2e3r4.tmp.dam", "out/.notes.tmp.txt"]
        for name in leftovers + kept:
            p = tmp_path / name
            p.parent.mkdir(parents=True, exist_ok=True)
            if "staging" in name or "replaced" in name:
                p.mkdir()
                (p / "a.exr").write_text("x")
            else:
                p.write_text("x")
        (tmp_path / "out" / "render.json").write_text("{}")
        with pytest.warns(UserWarning) as w:
            with command_locks():
                check_paths([], [folder_out(tmp_path / "out", replaces=holds("render.json")), file_out(tmp_path / "m.dam")])
        assert [n for n in leftovers if (tmp_path / n).exists()] == []
        assert [n for n in kept if not (tmp_path / n).exists()] == []
        lines = [str(m.message) for m in w]
        assert len(lines) == 2 and all("removed what an interrupted earlier run left" in line for line in lines)
        # outside a command (no lock held) nothing is removed
        (tmp_path / ".m.q1w2e3r4.tmp.dam").write_text("x")
        check_paths([], [file_out(tmp_path / "m.dam")])
        assert (tmp_path / ".m.q1w2e3r4.tmp.dam").exists()

    def test_an_earlier_output_set_aside_by_a_killed_run_is_put_back(self, tmp_path):
        aside = tmp_path / ".out.replaced-ab12cd34" / "out"
        aside.mkdir(parents=True)
        (aside / "render.json").write_text("{}")
        (tmp_path / ".out.staging-ef56gh78").mkdir()
        with pytest.warns(UserWarning) as w:
            with command_locks():
                check_paths([], [folder_out(tmp_path / "out", replaces=holds("render.json"))])
        assert [str(m.message).split(": ", 1)[1] for m in w] == [
            "put back the earlier output that an interrupted run had set aside",
            "removed what an interrupted earlier run left (.out.staging-ef56gh78)"]
        assert (tmp_path / "out" / "render.json").is_file() and sorted(p.name for p in tmp_path.iterdir()) == ["out"]

    def test_check_paths_accepts_disjoint_paths(self, tmp_path):
        (tmp_path / "in").mkdir()
        check_paths([tmp_path / "in", None], [file_out(tmp_path / "o" / "m.dam"), folder_out(tmp_path / "f"), None])


class TestInterrupts:
    def test_on_interrupt_says_what_was_kept(self):
        with pytest.raises(Interrupted) as e:
            with on_interrupt(lambda: "kept x"):
                raise KeyboardInterrupt
        assert e.value.kept == "kept x" and e.value.exit_code == 130
        with pytest.raises(Interrupted) as e:
            with on_interrupt(lambda: "kept y"):
                raise Terminated
        assert e.value.exit_code == 143

    @pytest.mark.parametrize("signal_exc, exit_code", [(KeyboardInterrupt, 130), (Terminated, 143)])
    def test_ctrl_c_during_fit_keeps_a_checkpoint_that_resumes(self, signal_exc, exit_code, small_capture, tmp_path, capsys,
                                                               monkeypatch):
        import damcap.cli.appearance_cmds as cmds

        real = cmds.progress_bar

        def interrupting(total, desc):
            def update(step, steps, stats):
                if step == 30:
                    raise signal_exc
            return update

        monkeypatch.setattr(cmds, "progress_bar", interrupting)
        out = tmp_path / "m.dam"
        args = ["fit", small_capture, "-o", out, "--steps", "60", "--checkpoint-every", "10"]
        code, _, err = run_cli(args, capsys)
        assert code == exit_code, err
        ckpt = tmp_path / "m.dam.ckpt"
        assert ckpt.is_file() and not out.exists()
        assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("interrupted")
        assert f"the checkpoint {ckpt} is kept; rerun the same command to resume" in err
        monkeypatch.setattr(cmds, "progress_bar", real)
        code, _, err = run_cli(args, capsys)
        assert code == 0, err
        assert "resuming m.dam.ckpt at step" in err and out.is_file() and not ckpt.exists()

    def test_ctrl_c_in_a_command_without_a_checkpoint(self, tmp_path, capsys, monkeypatch):
        import damcap.common.shapes as shapes

        def interrupted(name, path):
            raise KeyboardInterrupt

        monkeypatch.setattr(shapes, "write_shape", interrupted)
        code, _, err = run_cli(["shape", "sphere", tmp_path / "s.obj"], capsys)
        assert code == 130 and "Traceback" not in err and err.strip().startswith("interrupted: no output was completed")


class TestView:
    def test_port_out_of_range(self, tmp_path, capsys):
        inp = _inputs(tmp_path)
        for port in ("70000", "-1"):
            code, _, err = run_cli(["view", inp / "m.dam", "-o", tmp_path / "v.html", "--serve", "--port", port], capsys)
            assert_one_line_error(code, err, "--port", port)

    def test_serves_only_its_page_on_loopback(self, tmp_path):
        from damcap.export.viewer import page_server

        (tmp_path / "secret.txt").write_text("secret")
        with page_server(b"<html>page</html>", "v.html", 0) as httpd:
            host, port = httpd.server_address[:2]
            assert host == "127.0.0.1"
            thread = threading.Thread(target=httpd.serve_forever, daemon=True)
            thread.start()
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/v.html", timeout=10) as r:
                    assert r.status == 200 and r.read() == b"<html>page</html>"
                for path in ("/", "/secret.txt", "/../secret.txt", "/v.html/x"):
                    with pytest.raises(urllib.error.HTTPError) as e:
                        urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10)
                    assert e.value.code == 404
            finally:
                httpd.shutdown()
                thread.join(10)


class TestWarnings:
    def test_warnings_are_one_line(self, tmp_path, capsys, monkeypatch):
        import warnings

        import damcap.common.capture_folder as cf

        def warn_then_fail(path):
            warnings.warn("invalid value encountered\n  in divide", RuntimeWarning)
            raise DamcapError(f"{path}: stop")

        monkeypatch.setattr(cf, "inspect_capture", warn_then_fail)
        code, _, err = run_cli(["inspect", tmp_path], capsys)
        assert_one_line_error(code, err, "stop")
        assert "warning: invalid value encountered in divide" in err.splitlines()
        assert "RuntimeWarning" not in err and "warnings.warn" not in err


@pytest.fixture(scope="module")
def fitted_model(small_capture, tmp_path_factory):
    from damcap.cli.main import main

    out = tmp_path_factory.mktemp("fitp") / "m.dam"
    assert main(["fit", str(small_capture), "-o", str(out), "--steps", "30"]) == 0
    return out
