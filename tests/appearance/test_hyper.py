"""Learning-to-learn: the predictor network, its input, training (also data-parallel), files, CLI."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from damcap.appearance.dam_file import load_dam, save_dam
from damcap.appearance.fit import FitOptions, fit_dam, refine_dam, training_l1
from damcap.appearance.hyper import HyperArchitecture, HyperNet, predict_dam, predictor_image, rotation_y, view_crop
from damcap.appearance.hyper_file import load_predictor, save_predictor, shipped_predictor_path
from damcap.appearance.hyper_train import (HyperTrainOptions, corpus_training_captures, load_hyper_capture, train_hyper,
                                           validation_l1, weights_sha256)
from damcap.appearance.pixels import view_dir_world
from damcap.appearance.views import load_views, samples_of
from damcap.cli.main import main
from damcap.common.capture_folder import read_capture, read_frame
from damcap.common.errors import DamcapError

TINY = dict(input_size=32, channels=(4, 8, 8, 8, 8), steps=4, batch_size=2, pixels=256, pixels_per_capture=2048,
            eval_every=2, checkpoint_every=2)


def _crop_of(capture: Path, k: int = 0) -> torch.Tensor:
    cap = read_capture(capture)
    f = cap.frames[k]
    d = read_frame(cap, f, with_weights=False)
    return view_crop(d.radiance_lin, d.normal_world, view_dir_world(d.position_world, f.camera_centre_world), d.coverage)


@pytest.fixture(scope="module")
def tiny_corpus(tmp_path_factory) -> Path:
    """A corpus.json over three tiny closed-form captures (train split), as synth-set writes it."""
    from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

    root = tmp_path_factory.mktemp("corpus")
    entries = []
    for k, shape in enumerate(("sphere", "torus", "sphere")):
        name = f"c{k}"
        make_closed_form_capture(root / "captures" / name, ClosedFormOptions(shape=shape, views=6, resolution=24, train_views=3, seed=k))
        entries.append({"name": name, "path": f"captures/{name}", "split": "train"})
    entries.append({"name": "held", "path": "captures/held", "split": "heldout"})
    (root / "corpus.json").write_text(json.dumps({"captures": entries}))
    return root


def test_network_shapes_and_default_architecture():
    arch = HyperArchitecture()
    assert arch.input_size == 256 and len(arch.channels) == 8 and arch.dam.num_weights == 3360
    net = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8, 8, 8, 8)))
    out = net(torch.randn(3, 9, 32, 32))
    assert out.shape == (3, 3360) and torch.isfinite(out).all()
    full = HyperNet(arch)
    n_params = sum(p.numel() for p in full.parameters())
    assert n_params * 4 < 30e6  # the shipped file stays under ~30 MB in float32


def test_predictor_image_channels_units_and_augmentations(small_capture):
    crop = _crop_of(small_capture)
    img, scale = predictor_image(crop, 32)
    assert img.shape == (9, 32, 32) and scale > 0
    fg = img[3:6].norm(dim=0) > 0
    assert fg.any() and (~fg).any()
    assert torch.allclose(img[3:6].norm(dim=0)[fg], torch.ones(()), atol=1e-5)  # unit normals on the foreground
    assert (img[:, ~fg] == 0).all()  # covered pixels only
    # rotation about +y rotates every world vector and leaves RGB alone
    r = rotation_y(0.7)
    rot, scale_r = predictor_image(crop, 32, rotation=r)
    assert scale_r == scale and torch.equal(rot[:3], img[:3])
    assert torch.allclose(rot[3:6], torch.einsum("ij,jhw->ihw", r, img[3:6]), atol=1e-5)
    # mirroring twice is the identity; a gain of 2 leaves the normalised image unchanged and doubles the scale
    back = predictor_image(crop, 32, mirror=True)[0].flip(-1)
    assert torch.allclose(back[3], -img[3], atol=1e-5) and torch.allclose(back[6], -img[6], atol=1e-5)  # world x reflected
    assert torch.allclose(back[[0, 1, 2, 4, 5, 7, 8]], img[[0, 1, 2, 4, 5, 7, 8]], atol=1e-5)
    g, scale_g = predictor_image(crop, 32, rgb_gain=torch.full((3,), 2.0))
    assert math.isclose(scale_g, 2 * scale, rel_tol=1e-5) and torch.allclose(g, img, atol=1e-5)


def test_training_lowers_the_cost_and_resumes_exactly(tiny_corpus, tmp_path):
    paths = corpus_training_captures(tiny_corpus)
    assert [p.name for p in paths] == ["c0", "c1", "c2"]  # the held-out entry is never used (and not even rendered)
    opts = HyperTrainOptions(**{**TINY, "steps": 6, "val_fraction": 0.0})
    whole = train_hyper(paths, opts)
    assert whole.world_size == 1 and len(whole.curve) == 3

    class Stop(Exception):
        pass

    def stop_at_5(step, steps, stats):
        if step == 5:
            raise Stop

    ckpt = tmp_path / "p.state"
    with pytest.raises(Stop):
        train_hyper(paths, opts, checkpoint_path=ckpt, progress=stop_at_5)
    assert ckpt.is_file()
    resumed = train_hyper(paths, opts, checkpoint_path=ckpt)
    assert resumed.resumed_from == 4 and not ckpt.exists()
    assert weights_sha256(resumed.net) == weights_sha256(whole.net)


def test_longer_training_fits_the_training_captures(tiny_corpus):
    paths = corpus_training_captures(tiny_corpus)
    opts = HyperTrainOptions(**{**TINY, "steps": 150, "eval_every": 50, "learning_rate": 3e-3, "val_fraction": 0.0,
                                "augment": False, "checkpoint_every": 0})
    res = train_hyper(paths, opts)
    caps = [load_hyper_capture(p, 2048) for p in paths]
    untrained = HyperNet(opts.architecture, torch.Generator().manual_seed(0))
    before, after = validation_l1(untrained, caps), validation_l1(res.net, caps)
    assert after < 0.5 * before, (before, after)


@pytest.mark.slow
def test_two_torchrun_processes_hold_identical_weights(tiny_corpus, tmp_path):
    out = tmp_path / "ddp.safetensors"
    torchrun = Path(sys.executable).with_name("torchrun")
    cmd = [str(torchrun), "--nproc-per-node", "2", "--standalone", "-m", "damcap.cli.main", "train-hyper", str(tiny_corpus),
           "-o", str(out), "--steps", "3", "--batch-size", "4", "--pixels", "128", "--input-size", "32", "--channels", "4,8,8,8,8",
           "--val-fraction", "0"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    net, meta = load_predictor(out)
    t = meta["training"]
    assert t["launcher"]["world_size"] == 2
    digests = t["rank_weight_sha256"]
    assert len(digests) == 2 and digests[0] == digests[1] == weights_sha256(net)


def test_predictor_file_round_trip_and_bad_files(tmp_path, small_capture):
    net = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8)))
    path = tmp_path / "p.safetensors"
    save_predictor(path, net, {"command": "test"})
    back, meta = load_predictor(path)
    assert weights_sha256(back) == weights_sha256(net) and meta["training"]["command"] == "test"
    crop = _crop_of(small_capture)
    assert torch.equal(predict_dam(back, crop).get_flat_weights(), predict_dam(net, crop).get_flat_weights())

    truncated = tmp_path / "truncated.safetensors"
    truncated.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(DamcapError, match="not valid safetensors"):
        load_predictor(truncated)
    # metadata that states another architecture than the tensors hold
    from safetensors.torch import load_file, save_file

    wrong = tmp_path / "wrong.safetensors"
    arch = HyperArchitecture(input_size=32, channels=(4, 16)).to_json()
    save_file(load_file(path), wrong, metadata={"damcap": json.dumps({"format_version": 1, "kind": "dam-predictor", "architecture": arch})})
    with pytest.raises(DamcapError, match="do not match the stated architecture"):
        load_predictor(wrong)
    dam_file = tmp_path / "m.dam"
    save_dam(dam_file, predict_dam(net, crop), colorspace="lin_rec709", made_by="predict")
    with pytest.raises(DamcapError, match="not a predictor"):
        load_predictor(dam_file)
    with pytest.raises(DamcapError, match="not found"):
        load_predictor(tmp_path / "missing.safetensors")


def test_refinement_never_makes_the_training_cost_worse(small_capture):
    samples = samples_of(load_views(read_capture(small_capture), "train"))
    net = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8)))
    start = predict_dam(net, _crop_of(small_capture))
    refined, before, after = refine_dam(start, samples, 60)
    assert after <= before and math.isclose(before, training_l1(start, samples), rel_tol=1e-6)
    assert math.isclose(after, training_l1(refined, samples), rel_tol=1e-6)
    # from an already converged model a too-large step size cannot make it worse either
    fitted = fit_dam(samples, FitOptions(steps=400, holdout_views=0, checkpoint_every=0)).model
    again, b2, a2 = refine_dam(fitted, samples, 20, learning_rate=0.5)
    assert a2 <= b2 and training_l1(again, samples) <= training_l1(fitted, samples) + 1e-9


def test_shipped_predictor_predicts_the_heldout_sample(tmp_path):
    sample = Path(__file__).resolve().parents[2] / "samples" / "synth_spot_sunset"
    assert shipped_predictor_path().is_file(), "the trained predictor must ship with damcap"
    out = tmp_path / "pred.dam"
    assert main(["predict", str(sample), "-o", str(out)]) == 0
    dam, meta = load_dam(out)
    assert meta["made_by"] == "predict" and meta["provenance"]["predict_seconds"] < 1.0
    from damcap.appearance.evaluate import evaluate_split

    cap = read_capture(sample)
    train, test = load_views(cap, "train"), load_views(cap, "test")
    scores = evaluate_split(train, test, {"predict": dam}, baselines=True)
    # measured with the shipped predictor (dam-predictor-v1): novel-view DSSIM 0.161, RM++ 0.219, RM 0.247
    assert scores["predict"].mean < PREDICT_SAMPLE_BOUND
    assert scores["predict"].mean < scores["RM++"].mean < scores["RM"].mean


PREDICT_SAMPLE_BOUND = 0.20


def test_predict_and_evaluate_cli(tmp_path, small_capture):
    net = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8)))
    pred = tmp_path / "p.safetensors"
    save_predictor(pred, net, {"command": "test"})
    out = tmp_path / "pred.dam"
    assert main(["predict", str(small_capture), "-o", str(out), "--predictor", str(pred), "--refine-steps", "30"]) == 0
    prov = load_dam(out)[1]["provenance"]
    assert prov["train_l1_refined"] <= prov["train_l1_predicted"]
    assert main(["predict", str(small_capture), "-o", str(tmp_path / "x.dam"), "--predictor", str(pred), "--view", "nope"]) == 2
    assert main(["predict", str(small_capture), "-o", str(tmp_path / "x.dam"), "--predictor", str(tmp_path / "missing")]) == 2
    fitted = tmp_path / "fit.dam"
    assert main(["fit", str(small_capture), "-o", str(fitted), "--steps", "50"]) == 0
    js = tmp_path / "e.json"
    assert main(["evaluate", str(small_capture), "--model", str(out), "--model", str(fitted), "--json", str(js)]) == 0
    res = json.loads(js.read_text())
    assert set(res["models"]) == {"predict: pred", "fit: fit"}
    r = res["ratios"]["predict: pred / fit: fit"]["test"]
    assert math.isclose(r, res["results"]["test"]["predict: pred"]["mean"] / res["results"]["test"]["fit: fit"]["mean"], rel_tol=1e-9)


def test_train_hyper_cli_defaults_are_the_options_defaults():
    import dataclasses
    import inspect

    from damcap.cli.hyper_cmds import train_hyper_cmd

    params = inspect.signature(train_hyper_cmd).parameters
    fields = {f.name: f.default for f in dataclasses.fields(HyperTrainOptions)}
    shared = set(params) & set(fields) - {"channels"}
    assert {"steps", "batch_size", "pixels", "learning_rate", "input_size", "max_captures", "augment", "seed"} <= shared
    for name in shared:
        assert params[name].default.default == fields[name], name  # typer.Option(default, ...)
    assert tuple(int(c) for c in params["channels"].default.default.split(",")) == fields["channels"]
