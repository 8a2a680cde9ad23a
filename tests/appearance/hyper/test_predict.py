"""After the forward pass: re-synthesis error on the train views, the refinement advice, refinement
until held-out training views stop improving (``--refine-steps auto``), and the predict command."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.appearance.dam_file import load_dam
from damcap.appearance.fit import FitOptions, held_out, holdout_frames, refine_dam, training_l1
from damcap.appearance.hyper.file import load_predictor, save_predictor
from damcap.appearance.hyper.model import HyperArchitecture, HyperNet, predict_dam, predictor_input
from damcap.appearance.hyper.predict import (
    PredictOptions, Resynthesis, parse_refine_steps, refine_auto, refine_until_holdout_stops, refinement_needed, resynthesis_error,
    resynthesis_line,
)
from damcap.appearance.render import render_frame
from damcap.appearance.views import load_views, samples_of
from damcap.common.capture_folder import read_capture
from damcap.common.errors import DamcapError

from tests.conftest import assert_one_line_error
from tests.conftest import run_cli as run


def _dam(seed: int) -> DeepAppearanceMap:
    return DeepAppearanceMap(DamArchitecture(), 1.0, generator=torch.Generator().manual_seed(seed))


def _views_of(capture, model: DeepAppearanceMap, gain: float = 1.0):
    """The capture's train views with their radiance replaced by ``gain`` x the model's render."""
    views = load_views(read_capture(capture), "train")
    return [dataclasses.replace(v, data=dataclasses.replace(v.data, radiance_lin=gain * render_frame(model, v.data, v.centre_world)))
            for v in views]


def test_parse_refine_steps_takes_a_count_or_auto():
    assert parse_refine_steps("auto") == "auto" and parse_refine_steps("AUTO") == "auto"
    assert parse_refine_steps("0") == 0 and parse_refine_steps(" 30 ") == 30
    for bad in ("-1", "x", "2.5", "", "1e3", "100000000000000000000"):
        with pytest.raises(DamcapError, match=rf"--refine-steps must be an integer in \[0, 1000000000\] or 'auto', got {bad!r}"):
            parse_refine_steps(bad)
    PredictOptions(refine_steps="auto").validate()
    with pytest.raises(DamcapError, match="--refine-threshold"):
        PredictOptions(refine_threshold=1.5).validate()
    with pytest.raises(DamcapError, match="--refine-steps"):
        PredictOptions(refine_steps=-3).validate()


def test_resynthesis_error_of_the_dam_that_made_the_views_is_zero_and_of_half_the_radiance_is_closed_form(small_capture):
    model = _dam(1)
    exact = _views_of(small_capture, model)
    err = resynthesis_error(model, exact, samples_of(exact))
    assert err.views == 4
    assert err.dssim == pytest.approx(0.0, abs=1e-6) and err.l1 == pytest.approx(0.0, abs=1e-6)
    # the views twice as bright: L1 = mean |p - 2p| / scale = mean(p) / scale over the covered pixels
    doubled = _views_of(small_capture, model, gain=2.0)
    samples = samples_of(doubled)
    err2 = resynthesis_error(model, doubled, samples)
    assert err2.l1 == pytest.approx(float(samples.radiance_lin.double().mean()) / 2 / model.radiance_scale, rel=1e-5)
    assert err2.dssim > 0.01  # DSSIM normalises by the reference's brightness: half the radiance is a different image


def test_refinement_advice_follows_the_threshold():
    assert refinement_needed(0.06, 0.05) and not refinement_needed(0.05, 0.05) and refinement_needed(math.nan, 0.05)
    above = resynthesis_line(Resynthesis(0.2084, 0.1396, 10), 0.05)
    assert above.startswith("re-synthesis of the 10 train views: DSSIM 0.2084, L1 0.1396; above --refine-threshold 0.05")
    assert "--refine-steps auto refines only while an arc of held-out train views improves" in above and "\n" not in above
    assert "within --refine-threshold 0.3" in resynthesis_line(Resynthesis(0.2084, 0.1396, 10), 0.3)


def test_auto_refinement_lowers_the_held_out_error_and_keeps_its_best_weights(small_capture):
    target, start = _dam(1), _dam(2)
    views = _views_of(small_capture, target)
    samples = samples_of(views)
    before = start.get_flat_weights()
    r = refine_until_holdout_stops(start, samples, max_steps=150, patience_steps=50)
    assert torch.equal(start.get_flat_weights(), before)  # the start is not modified
    assert r.held_out == holdout_frames(4, 2) == [1, 2]  # the fit's stopping rule's views
    held = samples.subset(torch.isin(samples.frame_index, torch.tensor(r.held_out)))
    assert r.curve[0] == {"step": 0, "holdout_l1": training_l1(start, held)}
    assert [c["step"] for c in r.curve] == list(range(0, r.steps_run + 1, 25))
    best = min(r.curve, key=lambda c: c["holdout_l1"])
    assert r.steps_used == best["step"] > 0
    assert training_l1(r.model, held) == pytest.approx(best["holdout_l1"], rel=1e-6)  # the kept weights are the best's
    assert best["holdout_l1"] < 0.5 * r.curve[0]["holdout_l1"]
    # stopped at the cap or by patience, and says which
    assert (r.stopped_by, r.steps_run) == ("max_steps", 150) or (r.stopped_by == "patience" and r.steps_run - r.steps_used == 50)
    again = refine_until_holdout_stops(start, samples, max_steps=50, patience_steps=50)
    assert [c["holdout_l1"] for c in again.curve] == [c["holdout_l1"] for c in r.curve[:3]]  # seeded: the same run


def test_auto_refinement_keeps_a_perfect_prediction_and_stops_after_its_patience(small_capture):
    target = _dam(1)
    views = _views_of(small_capture, target)
    r = refine_until_holdout_stops(target, samples_of(views), max_steps=1000, patience_steps=50, eval_every=25)
    assert r.steps_used == 0 and r.steps_run == 50 and r.stopped_by == "patience"
    assert torch.equal(r.model.get_flat_weights(), target.get_flat_weights())
    capped = refine_until_holdout_stops(_dam(2), samples_of(views), max_steps=30, patience_steps=100)
    assert capped.steps_run == 30 and capped.stopped_by == "max_steps" and [c["step"] for c in capped.curve] == [0, 25, 30]


def test_auto_refinement_needs_views_to_hold_out(tmp_path):
    from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

    cap = make_closed_form_capture(tmp_path / "two", ClosedFormOptions(views=4, train_views=2, resolution=16, dtype="float"))
    samples = samples_of(load_views(cap, "train"))
    with pytest.raises(DamcapError, match="2 train view\\(s\\) leave none to hold out"):
        refine_until_holdout_stops(_dam(1), samples, max_steps=10, patience_steps=10)


@pytest.fixture(scope="module")
def tiny_predictor(tmp_path_factory):
    path = tmp_path_factory.mktemp("pred") / "p.safetensors"
    save_predictor(path, HyperNet(HyperArchitecture(input_size=32, channels=(4, 8)), torch.Generator().manual_seed(0)), {"command": "test"})
    return path


def test_predict_reports_its_resynthesis_error_and_refines_until_the_held_out_views_stop_improving(tmp_path, small_capture, tiny_predictor, capsys):
    out = tmp_path / "auto.dam"
    code, stdout, err = run(["predict", small_capture, "-o", out, "--predictor", tiny_predictor, "--refine-steps", "auto",
                             "--refine-max-steps", "60", "--refine-patience", "50"], capsys)
    assert code == 0, err
    model, meta = load_dam(out)
    prov = meta["provenance"]
    # the reported error is the library's, on the predicted DAM, before refinement
    net, _ = load_predictor(tiny_predictor)
    views = load_views(read_capture(small_capture), "train")
    _, crop, scale = predictor_input(views)
    predicted = predict_dam(net, crop, scale)
    samples = samples_of(views)
    ref = resynthesis_error(predicted, views, samples)
    assert (prov["train_dssim_predicted"], prov["train_l1_predicted"], prov["train_views"]) == (ref.dssim, ref.l1, 4)
    lines = stdout.strip().splitlines()
    default = PredictOptions().refine_threshold
    assert lines[0] == resynthesis_line(ref, default)
    assert prov["refinement_needed"] is refinement_needed(ref.dssim, default) and prov["refine_threshold"] == default
    # auto: the library's choice of K, then K steps on all train views (what --refine-steps K does)
    held = held_out(views, FitOptions())  # an arc of the train cameras, as the fit's stopping rule holds out
    refined, auto = refine_auto(predicted, samples, max_steps=60, patience_steps=50, held=held)
    assert prov["refine_steps"] == "auto" and prov["options"]["refine_max_steps"] == 60
    assert (prov["refine_steps_used"], prov["refine_steps_run"]) == (auto.steps_used, auto.steps_run)
    assert prov["refine_held_out_views"] == [views[k].name for k in held] == [views[0].name, views[1].name]
    assert prov["refine_holdout_curve"] == auto.curve
    assert np.array_equal(model.get_flat_weights().numpy(), refined.get_flat_weights().numpy())
    if auto.steps_used:
        assert np.array_equal(refined.get_flat_weights().numpy(), refine_dam(predicted, samples, auto.steps_used, PredictOptions.refine_learning_rate)[0].get_flat_weights().numpy())
    after = resynthesis_error(refined, views, samples)
    assert (prov["train_dssim_refined"], prov["train_l1_refined"]) == (after.dssim, after.l1)
    why = "held-out views stopped improving" if auto.stopped_by == "patience" else "held-out views still improving at --refine-max-steps 60"
    assert prov["refine_stopped_by"] == auto.stopped_by
    assert f"refined {auto.steps_used} steps (auto: {why}; {auto.steps_run} tried)" in lines[-1]


def test_auto_chooses_k_on_held_out_views_then_takes_k_steps_on_all(small_capture):
    target, start = _dam(1), _dam(2)
    samples = samples_of(_views_of(small_capture, target))
    model, chosen = refine_auto(start, samples, max_steps=100, patience_steps=50)
    assert chosen.steps_used > 0
    assert torch.equal(model.get_flat_weights(), refine_dam(start, samples, chosen.steps_used, PredictOptions.refine_learning_rate)[0].get_flat_weights())
    assert training_l1(model, samples) < training_l1(start, samples)
    kept, none = refine_auto(target, samples, max_steps=100, patience_steps=25)
    assert none.steps_used == 0 and kept is target  # nothing improved the held-out views: the start is kept


def test_predict_threshold_and_integer_refinement(tmp_path, small_capture, tiny_predictor, capsys):
    code, stdout, err = run(["predict", small_capture, "-o", tmp_path / "a.dam", "--predictor", tiny_predictor, "--refine-threshold", "1"], capsys)
    assert code == 0, err
    assert "within --refine-threshold 1:" in stdout
    prov = load_dam(tmp_path / "a.dam")[1]["provenance"]
    assert prov["refinement_needed"] is False and prov["refine_steps"] == 0 and "train_l1_refined" not in prov
    # the verdict is on the network's own output, also when predict then solves its output layer (the
    # solved model's train error predicted refinement's gain worse: bench/hyper_ood.md)
    raw = prov["train_dssim_predicted"]
    assert prov["train_dssim_readout"] < raw
    code, stdout, err = run(["predict", small_capture, "-o", tmp_path / "s.dam", "--predictor", tiny_predictor, "--refine-threshold",
                             str(prov["train_dssim_readout"])], capsys)
    assert code == 0, err
    assert f"train views: DSSIM {raw:.4f}" in stdout and "--refine-steps auto refines only while" in stdout
    assert load_dam(tmp_path / "s.dam")[1]["provenance"]["refinement_needed"] is True
    code, stdout, err = run(["predict", small_capture, "-o", tmp_path / "b.dam", "--predictor", tiny_predictor, "--refine-threshold", "0",
                             "--refine-steps", "20"], capsys)
    assert code == 0, err
    assert "above --refine-threshold 0: this capture is unlike the predictor's training set; --refine-steps auto refines only while" in stdout
    prov = load_dam(tmp_path / "b.dam")[1]["provenance"]
    assert prov["refinement_needed"] is True and prov["refine_steps"] == prov["refine_steps_used"] == 20
    assert prov["train_l1_refined"] <= prov["train_l1_predicted"]


@pytest.mark.parametrize("args,needles", [
    (["--refine-steps", "x"], ["--refine-steps", "'x'", "'auto'"]),
    (["--refine-steps", "-1"], ["--refine-steps", "'-1'"]),
    (["--refine-steps", "2.5"], ["--refine-steps", "'2.5'"]),
    (["--refine-steps", "autox"], ["--refine-steps", "'autox'"]),
    (["--refine-threshold", "2"], ["--refine-threshold", "2"]),
    (["--refine-threshold", "nan"], ["--refine-threshold", "nan"]),
    (["--refine-max-steps", "0"], ["--refine-max-steps", "0"]),
    (["--refine-patience", "0"], ["--refine-patience", "0"]),
    (["--readout-iterations", "-1"], ["--readout-iterations", "-1"]),
    (["--readout-samples", "0"], ["--readout-samples", "0"]),
    (["--joint-iterations", "-1"], ["--joint-iterations", "-1"]),
    (["--joint-samples", "0"], ["--joint-samples", "0"]),
    (["--joint-prior", "-1"], ["--joint-prior", "-1"]),
])
def test_predict_bad_refinement_options_are_one_line_errors(tmp_path, small_capture, tiny_predictor, capsys, args, needles):
    out = tmp_path / "x.dam"
    code, _, err = run(["predict", small_capture, "-o", out, "--predictor", tiny_predictor, *args], capsys)
    assert_one_line_error(code, err, *needles)
    assert not out.exists()


def test_predict_auto_on_two_train_views_is_a_one_line_error(tmp_path, tiny_predictor, capsys):
    from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

    make_closed_form_capture(tmp_path / "two", ClosedFormOptions(views=4, train_views=2, resolution=16, dtype="float"))
    out = tmp_path / "x.dam"
    code, _, err = run(["predict", tmp_path / "two", "-o", out, "--predictor", tiny_predictor, "--refine-steps", "auto"], capsys)
    assert_one_line_error(code, err, "--refine-steps auto", "give a number of steps")
    assert not out.exists()


def test_predict_solves_the_output_layer_then_the_first_and_output_layers_without_refinement_and_not_with_it(
        tmp_path, small_capture, tiny_predictor, capsys):
    from damcap.appearance.readout import solve_first_and_output_layers, solve_output_layer

    code, stdout, err = run(["predict", small_capture, "-o", tmp_path / "a.dam", "--predictor", tiny_predictor], capsys)
    assert code == 0, err
    model, meta = load_dam(tmp_path / "a.dam")
    prov = meta["provenance"]
    net, _ = load_predictor(tiny_predictor)
    views = load_views(read_capture(small_capture), "train")
    _, crop, scale = predictor_input(views)
    predicted, samples = predict_dam(net, crop, scale), samples_of(views)
    opts = PredictOptions()
    solved = solve_output_layer(predicted, samples, opts.readout_iterations, opts.readout_samples)
    joint = solve_first_and_output_layers(solved.model, samples, opts.joint_iterations, opts.joint_samples, opts.joint_prior)
    assert torch.equal(model.get_flat_weights(), joint.model.get_flat_weights())  # the library's solves, at the options' defaults
    assert prov["readout_iterations_used"] == solved.iterations >= 1
    assert prov["joint_iterations_used"] == joint.iterations >= 1
    after = resynthesis_error(solved.model, views, samples)
    assert (prov["train_dssim_readout"], prov["train_l1_readout"]) == (after.dssim, after.l1)
    assert prov["train_l1_readout"] < prov["train_l1_predicted"]  # the hidden layers' features mixed to the capture's pixels
    final = resynthesis_error(joint.model, views, samples)
    assert (prov["train_dssim_joint"], prov["train_l1_joint"]) == (final.dssim, final.l1)
    assert prov["train_l1_joint"] < prov["train_l1_readout"]  # the first layer moved too
    assert f"solving its output layer on {min(len(samples), opts.readout_samples)} train pixels ({solved.iterations} iterations)" in stdout
    assert f"solving its first and output layers together on {min(len(samples), opts.joint_samples)} ({joint.iterations} iterations)" in stdout
    assert f"L1 {prov['train_l1_predicted']:.4f} -> {final.l1:.4f}" in stdout
    # --joint-iterations 0: the output layer's solve alone
    code, _, err = run(["predict", small_capture, "-o", tmp_path / "o.dam", "--predictor", tiny_predictor, "--joint-iterations", "0"], capsys)
    assert code == 0, err
    only, meta = load_dam(tmp_path / "o.dam")
    assert torch.equal(only.get_flat_weights(), solved.model.get_flat_weights()) and "joint_iterations_used" not in meta["provenance"]
    # refinement starts from the network's own output; both counts 0 keep that output
    for args, name in ((["--refine-steps", "5"], "b.dam"), (["--readout-iterations", "0", "--joint-iterations", "0"], "c.dam")):
        code, _, err = run(["predict", small_capture, "-o", tmp_path / name, "--predictor", tiny_predictor, *args], capsys)
        assert code == 0, err
        prov = load_dam(tmp_path / name)[1]["provenance"]
        assert "readout_iterations_used" not in prov and "joint_iterations_used" not in prov
    assert torch.equal(load_dam(tmp_path / "c.dam")[0].get_flat_weights(), predicted.get_flat_weights())


def test_solve_prediction_runs_each_solve_at_its_own_count():
    from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
    from damcap.appearance.hyper.predict import solve_prediction
    from damcap.appearance.pixels import PixelSamples

    g = torch.Generator().manual_seed(4)
    n = 500
    v, nrm = (torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1) for _ in range(2))
    samples = PixelSamples(v, nrm, torch.rand(n, 3, generator=g), torch.ones(n), torch.zeros(n, dtype=torch.int64))
    model = DeepAppearanceMap(DamArchitecture(width=8, depth=2), 1.0, generator=g)
    none = solve_prediction(model, samples, PredictOptions(readout_iterations=0, joint_iterations=0))
    assert none.model is model and none.readout is None and none.joint is None
    joint_only = solve_prediction(model, samples, PredictOptions(readout_iterations=0, joint_iterations=2))
    assert joint_only.readout is None and joint_only.joint.iterations >= 1 and joint_only.joint.l1_after < joint_only.joint.l1_before
    both = solve_prediction(model, samples, PredictOptions(readout_iterations=2, joint_iterations=2))
    assert abs(both.joint.l1_before - both.readout.l1_after) < 1e-5 * both.readout.l1_after  # one after the other (all 500 samples in both)
    assert both.readout_seconds > 0 and both.joint_seconds > 0


def test_predict_capture_is_what_the_command_saves(tmp_path, small_capture, tiny_predictor, capsys):
    """The library call (a Capture in, no command line) gives the model, the lines and the
    provenance record ``damcap predict`` prints and saves."""
    import json

    from damcap.appearance.hyper.predict import predict_capture

    said = []
    result = predict_capture(read_capture(small_capture), PredictOptions(refine_steps=5), tiny_predictor, log=said.append)
    assert said == [result.advice] and result.advice.startswith("re-synthesis of the 4 train views")
    assert result.summary.startswith(", refined 5 steps: train DSSIM") and len(result.input_frames) == 1
    code, stdout, err = run(["predict", small_capture, "-o", tmp_path / "p.dam", "--predictor", tiny_predictor, "--refine-steps", "5"], capsys)
    assert code == 0, err
    model, meta = load_dam(tmp_path / "p.dam")
    assert torch.equal(model.get_flat_weights(), result.model.get_flat_weights())
    untimed = lambda record: {k: v for k, v in json.loads(json.dumps(record)).items() if not k.endswith("_seconds")}  # noqa: E731
    assert untimed(meta["provenance"]) == untimed(result.record)
    lines = stdout.strip().splitlines()
    assert lines[0] == result.advice and lines[-1].endswith(f"ms{result.summary})")
