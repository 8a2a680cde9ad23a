"""bench.segment at tiny sizes: ours vs k-means on one tiny two-material held-out capture."""

from __future__ import annotations

import json

from bench import segment


def test_segment_study_writes_segmentation_rows(tmp_path, tiny_corpus, is_dssim):
    corpus = tiny_corpus(materials=2)
    out = tmp_path / "out"
    argv = ["--corpus", str(corpus), "--no-auto", "--steps", "20", "--init-steps", "10", "--kmeans-steps", "20", "--out", str(out)]
    assert segment.main(argv) == 0
    doc = json.loads((out / "segment.json").read_text())
    assert doc["commands"] == [".venv/bin/python -m bench.segment " + " ".join(argv)]
    assert doc["segment_options"]["steps"] == 20 and doc["segment_options"]["materials"] == 3 and doc["kmeans_steps"] == 20
    (cap,) = doc["per_capture"]
    assert cap["materials"] == 2 and "auto" not in cap
    for method in ("ours (true weights)", "k-means (true weights)", "ours (estimated weights)", "k-means (estimated weights)"):
        assert is_dssim(cap["dssim"][method]["novel"])
    for name in ("ours", "k-means"):
        assert 0.0 <= cap["iou_train"][name] <= 1.0 and 0.0 <= cap["iou_test_carried"][name] <= 1.0
    env = doc["summary"]["env"]
    assert env["captures"] == 1 and env["ours/k-means (true weights)"] > 0
    md = (out / "segment.md").read_text()
    assert "| env (1) |" in md and "torus__env-grid__m2" in md
