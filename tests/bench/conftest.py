"""What the studies' smoke tests share: tiny corpora in the ``damcap synth-set`` layout."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


def write_corpus(root: Path, captures: list[tuple[str, str, int, str]]) -> Path:
    """A ``corpus.json`` listing finished held-out captures already under ``root/captures/``:
    (name, light kind, materials, light spec) each."""
    entries = [{"name": name, "path": f"captures/{name}", "split": "heldout", "object": name.split("__")[0], "light": light,
                "light_kind": kind, "materials": materials, "status": "done"} for name, kind, materials, light in captures]
    (root / "corpus.json").write_text(json.dumps({"captures": entries}))
    return root


def closed_form_corpus(root: Path, materials: int = 1, resolution: int = 24) -> Path:
    """One held-out closed-form capture (torus under an environment, 8 views, 3 train)."""
    from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

    name = f"torus__env-grid__m{materials}"
    make_closed_form_capture(root / "captures" / name, ClosedFormOptions(
        shape="torus", light="env", env_grid=8, materials=materials, views=8, train_views=3, resolution=resolution, seed=2, dtype="float"))
    return write_corpus(root, [(name, "env", materials, "env:closed-form")])


@pytest.fixture(autouse=True)
def _worker_thread_share(monkeypatch):
    """A study's ``main`` sets torch's thread count for its measured runs (2); its smoke test runs
    on the test process's share of the cores instead (tests/conftest.py: under pytest-xdist two
    threads per worker oversubscribe the cores, and small tensors then wait on each other)."""
    import torch

    monkeypatch.setattr(torch, "set_num_threads", lambda n: None)


@pytest.fixture()
def corpus_writer():
    """:func:`write_corpus`."""
    return write_corpus


@pytest.fixture()
def tiny_corpus(tmp_path):
    """:func:`closed_form_corpus` into the test's folder: ``tiny_corpus(materials)``."""
    return lambda materials=1: closed_form_corpus(tmp_path / "corpus", materials)


@pytest.fixture()
def is_dssim():
    """Whether a value is a DSSIM (a float in [0, 1])."""
    return lambda x: isinstance(x, float) and 0.0 <= x <= 1.0
