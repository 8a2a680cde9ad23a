"""Fitting the spatial factor after the DAM (``damcap fit --spatial albedo|auto``).

The DAM is fitted first (:func:`.fit.fit_dam`, unchanged); the albedo texture is then the
closed-form estimate of :func:`.spatial.estimate_spatial_albedo` from the training pixels' log
ratios to that DAM. Refitting the DAM to radiance / albedo and estimating again (alternation)
changed the real cape's novel-view DSSIM by less than 0.001 (0.2945 -> 0.2939), so one pass
is made.

``auto`` models only what the scene requires, like ``--materials auto`` and ``--target-dssim``:
the albedo is estimated from the training views the fit's stopping rule held out
(:func:`.fit.held_out`; the DAM never trained on them) left out as well, and kept only when
it lowers those held-out views' mean DSSIM by at least ``FitOptions.spatial_min_gain`` (a
fraction) and ``spatial_min_gain_abs``. The kept texture is then estimated again from every
training view.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

from damcap.common.errors import DamcapError

from damcap.appearance.dam import DeepAppearanceMap
from damcap.appearance.evaluate import score_view
from damcap.appearance.fit import FitOptions, held_out
from damcap.appearance.normal_field import surface_normals
from damcap.appearance.render import render_frame
from damcap.appearance.spatial import SpatialAlbedo, estimate_spatial_albedo, log_ratio, pixel_footprint_world
from damcap.appearance.views import ViewData, positions_of, samples_of

RATIO_FLOOR = 1e-3
"""radiance below this fraction of the model's radiance scale counts as this much in the log
ratios (a black pixel would otherwise ask for albedo 0)"""


@dataclass
class SpatialDecision:
    """What ``--spatial`` did, as recorded in the model's provenance."""

    model: DeepAppearanceMap
    """the DAM, carrying the spatial factor when one was kept"""
    mode: str
    """the option asked for: 'off', 'albedo' or 'auto'"""
    kept: bool
    footprint_world: float | None = None
    """median size of a training pixel on the surface, world units"""
    voxel_size: float | None = None
    heldout_dssim: dict[str, float] = field(default_factory=dict)
    """auto: mean DSSIM of the held-out training views without ('off') and with ('albedo') it"""
    seconds: float = 0.0

    def record(self) -> dict[str, Any]:
        sa = self.model.spatial
        return {"mode": self.mode, "kept": self.kept, "footprint_world": self.footprint_world, "voxel_size": self.voxel_size,
                "voxels": None if sa is None else int(sa.keys.size), "heldout_dssim": self.heldout_dssim or None,
                "seconds": self.seconds}

    def summary(self) -> str:
        """One line for the terminal."""
        h = self.heldout_dssim
        scores = f" (held-out DSSIM {h['off']:.4f} without, {h['albedo']:.4f} with)" if h else ""
        if self.mode == "off":
            return "spatial factor: off"
        if not self.kept:
            return f"spatial factor: not kept{scores}; the DAM alone models these views"
        sa = self.model.spatial
        assert sa is not None
        return f"spatial factor: albedo texture of {sa.keys.size} voxel corners ({self.voxel_size:.3g} world units){scores}"


def pays_on_heldout(without: float, with_: float, min_gain: float, min_gain_abs: float) -> bool:
    """The rule of every 'auto' surface factor: keep it when it lowers the held-out views' DSSIM
    from ``without`` to ``with_`` by at least ``min_gain`` (a fraction) and ``min_gain_abs``.

    >>> pays_on_heldout(0.40, 0.38, 0.02, 0.005), pays_on_heldout(0.403, 0.399, 0.02, 0.005)
    (True, False)
    """
    gain = without - with_
    return gain >= min_gain * without and gain >= min_gain_abs


def training_footprint(views: list[ViewData]) -> float:
    """Median over views of :func:`.spatial.pixel_footprint_world` (world units per pixel).

    Raises:
        DamcapError: no view has two adjacent foreground pixels.
    """
    sizes = [s for v in views if (s := pixel_footprint_world(v.data.position_world, v.data.coverage)) is not None]
    if not sizes:
        raise DamcapError("the spatial factor needs training views with foreground (no two adjacent covered pixels found)")
    return float(statistics.median(sizes))


@torch.no_grad()
def _predicted(model: DeepAppearanceMap, views: list[ViewData], chunk: int = 1 << 16) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(radiance, DAM prediction, weight) of the views' foreground pixels, in samples_of order
    (with the normals refined by the model's normal field where it has one)."""
    s = samples_of(views)
    n = torch.from_numpy(surface_normals(model.normal_field, s.normal_world.numpy(), positions_of(views))) if model.normal_field is not None \
        else s.normal_world
    pred = torch.cat([model(s.view_dir_world[i:i + chunk], n[i:i + chunk]) for i in range(0, len(s), chunk)]) \
        if len(s) else torch.zeros(0, 3)
    return s.radiance_lin.numpy(), pred.numpy(), s.weight.numpy()


def estimate_for(model: DeepAppearanceMap, views: list[ViewData], voxel_size: float, prior: float) -> SpatialAlbedo:
    """The closed-form albedo texture of ``views``' pixels given the DAM ``model``."""
    radiance, pred, weight = _predicted(model, views)
    r = log_ratio(radiance, pred, RATIO_FLOOR * model.radiance_scale)
    return estimate_spatial_albedo(positions_of(views), r, weight, voxel_size, prior)


def mean_dssim(model: DeepAppearanceMap, views: list[ViewData]) -> float:
    """Mean DSSIM of the model's renders of ``views`` (frames without foreground skipped)."""
    scores = [s for v in views if (s := score_view(v, render_frame(model, v.data, v.centre_world))) is not None]
    return float(np.mean(scores)) if scores else float("nan")


def choose_spatial(model: DeepAppearanceMap, views: list[ViewData], opts: FitOptions,
                   log: Callable[[str], None] | None = None, heldout_model: DeepAppearanceMap | None = None,
                   held: list[int] | None = None) -> SpatialDecision:
    """Apply ``opts.spatial`` to a fitted DAM (see the module docstring).

    Args:
        model: the DAM fitted to ``views`` (its own spatial factor, if any, is ignored).
        views: the training views, in the order the fit used (hold-out indices refer to it).
        opts: the fit's options (``spatial``, ``spatial_voxel_px``, ``spatial_prior``,
            ``spatial_min_gain``, ``holdout_views``).
        log: one line per decision.
        heldout_model: 'auto' decides with this model in place of ``model``: one whose normal
            field was refined without the held-out views
            (:attr:`.normal_fit.NormalRefineDecision.heldout_model`), so that they stay held out.
        held: the held-out views' indices (default: :func:`.fit.held_out` of ``views``).

    Raises:
        DamcapError: 'auto' without held-out training views; no foreground.
    """
    t0 = time.perf_counter()
    base = model.with_spatial(None)
    if opts.spatial == "off":
        return SpatialDecision(base, "off", False)
    footprint = training_footprint(views)
    voxel = opts.spatial_voxel_px * footprint
    scores: dict[str, float] = {}
    if opts.spatial == "auto":
        held = held_out(views, opts) if held is None else held
        if not held:
            raise DamcapError(f"--spatial auto decides on held-out training views: use --holdout-views >= 1 and at least 3 train views "
                              f"(got {opts.holdout_views} and {len(views)}), or --spatial albedo")
        rest = [v for k, v in enumerate(views) if k not in held]
        judge = base if heldout_model is None else heldout_model.with_spatial(None)
        probe = judge.with_spatial(estimate_for(judge, rest, voxel, opts.spatial_prior))
        held_views = [views[k] for k in held]
        scores = {"off": mean_dssim(judge, held_views), "albedo": mean_dssim(probe, held_views)}
        keep = pays_on_heldout(scores["off"], scores["albedo"], opts.spatial_min_gain, opts.spatial_min_gain_abs)
        if not keep:
            decision = SpatialDecision(base, "auto", False, footprint, voxel, scores, time.perf_counter() - t0)
            if log:
                log(decision.summary())
            return decision
    final = base.with_spatial(estimate_for(base, views, voxel, opts.spatial_prior))
    decision = SpatialDecision(final, opts.spatial, True, footprint, voxel, scores, time.perf_counter() - t0)
    if log:
        log(decision.summary())
    return decision
