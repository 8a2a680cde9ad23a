"""Fitting: beats RM++ by a margin on a closed-form capture; deterministic; resumable; W matters."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from damcap.appearance.evaluate import evaluate_split
from damcap.appearance.fit import FitOptions, fit_dam, holdout_frames, weighted_quantile_cost
from damcap.appearance.views import radiance_scale_of
from damcap.appearance.views import load_views, samples_of
from damcap.appearance.fit import training_frames
from damcap.appearance.fit import refine_dam, training_l1
from damcap.appearance.hyper.model import HyperArchitecture, HyperNet, predict_dam
from damcap.common.capture_folder import read_capture
from damcap.common.errors import DamcapError

from tests.appearance.conftest import _crop_of


@pytest.fixture(scope="module")
def sample_views(sample_capture):
    cap = read_capture(sample_capture)
    return load_views(cap, "train"), load_views(cap, "test")


@pytest.mark.slow
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


def interrupt_fit_at(samples, opts: FitOptions, ckpt, step: int) -> None:
    """Run a checkpointed fit and interrupt it (KeyboardInterrupt) at ``step``."""

    def stop(at, steps, stats):
        if at == step:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt) as info:
        fit_dam(samples, opts, checkpoint_path=ckpt, progress=stop, log=lambda m: None)
    # the interrupt propagates unchanged, with a note saying what was kept
    assert getattr(info.value, "__notes__", None) == [
        f"stopped after step {step} of {opts.steps}; kept {ckpt} (step {step}): rerun the same command to resume"]


def test_interrupted_fit_resumes_to_the_same_model(small_samples, tmp_path):
    opts = FitOptions(steps=200, checkpoint_every=50, eval_every=25, seed=2)
    ref = fit_dam(small_samples, opts)
    ckpt = tmp_path / "m.dam.ckpt"
    interrupt_fit_at(small_samples, opts, ckpt, 150)
    assert ckpt.is_file()
    resumed = fit_dam(small_samples, opts, checkpoint_path=ckpt)
    assert resumed.resumed_from == 150  # the interrupted step itself was checkpointed
    torch.testing.assert_close(resumed.model.get_flat_weights(), ref.model.get_flat_weights(), rtol=0, atol=0)
    assert not ckpt.exists()  # removed after a finished fit
    # a checkpoint of other options is not resumed
    interrupt_fit_at(small_samples, opts, ckpt, 150)
    other = fit_dam(small_samples, FitOptions(steps=200, checkpoint_every=50, eval_every=25, seed=3), checkpoint_path=ckpt)
    assert other.resumed_from == 0


def test_an_interrupt_between_checkpoints_keeps_the_interrupted_step_and_resumes_exactly(small_samples, tmp_path):
    from damcap.appearance.fit import load_checkpoint

    opts = FitOptions(steps=60, checkpoint_every=20, eval_every=10, seed=3)
    ref = fit_dam(small_samples, opts)
    ckpt = tmp_path / "m.dam.ckpt"
    interrupt_fit_at(small_samples, opts, ckpt, 27)  # after the checkpoint at 20, before the one at 40
    assert int(load_checkpoint(ckpt)["step"]) == 27
    messages: list[str] = []
    resumed = fit_dam(small_samples, opts, checkpoint_path=ckpt, log=messages.append)
    assert resumed.resumed_from == 27 and messages == ["resuming m.dam.ckpt at step 27 of 60"]
    torch.testing.assert_close(resumed.model.get_flat_weights(), ref.model.get_flat_weights(), rtol=0, atol=0)
    assert _without_seconds(resumed.history) == _without_seconds(ref.history)
    assert resumed.best_step == ref.best_step


def _without_seconds(history):
    return [{k: v for k, v in h.items() if k != "seconds"} for h in history]


def _other_capture_samples(samples):
    """The same pixels and count as ``samples`` with other radiance (another capture, same size)."""
    from damcap.appearance.pixels import PixelSamples

    return PixelSamples(samples.view_dir_world, samples.normal_world, samples.radiance_lin * 0.5 + 0.1, samples.weight,
                        samples.frame_index)


def test_a_checkpoint_of_another_capture_is_never_resumed(small_samples, tmp_path):
    opts = FitOptions(steps=60, checkpoint_every=20, eval_every=10, seed=3)
    other = _other_capture_samples(small_samples)
    assert len(other) == len(small_samples)  # the old rule (options + pixel count) would have resumed it
    fresh = fit_dam(other, opts)
    ckpt = tmp_path / "m.dam.ckpt"
    interrupt_fit_at(small_samples, opts, ckpt, 40)  # capture A's checkpoint at the output path
    a_state = ckpt.read_bytes()
    messages: list[str] = []
    b = fit_dam(other, opts, checkpoint_path=ckpt, log=messages.append)
    assert b.resumed_from == 0
    torch.testing.assert_close(b.model.get_flat_weights(), fresh.model.get_flat_weights(), rtol=0, atol=0)
    assert _without_seconds(b.history) == _without_seconds(fresh.history)
    assert messages == ["m.dam.ckpt was written for other inputs (capture, options or damcap version differ); "
                        "starting afresh (the old checkpoint kept as m.dam.ckpt.stale)"]
    assert (tmp_path / "m.dam.ckpt.stale").read_bytes() == a_state and not ckpt.exists()


def test_a_changed_option_or_version_invalidates_the_checkpoint(small_samples, tmp_path, monkeypatch):
    import damcap.appearance.fit as fit_module

    opts = FitOptions(steps=60, checkpoint_every=20, eval_every=10, seed=3)
    ckpt = tmp_path / "m.dam.ckpt"
    for changed in (replace(opts, learning_rate=2e-2), replace(opts, holdout_views=1), replace(opts, steps=80)):
        interrupt_fit_at(small_samples, opts, ckpt, 40)
        messages: list[str] = []
        r = fit_dam(small_samples, changed, checkpoint_path=ckpt, log=messages.append)
        assert r.resumed_from == 0 and len(messages) == 1 and "starting afresh" in messages[0], (changed, messages)
    interrupt_fit_at(small_samples, opts, ckpt, 40)
    monkeypatch.setattr(fit_module, "package_version", lambda: "999.0")
    messages = []
    assert fit_dam(small_samples, opts, checkpoint_path=ckpt, log=messages.append).resumed_from == 0
    assert "other inputs" in messages[0]


def test_an_old_or_unreadable_checkpoint_is_set_aside_not_resumed(small_samples, tmp_path):
    from damcap.appearance.fit import load_checkpoint, save_checkpoint

    opts = FitOptions(steps=60, checkpoint_every=20, eval_every=10, seed=3)
    ref = fit_dam(small_samples, opts)
    ckpt = tmp_path / "m.dam.ckpt"
    interrupt_fit_at(small_samples, opts, ckpt, 40)
    state = load_checkpoint(ckpt)
    del state["fingerprint"]  # the format before fingerprints: matched on options and pixel count only
    save_checkpoint(ckpt, state)
    messages: list[str] = []
    r = fit_dam(small_samples, opts, checkpoint_path=ckpt, log=messages.append)
    assert r.resumed_from == 0 and "starting afresh" in messages[0]
    torch.testing.assert_close(r.model.get_flat_weights(), ref.model.get_flat_weights(), rtol=0, atol=0)
    ckpt.write_bytes(b"not a checkpoint")
    messages = []
    with pytest.warns(UserWarning, match="unreadable checkpoint"):
        r = fit_dam(small_samples, opts, checkpoint_path=ckpt, log=messages.append)
    assert r.resumed_from == 0 and messages[0].startswith("m.dam.ckpt was written for nothing readable")
    assert (tmp_path / "m.dam.ckpt.stale").read_bytes() == b"not a checkpoint"


def test_an_interrupt_before_the_first_step_or_without_checkpoints_keeps_nothing(small_samples, tmp_path):
    ckpt = tmp_path / "m.dam.ckpt"

    def stop(at, steps, stats):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt) as info:
        fit_dam(small_samples, FitOptions(steps=20, checkpoint_every=0), checkpoint_path=ckpt, progress=stop)
    assert info.value.__notes__ == ["stopped after step 1 of 20; no checkpoint kept"] and not ckpt.exists()


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
    with pytest.raises(DamcapError, match=r"--steps must be an integer in \[1, 1000000000\], got 0"):
        FitOptions(steps=0).validate()
    with pytest.raises(DamcapError, match="learning-rate"):
        FitOptions(learning_rate=-1).validate()
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(DamcapError, match="--weight-decay must be a finite number"):
            FitOptions(weight_decay=bad).validate()
    for bad in (0.0, 1.0, -0.2):
        with pytest.raises(DamcapError, match=r"--quantile must be a finite number in \(0, 1\)"):
            FitOptions(quantile=bad).validate()
    with pytest.raises(DamcapError, match=r"--quantile must be a finite number in \(0, 1\), got nan"):
        FitOptions(quantile=float("nan")).validate()


def test_weight_decay_is_decoupled_and_follows_the_learning_rate_schedule(small_samples):
    """With no data gradient (every sample weight 0) Adam leaves the weights alone and AdamW's
    decay is all that acts: w_T = w_0 * prod_t (1 - lr_t * weight_decay), lr_t the cosine schedule."""
    s = small_samples
    blind = type(s)(s.view_dir_world, s.normal_world, s.radiance_lin, torch.zeros_like(s.weight), s.frame_index)
    steps, lr, wd = 40, 1e-2, 0.5
    opts = FitOptions(steps=steps, learning_rate=lr, holdout_views=0, checkpoint_every=0, seed=4)
    start = fit_dam(blind, opts).model.get_flat_weights().double()
    decayed = fit_dam(blind, replace(opts, weight_decay=wd)).model.get_flat_weights().double()
    lr_t = [lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * t / steps))) for t in range(steps)]
    factor = math.prod(1 - a * wd for a in lr_t)
    assert factor < 0.9
    torch.testing.assert_close(decayed, start * factor, rtol=1e-5, atol=1e-7)


# --------------------------------------------------------------------------------------------
# mixed precision (FitOptions.precision)
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_train_views(small_capture):
    return load_views(read_capture(small_capture), "train")


def test_bfloat16_fit_matches_float32_accuracy_with_float32_weights(small_train_views):
    """bf16 autocast changes the arithmetic, not the outcome: same-view DSSIM and training L1
    stay close to the float32 fit's, and the kept weights are float32 (not bf16-rounded)."""
    from damcap.appearance.fit import training_l1

    train = small_train_views
    s = samples_of(train)
    # leaky ReLU, the activation these bounds were measured with (the default's smoother units
    # reach a same-view DSSIM of 0.033 here in 400 steps: a slower fit of this tiny sphere)
    runs = {p: [fit_dam(s, FitOptions(steps=400, holdout_views=0, seed=seed, precision=p, activation="leaky_relu"))
                for seed in range(3)]
            for p in ("float32", "bfloat16")}
    for r in runs["float32"] + runs["bfloat16"]:
        assert r.model.weights_flat.dtype == torch.float32 and torch.isfinite(r.model.weights_flat).all()
    w16, w32 = runs["bfloat16"][0].model.weights_flat, runs["float32"][0].model.weights_flat
    # float32 master weights: almost none is representable in bf16 (bf16-stored ones all would be)
    assert (w16.to(torch.bfloat16).float() != w16).float().mean() > 0.9
    # the option is not ignored: bf16 arithmetic gives other weights than float32's, same seed
    assert not torch.equal(w16, w32)
    dssim = {p: sum(evaluate_split(train, train, {"DAM": r.model}, baselines=False)["DAM"].mean for r in rs) / 3 for p, rs in runs.items()}
    l1 = {p: sum(training_l1(r.model, s) for r in rs) / 3 for p, rs in runs.items()}
    # Measured (seeds 0-2, 400 steps, this 12-view 32x32 sphere): bf16 / f32 mean training L1
    # 0.99 and mean same-view DSSIM 0.97; per seed 0.86-1.07 (L1) and 0.72-1.17 (DSSIM) over
    # seeds 0-5. Keeping the master weights in bf16 instead (rounded after every Adam step)
    # measured 1.32 (L1) and 1.84 (DSSIM) on the same seeds, so these bounds catch that.
    assert 0.87 < l1["bfloat16"] / l1["float32"] < 1.15, l1
    assert 0.74 < dssim["bfloat16"] / dssim["float32"] < 1.35, dssim
    assert dssim["float32"] < 0.005, dssim  # the reference fit converged (measured 0.0019)


def test_bfloat16_fit_resumes_and_checkpoints_float32(small_samples, tmp_path):
    from damcap.appearance.fit import load_checkpoint

    opts = FitOptions(steps=200, checkpoint_every=50, eval_every=25, seed=2, precision="bfloat16")
    ref = fit_dam(small_samples, opts)
    ckpt = tmp_path / "m.dam.ckpt"
    interrupt_fit_at(small_samples, opts, ckpt, 150)
    state = load_checkpoint(ckpt)
    assert state["weights"].dtype == torch.float32 and state["best_weights"].dtype == torch.float32
    assert all(v.dtype == torch.float32 for st in state["optim"]["state"].values() for k, v in st.items() if k != "step")
    # a float32 run does not resume a bfloat16 checkpoint (the options differ)
    assert fit_dam(small_samples, FitOptions(steps=200, checkpoint_every=50, eval_every=25, seed=2), checkpoint_path=ckpt).resumed_from == 0
    interrupt_fit_at(small_samples, opts, ckpt, 150)
    resumed = fit_dam(small_samples, opts, checkpoint_path=ckpt)
    assert resumed.resumed_from == 150
    torch.testing.assert_close(resumed.model.get_flat_weights(), ref.model.get_flat_weights(), rtol=0, atol=0)


def test_bad_precision_is_refused():
    with pytest.raises(DamcapError, match=r"--precision must be one of float32, bfloat16, got 'float16'"):
        FitOptions(precision="float16").validate()  # type: ignore[arg-type]


def test_cli_precision_weight_decay_quantile_and_separable(small_capture, tmp_path, capsys):
    from safetensors.torch import load_file

    from damcap.appearance.dam_file import load_dam
    from tests.conftest import assert_one_line_error, run_cli

    out = tmp_path / "m.dam"
    code, _, err = run_cli(["fit", small_capture, "-o", out, "--steps", "30", "--precision", "bfloat16"], capsys)
    assert code == 0, err
    assert load_file(out)["weights"].dtype == torch.float32
    model, meta = load_dam(out)
    assert model.weights_flat.dtype == torch.float32 and meta["provenance"]["options"]["precision"] == "bfloat16"
    assert model.arch.separable and model.arch.num_weights == 1728  # the default DAM: separable, width 32
    code, _, err = run_cli(["fit", small_capture, "-o", tmp_path / "x.dam", "--precision", "fp8"], capsys)
    assert_one_line_error(code, err, "--precision", "'fp8'", "bfloat16")
    assert not (tmp_path / "x.dam").exists()
    code, _, err = run_cli(["fit", small_capture, "-o", tmp_path / "x.dam", "--weight-decay", "-0.5"], capsys)
    assert_one_line_error(code, err, "--weight-decay", "-0.5")
    assert not (tmp_path / "x.dam").exists()
    code, _, err = run_cli(["fit", small_capture, "-o", tmp_path / "x.dam", "--quantile", "1.5"], capsys)
    assert_one_line_error(code, err, "--quantile", "1.5")
    assert not (tmp_path / "x.dam").exists()
    code, _, err = run_cli(["fit", small_capture, "-o", out, "--steps", "30", "--separable", "--width", "44"], capsys)
    assert code == 0, err
    model, meta = load_dam(out)
    assert model.arch.separable and model.arch.num_weights == 3168 and meta["provenance"]["options"]["separable"]
    code, _, err = run_cli(["fit", small_capture, "-o", tmp_path / "x.dam", "--separable", "--encoding", "vn"], capsys)
    assert_one_line_error(code, err, "separable", "'vn'")
    assert not (tmp_path / "x.dam").exists()
    code, _, err = run_cli(["fit", small_capture, "-o", tmp_path / "x.dam", "--encoding", "vn"], capsys)  # separable by default
    assert_one_line_error(code, err, "'vn'", "--no-separable")
    assert not (tmp_path / "x.dam").exists()
    code, _, err = run_cli(["fit", small_capture, "-o", out, "--steps", "30", "--no-separable", "--encoding", "vn"], capsys)
    assert code == 0, err
    model, _ = load_dam(out)
    assert not model.arch.separable and model.arch.num_weights == 3360  # the paper's joint network


def _half_lit_samples(n: int = 20000, seed: int = 0):
    """A Lambertian object under one distant light, seen from everywhere: radiance =
    albedo * max(0, N.L), black on more than half the samples (a point-light capture's shape)."""
    from damcap.appearance.pixels import PixelSamples

    g = torch.Generator().manual_seed(seed)
    unit = lambda v: v / v.norm(dim=1, keepdim=True)  # noqa: E731
    normal = unit(torch.randn(n, 3, generator=g))
    view = unit(torch.randn(n, 3, generator=g))
    view = torch.where((view * normal).sum(1, keepdim=True) < 0, -view, view)
    light = torch.tensor([0.3, 0.8, 0.52])
    light = light / light.norm()
    radiance = torch.tensor([0.8, 0.5, 0.3]) * (normal @ light).clamp_min(0)[:, None]
    return PixelSamples(view, normal, radiance, torch.ones(n), torch.arange(n) % 10), radiance


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_default_activation_learns_a_half_black_target(seed):
    """Bias-free DAMs with the default (shifted softplus) units learn a point-light-like target
    instead of collapsing to black: mean L1 under a fifth of the all-black prediction's."""
    samples, radiance = _half_lit_samples(seed=seed)
    assert (radiance.sum(1) == 0).float().mean() > 0.45
    opts = FitOptions(steps=400, seed=seed, holdout_views=0, checkpoint_every=0)
    assert opts.activation == "shifted_softplus"
    model = fit_dam(samples, opts).model
    with torch.no_grad():
        pred = model(samples.view_dir_world, samples.normal_world)
    assert (pred - radiance).abs().mean() < 0.2 * radiance.abs().mean()


def _diffuse_plus_lobe_samples(n: int, azimuth_deg: tuple[float, float], g: torch.Generator):
    """Views on a band of azimuths (elevation within +-0.3 rad, y up), random visible normals,
    and a closed-form radiance of the form f(N) + g(R): a Lambertian term plus a Phong lobe
    (exponent 20) around one distant light."""
    from damcap.appearance.pixels import PixelSamples
    from damcap.common.numerics import reflect

    unit = lambda v: v / v.norm(dim=1, keepdim=True)  # noqa: E731
    az = torch.deg2rad(azimuth_deg[0] + torch.rand(n, generator=g) * (azimuth_deg[1] - azimuth_deg[0]))
    el = (torch.rand(n, generator=g) - 0.5) * 0.6
    view = torch.stack([torch.cos(az) * torch.cos(el), torch.sin(el), torch.sin(az) * torch.cos(el)], 1)
    normal = unit(torch.randn(n, 3, generator=g))
    normal = torch.where((view * normal).sum(1, keepdim=True) < 0, -normal, normal)
    light = unit(torch.tensor([[0.3, 0.8, 0.52]]))
    radiance = (torch.tensor([0.6, 0.4, 0.25]) * (normal @ light.T).clamp_min(0)
                + 2.0 * (reflect(view, normal) @ light.T).clamp_min(0) ** 20)
    return PixelSamples(view, normal, radiance, torch.ones(n), torch.arange(n) % 10)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_separable_dam_extrapolates_a_diffuse_plus_lobe_appearance_to_novel_views(seed):
    """Trained on views from 110 degrees of azimuth, scored on views from the other side (150-330
    degrees): there (N, R) pairs are new although N and R each were seen. The separable DAM's
    f(N) + g(R) extrapolates (measured: about 0.1x the joint DAM's error for both seeds); the
    joint one does not."""
    g = torch.Generator().manual_seed(seed)
    train, novel = _diffuse_plus_lobe_samples(20000, (0, 110), g), _diffuse_plus_lobe_samples(20000, (150, 330), g)
    errors = {}
    for separable, width in ((False, 32), (True, 44)):
        opts = FitOptions(steps=400, seed=seed, holdout_views=0, checkpoint_every=0, separable=separable, width=width)
        model = fit_dam(train, opts).model
        assert model.arch.separable == separable
        with torch.no_grad():
            errors[separable] = float((model(novel.view_dir_world, novel.normal_world) - novel.radiance_lin).abs().mean())
    assert errors[True] < 0.5 * errors[False], errors
    assert errors[True] < 0.5 * float(novel.radiance_lin.abs().mean()), errors


# --------------------------------------------------------------------------------------------
# the data cost's quantile (FitOptions.quantile)


def test_quantile_cost_is_l1_at_one_half_and_is_minimised_by_the_quantile():
    g = torch.Generator().manual_seed(0)
    pred, target, w = torch.randn(500, 3, generator=g), torch.randn(500, 3, generator=g), torch.rand(500, generator=g)
    l1 = ((pred - target).abs().mean(-1) * w).sum() / w.sum()
    torch.testing.assert_close(weighted_quantile_cost(pred, target, w), l1, rtol=0, atol=0)
    # over constant predictions, the minimiser is the q-quantile of the (unit-weight) targets
    values = torch.rand(1001, generator=g) ** 2
    grid = torch.linspace(0, 1, 2001)
    for q in (0.25, 0.5, 0.75, 0.9):
        cost = torch.stack([weighted_quantile_cost(c.expand(1001, 1), values[:, None], torch.ones(1001), q) for c in grid])
        assert abs(float(grid[cost.argmin()]) - float(torch.quantile(values, q))) <= 1e-3, q


def test_an_upper_quantile_fits_the_unshadowed_appearance():
    """Cast shadows darken a random 60 % of the samples regardless of (view, normal): the L1 fit
    learns the shadowed median, the 0.75-quantile fit the unshadowed radiance (the two-point
    distribution's 0.75-quantile)."""
    samples, lit = _half_lit_samples(seed=3)
    shadowed = torch.rand(len(lit), generator=torch.Generator().manual_seed(1)) < 0.6
    seen = type(samples)(samples.view_dir_world, samples.normal_world, torch.where(shadowed[:, None], 0.05 * lit, lit),
                         samples.weight, samples.frame_index)
    errors = {}
    for q in (0.5, 0.75):
        model = fit_dam(seen, FitOptions(steps=400, seed=0, checkpoint_every=0, quantile=q)).model
        with torch.no_grad():
            errors[q] = float((model(samples.view_dir_world, samples.normal_world) - lit).abs().mean())
    assert errors[0.75] < 0.3 * errors[0.5], errors
    assert errors[0.5] > 0.5 * float(lit.abs().mean()), errors  # the median is the shadowed value


def test_the_stopping_rule_scores_held_out_views_with_the_fits_cost(small_samples):
    s = small_samples
    opts = FitOptions(steps=60, eval_every=60, checkpoint_every=0, quantile=0.8, seed=1)
    result = fit_dam(s, opts)
    held = torch.zeros(len(s), dtype=torch.bool)
    for k in holdout_frames(int(s.frame_index.max()) + 1, opts.holdout_views):
        held |= s.frame_index == k
    m = result.model
    with torch.no_grad():
        pred = m(s.view_dir_world[held], s.normal_world[held]) / m.radiance_scale
    expected = weighted_quantile_cost(pred, s.radiance_lin[held].float() / m.radiance_scale, s.weight[held], 0.8)
    assert result.best_step == 60
    assert math.isclose(result.history[-1]["holdout_l1"], float(expected), rel_tol=1e-4)


def test_refinement_never_makes_the_training_cost_worse(small_capture):
    samples = samples_of(load_views(read_capture(small_capture), "train"))
    net = HyperNet(HyperArchitecture(input_size=32, channels=(4, 8)))
    start = predict_dam(net, _crop_of(small_capture))
    refined, before, after = refine_dam(start, samples, 60, 3e-3)
    assert after <= before and math.isclose(before, training_l1(start, samples), rel_tol=1e-6)
    assert math.isclose(after, training_l1(refined, samples), rel_tol=1e-6)
    # from an already converged model a too-large step size cannot make it worse either
    fitted = fit_dam(samples, FitOptions(steps=400, holdout_views=0, checkpoint_every=0)).model
    again, b2, a2 = refine_dam(fitted, samples, 20, learning_rate=0.5)
    assert a2 <= b2 and training_l1(again, samples) <= training_l1(fitted, samples) + 1e-9


def test_fingerprint_ignores_the_spatial_factor_options_only():
    """The spatial factor acts after fit_dam: a checkpoint stays resumable when only --spatial
    options change, and not when a DAM option does."""
    from dataclasses import replace

    from damcap.appearance.fit import fit_fingerprint

    s = _samples_for_fingerprint()
    base = FitOptions(steps=10)
    fp = fit_fingerprint(s, base)
    assert fit_fingerprint(s, replace(base, spatial="auto", spatial_voxel_px=1.0, spatial_prior=0.5)) == fp
    assert fit_fingerprint(s, replace(base, steps=11)) != fp


def _samples_for_fingerprint():
    from damcap.appearance.pixels import PixelSamples

    g = torch.Generator().manual_seed(0)
    n = 64
    v = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    return PixelSamples(v, v.flip(1), torch.rand(n, 3, generator=g), torch.ones(n), torch.arange(n) % 4)


def _ring(n: int, elevation: float = 0.0):
    import numpy as np

    a = 2 * np.pi * np.arange(n) / n
    return np.stack([np.cos(a) * np.cos(elevation), np.sin(a) * np.cos(elevation), np.full(n, np.sin(elevation))], 1)


def test_holdout_arc_takes_neighbours_on_a_ring_and_the_isolated_group_elsewhere():
    import numpy as np

    from damcap.appearance.fit import holdout_arc

    assert holdout_arc(_ring(10), 3) == [0, 1, 9]  # an arc of neighbours, the first seed on ties
    assert holdout_arc(_ring(10), 0) == [] and holdout_arc(_ring(2), 1) == []
    assert len(holdout_arc(_ring(4), 5)) == 2  # two views always train
    # a ring of 8 plus two cameras high above it: those two are held out (the fit must extrapolate to them)
    dirs = np.concatenate([_ring(8), _ring(2, np.radians(70))])
    assert holdout_arc(dirs, 2) == [8, 9]
    # the group's smallest angle to the rest is the largest of any group of that size
    rng = np.random.default_rng(0)
    d = rng.normal(size=(12, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ang = np.arccos(np.clip(d @ d.T, -1, 1))
    held = holdout_arc(d, 3)
    gap = lambda g: ang[np.ix_(g, [i for i in range(12) if i not in g])].min()  # noqa: E731
    nearest_groups = [list(np.argsort(ang[s])[:3]) for s in range(12)]
    assert gap(held) >= max(gap(g) for g in nearest_groups) - 1e-9


def test_held_out_follows_the_rule(sample_views):
    from damcap.appearance.fit import camera_directions, held_out, holdout_arc

    train, _ = sample_views
    assert held_out(train, FitOptions(holdout="spread")) == holdout_frames(len(train), 2)
    assert held_out(train, FitOptions()) == holdout_arc(camera_directions(train), 2)
    with pytest.raises(DamcapError, match="--holdout must be one of arc, spread, got 'ring'"):
        FitOptions(holdout="ring").validate()
    with pytest.raises(DamcapError, match="--prior must be one of off, predictor"):
        FitOptions(prior="yes").validate()


def test_given_held_frames_are_the_ones_scored(small_samples):
    s = small_samples
    opts = FitOptions(steps=40, eval_every=40, checkpoint_every=0, seed=2)
    a = fit_dam(s, opts, held_frames=[0])
    b = fit_dam(s, opts, held_frames=[1])
    assert a.history[-1]["holdout_l1"] != b.history[-1]["holdout_l1"]


def test_with_a_prior_the_initial_model_is_a_candidate_and_kept_when_no_step_beats_it(small_samples):
    """Start from a model; a learning rate so high that every step is worse: the start is kept."""
    from damcap.appearance.fit import PriorSamples, training_l1

    s = small_samples
    good = fit_dam(s, FitOptions(steps=300, checkpoint_every=0, seed=0)).model
    prior = PriorSamples(torch.zeros(0, 6), torch.zeros(0, 3), torch.zeros(0))
    wild = FitOptions(steps=50, eval_every=25, checkpoint_every=0, learning_rate=5.0, seed=0, prior_weight=0.0)
    kept = fit_dam(s, wild, init_model=good, prior=prior)
    assert kept.best_step == 0 and kept.history[0]["step"] == 0
    assert torch.equal(kept.model.get_flat_weights(), good.get_flat_weights())
    assert training_l1(kept.model, s) == training_l1(good, s)
