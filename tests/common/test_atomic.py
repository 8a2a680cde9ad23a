"""Atomic writes (common.atomic)."""

from __future__ import annotations

import pytest

from damcap.common.atomic import atomic_path


@pytest.mark.parametrize("keep_name", [False, True])
def test_atomic_path_renames_on_success_and_leaves_nothing_on_failure(tmp_path, keep_name):
    target = tmp_path / "out" / "shape.obj"
    with atomic_path(target, keep_name=keep_name) as tmp:
        assert tmp.suffix == ".obj"
        assert (tmp.name == target.name) == keep_name
        tmp.write_text("new")
    assert target.read_text() == "new"
    with pytest.raises(RuntimeError):
        with atomic_path(target, keep_name=keep_name) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash")
    assert target.read_text() == "new" and sorted(p.name for p in target.parent.iterdir()) == ["shape.obj"]


def test_cut_short_error_says_which_limit_was_met(tmp_path, monkeypatch):
    import errno
    import os

    from damcap.common import atomic

    tmp = tmp_path / ".a.x1y2z3w4.tmp.exr"
    tmp.write_bytes(b"x" * 100)
    assert atomic.cut_short_error(tmp, tmp_path / "a.exr", 10) is None

    class Full:
        f_bavail, f_frsize = 1, 4096
    monkeypatch.setattr(os, "statvfs", lambda p: Full())
    e = atomic.cut_short_error(tmp, tmp_path / "a.exr", 10 ** 6)
    assert e.errno == errno.ENOSPC and e.filename == str(tmp_path / "a.exr")


def test_the_test_pause_stops_at_the_kth_matching_rename_and_is_a_no_op_otherwise(tmp_path, monkeypatch):
    """pause_point (the kill tests' hook): unset or unmatched it changes nothing; set, the process
    stops before the K-th matching rename, after saying so on stderr, and stays stopped."""
    import os
    import subprocess
    import sys

    from damcap.common.atomic import PAUSE_ENV, write_text_atomic

    monkeypatch.delenv(PAUSE_ENV, raising=False)
    write_text_atomic(tmp_path / "a.txt", "1")
    monkeypatch.setenv(PAUSE_ENV, "b.txt")
    write_text_atomic(tmp_path / "a.txt", "2")  # another name: no pause
    assert (tmp_path / "a.txt").read_text() == "2"
    script = "import sys; from damcap.common.atomic import write_text_atomic as w; w(sys.argv[1] + '/b.txt', '1'); w(sys.argv[1] + '/b.txt', '2')"
    env = {**os.environ, PAUSE_ENV: "b.txt#2"}
    p = subprocess.Popen([sys.executable, "-c", script, str(tmp_path)], stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = p.stderr.readline()
        assert line == f"damcap test hook: paused before {tmp_path}/b.txt\n", line
        with pytest.raises(subprocess.TimeoutExpired):
            p.wait(timeout=0.5)
        assert (tmp_path / "b.txt").read_text() == "1"  # the first write renamed, the second stopped before its rename
    finally:
        p.kill()
        p.wait()
