"""bench.geometry_judge at tiny sizes: the judge and a plain fit on two given captures."""

from __future__ import annotations

import json

from bench import geometry_judge
from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture


def test_study_judges_two_given_captures(tmp_path, is_dssim):
    """The same capture given as both geometries: equal held-out scores, so the first (the
    incumbent) is kept; the report has its row."""
    cap = tmp_path / "cap"
    make_closed_form_capture(cap, ClosedFormOptions(views=12, train_views=4, resolution=24, seed=1))
    out = tmp_path / "out"
    assert geometry_judge.main(["--given", str(cap), str(cap), "--train-views", "5", "--steps", "20", "--out", str(out)]) == 0
    row = json.loads((out / "geometry_judge.json").read_text())["rows"][0]
    h = row["heldout_dssim"]
    assert row["judge"] == row["photo_consistency"] == "visual-hull" and h["visual-hull"] == h["dense"] and is_dssim(h["dense"])
    assert len(row["held_views"]) == 2 and row["judge_seconds"] > 0 and row["plain_fit_seconds"] > 0
    assert "| given | visual-hull | visual-hull |" in (out / "geometry_judge.md").read_text()
