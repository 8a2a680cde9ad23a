"""Fitting: beats RM++ by a margin on a closed-form capture; deterministic; resumable; W matters."""

from __future__ import annotations

import pytest
import torch

from damcap.appearance.evaluate import evaluate_split
from damcap.appearance.fit import FitOptions, fit_dam, holdout_frames, radiance_scale_of
from damcap.appearance.views import load_views, samples_of, training_frames
from damcap.common.capture_folder import read_capture
from damcap.common.errors import DamcapError


@pytest.fixture(scope="module")
def sample_views(sample_capture):
    cap = read_capture(sample_capture)
    return load_views(cap, "train"), load_views(cap, "test")


def test_fit_beats_rm_plus_plus_by_a_margin(sample_views):
    train, test = sample_views
    result = fit_dam(samples_of(train), FitOptions(steps=1500))
    scores = evaluate_split(train, test, {"DAM": result.model})
    dam, rmpp = scores["DAM"].mean, scores["RM++"].mean
    # measured: about 0.045 vs 0.128 (0.35x); the paper's DAM reaches 0.80x
    assert dam < 0.6 * rmpp, (dam, rmpp)
    assert scores["RM++"].mean < scores["RM"].mean


@pytest.fixture(scope="module")
def small_samples(small_capture):
    return samples_of(load_views(read_capture(small_capture), "train"))


def test_same_seed_same_model(small_samples):
    a = fit_dam(small_samples, FitOptions(steps=120, seed=5))
    b = fit_dam(small_samples, FitOptions(steps=120, seed=5))
    c = fit_dam(small_samples, FitOptions(steps=120, seed=6))
    torch.testing.assert_close(a.model.get_flat_weights(), b.model.get_flat_weights(), rtol=0, atol=0)
    assert not torch.equal(a.model.get_flat_weights(), c.model.get_flat_weights())


def test_interrupted_fit_resumes_to_the_same_model(small_samples, tmp_path):
    opts = FitOptions(steps=200, checkpoint_every=50, eval_every=25, seed=2)
    ref = fit_dam(small_samples, opts)
    ckpt = tmp_path / "m.dam.ckpt"

    def stop_at_150(step, steps, stats):
        if step == 150:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_dam(small_samples, opts, checkpoint_path=ckpt, progress=stop_at_150)
    assert ckpt.is_file()
    resumed = fit_dam(small_samples, opts, checkpoint_path=ckpt)
    assert resumed.resumed_from == 100
    torch.testing.assert_close(resumed.model.get_flat_weights(), ref.model.get_flat_weights(), rtol=0, atol=0)
    assert not ckpt.exists()  # removed after a finished fit
    # a checkpoint of other options is not resumed
    with pytest.raises(KeyboardInterrupt):
        fit_dam(small_samples, opts, checkpoint_path=ckpt, progress=stop_at_150)
    other = fit_dam(small_samples, FitOptions(steps=200, checkpoint_every=50, eval_every=25, seed=3), checkpoint_path=ckpt)
    assert other.resumed_from == 0


def test_zero_weight_samples_are_ignored(small_samples):
    clean = fit_dam(small_samples, FitOptions(steps=300, holdout_views=0))
    s = small_samples
    corrupt = type(s)(torch.cat([s.view_dir_world, s.view_dir_world]), torch.cat([s.normal_world, s.normal_world]),
                      torch.cat([s.radiance_lin, 50 * s.radiance_lin + 10]), torch.cat([s.weight, torch.zeros_like(s.weight)]),
                      torch.cat([s.frame_index, s.frame_index]))
    weighted = fit_dam(corrupt, FitOptions(steps=300, holdout_views=0))
    with torch.no_grad():
        x = (s.view_dir_world, s.normal_world)
        err_clean = (clean.model(*x) - s.radiance_lin).abs().mean()
        err_weighted = (weighted.model(*x) - s.radiance_lin).abs().mean()
    assert err_weighted < 2 * err_clean + 1e-3


def test_adversarial_cost_runs_and_stays_close(small_capture):
    views = load_views(read_capture(small_capture), "train")
    s = samples_of(views)
    opts = FitOptions(steps=100, adversarial=True, holdout_views=0)
    r = fit_dam(s, opts, frames_for_adversarial=training_frames(views, opts.encoding, radiance_scale_of(s.radiance_lin)))
    assert r.history[-1]["train_l1"] < 0.5
    with pytest.raises(DamcapError, match="whole training frames"):
        fit_dam(s, opts)


def test_holdout_frames_are_interior():
    assert holdout_frames(10, 2) == [3, 6]
    assert holdout_frames(2, 2) == []
    assert holdout_frames(10, 0) == []


def test_bad_options_are_clear():
    with pytest.raises(DamcapError, match="--steps must be >= 1"):
        FitOptions(steps=0).validate()
    with pytest.raises(DamcapError, match="learning-rate"):
        FitOptions(learning_rate=-1).validate()
