"""cli/paths.py, one writer per output: every writing command locks its outputs for its whole
life; a second run aimed at the same output is refused in one line naming the first run's pid."""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from damcap.cli.paths import Terminated, check_paths, command_locks, file_out, folder_out, lock_path
from damcap.common.errors import DamcapError

from tests.cli.test_paths import COMMANDS, _inputs, _listing
from tests.conftest import assert_one_line_error, run_cli, tree_digest


@contextlib.contextmanager
def held_by(lock: Path, pid: int):
    """Another holder of ``lock``: a flock on its own open file description, ``pid`` written in."""
    lock.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.ftruncate(fd, 0)
        os.write(fd, f"{pid}\n".encode())
        yield
    finally:
        os.close(fd)


def is_locked(lock: Path) -> bool:
    """Whether some open file description holds a flock on ``lock``."""
    if not lock.exists():
        return False
    fd = os.open(lock, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


BUSY = "is being written by another damcap run"


class TestRefusal:
    @pytest.mark.parametrize("name", sorted(COMMANDS))
    def test_every_writing_command_refuses_an_output_being_written(self, name, tmp_path, capsys):
        args_of, _, suffix, _ = COMMANDS[name]
        inp = _inputs(tmp_path)
        out = tmp_path / f"o{suffix}"
        with held_by(lock_path(out), 4242):
            before, listing = tree_digest(tmp_path), _listing(tmp_path)
            code, _, err = run_cli(args_of(inp, out), capsys)
            assert_one_line_error(code, err, f"{out} {BUSY} (pid 4242); wait for it or choose another -o")
            assert tree_digest(tmp_path) == before and _listing(tmp_path) == listing, "the refused run touched something"

    def test_after_release_the_command_runs_and_leaves_no_lock_file(self, tmp_path, capsys):
        out = tmp_path / "s.obj"
        with held_by(lock_path(out), 4242):
            code, _, err = run_cli(["shape", "sphere", out], capsys)
            assert_one_line_error(code, err, BUSY, "pid 4242")
            assert not out.exists()
        code, _, err = run_cli(["shape", "sphere", out], capsys)
        assert code == 0, err
        assert out.is_file() and sorted(p.name for p in tmp_path.iterdir()) == ["s.obj"]

    def test_another_spelling_of_the_same_output_shares_the_lock(self, tmp_path, capsys, monkeypatch):
        (tmp_path / "real").mkdir()
        (tmp_path / "link").symlink_to(tmp_path / "real")
        monkeypatch.chdir(tmp_path)
        assert lock_path("link/s.obj") == lock_path(tmp_path / "real" / "s.obj") == tmp_path / "real" / ".s.obj.lock"
        with held_by(tmp_path / "real" / ".s.obj.lock", 4242):
            code, _, err = run_cli(["shape", "sphere", "link/s.obj"], capsys)
            assert_one_line_error(code, err, "link/s.obj", BUSY, "pid 4242")

    def test_a_folder_output_is_locked_beside_it(self, tmp_path, capsys):
        out = tmp_path / "cap"
        assert lock_path(out) == tmp_path / ".cap.lock"
        with held_by(tmp_path / ".cap.lock", 4242):
            code, _, err = run_cli(["closed-form", out], capsys)
            assert_one_line_error(code, err, f"{out} {BUSY} (pid 4242)")
        assert not out.exists()

    def test_a_checkpoint_beside_the_output_is_locked_too(self, tmp_path):
        out = tmp_path / "m.dam"
        with command_locks():
            check_paths([], [file_out(out), file_out(tmp_path / "m.dam.ckpt")])
            assert is_locked(lock_path(out)) and is_locked(lock_path(tmp_path / "m.dam.ckpt"))
            assert lock_path(out).read_text() == f"{os.getpid()}\n"
        assert sorted(tmp_path.iterdir()) == []


class TestAnotherProcess:
    HOLDER = textwrap.dedent("""
        import sys, time
        from damcap.cli.paths import check_paths, command_locks, file_out
        with command_locks():
            check_paths([], [file_out(sys.argv[1])])
            print("locked", flush=True)
            time.sleep(60)
    """)

    def test_a_running_holder_refuses_and_a_killed_one_does_not_block(self, tmp_path, capsys):
        out = tmp_path / "s.obj"
        holder = subprocess.Popen([sys.executable, "-c", self.HOLDER, str(out)], stdout=subprocess.PIPE, text=True)
        try:
            assert holder.stdout.readline().strip() == "locked"
            code, _, err = run_cli(["shape", "sphere", out], capsys)
            assert_one_line_error(code, err, f"{out} {BUSY} (pid {holder.pid}); wait for it or choose another -o")
            assert not out.exists()
        finally:
            holder.kill()  # SIGKILL: no cleanup runs; the kernel releases the flock
            holder.wait()
        assert lock_path(out).read_text() == f"{holder.pid}\n", "a killed run leaves its lock file behind"
        code, _, err = run_cli(["shape", "sphere", out], capsys)
        assert code == 0 and err == "", err
        assert out.is_file() and not lock_path(out).exists()

    def test_a_stale_lock_file_with_a_dead_pid_does_not_block(self, tmp_path, capsys):
        gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True)
        out = tmp_path / "s.obj"
        lock_path(out).write_text(gone.stdout)
        code, _, err = run_cli(["shape", "sphere", out], capsys)
        assert code == 0 and err == "", err
        assert out.is_file() and not lock_path(out).exists()


    def test_a_torchrun_job_locks_once_through_its_rank_0(self, tmp_path, monkeypatch):
        """The ranks of one torchrun job are one run: rank 0 locks, the others take no lock (they
        would otherwise refuse each other; tests/appearance/hyper/test_train.py runs two ranks)."""
        out = tmp_path / "p.safetensors"
        monkeypatch.setenv("WORLD_SIZE", "2")
        monkeypatch.setenv("RANK", "0")
        with command_locks():
            check_paths([], [file_out(out)])
            assert lock_path(out).is_file()
        monkeypatch.setenv("RANK", "1")
        with command_locks():
            check_paths([], [file_out(out)])
            assert not lock_path(out).exists()

class TestRelease:
    def test_released_after_an_error(self, tmp_path, capsys):
        inp = _inputs(tmp_path)
        out = tmp_path / "m.dam"
        code, _, err = run_cli(["fit", inp / "cap", "-o", out], capsys)  # the stand-in capture is refused after the check
        assert code == 2 and "Traceback" not in err, err
        assert not lock_path(out).exists() and not lock_path(tmp_path / "m.dam.ckpt").exists()
        with command_locks():
            check_paths([], [file_out(out)])

    @pytest.mark.parametrize("signal_exc, exit_code", [(KeyboardInterrupt, 130), (Terminated, 143)])
    def test_held_while_running_and_released_after_an_interrupt(self, signal_exc, exit_code, tmp_path, capsys, monkeypatch):
        import damcap.common.shapes as shapes

        out = tmp_path / "new" / "s.obj"
        seen = []

        def interrupted(name, path):
            seen.append(is_locked(lock_path(out)))
            raise signal_exc

        monkeypatch.setattr(shapes, "write_shape", interrupted)
        code, _, err = run_cli(["shape", "sphere", out], capsys)
        assert code == exit_code and "Traceback" not in err, err
        assert seen == [True], "the output was not locked while the command ran"
        assert not is_locked(lock_path(out)) and not (tmp_path / "new").exists(), "the lock (or the folder made for it) outlived the run"

    def test_released_after_sigterm_delivered_to_the_process(self, tmp_path):
        out = tmp_path / "s.obj"
        script = textwrap.dedent("""
            import os, signal, sys
            import damcap.common.shapes as shapes
            from damcap.cli.main import main
            def write(name, path):
                print("running", flush=True)
                signal.pause()
            shapes.write_shape = write
            sys.exit(main(["shape", "sphere", sys.argv[1]]))
        """)
        proc = subprocess.Popen([sys.executable, "-c", script, str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert proc.stdout.readline().strip() == "running"
            assert is_locked(lock_path(out)) and lock_path(out).read_text() == f"{proc.pid}\n"
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=30)
        finally:
            proc.kill()
        assert proc.returncode == 143, err
        assert not lock_path(out).exists()


class TestScope:
    def test_outside_a_command_nothing_is_locked(self, tmp_path):
        check_paths([], [file_out(tmp_path / "m.dam"), folder_out(tmp_path / "f")])
        assert sorted(tmp_path.iterdir()) == []

    def test_a_command_that_checks_its_output_twice_does_not_refuse_itself(self, tmp_path):
        with command_locks():
            check_paths([], [folder_out(tmp_path / "cap")])
            with command_locks():  # nested: the outer command's locks
                check_paths([tmp_path / "photos"], [folder_out(tmp_path / "cap")])
            assert is_locked(tmp_path / ".cap.lock")
        assert not (tmp_path / ".cap.lock").exists()

    def test_refused_by_another_holder_in_library_use(self, tmp_path):
        with held_by(tmp_path / ".m.dam.lock", 77):
            with command_locks():
                with pytest.raises(DamcapError, match=r"m\.dam is being written by another damcap run \(pid 77\)"):
                    check_paths([], [file_out(tmp_path / "m.dam")])
