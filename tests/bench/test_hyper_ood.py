"""bench.hyper_ood at tiny sizes: two predictors and a snapshot on two small closed-form captures."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from bench import hyper_ood
from damcap.appearance.hyper.file import save_predictor
from damcap.appearance.hyper.model import HyperArchitecture, HyperNet


@pytest.mark.slow
def test_ood_study_writes_every_method_per_kind(tmp_path, is_dssim):
    paths = []
    for name, views in (("one", 1), ("set", 2)):
        p = tmp_path / f"{name}.safetensors"
        started = {"init": {"file": "first.safetensors", "steps": 10, "seconds": 2.0}, "best_step": 7} if name == "set" else {}
        arch = HyperArchitecture(input_size=32, channels=(4, 8), input_views=views, orientation="light" if name == "set" else "world")
        save_predictor(p, HyperNet(arch, torch.Generator().manual_seed(0)),
                       {"command": "test", "seconds": 1.0, **started})
        paths.append(p)
    snap = tmp_path / "set.step5.safetensors"
    save_predictor(snap, HyperNet(HyperArchitecture(input_size=32, channels=(4, 8), input_views=2)), {"snapshot_step": 5})
    other = tmp_path / "run2.step3.safetensors"  # a run named unlike any predictor: its own --init record counts
    save_predictor(other, HyperNet(HyperArchitecture(input_size=32, channels=(4, 8), input_views=2)),
                   {"snapshot_step": 3, "init": {"file": "x.safetensors", "steps": 40}})
    out = tmp_path / "out"
    argv = ["--predictors", *map(str, paths), "--snapshots", str(snap), str(other), "--corpus", str(tmp_path / "none"), "--real",
            "--closed-form", "2", "--res", "24", "--fit-steps", "20", "--refine-steps", "5", "--cache", str(tmp_path / "cache"),
            "--out", str(out), "--readout", "3", "--refine-from-readout", "--joint", "2", "--joint-prior", "1e-4", "0"]
    assert hyper_ood.main(argv) == 0
    doc = json.loads((out / "hyper_ood.json").read_text())
    assert [r["kind"] for r in doc["per_capture"]] == ["closed-form sphere, distant light", "closed-form sphere, environment"]
    for r in doc["per_capture"]:
        refined = {"one + 5", "one + 5 (lr 0.003)", "one + auto", "set + 5", "set + 5 (lr 0.003)", "set + auto",
                   "one readout + 5", "set readout + 5"}  # the last two refined from the solved output layer
        solved = {"one readout 3", "set readout 3", "one readout 3 + joint 2", "set readout 3 + joint 2",
                  "one readout 3 + joint 2 (prior 0)", "set readout 3 + joint 2 (prior 0)"}  # predict's own prior unnamed
        assert set(r["novel"]) == {"fit", "one", "set", "set.step5", "set.step5 readout 3", "run2.step3", "run2.step3 readout 3", "RM++", "RM"} | refined | solved
        assert set(r["readout_ms"]) == solved and r["readout_ms"]["one readout 3"] > r["predict_ms"]["one"]
        assert r["readout_ms"]["one readout 3 + joint 2"] > r["readout_ms"]["one readout 3"]  # timed from the forward pass on
        assert r["novel"]["set readout 3 + joint 2"] != r["novel"]["set readout 3 + joint 2 (prior 0)"]
        assert all(is_dssim(v) for v in r["novel"].values())
        assert set(r["refine_seconds"]) == refined and r["predict_ms"]["set"] > 0
        assert set(r["auto_steps"]) == {"one", "set"} and all(k >= 0 for k in r["auto_steps"].values())
        assert r["novel"]["one + 5"] != r["novel"]["one + 5 (lr 0.003)"]  # another rate, another model
        assert r["novel"]["set.step5 readout 3"] != r["novel"]["set.step5"]
    # the light orientation of the light-orientation predictor: found within a few degrees of the one distant light
    sun, sky = (r["light_orientation"]["set"] for r in doc["per_capture"])
    assert "one" not in doc["per_capture"][0]["light_orientation"] and sky["angle_to_light_deg"] is None
    assert sun["angle_to_light_deg"] < 20, sun
    assert "## Light orientation" in (out / "hyper_ood.md").read_text()
    assert "`orientation.terminator_fit`" in (out / "hyper_ood.md").read_text()
    assert doc["light_orientation_fit"] == "terminator_fit"
    # a result stored under the old keys ("light_frame", "light_frame_fit") renders the same table
    old = json.loads(json.dumps(doc).replace('"light_orientation', '"light_frame'))
    hyper_ood.write_markdown(doc, tmp_path / "new.md")
    hyper_ood.write_markdown(old, tmp_path / "old.md")
    assert (tmp_path / "old.md").read_text() == (tmp_path / "new.md").read_text()
    assert "| angle to the light, deg |" in (tmp_path / "old.md").read_text()
    assert doc["snapshots"] == {"set.step5": {"step": 5, "total": 15}, "run2.step3": {"step": 3, "total": 43}}  # counted after the 10 steps of the predictor it started from
    s = doc["summary"]["closed-form sphere, environment"]
    assert s["captures"] == 1 and s["novel"]["fit"] == doc["per_capture"][1]["novel"]["fit"]
    md = (out / "hyper_ood.md").read_text()
    assert "| closed-form sphere, environment | 1 |" in md and "| set.step5 | 5 | 15 | " in md and "| set | 7 | 17 | " in md
    curve = md.split("against training compute")[1].split("## Per capture")[0]
    assert "solved: mean DSSIM" in curve and all(line.count("| x") == 2 for line in curve.splitlines() if line.startswith("| set"))
    assert "| one readout 3 | " in md and "predict set readout 3 ms" in md and "| set readout 3 + joint 2 (prior 0) | " in md
    assert doc["readout_defaults"]["joint_iterations"] >= 1
    assert "## All captures" in md and "| one | " not in curve and "| one readout + 5 | " in md


def test_the_check_set_renders_other_seeds_of_the_same_kinds(tmp_path):
    caps = hyper_ood.closed_form_captures(tmp_path, 1, 16, hyper_ood.CLOSED_FORM_CHECK)
    assert caps == [("closed-form sphere, distant light", tmp_path / "sphere-directional-s4-16px")]
    assert (caps[0][1] / "transforms.json").exists()
    assert not set(hyper_ood.CLOSED_FORM_CHECK) & set(hyper_ood.CLOSED_FORM)


def test_the_committed_report_keeps_its_history_on_rerun():
    """bench/hyper_ood.md holds the study's history below the mark a rerun keeps, exactly once."""
    report = (Path(__file__).resolve().parents[2] / "bench" / "hyper_ood.md").read_text()
    assert report.count(hyper_ood.HISTORY_MARK) == 1
    kept = hyper_ood.with_history("# rerun\n", report)
    assert kept.startswith("# rerun\n") and kept.endswith(report[report.index(hyper_ood.HISTORY_MARK):])
    assert "### Run terminator" in kept and "### Run v1-v3" in kept  # the runs merged from the per-run reports
