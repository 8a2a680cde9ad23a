"""bench.reconstruct's geometry part at tiny sizes: the visual hull of a sphere from 8 photos
with the true cameras, against the known surface."""

from __future__ import annotations

import json

from bench import reconstruct


def test_reconstruct_geometry_part_writes_normal_errors(tmp_path):
    out = tmp_path / "out"
    argv = ["--part", "geometry", "--geometry-objects", "sphere", "--geometry-photos", "8", "--geometry-photo-size", "64",
            "--geometry-capture-size", "32", "--geometry-modes", "visual-hull", "--cache", str(tmp_path / "cache"), "--out", str(out)]
    assert reconstruct.main(argv) == 0
    doc = json.loads((out / "reconstruct.json").read_text())
    assert doc["commands"] == [".venv/bin/python -m bench.reconstruct " + " ".join(argv)]
    (mode,) = doc["geometry"]["sphere"].items()
    assert mode[0] == "visual-hull" and "error" not in mode[1]
    r = mode[1]
    assert 0.0 <= r["median_deg"] <= r["p90_deg"] < 45.0  # a sphere's hull from 8 views: normals within degrees
    assert r["pixels"] > 100 and 0.5 < r["coverage_ratio_est_over_gt"] < 2.0
    md = (out / "reconstruct.md").read_text()
    assert f"Results: `{out / 'reconstruct.json'}`" in md and "visual-hull" in md
