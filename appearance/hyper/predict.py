"""After the forward pass of ``damcap predict``: how far the capture lies from what the predictor
learned, whether to refine, and refinement until held-out training views stop improving.

Distance from the training set: the predictor is trained to re-synthesise *every* view of a
capture from one of them (the L1 cost of :mod:`.train`). Its own re-synthesis error on the
capture's train views (the views it was given, whose radiance is known) is therefore the one
measure of fit that needs no ground truth: where the capture is like the training set, the
predicted DAM reproduces them; where it is not, it does not (:func:`resynthesis_error`).

``--refine-steps auto`` (:func:`refine_auto`) chooses the number of steps K, then takes them:
:func:`refine_until_holdout_stops` holds out the training views that the fit's stopping rule holds
out (:func:`.fit.holdout_frames`), refines the predicted DAM on the others and finds the step K of
the lowest held-out L1, stopping once it has not improved for ``patience_steps`` (or at
``max_steps``); then :func:`.fit.refine_dam` refines the prediction for K steps on *all* train
views, so ``--refine-steps auto`` gives what ``--refine-steps K`` gives. (Keeping the held-out
choice's own weights instead, trained without the held-out views, was worse on novel views on 7
of 13 measured captures and better on 4: mean DSSIM 0.129 against 0.122, bench/hyper_ood.md.)
Pure: tensors and views in, a model out.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from damcap.common.errors import DamcapError
from damcap.common.validate import COUNT, COUNT_OR_ZERO, MAX_COUNT, check_ranges, in_range

from damcap.appearance.dam import DeepAppearanceMap, dam_forward, encode_inputs
from damcap.appearance.evaluate import score_view
from damcap.appearance.fit import FitOptions, held_out, holdout_frames, refine_dam, training_l1, weighted_quantile_cost
from damcap.appearance.pixels import PixelSamples
from damcap.appearance.readout import ReadoutResult, solve_first_and_output_layers, solve_output_layer
from damcap.appearance.render import render_frame
from damcap.appearance.views import ViewData

AUTO = "auto"
RefineSteps = int | Literal["auto"]


def parse_refine_steps(text: str) -> RefineSteps:
    """``--refine-steps``: a count in [0, MAX_COUNT] or 'auto'.

    >>> parse_refine_steps("auto"), parse_refine_steps(" 30 ")
    ('auto', 30)

    Raises:
        DamcapError: anything else, in one line naming the option and the value as typed.
    """
    t = text.strip()
    if t.lower() == AUTO:
        return AUTO
    try:
        value = int(t)
    except ValueError:
        value = None
    if value is None or not 0 <= value <= MAX_COUNT:
        raise DamcapError(f"--refine-steps must be an integer in [0, {MAX_COUNT}] or 'auto', got {text!r}")
    return value


@dataclass(frozen=True)
class PredictOptions:
    """Options of ``damcap predict`` after the forward pass (the capture, the predictor, the input
    view and the device are the command's own)."""

    refine_steps: RefineSteps = field(default=0, metadata={"cli_parse": parse_refine_steps})
    """refinement steps after predicting: a number K (0 = none) or 'auto'. K = K steps of the fit's
    cost on all train views; 'auto' = choose K as the step where the views the fit's stopping rule
    holds out stop improving (refining on the other train views, at most --refine-max-steps), then
    take K steps on all train views"""
    refine_max_steps: int = field(default=1000, metadata={**COUNT, "cli_panel": "advanced"})
    """--refine-steps auto: most steps it may choose (it runs at most twice this many: choosing, then
    refining)"""
    refine_patience: int = field(default=100, metadata={**COUNT, "cli_panel": "advanced"})
    """--refine-steps auto: stop after this many steps without a lower held-out L1 (evaluated every
    25 steps)"""
    refine_learning_rate: float = field(default=1e-2, metadata=in_range(0, 10, lo_open=True))
    """Adam learning rate of the refinement: the initial rate of K steps (cosine-decayed to 5 % of
    it, as the fit's), and the constant rate at which --refine-steps auto chooses K. On 11
    captures unlike v1's training set (bench/hyper_ood.md, run refine, 2026-11-27),
    300 steps from v1 (about 2 s) reached a mean novel-view DSSIM of 0.106
    (x0.86 of the fit) at 1e-2 against 0.110 (x0.93) at 3e-3, the rate before 2026-11-27: better
    on 7 captures, worse on 3 (by 0.001 to 0.012). More, smaller steps did no better (900 steps of 1024 pixels, 3.4 s:
    x0.87; bench/hyper_ood.md)"""
    readout_iterations: int = field(default=3, metadata={**COUNT_OR_ZERO, "cli_panel": "advanced"})
    """without refinement (--refine-steps 0): solve the predicted DAM's output layer (its last 96
    weights; the hidden layers stay as predicted, until --joint-iterations moves the first) on the
    train views' pixels in closed form, at most this many reweighted Gauss-Newton iterations of the fit's L1 cost (appearance/readout.py;
    0 = the network's output as it is). On 11 captures unlike either shipped predictor's training
    set (bench/hyper_ood.md, run readout, 2026-11-27), 3 iterations lowered predict's mean novel-view
    DSSIM from 0.201 to 0.166 (x2.51 to x1.98 of the fit) with v1 and from 0.198 to 0.165 (x2.36
    to x2.05) with v3 (and to 0.146, x1.64, with v4, trained through the solve), prediction and
    solve together in 44-72 ms; 1 and 5 iterations helped less
    (x2.05-x2.11, x2.00-x2.06). v6 reached 0.132 (x1.45; bench/hyper_ood.md, run v5), v8 0.121 (x1.23;
    bench/hyper_ood.md, run v9), v10, the default since, 0.103 (x0.91; bench/hyper_ood.md, run v10).
    Refinement starts from the network's own output instead: on the same captures, 300 steps from
    the solved output layer ended worse with v1, v3 and v4 (x0.98 against x0.86, x0.98 against
    x0.89 in a side study; x0.86 against x0.80, bench/hyper_ood.md, run v5) and no better with v6
    (mean DSSIM 0.0976 against 0.0967)"""
    readout_samples: int = field(default=4096, metadata={**COUNT, "cli_panel": "advanced"})
    """the output layer is solved on a seeded random subset of at most this many train pixels.
    16384 gave the same novel-view DSSIM within 0.0015 on average (bench/hyper_ood.md, run readout) and
    took 22-55 ms more"""
    joint_iterations: int = field(default=5, metadata={**COUNT_OR_ZERO, "cli_panel": "advanced"})
    """without refinement, after the output layer's solve: solve the predicted DAM's first layer
    (192 weights, where its kinks lie: a shadow terminator, a highlight's edge) and output layer
    together on the train pixels, the middle layers (3072 weights) as predicted, at most this
    many Levenberg-Marquardt iterations of the fit's L1 cost plus --joint-prior
    (appearance/readout.py; 0 = the output layer's solve alone). On the 11 captures of
    bench/hyper_ood.md, run joint (2026-11-28), 5 iterations took v10's mean novel-view DSSIM from
    x0.91 to x0.64 of the fit (the sphere under one distant light from x2.44 to x1.25, the blobs
    under one from x1.18 to x0.43), prediction and both solves in 56-79 ms; 3 and 8 iterations
    gave the same mean (x0.64), 3 less on the distant-light kinds (x1.32, x0.51), 8 no better
    than 5 (bench/hyper_ood.md, *The joint solve*). With the light orientation from
    orientation.terminator_fit since: x0.59, every kind within 1.15x of the fit, in 57-71 ms
    (bench/hyper_ood.md, run terminator)"""
    joint_samples: int = field(default=2048, metadata={**COUNT, "cli_panel": "advanced"})
    """the joint solve uses a seeded random subset of at most this many train pixels"""
    joint_prior: float = field(default=1e-4, metadata=in_range(0, 1e3, cli_panel="advanced"))
    """the joint solve's pull toward the predicted weights: its cost is the L1 plus this times the
    squared distance of the solved weights from them (L1 units per squared weight). On the
    Mitsuba captures under a point light, which a DAM cannot explain (the light's fall-off, cast
    shadows), 0 moved the kinks to fit the train views and did worse on novel ones than the
    output layer's solve alone (spot x1.16 against x0.91); 1e-4 gave x1.07. 1e-3 did better
    there (x0.74) but held back the terminators of the closed-form distant-light captures (the
    sphere x1.36 against x1.25; bench/hyper_ood.md, run joint)"""
    refine_threshold: float = field(default=0.10, metadata=in_range(0, 1))
    """the predicted DAM's mean DSSIM on the train views above which predict says refinement is
    needed (the capture lies outside what the predictor learned). Measured with the shipped
    predictor on 13 captures (bench/hyper_ood.md): the one where refining lowered the
    novel-view DSSIM by under 5% had train DSSIM 0.084; the 12 where it lowered it by 18% or more
    had 0.105 to 0.324. One capture on the 'not needed' side: a first calibration"""

    def validate(self) -> None:
        """Raise DamcapError naming the first bad value."""
        check_ranges(self)
        if self.refine_steps != AUTO:
            if isinstance(self.refine_steps, bool) or not isinstance(self.refine_steps, int):
                raise DamcapError(f"--refine-steps must be an integer or 'auto', got {self.refine_steps!r}")
            parse_refine_steps(str(self.refine_steps))


@dataclass(frozen=True)
class SolvedPrediction:
    """What :func:`solve_prediction` did."""

    model: DeepAppearanceMap
    """the DAM after both solves"""
    readout: ReadoutResult | None
    """the output layer's solve (None when --readout-iterations is 0)"""
    readout_seconds: float
    joint: ReadoutResult | None
    """then the first and output layers' (None when --joint-iterations is 0)"""
    joint_seconds: float


def solve_prediction(model: DeepAppearanceMap, samples: PixelSamples, opts: PredictOptions) -> SolvedPrediction:
    """``damcap predict`` without refinement, after the forward pass: the output layer solved on
    the train pixels (:func:`.readout.solve_output_layer`, ``opts.readout_iterations`` and
    ``readout_samples``), then the first and output layers together
    (:func:`.readout.solve_first_and_output_layers`, ``opts.joint_iterations``, ``joint_samples``,
    ``joint_prior``); either is skipped at 0 iterations. Each is timed."""
    readout = joint = None
    t = time.perf_counter()
    if opts.readout_iterations:
        readout = solve_output_layer(model, samples, opts.readout_iterations, opts.readout_samples)
        model = readout.model
    t1 = time.perf_counter()
    if opts.joint_iterations:
        joint = solve_first_and_output_layers(model, samples, opts.joint_iterations, opts.joint_samples, opts.joint_prior)
        model = joint.model
    return SolvedPrediction(model, readout, t1 - t, joint, time.perf_counter() - t1)


@dataclass(frozen=True)
class Resynthesis:
    """How well a DAM re-synthesises the views it came from."""

    dssim: float
    """mean DSSIM over the views (frames without foreground skipped; NaN if none has one)"""
    l1: float
    """the fit's data cost (:func:`.fit.training_l1`): weighted mean L1 of radiance divided by the
    model's radiance scale"""
    views: int
    """views scored"""


def resynthesis_error(model: DeepAppearanceMap, views: list[ViewData], samples: PixelSamples) -> Resynthesis:
    """The DAM's error on views whose radiance is known (for a predicted DAM: its train views).

    Args:
        model: the DAM.
        views: the views (each rendered with :func:`.render.render_frame`, scored with
            :func:`.metrics.dssim`).
        samples: their covered pixels (:func:`.views.samples_of`), for the L1.
    """
    scores = [s for v in views if (s := score_view(v, render_frame(model, v.data, v.centre_world))) is not None]
    return Resynthesis(float(np.mean(scores)) if scores else math.nan, training_l1(model, samples), len(views))


def refinement_needed(train_dssim: float, threshold: float) -> bool:
    """Refine when the predicted DAM's train-view DSSIM is above ``threshold`` (NaN: cannot tell,
    refine).

    >>> refinement_needed(0.12, 0.05), refinement_needed(0.03, 0.05), refinement_needed(float("nan"), 0.05)
    (True, False, True)
    """
    return not train_dssim <= threshold


def resynthesis_line(err: Resynthesis, threshold: float) -> str:
    """The one line predict prints about its re-synthesis error and what it means.

    >>> resynthesis_line(Resynthesis(0.0312, 0.0456, 10), 0.05)
    're-synthesis of the 10 train views: DSSIM 0.0312, L1 0.0456; within --refine-threshold 0.05: the prediction can be used as it is'
    """
    head = f"re-synthesis of the {err.views} train views: DSSIM {err.dssim:.4f}, L1 {err.l1:.4f}; "
    if refinement_needed(err.dssim, threshold):
        return head + (f"above --refine-threshold {threshold:g}: this capture is unlike the predictor's training set; "
                       f"--refine-steps auto refines only while an arc of held-out train views improves")
    return head + f"within --refine-threshold {threshold:g}: the prediction can be used as it is"


@dataclass
class AutoRefineResult:
    """What :func:`refine_until_holdout_stops` did."""

    model: DeepAppearanceMap
    """the weights with the lowest held-out L1 (the start when no step improved it), trained
    without the held-out views"""
    steps_used: int
    """the chosen number of steps K: the step of those weights (0 = the prediction as it was)"""
    steps_run: int
    """steps taken before stopping"""
    held_out: list[int]
    """the held-out views (positions in the train split)"""
    curve: list[dict[str, float]]
    """held-out L1 at step 0 and every evaluation: {"step", "holdout_l1"}"""
    stopped_by: Literal["patience", "max_steps"] = "patience"
    """why it stopped: the held-out L1 stopped falling, or the step cap came first"""


def refine_until_holdout_stops(model: DeepAppearanceMap, samples: PixelSamples, *, max_steps: int, patience_steps: int,
                               eval_every: int = 25, holdout_views: int = FitOptions.holdout_views,
                               learning_rate: float = PredictOptions.refine_learning_rate, batch_size: int = FitOptions.batch_size,
                               seed: int = 0, progress: Callable[[int, int, dict[str, float]], None] | None = None,
                               held: list[int] | None = None) -> AutoRefineResult:
    """Refine a (predicted) DAM until its held-out training views stop improving.

    The views the fit's stopping rule holds out (``held``: :func:`.fit.held_out` of the train
    views, an arc of cameras; None: :func:`.fit.holdout_frames`) are scored, every
    ``eval_every`` steps, by the fit's data cost (L1, :func:`.fit.training_l1`); the others train
    (Adam at a constant ``learning_rate``, ``batch_size`` random pixels a step, seeded). Training
    stops at ``max_steps`` or once ``patience_steps`` have passed since the held-out L1 last fell;
    the weights of its lowest value are kept.

    Args:
        model: the starting DAM (not modified); its radiance scale is kept.
        samples: covered pixels of the train views (frame_index = position in the split).
        max_steps: most steps; patience_steps: steps without improvement before stopping.

    Raises:
        DamcapError: fewer than 3 train views (nothing can be held out: use a fixed step count).
    """
    if max_steps < 1 or patience_steps < 1 or eval_every < 1:
        raise DamcapError(f"max_steps, patience_steps and eval_every must be >= 1, got {max_steps}, {patience_steps}, {eval_every}")
    n_frames = int(samples.frame_index.max()) + 1 if len(samples) else 0
    held = holdout_frames(n_frames, holdout_views) if held is None else sorted(held)
    if not held:
        raise DamcapError(f"--refine-steps auto holds training views out to know when to stop, and {n_frames} train view(s) "
                          f"leave none to hold out (it needs 3); give a number of steps instead")
    is_held = torch.isin(samples.frame_index, torch.tensor(held))
    fit_part, held_part = samples.subset(~is_held), samples.subset(is_held)
    if len(fit_part) == 0 or len(held_part) == 0:
        raise DamcapError("--refine-steps auto: the held-out or the remaining train views have no covered pixels; give a number of steps")
    arch = model.arch
    work = DeepAppearanceMap(arch, model.radiance_scale, model.get_flat_weights().cpu())
    x = encode_inputs(fit_part.view_dir_world, fit_part.normal_world, arch.encoding)
    y = fit_part.radiance_lin.float() / work.radiance_scale
    w = fit_part.weight
    gen = torch.Generator().manual_seed(seed)
    optim = torch.optim.Adam(work.parameters(), lr=learning_rate)
    best_l1 = training_l1(work, held_part)
    best_step, best_weights = 0, work.get_flat_weights()
    curve = [{"step": 0, "holdout_l1": best_l1}]
    step = 0
    n = x.shape[0]
    while step < max_steps and step - best_step < patience_steps:
        idx = torch.randint(0, n, (min(batch_size, n),), generator=gen)
        loss = weighted_quantile_cost(dam_forward(work.weights_flat, x[idx], arch), y[idx], w[idx])
        optim.zero_grad()
        loss.backward()
        optim.step()
        step += 1
        stats = {"loss": float(loss.detach())}
        if step % eval_every == 0 or step == max_steps:
            ho = training_l1(work, held_part)
            curve.append({"step": step, "holdout_l1": ho})
            stats["holdout"] = ho
            if ho < best_l1:
                best_l1, best_step, best_weights = ho, step, work.get_flat_weights()
        if progress:
            progress(step, max_steps, stats)
    if progress and step < max_steps:
        progress(step, step, {"holdout": best_l1})  # stopped early: the bar is complete
    out = DeepAppearanceMap(arch, model.radiance_scale, best_weights)
    stopped_by = "patience" if step - best_step >= patience_steps else "max_steps"
    return AutoRefineResult(out, best_step, step, held, curve, stopped_by)


def refine_auto(model: DeepAppearanceMap, samples: PixelSamples, *, max_steps: int, patience_steps: int,
                learning_rate: float = PredictOptions.refine_learning_rate,
                choose_progress: Callable[[int, int, dict[str, float]], None] | None = None,
                refine_progress: Callable[[int, int], Callable[[int, int, dict[str, float]], None]] | None = None,
                held: list[int] | None = None) -> tuple[DeepAppearanceMap, AutoRefineResult]:
    """``--refine-steps auto``: choose K with :func:`refine_until_holdout_stops`, then refine the
    start for K steps on all samples with :func:`.fit.refine_dam` (nothing when K = 0), both at
    ``learning_rate``.

    Args:
        choose_progress: progress of the choice; refine_progress: ``refine_progress(K)`` makes
            the progress callback of the K refinement steps.

    Returns:
        (the refined model, the choice: K = ``steps_used``).
    """
    chosen = refine_until_holdout_stops(model, samples, max_steps=max_steps, patience_steps=patience_steps,
                                        learning_rate=learning_rate, progress=choose_progress, held=held)
    if chosen.steps_used == 0:
        return model, chosen
    refined, _, _ = refine_dam(model, samples, chosen.steps_used, learning_rate,
                               progress=refine_progress(chosen.steps_used) if refine_progress else None)
    return refined, chosen


# --------------------------------------------------------------------------------------------
# A capture in, a predicted DAM out (what ``damcap predict`` runs)
# --------------------------------------------------------------------------------------------

BarFactory = Callable[[str, int], Callable[[int, int, dict], None]]
"""``(description, total) -> progress(step, steps, stats)``: one progress bar per loop"""


@dataclass(frozen=True)
class ForwardPass:
    """The predictor's forward pass on a capture's views (:func:`forward_pass`)."""

    model: DeepAppearanceMap
    input_views: list[int]
    """indices (into the views given) of the views the predictor read; the first is the chosen one"""
    light_fit: object
    """a light-orientation predictor's terminator fit (:func:`.orientation.terminator_fit`), else None"""
    seconds: float


def forward_pass(net, views: list[ViewData], view: str | None = None) -> ForwardPass:
    """The predictor ``net``'s DAM from ``views`` (its input views chosen among them; ``view``: the
    first one's name, else the best covered lit one), in its light orientation for a
    light-orientation predictor, before any solve.

    Raises:
        DamcapError: too few views with foreground, or ``view`` not among them.
    """
    from damcap.appearance.hyper.model import input_images, predict_from_images, predictor_inputs
    from damcap.appearance.hyper.orientation import rotation_to_up, terminator_fit

    ks, crops, capture_scale = predictor_inputs(views, net.arch.input_views, view)
    t0 = time.perf_counter()
    images, scale = input_images(crops, net.arch.input_size, capture_scale)
    # a light-orientation predictor: its rotation (orientation.light_rotation) is fitted once, for the network and the record
    light_fit = terminator_fit(images[None]) if net.arch.orientation == "light" else None
    model = predict_from_images(net, images, scale, None if light_fit is None else rotation_to_up(light_fit)[0])
    return ForwardPass(model, list(ks), light_fit, time.perf_counter() - t0)


def predict_views(views: list[ViewData], opts: PredictOptions = PredictOptions(), predictor_path=None, device: str = "cpu") -> DeepAppearanceMap:
    """``damcap predict``'s DAM from ``views`` without refinement: the default predictor's
    forward pass, then its solves on the views' pixels (:func:`solve_prediction`).

    Raises:
        DamcapError: an unreadable predictor; too few views with foreground.
    """
    from damcap.appearance.hyper.file import load_predictor, predictor_path as resolve_predictor
    from damcap.appearance.views import samples_of
    from damcap.common.device import resolve_device

    net, _ = load_predictor(resolve_predictor(predictor_path))
    net.to(resolve_device(device))
    model = forward_pass(net, views).model
    return solve_prediction(model, samples_of(views), opts).model


@dataclass
class PredictResult:
    """What :func:`predict_capture` made: the DAM, what to tell the user, and the record to save."""

    model: DeepAppearanceMap
    advice: str
    """the re-synthesis line of the prediction itself (:func:`resynthesis_line`): how well it
    re-synthesises the train views and whether refining is advised"""
    summary: str
    """what was done after the forward pass (solves, refinement) and what it changed, e.g.
    ``" + 12 ms solving its output layer ...: train DSSIM 0.1 -> 0.05, ..."``; "" for none"""
    record: dict
    """the provenance record to save with the model (``save_dam(provenance=...)``)"""
    input_frames: list
    """the capture's :class:`~damcap.common.capture_folder.Frame` s the predictor read (the first is ``--view``)"""
    predict_seconds: float
    """the forward pass (and the light orientation's fit), seconds"""
    capture: object
    """the :class:`~damcap.common.capture_folder.Capture` (its colorspace and up direction go with the model)"""
    normal_histogram: object
    """:func:`.coverage.training_normal_histogram` of the train pixels (saved with the model)"""


def predict_capture(capture, opts: PredictOptions = PredictOptions(), predictor_path=None, *, view: str | None = None,
                    device: str = "cpu", progress: BarFactory | None = None,
                    log: Callable[[str], None] | None = None) -> PredictResult:
    """Predict a DAM from a capture's train views (``damcap predict`` without the command line):
    the forward pass (in its light orientation for a light-orientation predictor), then predict's solves of
    the output layer and of the first and output layers together, or ``opts.refine_steps`` of
    refinement (``'auto'``: :func:`refine_auto`).

    Args:
        capture: a capture folder (path) or a :class:`~damcap.common.capture_folder.Capture`.
        opts: :class:`PredictOptions` (validated here).
        predictor_path: a predictor file, a shipped predictor's name, or None: the default
            (:data:`.file.DEFAULT_SHIPPED`).
        view: the (first) input frame, a train-split file_path or its stem; None: the best
            covered lit one.
        device: torch device of the predictor ('cpu', 'cuda', 'auto').
        progress: a progress bar per refinement loop (:data:`BarFactory`); None: none.
        log: called with the re-synthesis line (:attr:`PredictResult.advice`) as soon as it is
            known, before any solve or refinement.

    Raises:
        DamcapError: a bad option, predictor or capture, or a view that is not in the train split.
    """
    from pathlib import Path

    from damcap.appearance.coverage import training_normal_histogram
    from damcap.appearance.hyper.file import load_predictor, predictor_path as resolve_predictor
    from damcap.appearance.hyper.orientation import unit_direction
    from damcap.appearance.views import load_views, samples_of
    from damcap.common.capture_folder import Capture, read_capture
    from damcap.common.device import resolve_device
    from damcap.common.version import package_version
    from dataclasses import asdict

    opts.validate()
    bar = progress or (lambda desc, total: None)
    pred_path = resolve_predictor(predictor_path)
    net, meta = load_predictor(pred_path)
    net.to(resolve_device(device))
    cap = capture if isinstance(capture, Capture) else read_capture(capture)
    train_views = load_views(cap, "train")
    try:
        forward = forward_pass(net, train_views, None if view is None else Path(view).stem)
    except DamcapError as e:
        raise DamcapError(f"{cap.root}: {e}") from None
    model, light_fit, predict_s = forward.model, forward.light_fit, forward.seconds
    frames = [cap.split("train")[k] for k in forward.input_views]
    samples = samples_of(train_views)
    err = resynthesis_error(model, train_views, samples)
    advice = resynthesis_line(err, opts.refine_threshold)
    if log is not None:
        log(advice)
    # where the light orientation put the light: a diagnosis of a poor prediction (orientation.light_up_world)
    light_record = {} if light_fit is None else {"light_up_world": [float(x) for x in unit_direction(light_fit)[0]]}
    record = {"damcap_package_version": package_version(), "capture": str(Path(cap.root).resolve()), "predictor": str(Path(pred_path).resolve()),
              "predictor_command": meta.get("training", {}).get("command"), "view": frames[0].file_path,
              "input_views": [f.file_path for f in frames],
              "predict_seconds": predict_s, "options": asdict(opts), "refine_steps": opts.refine_steps,
              "train_views": err.views, "train_dssim_predicted": err.dssim, "train_l1_predicted": err.l1,
              "refine_threshold": opts.refine_threshold, "refinement_needed": refinement_needed(err.dssim, opts.refine_threshold),
              **light_record}
    summary = ""
    if not opts.refine_steps and (opts.readout_iterations or opts.joint_iterations):
        solved = solve_prediction(model, samples, opts)
        model, parts = solved.model, []
        if solved.readout is not None:
            after = resynthesis_error(solved.readout.model, train_views, samples)
            record.update(readout_seconds=solved.readout_seconds, readout_iterations_used=solved.readout.iterations,
                          train_dssim_readout=after.dssim, train_l1_readout=after.l1)
            parts.append(f"{1000 * solved.readout_seconds:.0f} ms solving its output layer on {min(len(samples), opts.readout_samples)} "
                         f"train pixels ({solved.readout.iterations} iterations)")
        if solved.joint is not None:
            after = resynthesis_error(model, train_views, samples)
            record.update(joint_seconds=solved.joint_seconds, joint_iterations_used=solved.joint.iterations,
                          train_dssim_joint=after.dssim, train_l1_joint=after.l1)
            parts.append(f"{1000 * solved.joint_seconds:.0f} ms solving its first and output layers together on "
                         f"{min(len(samples), opts.joint_samples)} ({solved.joint.iterations} iterations)")
        summary = " + " + " + ".join(parts) + f": train DSSIM {err.dssim:.4f} -> {after.dssim:.4f}, L1 {err.l1:.4f} -> {after.l1:.4f}"
    if opts.refine_steps == AUTO:
        t1 = time.perf_counter()
        model, auto = refine_auto(model, samples, max_steps=opts.refine_max_steps, patience_steps=opts.refine_patience,
                                  learning_rate=opts.refine_learning_rate,
                                  choose_progress=bar("choose refine steps", opts.refine_max_steps),
                                  refine_progress=lambda n: bar("refine", n), held=held_out(train_views, FitOptions()))
        record.update(refine_seconds=time.perf_counter() - t1, refine_steps_used=auto.steps_used, refine_steps_run=auto.steps_run,
                      refine_stopped_by=auto.stopped_by, refine_held_out_views=[train_views[i].name for i in auto.held_out],
                      refine_holdout_curve=auto.curve)
        why = ("held-out views stopped improving" if auto.stopped_by == "patience"
               else f"held-out views still improving at --refine-max-steps {opts.refine_max_steps}")
        summary = f", refined {auto.steps_used} steps (auto: {why}; {auto.steps_run} tried)"
    elif opts.refine_steps:
        t1 = time.perf_counter()
        model, _, _ = refine_dam(model, samples, opts.refine_steps, opts.refine_learning_rate, progress=bar("refine", opts.refine_steps))
        record.update(refine_seconds=time.perf_counter() - t1, refine_steps_used=opts.refine_steps)
        summary = f", refined {opts.refine_steps} steps"
    if opts.refine_steps:
        after = resynthesis_error(model, train_views, samples)
        record.update(train_dssim_refined=after.dssim, train_l1_refined=after.l1)
        summary += f": train DSSIM {err.dssim:.4f} -> {after.dssim:.4f}, L1 {err.l1:.4f} -> {after.l1:.4f}"
    return PredictResult(model=model, advice=advice, summary=summary, record=record, input_frames=frames, predict_seconds=predict_s,
                         capture=cap, normal_histogram=training_normal_histogram(samples))
