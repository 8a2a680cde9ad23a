"""damcap fit's path on views (appearance/fit_views.py): held-out arc, prior, factors, record."""

from __future__ import annotations

import pytest

from damcap.appearance.fit import FitOptions, held_out
from damcap.appearance.fit_views import fit_views
from damcap.appearance.views import load_views
from damcap.common.capture_folder import read_capture


@pytest.fixture(scope="module")
def views(sample_capture):
    return load_views(read_capture(sample_capture), "train")


def test_plain_fit_records_the_held_out_arc(views):
    opts = FitOptions(steps=60, eval_every=30, checkpoint_every=0, normal_refine="off", spatial="off", prior="off")
    out = fit_views(views, opts)
    assert out.held == held_out(views, opts) and len(out.held) == 2
    rec = out.record(views)
    assert rec["held_out_views"] == [views[k].name for k in out.held]
    assert rec["prior_seconds"] == 0.0 and rec["normal_refine"]["mode"] == "off" and rec["spatial"]["mode"] == "off"
    assert out.model is out.spatial.model


def test_the_predictor_prior_starts_from_the_prediction_without_the_held_out_views(views, monkeypatch):
    """With the predictor's architecture the fit starts from its prediction, made from the views
    that train only (the held-out arc stays a fair judge), and scores it as step 0."""
    import damcap.appearance.hyper.predict as predict

    seen = {}
    real = predict.predict_views

    def spy(vs, *a, **k):
        seen["names"] = [v.name for v in vs]
        return real(vs, *a, **k)

    monkeypatch.setattr(predict, "predict_views", spy)
    opts = FitOptions(steps=50, eval_every=25, checkpoint_every=0, prior="predictor", activation="leaky_relu", prior_samples=4096,
                      normal_refine="off", spatial="off")
    from damcap.appearance.hyper.file import load_predictor, predictor_path

    arch = load_predictor(predictor_path(None))[0].arch.dam
    opts = opts.for_architecture(arch)
    out = fit_views(views, opts)
    held_names = {views[k].name for k in out.held}
    assert seen["names"] and not held_names & set(seen["names"])
    assert out.result.history[0]["step"] == 0 and out.prior_seconds > 0


def test_prior_auto_keeps_the_fit_whose_held_out_views_score_better(views):
    from dataclasses import replace

    from damcap.appearance.fit_views import best_holdout_l1

    base = FitOptions(steps=40, eval_every=20, checkpoint_every=0, normal_refine="off", spatial="off", prior_samples=2048)
    out = fit_views(views, replace(base, prior="auto"))
    choice = out.prior_choice
    assert set(choice) == {"off", "predictor", "kept"} and choice["kept"] is (choice["predictor"] < choice["off"])
    # the kept one is the fit the same options give alone
    alone = fit_views(views, replace(base, prior="predictor" if choice["kept"] else "off"))
    assert best_holdout_l1(alone.result) == min(choice["off"], choice["predictor"])
    assert out.record(views)["prior_choice"] == choice
    # nothing held out: nothing to judge on, the plain fit
    none = fit_views(views, replace(base, prior="auto", holdout_views=0))
    assert none.prior_choice == {} and none.prior_seconds == 0.0


def test_prior_auto_falls_back_to_the_plain_fit_when_the_predictor_cannot_predict(views, monkeypatch):
    import damcap.appearance.hyper.predict as predict
    from damcap.common.errors import DamcapError

    def refuse(*a, **k):
        raise DamcapError("no view with foreground")

    monkeypatch.setattr(predict, "predict_views", refuse)
    said = []
    base = FitOptions(steps=20, eval_every=20, checkpoint_every=0, normal_refine="off", spatial="off")
    out = fit_views(views, base, log=said.append)
    assert out.prior_choice == {} and any(m.startswith("prior: none (the predictor could not predict") for m in said)
    with pytest.raises(DamcapError, match="no view with foreground"):  # asked for explicitly: refused
        fit_views(views, FitOptions(**{**base.__dict__, "prior": "predictor"}))


def _with_tilted_normals(views, degrees: float, seed: int = 0):
    """The same views with every normal tilted by ``degrees`` about a random axis per pixel (a
    worse geometry of the same photos)."""
    import dataclasses

    import numpy as np

    rng = np.random.default_rng(seed)
    out = []
    for v in views:
        n = v.data.normal_world.astype(np.float64)
        axis = rng.normal(size=n.shape)
        axis -= (axis * n).sum(-1, keepdims=True) * n  # perpendicular to the normal
        axis /= np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-12)
        t = np.radians(degrees)
        tilted = (np.cos(t) * n + np.sin(t) * axis).astype(np.float32)
        out.append(dataclasses.replace(v, data=dataclasses.replace(v.data, normal_world=tilted)))
    return out


def test_the_geometry_judge_keeps_the_geometry_a_fit_generalises_from(views):
    """Two 'geometries' of the same views, one with every normal tilted by 35 deg at random: the
    judge holds out the same views for both and takes the true one even when it comes second;
    with the true one first, the tilted one does not win. Views that differ are refused."""
    from damcap.appearance.fit_views import judge_geometries
    from damcap.common.errors import DamcapError

    opts = FitOptions(steps=80, eval_every=40, checkpoint_every=0, normal_refine="off", spatial="off", prior="off")
    wrong = _with_tilted_normals(views, 35.0)
    verdict = judge_geometries({"tilted": wrong, "true": views}, opts)
    assert verdict.chosen == "true" and verdict.heldout_dssim["true"] < 0.9 * verdict.heldout_dssim["tilted"], verdict
    assert verdict.held_views == [views[k].name for k in held_out(views, opts)]
    assert judge_geometries({"true": views, "tilted": wrong}, opts).chosen == "true"
    with pytest.raises(DamcapError, match="same views"):
        judge_geometries({"a": views, "b": views[1:]}, opts)
