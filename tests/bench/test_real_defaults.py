"""bench.real_defaults at tiny sizes: the ring and arc splits, and every method scored on a given capture."""

from __future__ import annotations

import json

import numpy as np

from bench import real_defaults
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture


def test_ring_split_trains_on_one_band_and_tests_the_others():
    a = np.arange(10) * 2 * np.pi / 10
    ring = lambda e: np.stack([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.full(10, np.sin(e))], 1)  # noqa: E731
    dirs = np.concatenate([ring(np.radians(10)), ring(np.radians(45)), ring(np.radians(45.5))[:3]])
    train, test = real_defaults.ring_split(dirs, np.array([0, 0, 1.0]), 5)
    assert all(i >= 10 for i in train) and len(train) == 5  # the fuller band (45 deg) trains
    assert test == list(range(10))  # the 10 deg ring is 35 deg away


def test_study_scores_each_method_on_a_given_capture(tmp_path, is_dssim):
    cap = tmp_path / "cap"
    make_closed_form_capture(cap, ClosedFormOptions(views=12, train_views=4, resolution=24, seed=1))
    out = tmp_path / "out"
    methods = ["fit (old default)", "defaults", "predict"]
    assert real_defaults.main(["--capture", f"sphere={cap}", "--methods", ",".join(methods), "--train-views", "5", "--steps", "30",
                               "--refine-steps", "4", "--out", str(out)]) == 0
    doc = json.loads((out / "real_defaults.json").read_text())
    assert [r["method"] for r in doc["rows"]] == methods
    assert doc["splits"]["sphere/given"]["split"] == "arc" and doc["splits"]["sphere/given"]["test"] > 0
    for r in doc["rows"]:
        assert is_dssim(r["novel_dssim"]) and r["x_rmpp"] > 0
    assert "| defaults |" in (out / "real_defaults.md").read_text()
