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
