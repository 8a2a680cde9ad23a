"""fit --target-dssim: the smallest DAM that reaches the accuracy asked for."""

from __future__ import annotations

import pytest

from damcap.appearance.dam_file import load_dam
from damcap.appearance.fit import FitOptions
from damcap.appearance.model_size import fit_to_target, sizes_by_weight_count
from damcap.appearance.views import load_views
from damcap.cli.main import main
from damcap.common.capture_folder import read_capture
from damcap.common.errors import DamcapError


@pytest.fixture(scope="module")
def train_views(small_capture):
    return load_views(read_capture(small_capture), "train")


def test_a_loose_target_keeps_the_smallest_dam(train_views):
    choice = fit_to_target(train_views, 0.99, FitOptions(steps=60, holdout_views=1, checkpoint_every=0, separable=False))
    smallest = sizes_by_weight_count("nr")[0]
    assert choice.reached and (choice.width, choice.depth) == smallest[:2] and len(choice.tried) == 1
    assert choice.model.arch.num_weights == smallest[2]


def test_a_separable_ladder_counts_separable_weights(train_views):
    choice = fit_to_target(train_views, 0.99, FitOptions(steps=30, holdout_views=1, checkpoint_every=0, separable=True))
    smallest = sizes_by_weight_count("nr", separable=True)[0]
    assert choice.reached and choice.model.arch.separable and choice.tried[0]["weights"] == smallest[2]
    assert choice.model.arch.num_weights == smallest[2] < sizes_by_weight_count("nr")[0][2]


def test_an_unreachable_target_tries_every_size_and_keeps_the_most_accurate(train_views):
    choice = fit_to_target(train_views, 1e-9, FitOptions(steps=40, holdout_views=1, checkpoint_every=0))
    assert not choice.reached and len(choice.tried) == len(sizes_by_weight_count("nr"))
    best = min(choice.tried, key=lambda t: t["heldout_dssim"])
    assert (choice.width, choice.depth) == (best["width"], best["depth"])
    weights = [t["weights"] for t in choice.tried]
    assert weights == sorted(weights)


def test_bad_targets_and_no_holdout_are_refused(train_views):
    with pytest.raises(DamcapError, match="target-dssim"):
        fit_to_target(train_views, 1.5, FitOptions(steps=10))
    with pytest.raises(DamcapError, match="holdout-views"):
        fit_to_target(train_views, 0.5, FitOptions(steps=10, holdout_views=0))


def test_cli(small_capture, tmp_path):
    out = tmp_path / "m.dam"
    assert main(["fit", str(small_capture), "-o", str(out), "--target-dssim", "0.99", "--steps", "40", "--holdout-views", "1"]) == 0
    meta = load_dam(out)[1]
    assert meta["provenance"]["target_reached"] and meta["provenance"]["sizes_tried"][0]["weights"] == sizes_by_weight_count("nr", separable=True)[0][2]  # separable by default
    assert main(["fit", str(small_capture), "-o", str(out), "--target-dssim", "0.5", "--width", "8"]) == 2
    assert main(["fit", str(small_capture), "-o", str(out), "--target-dssim", "0"]) == 2


def _recording_fit_dam(monkeypatch):
    """Wrap model_size's fit_dam: list of (width, depth, resumed_from) per call."""
    from damcap.appearance import model_size

    calls: list[tuple[int, int, int]] = []
    real = model_size.fit_dam

    def fit_dam(samples, opts, **kw):
        r = real(samples, opts, **kw)
        calls.append((opts.width, opts.depth, r.resumed_from))
        return r

    monkeypatch.setattr(model_size, "fit_dam", fit_dam)
    return calls


def test_an_interrupted_target_run_resumes_without_refitting_finished_sizes(train_views, tmp_path, monkeypatch):
    import torch

    from damcap.appearance.model_size import size_checkpoint_path, sizes_record_path

    opts = FitOptions(steps=80, holdout_views=1, checkpoint_every=20, eval_every=20)
    ref = fit_to_target(train_views, 1e-9, opts)  # unreachable: every size is fitted
    (w1, d1, _), (w2, d2, _), (w3, d3, _) = sizes_by_weight_count("nr")[:3]
    ckpt = tmp_path / "m.dam.ckpt"
    calls = _recording_fit_dam(monkeypatch)

    def stop_in_third_size(step, steps, stats):  # size 3 of the ladder, between its checkpoints at 40 and 60
        if len(calls) == 2 and step == 50:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_to_target(train_views, 1e-9, opts, checkpoint_path=ckpt, fit_progress=stop_in_third_size)
    assert calls == [(w1, d1, 0), (w2, d2, 0)]
    assert sizes_record_path(ckpt).is_file() and size_checkpoint_path(ckpt, w3, d3).is_file()
    assert not size_checkpoint_path(ckpt, w1, d1).exists()  # a finished size's fit checkpoint is gone

    calls.clear()
    lines: list[str] = []
    resumed = fit_to_target(train_views, 1e-9, opts, progress=lines.append, checkpoint_path=ckpt)
    # finished sizes are not refitted; the size in progress resumes at the interrupted step (checkpointed then)
    assert [c[:2] for c in calls] == [(w, d) for w, d, _ in sizes_by_weight_count("nr")[2:]]
    assert calls[0] == (w3, d3, 50) and all(c[2] == 0 for c in calls[1:])
    assert lines[0].endswith("(recorded)") and lines[1].endswith("(recorded)") and "resumed from step 50" in lines[2]
    # the same choice as the uninterrupted run, bit for bit
    assert (resumed.width, resumed.depth, resumed.reached) == (ref.width, ref.depth, ref.reached)
    assert [t["heldout_dssim"] for t in resumed.tried] == [t["heldout_dssim"] for t in ref.tried]
    torch.testing.assert_close(resumed.model.get_flat_weights(), ref.model.get_flat_weights(), rtol=0, atol=0)
    assert list(tmp_path.iterdir()) == []  # the sidecar files are removed when the run completes


def test_a_record_of_other_options_is_not_reused(train_views, tmp_path, monkeypatch):
    opts = FitOptions(steps=40, holdout_views=1, checkpoint_every=0)
    ckpt = tmp_path / "m.dam.ckpt"
    calls = _recording_fit_dam(monkeypatch)

    def stop_after_first_size(line):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_to_target(train_views, 1e-9, opts, progress=stop_after_first_size, checkpoint_path=ckpt)
    assert len(calls) == 1
    calls.clear()
    lines: list[str] = []
    choice = fit_to_target(train_views, 0.99, FitOptions(steps=40, holdout_views=1, checkpoint_every=0, seed=1),
                           progress=lines.append, checkpoint_path=ckpt)
    assert "other fit options" in lines[0] and len(calls) == 1 and choice.reached
    # a looser target with the same options reuses the finished first size without fitting
    with pytest.raises(KeyboardInterrupt):
        fit_to_target(train_views, 1e-9, opts, progress=stop_after_first_size, checkpoint_path=ckpt)
    calls.clear()
    choice = fit_to_target(train_views, 0.99, opts, checkpoint_path=ckpt)
    assert calls == [] and choice.reached and len(choice.tried) == 1
    assert list(tmp_path.iterdir()) == []


def test_cli_resume_and_no_resume(small_capture, tmp_path, capsys):
    from damcap.appearance.fit import save_checkpoint
    from damcap.appearance.model_size import sizes_record_path
    from tests.conftest import run_cli

    out = tmp_path / "m.dam"
    record = sizes_record_path(out.with_name("m.dam.ckpt"))
    args = ["fit", small_capture, "-o", out, "--target-dssim", "0.99", "--steps", "20", "--holdout-views", "1"]
    save_checkpoint(record, {"key": "from another run", "finished": []})
    code, _, err = run_cli(args + ["--no-resume"], capsys)
    assert code == 0 and "resuming" not in err and "other fit options" not in err, err  # --no-resume ignores it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.dam"]
    save_checkpoint(record, {"key": "from another run", "finished": []})
    code, _, err = run_cli(args, capsys)
    assert code == 0 and "resuming from m.dam.ckpt.sizes" in err and "other fit options" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.dam"]
