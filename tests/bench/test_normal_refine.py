"""bench.normal_refine at tiny sizes: every row scored on a small closed-form capture."""

from __future__ import annotations

import json

from bench import normal_refine
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture


def test_normal_refine_study_scores_each_row(tmp_path, is_dssim):
    cap = tmp_path / "cap"
    make_closed_form_capture(cap, ClosedFormOptions(views=6, train_views=3, resolution=24, seed=1))
    out = tmp_path / "out"
    assert normal_refine.main(["--capture", str(cap), "--voxel-px", "2", "--steps", "5", "--fit-steps", "20", "--lr-dam", "1e-3",
                               "--step-variants", "3", "--priors", "0.5", "--out", str(out)]) == 0
    doc = json.loads((out / "normal_refine.json").read_text())
    assert [r["method"] for r in doc["rows"]] == ["DAM (fit)", "control: DAM + 5 more steps, normals kept", "normals refined, voxel 2 px",
                                                  "normals and DAM weights refined (lr_dam 0.001), voxel 2 px",
                                                  "normals refined, voxel 2 px, 3 steps", "normals refined, voxel 2 px, prior 0.5 (default 0.01)"]
    for r in doc["rows"]:
        assert all(is_dssim(r[k]) for k in ("same", "novel", "same_albedo", "novel_albedo", "heldout", "heldout_albedo"))
    assert [r.get("lr_dam") for r in doc["rows"]] == [None, 1e-3, 0.0, 1e-3, 0.0, 0.0]
    assert [(r.get("steps"), r.get("prior")) for r in doc["rows"][1:]] == [(5, 0.01)] * 3 + [(3, 0.01), (5, 0.5)]
    assert doc["rows"][4]["novel"] != doc["rows"][2]["novel"] != doc["rows"][5]["novel"]  # each knob changes the refinement
    assert doc["rows"][2]["corners"] > 0 and doc["train_views"] == 3 and doc["test_views"] == 3 and len(doc["heldout_views"]) == 1
    assert "| normals refined, voxel 2 px |" in (out / "normal_refine.md").read_text()
