"""bench.segment_prior at tiny sizes: each prior mode scored on the closed-form torus, with IoU against its true weights."""

from __future__ import annotations

import json

from bench import segment_prior


def test_study_scores_each_prior_mode(tmp_path, is_dssim):
    out = tmp_path / "out"
    assert segment_prior.main(["--captures", "torus", "--modes", "off,predictor", "--seeds", "0", "--steps", "10", "--init-steps", "5",
                               "--torus-px", "24", "--out", str(out)]) == 0
    doc = json.loads((out / "segment_prior.json").read_text())
    assert [r["mode"] for r in doc["rows"]] == ["off", "predictor"]
    for r in doc["rows"]:
        assert is_dssim(r["novel_dssim"]) and r["x_rmpp"] > 0 and 0 <= r["iou_train"] <= 1
    assert doc["rows"][1]["prior"]["used"] is True
    assert "| predictor | 5 + 10 | 0 |" in (out / "segment_prior.md").read_text()
