"""bench.hyper at tiny sizes: the shipped predictor vs a short SGD fit on one tiny held-out capture."""

from __future__ import annotations

import json

from bench import hyper


def test_hyper_study_writes_learning_to_learn_rows(tmp_path, tiny_corpus, is_dssim):
    corpus = tiny_corpus()
    out = tmp_path / "out"
    argv = ["--corpus", str(corpus), "--refine-steps", "0", "5", "--fit-seeds", "0", "--fit-steps", "20", "--timing-runs", "2",
            "--out", str(out)]
    assert hyper.main(argv) == 0
    doc = json.loads((out / "hyper.json").read_text())
    assert doc["command"].startswith(".venv/bin/python -m bench.hyper --corpus")
    (cap,) = doc["per_capture"]
    assert cap["capture"] == "torus__env-grid__m1" and cap["light_kind"] == "env"
    assert [r["refine_steps"] for r in cap["refine"]] == [0, 5]
    for r in cap["refine"]:
        assert is_dssim(r["novel"]) and is_dssim(r["same"])
    k0, k5 = cap["refine"]
    assert k0["train_l1_before"] == k0["train_l1_after"] == k5["train_l1_before"]
    assert k5["train_l1_after"] <= k5["train_l1_before"]  # refinement never makes the training cost worse
    assert is_dssim(cap["rmpp_novel"]) and is_dssim(cap["sgd_novel_mean"]) and all(is_dssim(x) for x in cap["default_fit_novel"])
    assert 0 < cap["predict_ms_median"] < 10_000 and len(cap["predict_ms_all"]) == 2
    env = doc["summary"]["env"]
    assert abs(env["by_refine"]["0"]["ratio_to_sgd"] - cap["refine"][0]["novel"] / cap["sgd_novel_mean"]) < 1e-12
    assert "point" not in doc["summary"] and set(doc["summary"]["targets"]["predict_alone_ratio"]) == {"env"}
    md = (out / "hyper.md").read_text()
    assert "| predict + 5 refine steps |" in md and "torus__env-grid__m1" in md
