"""bench.dam_core at tiny sizes: the default fit (shortened) and the predictor on a 24 px capture."""

from __future__ import annotations

import json

from bench import dam_core


def test_dam_core_study_writes_fit_rows(tmp_path, is_dssim):
    out = tmp_path / "out"
    argv = ["--only", "default", "predict_k0", "--seeds", "0", "--captures", "sphere_env", "--render-runs", "0",
            "--quiet-wait", "0", "--max-aborts", "0", "--resolution", "16", "--views", "6", "--train-views", "3", "--steps", "30", "--cache", str(tmp_path / "cache"),
            "--out", str(out)]
    assert dam_core.main(argv) == 0
    doc = json.loads((out / "dam_core.json").read_text())
    assert doc["command"].endswith(" && .venv/bin/python -m bench.dam_core " + " ".join(argv))
    cap = doc["captures"]["sphere_env"]
    assert cap["capture_options"]["resolution"] == 16 and cap["n_train_views"] == 3 and cap["n_test_views"] == 3
    assert is_dssim(cap["baselines"]["test"]["RM++"]) and is_dssim(cap["baselines"]["test"]["RM"])
    rows = {r["name"]: r for r in cap["settings"]}
    assert rows["default"]["options"]["steps"] == 30 and rows["default"]["per_seed"][0]["seed"] == 0
    for name in ("default", "predict_k0"):
        r = rows[name]
        assert is_dssim(r["dssim_test"]["mean"]) and is_dssim(r["dssim_train"]["mean"]) and r["diverged_seeds"] == []
        assert abs(r["ratio_test_to_rmpp"]["mean"] - r["dssim_test"]["mean"] / cap["baselines"]["test"]["RM++"]) < 1e-12
    assert rows["shifted_softplus"] == {"name": "shifted_softplus", "alias_of": "default"}
    assert (out / "dam_core_pareto.png").stat().st_size > 1000
    md = (out / "dam_core.md").read_text()
    assert "views=6, resolution=16, train_views=3" in md and "predict_k0" in md
