"""Training the predictor: the cost falls, resuming is exact, data-parallel ranks agree, CLI defaults."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from damcap.appearance.hyper.file import load_predictor
from damcap.appearance.hyper.model import HyperNet
from damcap.appearance.hyper.train import (HyperTrainOptions, corpus_loader, corpus_training_captures, load_hyper_capture,
                                           train_hyper, validation_l1, weights_sha256)


TINY = dict(input_size=32, channels=(4, 8, 8, 8, 8), steps=4, batch_size=2, pixels=256, pixels_per_capture=2048,
            eval_every=2, checkpoint_every=2)


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


def test_a_state_of_other_capture_content_or_options_is_never_resumed(tiny_corpus, tmp_path):
    import shutil

    from damcap.appearance.fit import load_checkpoint, save_checkpoint
    from damcap.synth.closed_form import ClosedFormOptions, make_closed_form_capture

    paths = corpus_training_captures(tiny_corpus)
    other_root = tmp_path / "other"
    shutil.copytree(tiny_corpus, other_root)  # same names, one capture re-rendered with other content
    shutil.rmtree(other_root / "captures" / "c1")
    make_closed_form_capture(other_root / "captures" / "c1", ClosedFormOptions(shape="torus", views=6, resolution=24, train_views=3, seed=7))
    other = corpus_training_captures(other_root)
    opts = HyperTrainOptions(**{**TINY, "steps": 6, "val_fraction": 0.0})
    fresh = train_hyper(other, opts)

    def stop_at_5(step, steps, stats):
        if step == 5:
            raise KeyboardInterrupt

    ckpt = tmp_path / "p.state"
    with pytest.raises(KeyboardInterrupt):  # never swallowed by the loop
        train_hyper(paths, opts, checkpoint_path=ckpt, progress=stop_at_5)
    assert int(load_checkpoint(ckpt)["step"]) == 4  # the last periodic checkpoint stays
    messages: list[str] = []
    res = train_hyper(other, opts, checkpoint_path=ckpt, log=messages.append)
    assert res.resumed_from == 0 and weights_sha256(res.net) == weights_sha256(fresh.net)
    assert ("p.state was written for other inputs (captures, options or damcap version differ); starting afresh "
            "(the old checkpoint kept as p.state.stale)") in messages
    assert (tmp_path / "p.state.stale").is_file() and not ckpt.exists()
    # other options (the learning rate) and an old state without a fingerprint start afresh too
    with pytest.raises(KeyboardInterrupt):
        train_hyper(paths, opts, checkpoint_path=ckpt, progress=stop_at_5)
    messages = []
    assert train_hyper(paths, HyperTrainOptions(**{**TINY, "steps": 6, "val_fraction": 0.0, "learning_rate": 1e-3}),
                       checkpoint_path=ckpt, log=messages.append).resumed_from == 0
    assert any("starting afresh" in m for m in messages)
    with pytest.raises(KeyboardInterrupt):
        train_hyper(paths, opts, checkpoint_path=ckpt, progress=stop_at_5)
    state = load_checkpoint(ckpt)
    del state["fingerprint"]
    save_checkpoint(ckpt, state)
    assert train_hyper(paths, opts, checkpoint_path=ckpt, log=lambda m: None).resumed_from == 0


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
@pytest.mark.parametrize("orientation", ["world", "light"])
def test_random_scenes_alone_lower_the_validation_loss(orientation):
    from functools import partial

    from damcap.synth.procedural import ProceduralOptions, render_scenes

    scenes = partial(render_scenes, opts=ProceduralOptions(scene_px=24, scene_views_max=8))
    opts = HyperTrainOptions(**{**TINY, "steps": 60, "batch_size": 8, "eval_every": 1, "procedural": 1.0, "input_views": 2,
                                "val_scenes": 8, "learning_rate": 3e-3, "checkpoint_every": 0, "orientation": orientation})
    with pytest.raises(Exception, match="needs a scene source"):
        train_hyper([], opts)
    res = train_hyper([], opts, scenes=scenes)
    first, best = res.curve[0]["val_scenes_l1"], min(c["val_scenes_l1"] for c in res.curve)
    assert best < 0.93 * first, (first, best)  # measured: 0.372 after one step, 0.328 at best
    assert res.best_step == min(res.curve, key=lambda c: c["val_l1"])["step"] and res.net.arch.input_views == 2


def test_loader_workers_draw_exactly_what_the_main_thread_draws(tiny_corpus):
    caps = [load_hyper_capture(p, 2048) for p in corpus_training_captures(tiny_corpus)]
    opts = HyperTrainOptions(**{**TINY, "steps": 5, "input_views": 2})
    main_thread = [next(it) for it in [corpus_loader(caps, 2, opts, 0, 1, pin=False)] for _ in range(4)]
    with_workers = corpus_loader(caps, 2, HyperTrainOptions(**{**TINY, "steps": 5, "input_views": 2, "loader_workers": 2}), 0, 1, pin=False)
    for a in main_thread:
        b = next(with_workers)
        assert torch.equal(a.images, b.images) and torch.equal(a.radiance_norm, b.radiance_norm) and torch.equal(a.view_mask, b.view_mask)
    assert main_thread[0].images.shape == (2, 2, 9, 32, 32)


@pytest.mark.slow
def test_two_torchrun_processes_hold_identical_weights(tiny_corpus, tmp_path):
    out = tmp_path / "ddp.safetensors"
    torchrun = Path(sys.executable).with_name("torchrun")
    cmd = [str(torchrun), "--nproc-per-node", "2", "--standalone", "-m", "damcap.cli.main", "train-hyper", str(tiny_corpus),
           "-o", str(out), "--steps", "3", "--batch-size", "4", "--pixels", "128", "--input-size", "32", "--channels", "4,8,8,8,8",
           "--val-fraction", "0", "--procedural", "0.5", "--scene-px", "16", "--val-scenes", "4"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    net, meta = load_predictor(out)
    t = meta["training"]
    assert t["launcher"]["world_size"] == 2
    digests = t["rank_weight_sha256"]
    assert len(digests) == 2 and digests[0] == digests[1] == weights_sha256(net)


def test_train_hyper_cli_defaults_are_the_options_defaults(tiny_corpus, tmp_path, monkeypatch, capsys):
    """``damcap train-hyper`` with no option hands train_hyper exactly HyperTrainOptions(); a flag
    changes only its own field (the CLI is derived from the dataclass, nothing restated)."""
    import dataclasses

    import damcap.appearance.hyper.train as train_module
    from tests.conftest import run_cli

    seen = []

    class Stop(Exception):
        pass

    def fake_train(paths, opts, *args, **kwargs):
        seen.append(opts)
        raise Stop

    monkeypatch.setattr(train_module, "train_hyper", fake_train)
    for args in ([], ["--channels", "4,8,8,8,8", "--steps", "7"]):
        with pytest.raises(Stop):
            run_cli(["train-hyper", tiny_corpus, "-o", tmp_path / "p.safetensors", *args], capsys)
    assert seen[0] == HyperTrainOptions()
    assert seen[1] == dataclasses.replace(HyperTrainOptions(), channels=(4, 8, 8, 8, 8), steps=7)


def test_init_starts_from_a_predictor_and_never_ends_worse(tmp_path):
    """``--init``: the run starts from the file's weights (its step-0 validation is that
    predictor's own), counts the steps already in it, keeps the start when training does not
    beat it, and refuses a predictor of another architecture with one line naming the file."""
    from functools import partial

    from damcap.appearance.hyper.file import save_predictor
    from damcap.common.errors import DamcapError
    from damcap.synth.procedural import ProceduralOptions, render_scenes

    scenes = partial(render_scenes, opts=ProceduralOptions(scene_px=24, scene_views_max=8))
    base = {**TINY, "batch_size": 4, "eval_every": 5, "procedural": 1.0, "val_scenes": 8, "checkpoint_every": 0}
    first = train_hyper([], HyperTrainOptions(**{**base, "steps": 10, "learning_rate": 3e-3}), scenes=scenes)
    start = tmp_path / "start.safetensors"
    save_predictor(start, first.net, {"options": {"steps": 10}, "seconds": 2.5})
    again = train_hyper([], HyperTrainOptions(**{**base, "steps": 5, "learning_rate": 1.0, "init": str(start)}), scenes=scenes)
    assert again.curve[0]["step"] == 0 and again.curve[0]["val_l1"] == pytest.approx(min(c["val_l1"] for c in first.curve), rel=1e-5)
    assert again.init == {"file": "start.safetensors", "weights_sha256": weights_sha256(first.net), "steps": 10, "seconds": 2.5,
                          "orientation": "world"}
    # a learning rate of 1 throws the weights off: the result is the start, not the wreck
    assert again.best_step == 0 and weights_sha256(again.net) == weights_sha256(first.net)
    with pytest.raises(DamcapError, match=r"start\.safetensors: --init predictor has architecture"):
        train_hyper([], HyperTrainOptions(**{**base, "input_views": 2, "init": str(start)}), scenes=scenes)
    # the orientation is not a shape: a world-orientation predictor may start a light-orientation run
    snaps = []
    turned = train_hyper([], HyperTrainOptions(**{**base, "steps": 2, "orientation": "light", "init": str(start), "snapshot_every": 1}),
                         scenes=scenes, snapshot=lambda step, net, init: snaps.append((step, init)))
    assert turned.net.arch.orientation == "light" and turned.init["orientation"] == "world"
    assert snaps == [(1, turned.init), (2, turned.init)]  # each snapshot knows the 10 steps it started from


def test_training_through_the_readout_solve_lowers_its_own_validation_loss(tiny_corpus):
    """--readout-iterations: the validation cost is the L1 after each DAM's output layer is solved
    on half the samples, scored on the other half; a short run lowers it and stays finite."""
    paths = corpus_training_captures(tiny_corpus)
    opts = HyperTrainOptions(**{**TINY, "steps": 40, "eval_every": 10, "learning_rate": 3e-3, "val_fraction": 0.0,
                                "augment": False, "checkpoint_every": 0, "readout_iterations": 2})
    res = train_hyper(paths, opts)
    caps = [load_hyper_capture(p, 2048) for p in paths]
    untrained = HyperNet(opts.architecture, torch.Generator().manual_seed(0))
    before, after = validation_l1(untrained, caps, readout_iterations=2), validation_l1(res.net, caps, readout_iterations=2)
    assert after < 0.8 * before, (before, after)
    assert all(torch.isfinite(p).all() for p in res.net.parameters())
    # the solve helps the untrained network's own output: a readout is a better start than none
    assert before < validation_l1(untrained, caps)
