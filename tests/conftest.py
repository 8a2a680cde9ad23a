"""Shared fixtures: real third-party data (one fixture), small generated captures, tolerances."""

from __future__ import annotations

import functools
import hashlib
import os
import re
import shutil
from pathlib import Path

import pytest
import torch

from damcap.common.data_dir import shared_data_dir

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = shared_data_dir(fallback=REPO.parent / "shared" / "data")
SAMPLE_CAPTURE = REPO / "samples" / "torus_env"

#: tolerances per dtype, in one place
TOL = {torch.float64: 1e-10, torch.float32: 1e-5, torch.float16: 2e-3}

#: torch's intra-op threads in a test process: at most 2, and under pytest-xdist (``make test``
#: runs one worker per core) each worker's share of the cores, so that workers do not oversubscribe
#: them: the tests' tensors are small, and an OpenMP thread that waits on a descheduled sibling
#: costs more than it gains (measured on 2 loaded cores: test_table2_covers_all_three_tasks 52 s
#: with 2 threads, 7 s with 1). Subprocesses the tests start inherit the share (OMP_NUM_THREADS).
XDIST_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
TORCH_THREADS = max(1, min(2, torch.get_num_threads() // max(1, XDIST_WORKERS)))
torch.set_num_threads(TORCH_THREADS)
if XDIST_WORKERS:
    os.environ.setdefault("OMP_NUM_THREADS", str(TORCH_THREADS))

#: a module-scoped fixture's definition in a test module's source
MODULE_FIXTURE = re.compile(r"""fixture\(\s*scope\s*=\s*["']module["']""")


@functools.lru_cache(maxsize=None)
def _shares_module_fixtures(module: Path) -> bool:
    """Whether a test module defines a module-scoped fixture (its tests then run as one unit under
    make test: :func:`pytest_xdist_make_scheduler`)."""
    try:
        return MODULE_FIXTURE.search(module.read_text(encoding="utf-8")) is not None
    except OSError:
        return False


def pytest_collection_modifyitems(config, items):
    """The tests marked ``slow``, and the modules whose tests share a module-scoped fixture, first:
    under pytest-xdist (make test) they are handed out before the rest, so that no long test or
    module starts last while the other workers idle; the many short tests after them fill the
    workers up evenly."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None and not _shares_module_fixtures(item.path))  # stable


def pytest_xdist_make_scheduler(config, log):
    """make test's ``--dist loadgroup``: the tests of a module that defines a module-scoped
    fixture go to one worker together (so the fixture is built once), every other test on its own.

    With pytest 9.2 and pytest-xdist 3.8 the ``xdist_group`` mark is not applied (xdist renames
    ``item._nodeid``, which pytest 9 no longer reads), so loadgroup alone hands out one test at a
    time: the tests of a module went to both workers, interleaved with other modules' tests and
    their slow ones ahead of the rest, and a module's fixture was built on each worker, often
    more than once (test_spatial_fit's three times in a make test run)."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    root = config.rootpath

    class ModuleFixtureScheduling(LoadGroupScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return module if _shares_module_fixtures(root / module) else super()._split_scope(nodeid)

    return ModuleFixtureScheduling(config, log)


@pytest.fixture(autouse=True)
def _torch_threads_kept():
    """A test that sets torch's thread count (a study's ``main`` sets 2) leaves the worker's as it was."""
    yield
    if torch.get_num_threads() != TORCH_THREADS:
        torch.set_num_threads(TORCH_THREADS)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (real third-party data). Missing data fails under CI=true, skips elsewhere."""
    if not (SHARED_DATA / "MANIFEST.md").is_file():
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"shared test data not found at {SHARED_DATA} (CI requires it)")
        pytest.skip(f"shared test data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def sample_capture() -> Path:
    """The bundled closed-form capture (torus under an environment, 32 views at 96x96)."""
    if not (SAMPLE_CAPTURE / "transforms.json").is_file():
        pytest.fail(f"bundled sample missing: {SAMPLE_CAPTURE}")
    return SAMPLE_CAPTURE


@pytest.fixture(scope="session")
def small_capture(tmp_path_factory) -> Path:
    """A tiny closed-form capture: sphere, directional light, 12 views at 32x32, 4 train."""
    from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

    out = tmp_path_factory.mktemp("cap") / "sphere"
    make_closed_form_capture(out, ClosedFormOptions(views=12, resolution=32, train_views=4, seed=1, dtype="float"))
    return out


@pytest.fixture()
def capture_copy(small_capture, tmp_path) -> Path:
    """A private copy of the tiny capture that a test may damage."""
    dst = tmp_path / "copy"
    shutil.copytree(small_capture, dst)
    return dst


def tree_digest(root: Path) -> str:
    """Hash of every file's path and bytes under root (to prove inputs are untouched)."""
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def run_cli(args, capsys) -> tuple[int, str, str]:
    """Run ``damcap ARGS`` in-process: (exit code, stdout, stderr)."""
    from damcap.cli.main import main

    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, err: str, *needles: str, exit_code: int | None = 2) -> None:
    """A user mistake: exit ``exit_code`` (None = any non-zero), the last stderr line is
    ``error: ...`` containing every needle, and no traceback."""
    if exit_code is None:
        assert code != 0
    else:
        assert code == exit_code
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert lines and lines[-1].startswith("error:") and "Traceback" not in err, err
    for n in needles:
        assert n in lines[-1], (n, lines[-1])


def write_tetra_obj_with_materials(folder) -> Path:
    """A unit right tetrahedron as an OBJ in three material groups (a: face 1, b: face 2, c: faces 3, 4),
    with its material library; the OBJ's path."""
    (folder / "m.mtl").write_text("newmtl a\nKd 1 0 0\nnewmtl b\nKd 0 1 0\nnewmtl c\nKd 0 0 1\n")
    faces = ["usemtl a", "f 1 3 2", "usemtl b", "f 1 2 4", "usemtl c", "f 1 4 3", "f 2 3 4"]
    (folder / "t.obj").write_text("\n".join(["mtllib m.mtl"] + [f"v {x:g} {y:g} {z:g}" for x, y, z in [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]] + faces) + "\n")
    return folder / "t.obj"
