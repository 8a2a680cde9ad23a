"""``damcap fit`` on a capture's views, without the command line: the held-out views, the prior,
the DAM's fit, then the normal refinement and the spatial factor (each as ``FitOptions`` asks).

1. The held-out views (:func:`.fit.held_out`): the stopping rule and every 'auto' decision
   judge the fit on them; by default an arc of cameras farthest from the rest.
2. The prior (``prior='predictor'`` or ``'auto'``, :mod:`.prior`): the shipped predictor's DAM from
   the views that train (not the held-out ones, so that they stay a fair judge), sampled once.
3. :func:`.fit.fit_dam` on the views that train, stopped at the step the held-out views score
   best; with ``prior='auto'`` twice, without and with the prior, and the fit whose held-out
   views score the lower L1 is kept (the second fit keeps no checkpoint).
4. :func:`.normal_fit.choose_normal_refine`, then :func:`.spatial_fit.choose_spatial`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

from damcap.common.errors import DamcapError

from damcap.appearance.fit import FitOptions, FitResult, TrainingFrame, adversarial_frames, fit_dam, held_out
from damcap.appearance.normal_fit import NormalRefineDecision, choose_normal_refine
from damcap.appearance.prior import prior_samples
from damcap.appearance.spatial_fit import SpatialDecision, choose_spatial, mean_dssim, pays_on_heldout
from damcap.appearance.views import ViewData, radiance_scale_of, samples_of


@dataclass
class FitOutcome:
    """What :func:`fit_views` made."""

    result: FitResult
    """the DAM's fit (the model before the surface factors)"""
    normals: NormalRefineDecision
    spatial: SpatialDecision
    held: list[int]
    """indices of the held-out views"""
    prior_seconds: float
    """the prediction and the prior's samples (0 without a prior)"""
    samples: int
    """training pixels"""
    seconds: float = 0.0
    """the whole path, wall clock (prior, fit, normal refinement, spatial factor)"""
    prior_choice: dict = field(default_factory=dict)
    """prior 'auto': the held-out L1 without ('off') and with ('predictor') the prior, and whether it was kept"""

    @property
    def model(self):
        """The final DAM, with the surface factors that were kept."""
        return self.spatial.model

    def record(self, views: list[ViewData]) -> dict:
        """The provenance entries of this fit (beside the options and the capture)."""
        last = self.result.history[-1] if self.result.history else {}
        return {"pixels": self.samples, "best_step": self.result.best_step, "train_l1": last.get("train_l1"),
                "holdout_l1": last.get("holdout_l1"), "held_out_views": [views[k].name for k in self.held],
                "prior_seconds": self.prior_seconds, "prior_choice": self.prior_choice or None, "seconds": self.result.seconds, "total_seconds": self.seconds, "threads": self.result.threads,
                "history": self.result.history, "normal_refine": self.normals.record(), "spatial": self.spatial.record()}


def fit_views(views: list[ViewData], opts: FitOptions, *, checkpoint_path: str | Path | None = None,
              progress: Callable | None = None, refine_progress: Callable | None = None,
              log: Callable[[str], None] | None = None, held: list[int] | None = None) -> FitOutcome:
    """Fit a DAM (and the surface factors ``opts`` asks for) to ``views`` (module docstring).

    Args:
        views: the training views.
        opts: the fit's options (validated by the caller).
        checkpoint_path: the fit's checkpoint (kept until the caller removes it: a rerun after an
            interrupt during the surface factors resumes the fit, then redoes them).
        progress: the fit's progress(step, steps, stats); refine_progress: the normal
            refinement's progress(step, loss).
        log: one-line messages (resuming, decisions).
        held: the held-out views' indices (default: :func:`.fit.held_out` of ``views``).

    Raises:
        DamcapError: no covered pixels; a prior without views to predict from; an 'auto' rule
            without held-out views.
    """
    t_all = time.perf_counter()
    samples = samples_of(views)
    held = held_out(views, opts) if held is None else held
    frames: list[TrainingFrame] | None = adversarial_frames(views, samples, opts)
    prior, init, prior_s, predicted = None, None, 0.0, None
    if opts.prior == "auto" and not held:  # nothing to judge the prior on: the plain fit
        opts = replace(opts, prior="off")
    if opts.prior in ("predictor", "auto"):
        from damcap.appearance.hyper.predict import predict_views

        t0 = time.perf_counter()
        try:
            predicted = predict_views([v for k, v in enumerate(views) if k not in held], device=opts.device)
        except DamcapError as e:
            if opts.prior != "auto":
                raise
            if log:
                log(f"prior: none (the predictor could not predict from these views: {e})")
            predicted, opts = None, replace(opts, prior="off")
    if predicted is not None:
        if predicted.arch == opts.architecture:  # start from the prediction itself (the fit keeps its radiance scale)
            init = predicted
        scale = predicted.radiance_scale if init is not None else radiance_scale_of(samples.radiance_lin, samples.weight)
        prior = prior_samples(predicted, samples, opts.encoding, scale, opts.prior_samples, opts.prior_sigma, opts.seed)
        prior_s = time.perf_counter() - t0
    prior_choice: dict = {}
    if opts.prior == "auto":  # both fits, the one whose held-out views score better is kept
        plain = fit_dam(samples, replace(opts, prior="off"), frames_for_adversarial=frames, checkpoint_path=checkpoint_path,
                        progress=progress, log=log, remove_checkpoint=False, held_frames=held)
        leaned = fit_dam(samples, opts, frames_for_adversarial=frames, progress=progress, log=log, held_frames=held, prior=prior,
                         init_model=init)
        prior_choice = {"off": best_holdout_l1(plain), "predictor": best_holdout_l1(leaned)}
        prior_choice["kept"] = prior_choice["predictor"] < prior_choice["off"]
        result = leaned if prior_choice["kept"] else plain
        if log:
            log(f"prior: {'the predictor' if prior_choice['kept'] else 'none'} (held-out L1 {prior_choice['off']:.4f} without the "
                f"predictor's prior, {prior_choice['predictor']:.4f} with it)")
    else:
        result = fit_dam(samples, opts, frames_for_adversarial=frames, checkpoint_path=checkpoint_path, progress=progress, log=log,
                         remove_checkpoint=False, held_frames=held, prior=prior, init_model=init)
    normals = choose_normal_refine(result.model, views, opts, log=log, progress=refine_progress, held=held)
    spatial = choose_spatial(normals.model, views, opts, log=log, heldout_model=normals.heldout_model, held=held)
    return FitOutcome(result, normals, spatial, held, prior_s, len(samples), time.perf_counter() - t_all, prior_choice)


def best_holdout_l1(result: FitResult) -> float:
    """The lowest held-out cost a fit's history records (the one its stopping rule kept); inf for
    a fit without held-out evaluations."""
    return min((h["holdout_l1"] for h in result.history), default=float("inf"))


def heldout_dssim(outcome: FitOutcome, views: list[ViewData]) -> float:
    """Mean DSSIM of the held-out views under the path :func:`fit_views` kept, as its last 'auto'
    decision measured it (those views never trained it); for a path without such a decision,
    the DAM's own renders of them (its fit never trained on them either).

    Raises:
        DamcapError: ``outcome`` has no held-out views.
    """
    if not outcome.held:
        raise DamcapError("no held-out views to score the fit on")
    if outcome.spatial.heldout_dssim:
        return outcome.spatial.heldout_dssim["albedo" if outcome.spatial.kept else "off"]
    if outcome.normals.heldout_dssim:
        return outcome.normals.heldout_dssim["on" if outcome.normals.kept else "off"]
    return mean_dssim(outcome.result.model, [views[k] for k in outcome.held])


@dataclass
class GeometryScores:
    """:func:`judge_geometries`' verdict."""

    chosen: str
    heldout_dssim: dict[str, float]
    """geometry -> mean DSSIM of the held-out views under its fit"""
    held_views: list[str]
    seconds: float

    def why(self) -> str:
        """One line: the scores, the held-out views' count and the time."""
        scores = ", ".join(f"{g} {d:.4f}" for g, d in self.heldout_dssim.items())
        return f"held-out DSSIM {scores} (fit on the train split, {len(self.held_views)} views held out, {self.seconds:.0f} s)"

    def record(self) -> dict:
        return {"chosen": self.chosen, "heldout_dssim": self.heldout_dssim, "held_views": self.held_views, "seconds": self.seconds}


def judge_fit() -> FitOptions:
    """The fit :func:`judge_geometries` runs for ``reconstruct --geometry auto``: fit's defaults
    without the prior (its second fit) and with half the steps of the DAM and of the normal
    refinement (its choices and time against a plain fit: bench/geometry_judge.md)."""
    d = FitOptions()
    return replace(d, prior="off", steps=d.steps // 2, normal_refine_steps=d.normal_refine_steps // 2)


def judge_geometries(views_by_geometry: dict[str, list[ViewData]], opts: FitOptions,
                     log: Callable[[str], None] | None = None) -> GeometryScores:
    """Which geometry's capture a fit generalises from best: the same views (same names, same
    order) of each, the same views held out (:func:`.fit.held_out` of the first), a
    :func:`fit_views` on each, scored by :func:`heldout_dssim`. The first geometry is kept unless
    another lowers the held-out DSSIM by the surface factors' margin
    (:func:`.spatial_fit.pays_on_heldout` with ``opts.spatial_min_gain`` and ``opts.spatial_min_gain_abs``).

    Raises:
        DamcapError: fewer than two geometries, views that differ between them, or too few views to
            hold any out.
    """
    t0 = time.perf_counter()
    names = [[v.name for v in views] for views in views_by_geometry.values()]
    if len(names) < 2 or any(n != names[0] for n in names):
        raise DamcapError("judging geometries needs two or more captures of the same views")
    first = next(iter(views_by_geometry.values()))
    held = held_out(first, opts)
    if not held:
        raise DamcapError(f"judging geometries needs views to hold out: {len(first)} train views, --holdout-views {opts.holdout_views}")
    scores = {g: heldout_dssim(fit_views(views, opts, held=held), views) for g, views in views_by_geometry.items()}
    chosen = next(iter(scores))
    for g, d in scores.items():
        if pays_on_heldout(scores[chosen], d, opts.spatial_min_gain, opts.spatial_min_gain_abs):
            chosen = g
    verdict = GeometryScores(chosen, scores, [first[k].name for k in held], time.perf_counter() - t0)
    if log:
        log(f"geometry judged: {chosen} ({verdict.why()})")
    return verdict
