"""Fitting a DAM to a capture by gradient descent (Maximov et al. 2019, Sec. 3.2, Eq. 3).

Cost: the per-sample-weighted L1 distance between the DAM's radiance and the captured radiance
over covered training pixels (or, with ``FitOptions.quantile``, a pinball loss that is L1 at 0.5),
plus optionally alpha times an adversarial cost. Radiance is divided by the capture's radiance
scale (95th percentile of the training foreground) so that learning rates do not depend on the
units.

Stopping rule: a few training views are held out; the weights with the lowest held-out data
cost (L1 at the default quantile) are kept (training on a few thousand weights can overfit the
training views and get worse on novel ones). ``holdout_views = 0`` trains on all views and keeps
the last weights. The history's ``train_l1`` / ``holdout_l1`` are that data cost.

Precision: ``FitOptions.precision = "bfloat16"`` runs the training step's DAM forward pass and
data cost under ``torch.autocast`` (bfloat16 matrix products; :func:`.dam.dam_forward` returns
float32 radiance). The master weights, Adam's state, the held-out evaluation, checkpoints and
the fitted model stay float32; the adversarial cost's patches and discriminator stay float32.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable, ContextManager, Literal

import numpy as np
import torch

from damcap.common.atomic import atomic_path
from damcap.common.device import fixed_threads, resolve_device
from damcap.common.errors import DamcapError
from damcap.common.validate import COUNT, COUNT_OR_ZERO, MAX_BATCH_PIXELS, MAX_DAM_DEPTH, MAX_DAM_WIDTH, SEED, check_ranges, in_range
from damcap.common.fingerprint import FINGERPRINT_KEY, fingerprint
from damcap.common.version import package_version

from damcap.appearance.adversarial import PatchDiscriminator, discriminator_loss, generator_loss
from damcap.appearance.dam import Activation, DamArchitecture, DeepAppearanceMap, Encoding, dam_forward, encode_inputs
from damcap.appearance.normal_refine import NormalRefineOptions
from damcap.appearance.pixels import FOREGROUND_COVERAGE, PixelSamples, view_dir_world
from damcap.appearance.views import ViewData, radiance_scale_of

Precision = Literal["float32", "bfloat16"]
PRECISIONS: tuple[str, ...] = ("float32", "bfloat16")
SpatialMode = Literal["off", "albedo", "auto"]
SPATIAL_MODES: tuple[str, ...] = ("off", "albedo", "auto")
NormalRefineMode = Literal["off", "on", "auto"]
NORMAL_REFINE_MODES: tuple[str, ...] = ("off", "on", "auto")
HoldoutRule = Literal["arc", "spread"]
HOLDOUT_RULES: tuple[str, ...] = ("arc", "spread")
PriorMode = Literal["off", "predictor", "auto"]
PRIOR_MODES: tuple[str, ...] = ("off", "predictor", "auto")
AFTER_FIT_PREFIXES = ("spatial", "normal_refine")
"""options whose names start so act after :func:`fit_dam` (they are not part of its fingerprint)"""
_REFINE = {f.name: f for f in fields(NormalRefineOptions)}


@dataclass(frozen=True)
class FitOptions:
    """Options of ``damcap fit`` (every knob that trades speed for accuracy is here)."""

    steps: int = field(default=2000, metadata=COUNT)
    """optimiser steps (Adam); time grows linearly"""
    batch_size: int = field(default=4096, metadata=in_range(1, MAX_BATCH_PIXELS))
    """pixels per step"""
    learning_rate: float = field(default=1e-2, metadata=in_range(0, 10, lo_open=True))
    """initial Adam learning rate; cosine-decayed to 5% of it"""
    width: int = field(default=32, metadata=in_range(1, MAX_DAM_WIDTH))
    """DAM hidden units per layer"""
    depth: int = field(default=4, metadata=in_range(1, MAX_DAM_DEPTH))
    """DAM hidden layers"""
    activation: Activation = field(default="shifted_softplus", metadata={"cli_panel": "advanced"})
    """DAM hidden non-linearity. 'shifted_softplus' (softplus - ln 2) extrapolates to novel views
    more smoothly than 'leaky_relu': on seven training-part Mitsuba captures, novel-view
    DSSIM / RM++ 0.47 vs 0.57, better on each (bench/synth.md); plain 'softplus' collapses
    to black on point-light captures"""
    encoding: Encoding = field(default="nr", metadata={"cli_what": "DAM input encoding"})
    """DAM input: 'vn' (paper), 'nr' (normal + mirrored view), 'vnr'"""
    separable: bool = field(default=True, metadata={"cli_panel": "advanced"})
    """DAM = softplus(f(N) + g(R)), two branches; off: the paper's joint DAM, for 'vn'/'vnr'.
    ``DamArchitecture.separable``: encoding 'nr', an even width; 1728 weights at the default
    width 32, 3168 at 44. A novel view pairs normals and mirror directions the training views
    saw only apart, and the sum extrapolates to such pairs. Trained on one ring of cameras and scored on the others, it
    beat the joint network on every capture of bench/real_defaults.md but the studio sample's
    dense surface (real cape 0.267 against 0.268, fox 0.303 against 0.308, studio 0.294 against
    0.321, blob 0.146 against 0.156); width 44 did worse than 32 on three of the four"""
    adversarial: bool = False
    """add the paper's adversarial cost (patch discriminator)"""
    adversarial_alpha: float = field(default=0.001, metadata=in_range(0, 1e6, cli_panel="advanced"))
    """weight of the adversarial cost (the paper: 0.001)"""
    holdout_views: int = field(default=2, metadata=COUNT_OR_ZERO)
    """training views held out for the stopping rule and the 'auto' decisions (0 = none, keep the
    last weights)"""
    holdout: HoldoutRule = field(default="arc", metadata={"cli_panel": "advanced"})
    """which training views are held out: 'arc' (a group of neighbouring cameras that lies
    farthest from the others, so that the stopping rule and the 'auto' decisions judge views the
    fit must extrapolate to, as novel views are; :func:`holdout_arc`) or 'spread' (views spread
    over the training order, each between two that train)"""
    eval_every: int = field(default=100, metadata={**COUNT, "cli_panel": "advanced"})
    """steps between held-out evaluations"""
    prior: PriorMode = field(default="auto", metadata={"cli_what": "prior"})
    """a prior on the DAM: 'off', 'predictor' (the shipped predictor's prediction from the
    training views pulls the fit, most where the training views constrain it least:
    appearance/prior.py) or 'auto' (fit without and with it, keep the fit whose held-out views
    score better)"""
    prior_weight: float = field(default=1.0, metadata=in_range(0, 1e6, cli_panel="advanced"))
    """weight of the prior's cost against the data cost (both L1 of radiance / scale)"""
    prior_sigma: float = field(default=0.25, metadata=in_range(0, 10, lo_open=True, cli_panel="advanced"))
    """distance in the DAM's input encoding (unit vectors) over which the training pixels take
    over from the prior: a prior sample that far from every training pixel has weight 0.63"""
    prior_samples: int = field(default=32768, metadata={**COUNT, "cli_panel": "advanced"})
    """prior: (view, normal) samples drawn once, over the training normals and their hemispheres"""
    seed: int = field(default=0, metadata=SEED)
    """seeds initialisation and pixel sampling: same seed, same model"""
    device: str = "cpu"
    """'cpu', 'cuda' or 'auto'"""
    checkpoint_every: int = field(default=250, metadata={**COUNT_OR_ZERO, "cli_panel": "advanced"})
    """steps between checkpoints (0 = never)"""
    precision: Precision = "float32"
    """compute dtype of the training step's DAM forward pass and data cost: 'float32' or
    'bfloat16' (autocast; weights, optimiser, evaluation and the saved model stay float32)"""
    weight_decay: float = field(default=0.0, metadata=in_range(0, 1e6, cli_panel="advanced"))
    """decoupled weight decay (AdamW; each step multiplies the weights by 1 - lr x weight_decay).
    It trades fit for smoothness: 0.1 lowered the mean novel-view DSSIM / RM++ over seven
    path-traced training-part captures (shadows, interreflection) from 0.47 to 0.43 (0.39 with
    8000 steps) but raised it on the closed-form ones (bench/synth.md, bench/dam_core.md), so the
    default is none"""
    quantile: float = field(default=0.5, metadata=in_range(0, 1, lo_open=True, hi_open=True, cli_panel="advanced"))
    """quantile q of the data cost (:func:`weighted_quantile_cost`): 0.5 is the paper's L1. Cast
    shadows and occlusion only darken a pixel, so at each (view, normal) an upper quantile is
    nearer the unshadowed appearance that a DAM can represent (see bench/synth.md, stage
    'quantile', for the measured effect on path-traced captures). The stopping rule scores the
    held-out views with the same cost"""

    spatial: SpatialMode = field(default="auto", metadata={"cli_what": "spatial factor"})
    """an albedo texture on the surface that multiplies the DAM (the spatial factor). 'off' (the
    DAM alone, a function of view and normal only), 'albedo' (an RGB albedo texture on the surface
    multiplies the DAM: print, tarnish, fine relief) or 'auto' (the albedo only when it lowers the
    DSSIM of the held-out training views by at least ``spatial_min_gain``). On the real cape (8
    train views, 256 px, dense geometry) the albedo lowered novel-view DSSIM from 0.411 to 0.266
    (bench/reconstruct.md). The factor: appearance/spatial.py."""
    spatial_voxel_px: float = field(default=0.75, metadata=in_range(0.05, 64, cli_panel="advanced"))
    """spatial factor: voxel edge of the albedo texture, in pixels' footprints on the surface
    (smaller: sharper texture, fewer training pixels per voxel)"""
    spatial_prior: float = field(default=0.05, metadata=in_range(0, 1e6, cli_panel="advanced"))
    """spatial factor: ridge strength pulling sparsely seen voxels toward albedo 1, in units of
    one training pixel's weight"""
    spatial_min_gain: float = field(default=0.02, metadata=in_range(0, 1, hi_open=True, cli_panel="advanced"))
    """--spatial auto keeps the albedo only when it lowers the held-out views' DSSIM by at least
    this fraction"""
    spatial_min_gain_abs: float = field(default=0.005, metadata=in_range(0, 1, hi_open=True, cli_panel="advanced"))
    """--spatial auto keeps the albedo only when it lowers the held-out views' DSSIM by at least
    this absolute amount. On a uniform closed-form torus it lowered 0.00085 to 0.00071, 17%, and
    changed nothing on the novel views."""

    normal_refine: NormalRefineMode = field(default="auto", metadata={"cli_what": "normal refinement"})
    """normal offsets fitted with the DAM, for relief the geometry lacks
    (appearance/normal_refine.py). 'off' (the geometry's normals), 'on' (a field of normal offsets
    on the surface, optimised together with the DAM so that it reproduces the training photos:
    relief the geometry lacks) or 'auto' (the field only when it lowers the DSSIM of the held-out
    training views by at least ``normal_refine_min_gain``). On the real cape (8 train views, 256 px,
    dense geometry) it lowered novel-view DSSIM from 0.411 to 0.272, 0.244 with the albedo
    (bench/normal_refine.md). Its cost is steps x pixels per step, whatever the capture's size
    ('auto' decides with half the steps, then gives a kept field the other half)"""
    normal_refine_voxel_px: float = field(default=_REFINE["voxel_px"].default, metadata={**_REFINE["voxel_px"].metadata, "cli_panel": "advanced"})
    """normal refinement: voxel edge of the offset field, in pixels' footprints on the surface.
    Finer resolves finer relief (1, 2, 4 px measured in bench/normal_refine.md)."""
    normal_refine_steps: int = field(default=_REFINE["steps"].default, metadata={**_REFINE["steps"].metadata, "cli_panel": "advanced"})
    """normal refinement: Adam steps, each on 16,384 pixels (NormalRefineOptions.batch)"""
    normal_refine_prior: float = field(default=_REFINE["prior"].default, metadata={**_REFINE["prior"].metadata, "cli_panel": "advanced"})
    """normal refinement: weight of the L2 prior on the offsets"""
    normal_refine_min_gain: float = field(default=0.02, metadata=in_range(0, 1, hi_open=True, cli_panel="advanced"))
    """--normal-refine auto keeps the field only when it lowers the held-out views' DSSIM by at
    least this fraction"""
    normal_refine_min_gain_abs: float = field(default=0.005, metadata=in_range(0, 1, hi_open=True, cli_panel="advanced"))
    """--normal-refine auto keeps the field only when it lowers the held-out views' DSSIM by at
    least this absolute amount"""

    def validate(self) -> None:
        """Raise DamcapError naming the first value outside its declared range."""
        check_ranges(self)
        if self.precision not in PRECISIONS:
            raise DamcapError(f"--precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        if self.spatial not in SPATIAL_MODES:
            raise DamcapError(f"--spatial must be one of {', '.join(SPATIAL_MODES)}, got {self.spatial!r}")
        if self.holdout not in HOLDOUT_RULES:
            raise DamcapError(f"--holdout must be one of {', '.join(HOLDOUT_RULES)}, got {self.holdout!r}")
        if self.prior not in PRIOR_MODES:
            raise DamcapError(f"--prior must be one of {', '.join(PRIOR_MODES)}, got {self.prior!r}")
        if self.normal_refine not in NORMAL_REFINE_MODES:
            raise DamcapError(f"--normal-refine must be one of {', '.join(NORMAL_REFINE_MODES)}, got {self.normal_refine!r}")
        if self.separable and (self.encoding != "nr" or self.width % 2):
            raise DamcapError(f"a separable DAM (the default) needs --encoding nr and an even --width, got --encoding {self.encoding!r}, "
                              f"--width {self.width}; add --no-separable for a joint DAM")
        self.architecture  # width and depth within DamArchitecture's bounds (named in its error)

    @property
    def normal_refine_options(self) -> NormalRefineOptions:
        """The refinement's options (its other knobs at their defaults; the fit's seed)."""
        return NormalRefineOptions(voxel_px=self.normal_refine_voxel_px, steps=self.normal_refine_steps,
                                   prior=self.normal_refine_prior, seed=self.seed)

    @property
    def architecture(self) -> DamArchitecture:
        return DamArchitecture(width=self.width, depth=self.depth, activation=self.activation, encoding=self.encoding,
                               separable=self.separable)

    def for_architecture(self, arch: DamArchitecture) -> "FitOptions":
        """These options fitting ``arch`` (its width, depth, activation, encoding and separability)."""
        return replace(self, width=arch.width, depth=arch.depth, activation=arch.activation, encoding=arch.encoding,
                       separable=arch.separable)


@dataclass
class TrainingFrame:
    """A training frame as the adversarial cost needs it (whole images)."""

    radiance_norm: torch.Tensor
    """(3, H, W) radiance / scale, 0 on background"""
    inputs: torch.Tensor
    """(H, W, C) encoded DAM inputs (0 on background)"""
    foreground: torch.Tensor
    """(H, W) bool"""


@dataclass
class FitResult:
    """A fitted model and how it got there."""

    model: DeepAppearanceMap
    history: list[dict[str, float]] = field(default_factory=list)
    best_step: int = 0
    seconds: float = 0.0
    resumed_from: int = 0
    threads: int = 0
    """torch CPU threads the fit ran on (:func:`.device.fixed_threads`): the same samples, options
    and thread count give the same model bit for bit"""


def holdout_frames(n_frames: int, k: int) -> list[int]:
    """k training-frame indices spread over the interior of the (consecutive) training views.

    >>> holdout_frames(10, 2)
    [3, 6]
    """
    if k <= 0 or n_frames < 3:
        return []
    k = min(k, n_frames - 2)
    return sorted({int(round((i + 1) * (n_frames - 1) / (k + 1))) for i in range(k)})


def holdout_arc(directions: np.ndarray, k: int) -> list[int]:
    """k views that together lie farthest from the others: a seed view and its k - 1 nearest
    neighbours by angle, for the seed whose group's smallest angle to any view outside it is the
    largest (ties: the lowest seed index). On one ring of cameras that is an arc of k neighbours;
    where the cameras are denser in one place than another, the most isolated group. Held out,
    such a group is judged as novel views are: by how the fit extrapolates, not by how it
    interpolates between neighbours on either side.

    Args:
        directions: (N, 3) unit vectors from the object's centre towards each camera (world).
        k: views to hold out (at most N - 2, so that two train).

    Returns:
        sorted indices (empty when k <= 0 or N < 3).

    >>> a = np.arange(8) * np.pi / 4
    >>> holdout_arc(np.stack([np.cos(a), np.sin(a), 0 * a], 1), 2)
    [0, 1]
    >>> b = np.array([0, 0.1, 0.2, 0.3, 2.0, 2.1])
    >>> holdout_arc(np.stack([np.cos(b), np.sin(b), 0 * b], 1), 2)
    [4, 5]
    """
    d = np.asarray(directions, np.float64)
    n = d.shape[0]
    if k <= 0 or n < 3:
        return []
    k = min(k, n - 2)
    angle = np.arccos(np.clip(d @ d.T, -1.0, 1.0))
    np.fill_diagonal(angle, -1.0)  # each view is its own nearest
    order = np.argsort(angle, axis=1, kind="stable")
    best: list[int] = []
    best_gap = -np.inf
    for seed in range(n):
        group = order[seed, :k]
        outside = np.ones(n, bool)
        outside[group] = False
        gap = float(angle[np.ix_(group, np.flatnonzero(outside))].min())
        if gap > best_gap + 1e-9:
            best, best_gap = sorted(int(i) for i in group), gap
    return best


def camera_directions(views: list[ViewData]) -> np.ndarray:
    """(N, 3) unit vectors from the object's centre (the mean of the views' mean foreground
    surface points; the world origin where no view has foreground) towards each view's camera."""
    means = [v.data.position_world[fg].mean(0) for v in views if (fg := v.data.coverage > FOREGROUND_COVERAGE).any()]
    centre = np.mean(means, 0) if means else np.zeros(3)
    d = np.array([v.centre_world for v in views], np.float64).reshape(-1, 3) - centre
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def held_out(views: list[ViewData], opts: "FitOptions") -> list[int]:
    """The training views ``opts`` holds out (``holdout_views`` of them, by the ``holdout`` rule):
    the stopping rule's and every 'auto' decision's judges. The first and last view always train
    under 'spread'; two views always train under 'arc'."""
    if opts.holdout == "spread" or len(views) < 3:
        return holdout_frames(len(views), opts.holdout_views)
    return holdout_arc(camera_directions(views), opts.holdout_views)


@dataclass
class PriorSamples:
    """Samples of a prior DAM that a fit is pulled towards (:func:`fit_dam`, ``prior``), built by
    :func:`.prior.prior_samples`."""

    inputs: torch.Tensor
    """(M, C) encoded DAM inputs, in the fit's encoding"""
    target: torch.Tensor
    """(M, 3) the prior's radiance / the fit's radiance scale"""
    weight: torch.Tensor
    """(M,) in [0, 1]: how little the training pixels constrain each sample (0: a training pixel
    lies on it)"""


def quantile_loss(pred: torch.Tensor, target: torch.Tensor, quantile: float) -> torch.Tensor:
    """(N,) per-sample pinball loss 2 max(q u, (q - 1) u), u = target - pred, averaged over the
    channels of (N, C) radiance; exactly the mean absolute difference at q = 0.5."""
    u = target - pred
    return (2 * torch.maximum(quantile * u, (quantile - 1) * u)).mean(-1)


def weighted_quantile_cost(pred: torch.Tensor, target: torch.Tensor, w: torch.Tensor, quantile: float = 0.5) -> torch.Tensor:
    """The fit's data cost: per-sample-weighted pinball (quantile) loss, scaled so that
    quantile 0.5 is the paper's L1 distance exactly.

    For a residual u = target - pred the loss is 2 max(q u, (q - 1) u): |u| at q = 0.5; above it
    a prediction below the target costs more than one above, so the minimiser over a constant is
    the q-quantile of the targets instead of their median.

    Args:
        pred, target: (N, 3) radiance (any common unit).
        w: (N,) per-sample weights W >= 0.
        quantile: q in (0, 1).

    Returns:
        () weighted mean over samples of the channel-mean loss, in the unit of the radiance.

    >>> p, t, w = torch.zeros(2, 3), torch.tensor([[1.0] * 3, [-1.0] * 3]), torch.ones(2)
    >>> float(weighted_quantile_cost(p, t, w)), float(weighted_quantile_cost(p, t, w, 0.75))
    (1.0, 1.0)
    >>> float(weighted_quantile_cost(p, t, torch.tensor([1.0, 0.0]), 0.75))
    1.5
    """
    return (quantile_loss(pred, target, quantile) * w).sum() / w.sum().clamp_min(1e-12)


def _state_json(opts: FitOptions) -> str:
    return json.dumps(asdict(opts), sort_keys=True)


STALE_SUFFIX = ".stale"
"""a checkpoint made from other inputs is kept aside as ``CKPT.stale`` (one generation) instead of
being resumed or deleted"""


def fit_fingerprint(samples: PixelSamples, opts: FitOptions, frames_for_adversarial: list[TrainingFrame] | None = None,
                    init_model: DeepAppearanceMap | None = None, held: list[int] | None = None,
                    prior: PriorSamples | None = None) -> str:
    """What a fit's result depends on: the training pixels (every tensor of ``samples``, bit for
    bit), the adversarial cost's whole frames, the initial model, the resolved options (but the
    spatial factor's and the normal refinement's, which act after the fit) and the damcap version. A checkpoint is resumed only by a fit with the same fingerprint."""
    dam_opts = {k: v for k, v in asdict(opts).items() if not k.startswith(AFTER_FIT_PREFIXES)}  # applied after fit_dam
    parts: list[Any] = ["fit", package_version(), dam_opts, samples.view_dir_world, samples.normal_world,
                        samples.radiance_lin, samples.weight, samples.frame_index]
    for f in frames_for_adversarial or []:
        parts += [f.radiance_norm, f.inputs, f.foreground]
    if init_model is not None:
        parts += [init_model.get_flat_weights(), float(init_model.radiance_scale)]
    if held is not None:
        parts += [{"held_frames": list(held)}]
    if prior is not None:
        parts += [prior.inputs, prior.target, prior.weight]
    return fingerprint(*parts)


def set_aside_stale(path: Path, why: str, say: Callable[[str], None]) -> None:
    """Move a checkpoint that must not be resumed to ``path.stale`` (replacing an older one) and
    say so in one line; the job then starts afresh."""
    stale = path.with_name(path.name + STALE_SUFFIX)
    try:
        os.replace(path, stale)
        kept = f"kept as {stale.name}"
    except OSError as e:  # cannot move it: the new run's first checkpoint overwrites it
        kept = f"could not be moved aside ({e.__class__.__name__}); the new run overwrites it"
    say(f"{path.name} was written for {why}; starting afresh (the old checkpoint {kept})")


def _warn(message: str) -> None:
    import warnings

    warnings.warn(message, stacklevel=3)


def interrupted_note(path: Path | None, step: int, steps: int, kept_step: int | None) -> str:
    """The line an interrupted job adds to its exception (``e.__notes__``): what was kept.

    Args:
        path: the job's checkpoint file (None: the job does not checkpoint).
        step: steps completed when the job stopped; steps: of all.
        kept_step: the step of the checkpoint left at ``path``, None when none is there.

    >>> interrupted_note(Path("m.dam.ckpt"), 120, 2000, 100)
    'stopped after step 120 of 2000; kept m.dam.ckpt (step 100): rerun the same command to resume'
    """
    if path is None or kept_step is None:
        return f"stopped after step {step} of {steps}; no checkpoint kept"
    return f"stopped after step {step} of {steps}; kept {path} (step {kept_step}): rerun the same command to resume"


def compute_precision(device: torch.device, precision: Precision) -> ContextManager:
    """The context a training step's forward pass and cost run in: ``torch.autocast`` to
    bfloat16 on ``device``'s type for 'bfloat16', a no-op for 'float32'."""
    if precision == "bfloat16":
        return torch.autocast(device_type=device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def _on_fixed_threads(fit: Callable[..., FitResult]) -> Callable[..., FitResult]:
    """Run ``fit`` on the thread count in force when it is called, held fixed (no dynamic thread
    adjustment by oneMKL or OpenMP, whatever the machine's load), and record it in the result."""

    @functools.wraps(fit)
    def run(*args: Any, **kwargs: Any) -> FitResult:
        with fixed_threads() as threads:
            result = fit(*args, **kwargs)
        result.threads = threads
        return result

    return run


@_on_fixed_threads
def fit_dam(
    samples: PixelSamples,
    opts: FitOptions,
    *,
    frames_for_adversarial: list[TrainingFrame] | None = None,
    checkpoint_path: str | os.PathLike | None = None,
    progress: Callable[[int, int, dict[str, float]], None] | None = None,
    init_model: DeepAppearanceMap | None = None,
    log: Callable[[str], None] | None = None,
    remove_checkpoint: bool = True,
    held_frames: list[int] | None = None,
    prior: PriorSamples | None = None,
) -> FitResult:
    """Fit one DAM to pixel samples.

    Args:
        samples: training pixels (frame_index says which training frame each came from).
        opts: options.
        frames_for_adversarial: whole training frames (needed when opts.adversarial).
        checkpoint_path: where to checkpoint (atomically, every ``opts.checkpoint_every`` steps
            and when interrupted). An existing checkpoint is resumed only when its
            :func:`fit_fingerprint` (training pixels, options, initial model, damcap version)
            equals this fit's, and then the result is the same as an uninterrupted run, bit for
            bit. Any other checkpoint (another capture at the same output path, other options,
            an old one without a fingerprint, an unreadable one) is never loaded: it is moved
            to ``CKPT.stale``, ``log`` says so, and the fit starts afresh. On completion the
            checkpoint is removed unless ``remove_checkpoint`` is False (a caller that still has
            to save the result removes it itself once the result is safe).
        progress: called as progress(step, steps, stats) after every step.
        init_model: optional initial DAM (e.g. a predicted one) instead of random weights; its
            architecture must be opts' and its radiance scale is kept.
        log: one-line messages (resuming; starting afresh); without it, starting afresh is a
            ``warnings.warn`` and resuming is silent.
        held_frames: the training frames (``samples.frame_index`` values) the stopping rule holds
            out (:func:`held_out`); None: :func:`holdout_frames` of ``opts.holdout_views``.
        prior: samples of a prior DAM (:func:`.prior.prior_samples`): each step adds
            ``opts.prior_weight`` times their weighted L1 (a batch of a quarter of
            ``opts.batch_size``) to the cost. With an initial model and held-out views, the initial
            model is scored too (step 0), so the fit keeps it where no step beats it.

    Raises:
        KeyboardInterrupt, SystemExit and any other exception of the loop propagate unchanged
        after the state of the last completed step is checkpointed (when ``checkpoint_path``
        and ``opts.checkpoint_every`` are set and the step had completed); a note
        (``e.__notes__``, :func:`interrupted_note`) says what was kept.

    Returns:
        the fitted model (on CPU), its training history and the CPU thread count it ran on (held
        fixed during the fit, so that the machine's load cannot change it).
    """
    opts.validate()
    if len(samples) == 0:
        raise DamcapError("no covered training pixels to fit (is the train split's coverage A all 0?)")
    if opts.adversarial and not frames_for_adversarial:
        raise DamcapError("the adversarial cost needs whole training frames")
    device = resolve_device(opts.device)
    arch = opts.architecture
    if init_model is not None and init_model.arch != arch:
        raise DamcapError(f"the initial model's architecture {init_model.arch} differs from the fit's {arch}")
    scale = init_model.radiance_scale if init_model is not None else radiance_scale_of(samples.radiance_lin, samples.weight)
    gen = torch.Generator().manual_seed(opts.seed)
    model = DeepAppearanceMap(arch, scale, None if init_model is None else init_model.get_flat_weights(), generator=gen).to(device)

    n_frames = int(samples.frame_index.max()) + 1
    held = sorted(int(k) for k in held_frames) if held_frames is not None else holdout_frames(n_frames, opts.holdout_views)
    if log is not None and held_frames is None and len(held) < opts.holdout_views:
        log(f"note: {len(held)} of {n_frames} training views held out for the stopping rule (--holdout-views "
            f"{opts.holdout_views} leaves the first and last view to fit)")
    is_held = torch.zeros(len(samples), dtype=torch.bool)
    for k in held:
        is_held |= samples.frame_index == k
    if is_held.all():
        is_held[:] = False
    inputs = encode_inputs(samples.view_dir_world, samples.normal_world, arch.encoding)
    target = samples.radiance_lin.float() / scale
    train_idx = torch.nonzero(~is_held).squeeze(1)
    x_tr, y_tr, w_tr = inputs[train_idx].to(device), target[train_idx].to(device), samples.weight[train_idx].to(device)
    x_ho, y_ho, w_ho = inputs[is_held].to(device), target[is_held].to(device), samples.weight[is_held].to(device)

    optim = (torch.optim.AdamW(model.parameters(), lr=opts.learning_rate, weight_decay=opts.weight_decay) if opts.weight_decay > 0
             else torch.optim.Adam(model.parameters(), lr=opts.learning_rate))
    lr_at = lambda s: opts.learning_rate * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * s / opts.steps)))  # noqa: E731
    disc = d_optim = None
    adv_frames = [f for k, f in enumerate(frames_for_adversarial or []) if k not in held] or frames_for_adversarial
    if opts.adversarial:
        with torch.random.fork_rng(devices=[]):  # seeded, without touching the global RNG
            torch.manual_seed(opts.seed)
            disc = PatchDiscriminator().to(device)
        d_optim = torch.optim.Adam(disc.parameters(), lr=2e-4, betas=(0.5, 0.999))

    start, best_loss, best_step = 0, math.inf, 0
    best_weights = model.get_flat_weights()
    history: list[dict[str, float]] = []
    elapsed_before = 0.0
    ckpt = Path(checkpoint_path) if checkpoint_path else None
    say = log or _warn
    fp = fit_fingerprint(samples, opts, frames_for_adversarial, init_model, held, prior) if ckpt else ""
    if prior is not None:
        px, pt, pw = prior.inputs.to(device), prior.target.to(device), prior.weight.to(device)
        prior_batch = max(1, min(opts.batch_size // 4, px.shape[0]))
    if ckpt and ckpt.is_file():
        state = load_checkpoint(ckpt)
        if state.get(FINGERPRINT_KEY) != fp:
            set_aside_stale(ckpt, "other inputs (capture, options or damcap version differ)" if state
                            else "nothing readable", say)
        else:
            model.set_flat_weights(state["weights"].to(device))
            optim.load_state_dict(state["optim"])
            gen.set_state(state["generator"])
            start, best_loss, best_step = int(state["step"]), float(state["best_loss"]), int(state["best_step"])
            best_weights = state["best_weights"]
            history = json.loads(state["history"])
            elapsed_before = float(state["elapsed"])
            if disc is not None and "disc" in state:
                disc.load_state_dict(state["disc"])
                d_optim.load_state_dict(state["d_optim"])  # type: ignore[union-attr]
            if log:
                log(f"resuming {ckpt.name} at step {start} of {opts.steps}")
    resumed_from = start

    def snapshot() -> dict[str, Any]:
        """The training state after the last completed step (what a checkpoint holds)."""
        return {
            FINGERPRINT_KEY: fp, "damcap_package_version": package_version(), "options": _state_json(opts), "n_samples": len(samples),
            "step": completed, "weights": model.get_flat_weights().cpu(), "optim": optim.state_dict(),
            "generator": gen_after, "best_loss": best_loss, "best_step": best_step, "best_weights": best_weights,
            "history": json.dumps(history), "elapsed": elapsed_before + time.perf_counter() - t0,
            **({"disc": disc.state_dict(), "d_optim": d_optim.state_dict()} if disc is not None else {}),  # type: ignore[union-attr]
        }

    t0 = time.perf_counter()
    n_tr = x_tr.shape[0]
    if start == 0 and init_model is not None and prior is not None and x_ho.shape[0]:  # the prior itself is a candidate
        best_loss = _evaluate_cost(model, x_ho, y_ho, w_ho, arch, opts.quantile)
        history.append({"step": 0, "train_l1": _evaluate_cost(model, x_tr, y_tr, w_tr, arch, opts.quantile), "holdout_l1": best_loss,
                        "seconds": 0.0})
    # ``completed``/``gen_after``: the last step whose update and bookkeeping finished and the
    # generator state after it; ``mutating``: a step is changing weights, optimiser or records
    # (an interrupt there cannot be checkpointed exactly: the last periodic checkpoint stays).
    completed, gen_after, mutating, saved_step = start, gen.get_state(), False, start
    try:
        for step in range(start, opts.steps):
            for g in optim.param_groups:
                g["lr"] = lr_at(step)
            idx = torch.randint(0, n_tr, (min(opts.batch_size, n_tr),), generator=gen).to(device)
            with compute_precision(device, opts.precision):
                pred = dam_forward(model.weights_flat, x_tr[idx], arch)
                loss = weighted_quantile_cost(pred, y_tr[idx], w_tr[idx], opts.quantile)
            stats = {"loss": float(loss.detach())}
            if prior is not None and opts.prior_weight > 0:
                j = torch.randint(0, px.shape[0], (prior_batch,), generator=gen).to(device)
                with compute_precision(device, opts.precision):
                    prior_cost = (quantile_loss(dam_forward(model.weights_flat, px[j], arch), pt[j], 0.5) * pw[j]).mean()
                loss = loss + opts.prior_weight * prior_cost
                stats["prior"] = float(prior_cost.detach())
            if disc is not None:
                real, fake = _patches(model, adv_frames, arch, gen, device)  # type: ignore[arg-type]
                d_optim.zero_grad()  # type: ignore[union-attr]
                discriminator_loss(disc, real, fake).backward()
                mutating = True
                d_optim.step()  # type: ignore[union-attr]
                adv = generator_loss(disc, fake)
                loss = loss + opts.adversarial_alpha * adv
                stats["adv"] = float(adv.detach())
            optim.zero_grad()
            loss.backward()
            mutating = True
            optim.step()
            done = step + 1
            if done % opts.eval_every == 0 or done == opts.steps:
                ho = _evaluate_cost(model, x_ho, y_ho, w_ho, arch, opts.quantile) if x_ho.shape[0] else stats["loss"]
                record = {"step": done, "train_l1": stats["loss"], "holdout_l1": ho, "seconds": elapsed_before + time.perf_counter() - t0}
                history.append(record)
                if x_ho.shape[0] == 0 or ho < best_loss:
                    best_loss, best_step, best_weights = ho, done, model.get_flat_weights().cpu()
                stats["holdout"] = ho
            completed, gen_after, mutating = done, gen.get_state(), False
            if progress:
                progress(done, opts.steps, stats)
            if ckpt and opts.checkpoint_every and done % opts.checkpoint_every == 0 and done < opts.steps:
                save_checkpoint(ckpt, snapshot())
                saved_step = done
    except BaseException as e:  # Ctrl-C, SIGTERM or an error: keep the last completed step, then re-raise
        if ckpt and opts.checkpoint_every and not mutating and completed > saved_step:
            try:
                save_checkpoint(ckpt, snapshot())
                saved_step = completed
            except Exception as save_error:  # the original exception matters more; say why nothing new was kept
                e.add_note(f"{ckpt}: could not checkpoint the interrupted fit ({save_error.__class__.__name__}: {save_error})")
        kept = saved_step if ckpt is not None and saved_step > 0 and ckpt.is_file() else None
        e.add_note(interrupted_note(ckpt, completed, opts.steps, kept))
        raise
    final = DeepAppearanceMap(arch, scale, best_weights.cpu())
    if remove_checkpoint and ckpt and ckpt.is_file():
        ckpt.unlink()
    return FitResult(final, history, best_step, elapsed_before + time.perf_counter() - t0, resumed_from)


def training_l1(model: DeepAppearanceMap, samples: PixelSamples) -> float:
    """The fit's data cost over all samples: weighted mean L1 of radiance / the model's scale."""
    x = encode_inputs(samples.view_dir_world, samples.normal_world, model.arch.encoding)
    return _evaluate_cost(model, x, samples.radiance_lin.float() / model.radiance_scale, samples.weight, model.arch)


def refine_dam(model: DeepAppearanceMap, samples: PixelSamples, steps: int, learning_rate: float, seed: int = 0,
               progress: Callable[[int, int, dict[str, float]], None] | None = None) -> tuple[DeepAppearanceMap, float, float]:
    """K steps of the fit's cost starting from ``model`` (a learned initialisation), Adam from
    ``learning_rate`` cosine-decayed to 5 % of it (``damcap predict``'s rate:
    :attr:`.hyper.predict.PredictOptions.refine_learning_rate`).

    All samples train (no hold-out); the result is whichever of the start and the refined
    weights has the lower training cost, so refinement never makes it worse.

    Returns:
        (model, training L1 before, training L1 after).
    """
    before = training_l1(model, samples)
    if steps <= 0:
        return model, before, before
    opts = FitOptions(steps=steps, learning_rate=learning_rate, holdout_views=0, eval_every=steps, seed=seed,
                      checkpoint_every=0).for_architecture(model.arch)
    refined = fit_dam(samples, opts, init_model=model, progress=progress).model
    after = training_l1(refined, samples)
    return (refined, before, after) if after <= before else (model, before, before)


@torch.no_grad()
def _evaluate_cost(model: DeepAppearanceMap, x: torch.Tensor, y: torch.Tensor, w: torch.Tensor, arch: DamArchitecture,
                   quantile: float = 0.5, chunk: int = 1 << 16) -> float:
    """:func:`weighted_quantile_cost` of the model over many samples, in chunks (L1 at 0.5)."""
    total, wsum = 0.0, 0.0
    for s in range(0, x.shape[0], chunk):
        p = dam_forward(model.weights_flat, x[s:s + chunk], arch)
        total += float((quantile_loss(p, y[s:s + chunk], quantile) * w[s:s + chunk]).sum())
        wsum += float(w[s:s + chunk].sum())
    return total / max(wsum, 1e-12)


def _patches(model: DeepAppearanceMap, frames: list[TrainingFrame], arch: DamArchitecture, gen: torch.Generator, device: torch.device, n: int = 4, size: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """n random (real, re-synthesised) patch pairs, (n, 3, size, size) each, centred on foreground."""
    reals, fakes = [], []
    for _ in range(n):
        f = frames[int(torch.randint(0, len(frames), (1,), generator=gen))]
        fg = torch.nonzero(f.foreground)
        i, j = fg[int(torch.randint(0, fg.shape[0], (1,), generator=gen))].tolist()
        h, w = f.foreground.shape
        top = min(max(i - size // 2, 0), max(h - size, 0))
        left = min(max(j - size // 2, 0), max(w - size, 0))
        sl = (slice(top, top + size), slice(left, left + size))
        mask = f.foreground[sl].to(device)
        x = f.inputs[sl].to(device)
        pred = dam_forward(model.weights_flat, x.reshape(-1, x.shape[-1]), arch).reshape(*x.shape[:2], 3)
        fake = torch.where(mask[..., None], pred, torch.zeros_like(pred)).permute(2, 0, 1)
        real = f.radiance_norm[:, sl[0], sl[1]].to(device)
        ph, pw = real.shape[1:]
        pad = (0, size - pw, 0, size - ph)
        reals.append(torch.nn.functional.pad(real, pad))
        fakes.append(torch.nn.functional.pad(fake, pad))
    return torch.stack(reals), torch.stack(fakes)


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write a training state (tensors and plain values) atomically (through a Python file, so a
    full disk is an OSError naming ``path``, not torch's RuntimeError)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        try:
            torch.save(state, f)
        except RuntimeError as e:  # torch's zip writer turns the file's OSError into "unexpected pos"
            if isinstance(e.__context__, OSError):
                raise e.__context__ from None
            raise


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a training state (tensors only, nothing executed); {} with a warning if unreadable."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # a damaged checkpoint is not fatal: start afresh
        import warnings

        warnings.warn(f"{path}: ignoring unreadable checkpoint ({e.__class__.__name__})", stacklevel=2)
        return {}


def training_frames(views: list[ViewData], encoding: Encoding, radiance_scale: float) -> list[TrainingFrame]:
    """Whole frames for the adversarial cost."""
    out = []
    for v in views:
        fg = v.data.coverage > FOREGROUND_COVERAGE
        vd = torch.from_numpy(view_dir_world(v.data.position_world, v.centre_world))
        nd = torch.from_numpy(v.data.normal_world)
        x = torch.where(torch.from_numpy(fg)[..., None], encode_inputs(vd, nd, encoding), torch.zeros(()))
        rad = torch.from_numpy(np.where(fg[..., None], v.data.radiance_lin, 0) / radiance_scale).float().permute(2, 0, 1)
        out.append(TrainingFrame(rad, x, torch.from_numpy(fg)))
    return out


def adversarial_frames(views: list[ViewData], samples: PixelSamples, opts: FitOptions) -> list[TrainingFrame] | None:
    """The whole frames ``fit_dam`` needs for ``opts``' adversarial cost (None when it is off):
    :func:`training_frames` of ``views`` at the radiance scale of their pixels ``samples``."""
    if not opts.adversarial:
        return None
    return training_frames(views, opts.encoding, radiance_scale_of(samples.radiance_lin))
