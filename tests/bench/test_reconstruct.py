"""bench.reconstruct's geometry part at tiny sizes: the visual hull of a sphere from 8 photos
with the true cameras, against the known surface, and a dense-knob row."""

from __future__ import annotations

import json

from bench import reconstruct


def test_reconstruct_geometry_part_writes_normal_errors(tmp_path):
    out = tmp_path / "out"
    argv = ["--part", "geometry", "--geometry-objects", "sphere", "--geometry-photos", "8", "--geometry-photo-size", "64",
            "--geometry-capture-size", "32", "--geometry-modes", "visual-hull", "--geometry-dense-knobs", "48x16",
            "--cache", str(tmp_path / "cache"), "--out", str(out)]
    assert reconstruct.main(argv) == 0
    doc = json.loads((out / "reconstruct.json").read_text())
    assert doc["commands"] == [".venv/bin/python -m bench.reconstruct " + " ".join(argv)]
    assert list(doc["geometry"]["sphere"]) == ["visual-hull", "dense (48 px, 16 planes)"]
    knob = doc["geometry"]["sphere"]["dense (48 px, 16 planes)"]
    # 8 photos of 64 px matched at 48 px leave no consistent depth: the row records dense's own clear refusal
    assert knob["error"].startswith("DamcapError: dense geometry: only") and "too little texture" in knob["error"], knob
    r = doc["geometry"]["sphere"]["visual-hull"]
    assert "error" not in r
    assert 0.0 <= r["median_deg"] <= r["p90_deg"] < 45.0  # a sphere's hull from 8 views: normals within degrees
    assert r["pixels"] > 100 and 0.5 < r["coverage_ratio_est_over_gt"] < 2.0
    md = (out / "reconstruct.md").read_text()
    assert f"Results: `{out / 'reconstruct.json'}`" in md and "visual-hull" in md
