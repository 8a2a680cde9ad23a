"""Evaluation: per-frame DSSIM of models and the RM / RM++ baselines, the source spread, the plot."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.appearance.evaluate import MethodScores, evaluate_split, plot_sorted_dssim, rm_source_spread, score_view
from damcap.appearance.render import render_frame
from damcap.appearance.views import load_views
from damcap.common.capture_folder import read_capture


@pytest.fixture(scope="module")
def views(small_capture):
    cap = read_capture(small_capture)
    return load_views(cap, "train"), load_views(cap, "test")


def test_mean_skips_frames_without_foreground():
    assert MethodScores({"a": 0.1, "b": None, "c": 0.3}).mean == pytest.approx(0.2)
    assert math.isnan(MethodScores({"a": None}).mean) and math.isnan(MethodScores().mean)


def test_rm_source_spread_closed_form():
    sp = rm_source_spread({"a": 0.3, "b": 0.1, "c": float("nan"), "d": 0.5, "e": float("inf"), "f": 0.2})
    assert sp == {"n": 4, "min": 0.1, "median": pytest.approx(0.25), "max": 0.5, "scores": [0.1, 0.2, 0.3, 0.5]}
    assert rm_source_spread({"a": 0.3, "b": float("nan")}) is None and rm_source_spread({}) is None


def test_score_view_is_zero_for_the_truth_and_grows_with_error(views):
    v = views[1][0]
    assert score_view(v, v.data.radiance_lin) == pytest.approx(0.0, abs=1e-5)  # float32 SSIM
    noisy = v.data.radiance_lin * np.random.default_rng(0).uniform(0.5, 1.5, v.data.radiance_lin.shape).astype(np.float32)
    assert 0.01 < score_view(v, noisy) < 0.5


def test_evaluate_split_scores_each_model_and_the_baselines(views):
    train, test = views
    arch = DamArchitecture()
    zero = DeepAppearanceMap(arch, radiance_scale=1.0, weights_flat=torch.zeros(arch.num_weights))
    calls: list[tuple[str, int, int]] = []
    res = evaluate_split(train, test, {"zero": zero}, progress=lambda *a: calls.append(a), split="novel view")
    assert list(res) == ["zero", "RM++", "RM"]
    assert calls == [("novel view: zero", k + 1, len(test)) for k in range(len(test))] + [("novel view: RM++ and RM", k, 2) for k in range(3)]
    assert set(res["zero"].per_frame) == {t.name for t in test}
    for t in test:
        assert res["zero"].per_frame[t.name] == pytest.approx(score_view(t, render_frame(zero, t.data, t.centre_world)), abs=1e-9)
    # a constant grey cannot reproduce a shaded sphere; the baselines use the radiance itself
    assert res["zero"].mean > res["RM++"].mean and res["RM"].mean < res["zero"].mean
    assert res["RM"].note.startswith("source ") and set(res["RM"].per_source) == {v.name for v in train}
    assert min(res["RM"].per_source.values()) == pytest.approx(res["RM"].mean, abs=1e-9)
    only = evaluate_split(train, test, {"zero": zero}, baselines=False)
    assert list(only) == ["zero"] and only["zero"].per_frame == res["zero"].per_frame
    assert list(evaluate_split(train[:1], test, {})) == []  # one source: no baselines


def test_plot_writes_a_png(tmp_path):
    res = {"train": {"m": MethodScores({"a": 0.1, "b": 0.2})}, "test": {"m": MethodScores({"c": 0.3, "d": None})}}
    plot_sorted_dssim(res, tmp_path / "plot.png", title="t")
    data = (tmp_path / "plot.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    assert [p.name for p in tmp_path.iterdir()] == ["plot.png"]
