"""bench.real_limits at tiny sizes: the defaults taken apart on a given capture."""

from __future__ import annotations

import json

import numpy as np

from bench import real_limits
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture


def test_best_gain_undoes_an_exposure_per_channel():
    rng = np.random.default_rng(0)
    pred = rng.random((8, 8, 3)) + 0.1
    fg = np.ones((8, 8), bool)
    fg[0] = False
    ref = pred * np.array([0.5, 2.0, 1.0])
    ref[0] = 100.0  # background: not counted
    assert np.allclose(real_limits.best_gain(ref, pred, fg), [0.5, 2.0, 1.0])
    assert real_limits.best_gain(ref, np.zeros_like(pred), fg).tolist() == [1.0, 1.0, 1.0]


def test_study_takes_the_defaults_apart_on_a_given_capture(tmp_path, is_dssim):
    cap = tmp_path / "cap"
    make_closed_form_capture(cap, ClosedFormOptions(views=12, train_views=4, resolution=24, seed=1))
    out = tmp_path / "out"
    assert real_limits.main(["--capture", f"sphere={cap}", "--train-views", "5", "--steps", "20", "--out", str(out)]) == 0
    row = json.loads((out / "real_limits.json").read_text())["rows"][0]
    assert row["split"] == "arc" and row["novel"] > 0
    assert set(row["swaps"]) == {"defaults (everything from the training ring)", "normals from every view", "DAM and normals from every view",
                                 "DAM and normals from every view, no albedo", "albedo from every view", "everything from every view"}
    assert all(is_dssim(s) for s in row["swaps"].values())
    t = row["image_tests"]
    assert t["as_is"] == row["swaps"]["defaults (everything from the training ring)"]  # the same renders scored the same way
    assert t["shift"] <= t["as_is"] and t["mean_gain"] > 0  # the shift search includes no shift
    assert "| everything from every view |" in (out / "real_limits.md").read_text()
