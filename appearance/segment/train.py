"""Joint training of the n DAMs and Psi (Maximov et al. 2019, Sec. 3.4, Eq. 3):
c_d = mean_x sum_k W_k(x) |DAM_k(V(x), N(x)) - L(x)|, c_s = mean_x (1 - sum_k W_k(x)^2),
cost = c_d + beta c_s."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from damcap.common.device import resolve_device
from damcap.common.errors import DamcapError

from damcap.appearance.dam import DeepAppearanceMap, Encoding, dam_forward, encode_inputs, init_weights
from damcap.appearance.views import ViewData, radiance_scale_of
from damcap.appearance.pixels import FOREGROUND_COVERAGE, view_dir_world
from damcap.appearance.segment.cluster import initial_labels
from damcap.appearance.segment.model import SegmentationModel, SegmentationNet, psi_inputs, scene_bounds
from damcap.appearance.segment.options import SegmentOptions
from damcap.appearance.segment.prior import predict_material_priors, prior_cost


@dataclass
class _Frames:
    images: torch.Tensor  # (F, 9, H, W)
    fg_index: list[torch.Tensor]  # per frame: (P_f,) flat pixel indices of the foreground
    dam_inputs: list[torch.Tensor]  # per frame: (P_f, C)
    targets: list[torch.Tensor]  # per frame: (P_f, 3) radiance / scale


def _prepare(views: list[ViewData], encoding: Encoding, scale: float, centre: np.ndarray, radius: float) -> _Frames:
    images, fg_index, inputs, targets = [], [], [], []
    for v in views:
        d = v.data
        fg = d.coverage > FOREGROUND_COVERAGE
        images.append(psi_inputs(v, scale, centre, radius))
        fg_index.append(torch.from_numpy(np.flatnonzero(fg.reshape(-1))))
        vd = torch.from_numpy(view_dir_world(d.position_world[fg], v.centre_world))
        inputs.append(encode_inputs(vd, torch.from_numpy(np.ascontiguousarray(d.normal_world[fg])), encoding))
        targets.append(torch.from_numpy(np.ascontiguousarray(d.radiance_lin[fg])).float() / scale)
    return _Frames(torch.stack(images), fg_index, inputs, targets)


def segment_materials(views: list[ViewData], opts: SegmentOptions, progress: Callable[[int, int, dict[str, float]], None] | None = None,
                      log: Callable[[str], None] | None = None) -> SegmentationModel:
    """Train n DAMs and Psi jointly on training views (unsupervised).

    With ``opts.prior`` 'predictor', each material's DAM starts from, and is pulled towards, the
    shipped predictor's prediction for the pixels the initial clustering gave it (:mod:`.prior`);
    where the predictor cannot predict, the plain path runs and ``log`` says so in one line. With
    'auto', :func:`choose_prior` decides on an arc of held-out training views.

    Args:
        views: training views (colour, normals, positions).
        opts: options.
        progress: progress(step, total, stats) after every step.
        log: one-line messages (the prior's decisions and fallbacks; default: ``warnings.warn``).
    """
    opts.validate()
    if not views:
        raise DamcapError("segment needs at least one training view")
    if opts.frames_per_step > len(views):
        raise DamcapError(f"--frames-per-step must be at most the {len(views)} training views, got {opts.frames_per_step}")
    if opts.prior == "auto":
        return choose_prior(views, opts, progress, log)
    return _segment(views, opts, progress, log or _warn)


def choose_prior(views: list[ViewData], opts: SegmentOptions, progress: Callable[[int, int, dict[str, float]], None] | None = None,
                 log: Callable[[str], None] | None = None) -> SegmentationModel:
    """``--prior auto``: segment the training views but ``opts.prior_holdout_views`` held out (an
    arc of neighbouring cameras farthest from the others, :func:`.fit.holdout_arc`) without and
    with the predictor's prior, score both on the held-out views (mean DSSIM on the surface the
    other views saw, as ``--materials auto`` scores), then segment all views with the mode that
    scored lower. Without views to hold out (fewer than 3), the plain path.

    The result's ``prior_choice`` records both scores and the mode kept.
    """
    from damcap.appearance.fit import FitOptions, held_out
    from damcap.appearance.segment.score import novel_view_dssim

    say = log or _warn
    t0 = time.perf_counter()
    held = held_out(views, FitOptions(holdout_views=opts.prior_holdout_views))
    if not held:
        model = _segment(views, replace(opts, prior="off"), progress, say)
        model.prior_choice = {"mode": "auto", "kept": "off", "why": "no views to hold out"}
        return model
    rest = [v for k, v in enumerate(views) if k not in held]
    judges = [views[k] for k in held]
    sub = replace(opts, frames_per_step=min(opts.frames_per_step, len(rest)))
    plain = _segment(rest, replace(sub, prior="off"), progress, say)
    leaned = _segment(rest, replace(sub, prior="predictor"), progress, say)
    score = {"off": novel_view_dssim(plain, judges, seen_only=True)}
    if leaned.prior_choice.get("used"):
        score["predictor"] = novel_view_dssim(leaned, judges, seen_only=True)
        kept = "predictor" if score["predictor"] < score["off"] else "off"
        say(f"prior: {'the predictor' if kept == 'predictor' else 'none'} (held-out DSSIM {score['off']:.4f} without the "
            f"predictor's prior, {score['predictor']:.4f} with it, on {', '.join(v.name for v in judges)})")
    else:
        kept = "off"
    model = _segment(views, replace(opts, prior=kept), progress, say)
    model.prior_choice = {**model.prior_choice, "mode": "auto", "kept": kept, "held_out_dssim": score,
                          "held_out_views": [v.name for v in judges]}
    model.seconds = time.perf_counter() - t0
    return model


def _segment(views: list[ViewData], opts: SegmentOptions, progress: Callable[[int, int, dict[str, float]], None] | None,
             log: Callable[[str], None]) -> SegmentationModel:
    """:func:`segment_materials` with ``opts.prior`` 'off' or 'predictor' (validated by the caller)."""
    t0 = time.perf_counter()
    device = resolve_device(opts.device)
    arch = opts.architecture
    n = opts.materials
    gen = torch.Generator().manual_seed(opts.seed)
    scale = radiance_scale_of(torch.from_numpy(np.concatenate([v.data.radiance_lin[v.data.coverage > FOREGROUND_COVERAGE] for v in views])))
    centre, radius = scene_bounds(views)
    frames = _prepare(views, arch.encoding, scale, centre, radius)
    labels_np = initial_labels(views, scale, opts)
    init_labels = [torch.from_numpy(lab) for lab in labels_np]
    priors, prior_record = None, {"mode": opts.prior}
    if opts.prior == "predictor":
        try:
            priors = predict_material_priors(views, labels_np, n, scale, arch, opts.prior_samples, opts.prior_sigma, opts.seed,
                                             opts.device)
        except DamcapError as e:
            log(f"prior: none (the predictor could not predict each material from these views: {e})")
        prior_record["used"] = priors is not None

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(opts.seed)
        psi = SegmentationNet(n, channels=opts.psi_channels, resolution=opts.psi_resolution).to(device)
    start = [init_weights(arch, gen) for _ in range(n)]
    gain = None
    if priors is not None:
        predicted, gain = priors.start(arch, scale)
        start = [p if p is not None else w for p, w in zip(predicted, start)]
        prior_record.update(started_from_prediction=[p is not None for p in predicted], seconds=priors.seconds)
        gain = gain.to(device)
        priors = replace(priors, inputs=priors.inputs.to(device), target=priors.target.to(device), weight=priors.weight.to(device),
                         share=priors.share.to(device))
        prior_batch = max(1, min(opts.batch_pixels // 4, priors.inputs.shape[1]))
    dam_w = nn.Parameter(torch.stack(start).to(device))
    opt = torch.optim.Adam([{"params": [dam_w], "lr": opts.learning_rate}, {"params": psi.parameters(), "lr": opts.learning_rate / 5}])
    total = opts.init_steps + opts.steps
    history: list[dict[str, float]] = []
    images = frames.images.to(device)
    n_frames = images.shape[0]
    for step in range(total):
        joint = step >= opts.init_steps
        lr_scale = 1.0 if not joint else 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * (step - opts.init_steps) / max(opts.steps, 1)))
        opt.param_groups[0]["lr"] = opts.learning_rate * lr_scale
        opt.param_groups[1]["lr"] = opts.learning_rate / 5 * lr_scale
        fidx = torch.randperm(n_frames, generator=gen)[: opts.frames_per_step].tolist()
        logits = psi(images[fidx])  # (B, n, H, W)
        per = max(1, opts.batch_pixels // len(fidx))
        w_list, x_list, y_list, lab_list = [], [], [], []
        for b, f in enumerate(fidx):
            m = frames.fg_index[f].shape[0]
            if m == 0:
                continue
            pick = torch.randint(0, m, (min(per, m),), generator=gen)
            flat = logits[b].reshape(n, -1)[:, frames.fg_index[f][pick].to(device)].T  # (P, n)
            w_list.append(flat)
            x_list.append(frames.dam_inputs[f][pick])
            y_list.append(frames.targets[f][pick])
            lab_list.append(init_labels[f][pick])
        logit_px = torch.cat(w_list)
        x = torch.cat(x_list).to(device)
        y = torch.cat(y_list).to(device)
        pred = dam_forward(dam_w, x.expand(n, *x.shape), arch)  # (n, P, 3)
        if gain is not None:
            pred = pred * gain[:, None, None]
        l1 = (pred - y[None]).abs().mean(-1).T  # (P, n)
        lab = torch.cat(lab_list).to(device)
        known = lab >= 0
        ce = F.cross_entropy(logit_px[known], lab[known]) if known.any() else logit_px.sum() * 0
        if not joint:  # teach Psi the k-means labels; fit each DAM to its cluster
            onehot = F.one_hot(lab.clamp_min(0), n).float() * known[:, None]
            data = (onehot * l1).sum(1).sum() / known.sum().clamp_min(1)
            loss = data + ce
            stats = {"l1": float(data.detach()), "ce": float(ce.detach())}
        else:
            w = torch.softmax(logit_px, 1)
            data = (w * l1).sum(1).mean()
            sparsity = (1 - (w * w).sum(1)).mean()
            loss = data + opts.sparsity_beta * sparsity + opts.prior_weight * ce
            stats = {"l1": float(data.detach()), "sparsity": float(sparsity.detach()), "prior_ce": float(ce.detach())}
        if priors is not None and opts.prior_dam_weight > 0:
            j = torch.randint(0, priors.inputs.shape[1], (n, prior_batch), generator=gen).to(device)
            dam_prior = prior_cost(dam_w, gain, priors, j, arch)
            loss = loss + opts.prior_dam_weight * dam_prior
            stats["prior_dam"] = float(dam_prior.detach())
        opt.zero_grad()
        loss.backward()
        opt.step()
        if (step + 1) % 100 == 0 or step + 1 == total:
            history.append({"step": step + 1, **stats, "seconds": time.perf_counter() - t0})
        if progress:
            progress(step + 1, total, stats)

    psi = psi.cpu().eval()
    dams = [DeepAppearanceMap(arch, scale if gain is None else scale * float(gain[k]), dam_w.detach()[k].cpu()) for k in range(n)]
    model = SegmentationModel(dams, psi, scale, centre, radius, np.zeros((0, 3), np.float32), np.zeros((0, n), np.float32), history)
    model.prior_choice = prior_record
    pts, wts = [], []
    for v in views:
        fg = v.data.coverage > FOREGROUND_COVERAGE
        pts.append(v.data.position_world[fg])
        wts.append(model.weights_of(v)[fg])
    pts_a, wts_a = np.concatenate(pts), np.concatenate(wts)
    if len(pts_a) > 200_000:
        keep = np.random.default_rng(opts.seed).choice(len(pts_a), 200_000, replace=False)
        pts_a, wts_a = pts_a[keep], wts_a[keep]
    model.points_world, model.point_weights = pts_a.astype(np.float32), wts_a.astype(np.float32)
    model.seconds = time.perf_counter() - t0
    return model


def _warn(message: str) -> None:
    import warnings

    warnings.warn(message, stacklevel=3)
