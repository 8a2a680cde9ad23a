"""Refining the normals after the DAM's fit (``damcap fit --normal-refine on|auto``).

The DAM is fitted first (:func:`.fit.fit_dam`, unchanged); a field of normal offsets on the
surface and the DAM's weights are then optimised together on the training pixels
(:func:`.normal_refine.refine_normals`). The model carries the field (``model.normal_field``):
render, evaluate and export on the capture's own surface shade with the refined normals.

``auto`` models only what the scene requires, like ``--spatial auto``: the field is refined on
the training views without the ones the fit's stopping rule held out (:func:`.fit.held_out`;
the DAM never trained on them) and kept only when it lowers those held-out views' mean DSSIM by at
least ``FitOptions.normal_refine_min_gain`` (a fraction) and ``normal_refine_min_gain_abs``. The
probe takes half the steps (:func:`probe_steps`); a kept field then takes the other half on every
training view, starting from the probe's offsets, so 'auto' costs one refinement.

The final field has seen the held-out views, so a later decision on them (``--spatial auto``)
would score views the model has fitted. The decision therefore also returns the model refined
without them (``heldout_model``: auto's probe, or for 'on' with ``--spatial auto`` one more
refinement), for later decisions to be made with.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from damcap.common.errors import DamcapError

from damcap.appearance.dam import DeepAppearanceMap
from damcap.appearance.fit import FitOptions, held_out
from damcap.appearance.normal_field import NormalField
from damcap.appearance.normal_refine import refine_normals
from damcap.appearance.spatial_fit import mean_dssim, pays_on_heldout, training_footprint
from damcap.appearance.views import ViewData, positions_of, samples_of


@dataclass
class NormalRefineDecision:
    """What ``--normal-refine`` did, as recorded in the model's provenance."""

    model: DeepAppearanceMap
    """the DAM (refined weights and the field when one was kept; the fit's DAM otherwise)"""
    mode: str
    """the option asked for: 'off', 'on' or 'auto'"""
    kept: bool
    footprint_world: float | None = None
    """median size of a training pixel on the surface, world units"""
    voxel_size: float | None = None
    heldout_dssim: dict[str, float] = field(default_factory=dict)
    """auto: mean DSSIM of the held-out training views with the geometry's normals ('off') and refined ('on')"""
    seconds: float = 0.0
    heldout_model: DeepAppearanceMap | None = None
    """the kept refinement made without the held-out training views (None: none was kept, or
    none was needed); later held-out decisions use it in place of ``model``"""

    def record(self) -> dict[str, Any]:
        nf = self.model.normal_field
        return {"mode": self.mode, "kept": self.kept, "footprint_world": self.footprint_world, "voxel_size": self.voxel_size,
                "voxels": None if nf is None else int(nf.keys.size), "tilt_deg": None if nf is None else tilt_deg(nf),
                "heldout_dssim": self.heldout_dssim or None, "seconds": self.seconds}

    def summary(self) -> str:
        """One line for the terminal."""
        h = self.heldout_dssim
        scores = f" (held-out DSSIM {h['off']:.4f} with the geometry's normals, {h['on']:.4f} refined)" if h else ""
        if self.mode == "off":
            return "normal refinement: off"
        if not self.kept:
            return f"normal refinement: not kept{scores}; the geometry's normals serve"
        nf = self.model.normal_field
        assert nf is not None
        t = tilt_deg(nf)
        return (f"normal refinement: {nf.keys.size} voxel corners ({self.voxel_size:.3g} world units), tilt median "
                f"{t['median']:.1f} deg, p90 {t['p90']:.1f} deg{scores} in {self.seconds:.0f} s")


def tilt_deg(nf: NormalField) -> dict[str, float]:
    """Median and 90th percentile over corners of the tilt the offsets give a normal, degrees
    (the tangent part of an offset is at most its length, so these are upper bounds)."""
    if nf.keys.size == 0:
        return {"median": 0.0, "p90": 0.0}
    t = np.degrees(np.arctan(np.linalg.norm(nf.offset, axis=-1)))
    return {"median": float(np.median(t)), "p90": float(np.quantile(t, 0.9))}


def _refined(model: DeepAppearanceMap, views: list[ViewData], footprint: float, opts: FitOptions,
             progress: Callable[[int, float], None] | None, steps: int | None = None,
             initial: DeepAppearanceMap | None = None) -> DeepAppearanceMap:
    """The DAM refined on ``views`` together with a new normal field (``steps`` steps, default the
    options'; started from ``initial``'s field), carrying it (and ``model``'s spatial factor)."""
    ropts = opts.normal_refine_options if steps is None else replace(opts.normal_refine_options, steps=steps)
    refined, nf = refine_normals(model, samples_of(views), positions_of(views), footprint, ropts, progress,
                                 initial=None if initial is None else initial.normal_field)
    return refined.with_spatial(model.spatial).with_normal_field(nf)


def probe_steps(steps: int) -> int:
    """'auto': the steps of the refinement it decides with (without the held-out views); a kept
    field then takes the rest on every view, so 'auto' costs one refinement, not two.

    >>> probe_steps(400), probe_steps(1)
    (200, 1)
    """
    return max(1, steps // 2)


def choose_normal_refine(model: DeepAppearanceMap, views: list[ViewData], opts: FitOptions,
                         log: Callable[[str], None] | None = None,
                         progress: Callable[[int, float], None] | None = None,
                         held: list[int] | None = None) -> NormalRefineDecision:
    """Apply ``opts.normal_refine`` to a fitted DAM (see the module docstring).

    Args:
        model: the DAM fitted to ``views`` (its own normal field, if any, is dropped).
        views: the training views, in the order the fit used (hold-out indices refer to it).
        opts: the fit's options (``normal_refine*``, ``holdout_views``, ``seed``; ``spatial``: 'auto'
            makes 'on' refine without the held-out views as well).
        log: one line per decision.
        progress: progress(step, loss) after each refinement step (each refinement restarts at 1).
        held: the held-out views' indices (default: :func:`.fit.held_out` of ``views``).

    Raises:
        DamcapError: 'auto' without held-out training views; no foreground.
    """
    t0 = time.perf_counter()
    base = model.with_normal_field(None)
    if opts.normal_refine == "off":
        return NormalRefineDecision(base, "off", False)
    footprint = training_footprint(views)
    voxel = opts.normal_refine_voxel_px * footprint
    scores: dict[str, float] = {}
    held = held_out(views, opts) if held is None else held
    probe = None
    if opts.normal_refine == "auto" or (opts.spatial == "auto" and held):
        if not held:
            raise DamcapError(f"--normal-refine auto decides on held-out training views: use --holdout-views >= 1 and at least 3 "
                              f"train views (got {opts.holdout_views} and {len(views)}), or --normal-refine on")
        rest = [v for k, v in enumerate(views) if k not in held]
        steps = probe_steps(opts.normal_refine_steps) if opts.normal_refine == "auto" else None
        probe = _refined(base, rest, footprint, opts, progress, steps)
    if opts.normal_refine == "auto":
        assert probe is not None
        held_views = [views[k] for k in held]
        scores = {"off": mean_dssim(base, held_views), "on": mean_dssim(probe, held_views)}
        if not pays_on_heldout(scores["off"], scores["on"], opts.normal_refine_min_gain, opts.normal_refine_min_gain_abs):
            decision = NormalRefineDecision(base, "auto", False, footprint, voxel, scores, time.perf_counter() - t0)
            if log:
                log(decision.summary())
            return decision
    if opts.normal_refine == "auto":  # the probe's field, refined on every view for the remaining steps
        assert probe is not None
        final = _refined(base, views, footprint, opts, progress, max(1, opts.normal_refine_steps - probe_steps(opts.normal_refine_steps)), probe)
    else:
        final = _refined(base, views, footprint, opts, progress)
    decision = NormalRefineDecision(final, opts.normal_refine, True, footprint, voxel, scores, time.perf_counter() - t0, probe)
    if log:
        log(decision.summary())
    return decision
