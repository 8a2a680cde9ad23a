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
