"""bench.real_defaults at tiny sizes: every method scored on a given capture, split by its cameras."""

from __future__ import annotations

import json

from bench import real_defaults
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture


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
