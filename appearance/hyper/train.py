"""Training the predictor (``damcap train-hyper``): data, the loop, checkpoints, data-parallel.

Cost (the paper's, Sec. 3.3): the L1 re-synthesis error of the predicted DAM over the capture's
pixels. Each step draws ``batch_size`` (capture, input view) pairs, augments them exactly
(:func:`.hyper.predictor_image`: rotation about +y, mirror, tinted light), predicts the weights
from the view and scores them on ``pixels`` random covered pixels of *all* the capture's views.

Data-parallel: launched with ``torchrun --nproc-per-node N``, every process (rank) draws its own
share of the batch and PyTorch's DistributedDataParallel averages the gradients (gloo on CPU,
nccl on GPU), so all ranks hold identical weights; rank 0 validates, checkpoints and writes. The
random draws of a step depend only on (seed, rank, step), so a resumed run continues exactly.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.distributed as dist

from damcap.common.capture_folder import read_capture, read_frame
from damcap.common.device import resolve_device
from damcap.common.corpus_index import finished_captures
from damcap.common.errors import DamcapError
from damcap.common.validate import COUNT, COUNT_OR_ZERO, MAX_BATCH_PIXELS, MAX_CHANNELS, MAX_IMAGE_SIDE, SEED, check_ranges, in_range

from damcap.appearance.dam import DamArchitecture, Encoding
from damcap.common.fingerprint import FINGERPRINT_KEY, fingerprint
from damcap.common.version import damcap_version

from damcap.appearance.fit import load_checkpoint, save_checkpoint, set_aside_stale
from damcap.appearance.views import radiance_scale_of
from damcap.appearance.hyper.model import HyperArchitecture, HyperNet, predicted_loss, predictor_image, rotation_y, view_crop
from damcap.appearance.pixels import FOREGROUND_COVERAGE, view_dir_world


@dataclass(frozen=True)
class HyperTrainOptions:
    """Options of ``damcap train-hyper`` (each knob that trades speed for accuracy is here)."""

    steps: int = field(default=3000, metadata=COUNT)
    """optimiser steps (Adam)"""
    batch_size: int = field(default=8, metadata=in_range(1, 65536))
    """(capture, view) pairs per step, over all ranks together"""
    pixels: int = field(default=4096, metadata=in_range(1, MAX_BATCH_PIXELS))
    """pixels per capture and step scored by the L1 cost"""
    learning_rate: float = field(default=5e-4, metadata=in_range(0, 10, lo_open=True))
    """initial Adam learning rate; cosine-decayed to 5% of it"""
    input_size: int = field(default=256, metadata=in_range(1, MAX_IMAGE_SIDE))
    """side of the predictor's input image, pixels"""
    channels: tuple[int, ...] = field(default=(16, 32, 64, 64, 128, 128, 256, 256), metadata=in_range(1, MAX_CHANNELS))
    """convolution channels (one stride-2 layer each)"""
    encoding: Encoding = "nr"
    """input encoding of the predicted DAM (32 x 4, no biases)"""
    augment: bool = True
    """exact augmentations: rotation about +y, mirror, tinted light"""
    max_captures: int = field(default=0, metadata=COUNT_OR_ZERO)
    """use at most this many training captures (0 = all): the training-set-size knob"""
    val_fraction: float = field(default=0.1, metadata=in_range(0, 1, hi_open=True))
    """training captures kept out for the validation curve and the stopping rule"""
    eval_every: int = field(default=100, metadata=COUNT)
    """steps between validations"""
    pixels_per_capture: int = field(default=32768, metadata=in_range(1, MAX_BATCH_PIXELS))
    """covered pixels kept in memory per capture (spread over all its views)"""
    seed: int = field(default=0, metadata=SEED)
    """seeds initialisation and every random draw"""
    device: str = "cpu"
    """'cpu', 'cuda' or 'auto' (under torchrun each rank uses its LOCAL_RANK GPU)"""
    checkpoint_every: int = field(default=100, metadata=COUNT_OR_ZERO)
    """steps between checkpoints (0 = never)"""
    grad_clip: float = field(default=1.0, metadata=in_range(0, 1e6))
    """largest gradient norm of a step (0 = no clipping): a hypernetwork's output weights
    multiply through the DAM's layers, so one bad batch can otherwise throw it far off"""

    def validate(self) -> None:
        """Raise DamcapError naming the first value outside its range."""
        check_ranges(self)
        self.architecture  # channels and input size within HyperArchitecture's bounds (named in its error)

    @property
    def architecture(self) -> HyperArchitecture:
        return HyperArchitecture(self.input_size, tuple(self.channels), DamArchitecture(encoding=self.encoding))


@dataclass
class HyperCapture:
    """One training capture in memory."""

    name: str
    crops: list[torch.Tensor]
    """per lit view, (10, s, s) float16 :func:`.hyper.view_crop`"""
    radiance_scale: float
    """pooled radiance scale of all the capture's views (what the targets are divided by)"""
    view_dir_world: torch.Tensor
    """(M, 3) float32, covered pixels of all views"""
    normal_world: torch.Tensor
    """(M, 3) float32"""
    radiance_lin: torch.Tensor
    """(M, 3) float32"""

    @property
    def best_view(self) -> int:
        """Index of the best-covered view (the fixed validation input)."""
        return int(np.argmax([float(c[9].float().sum()) for c in self.crops]))


@dataclass
class HyperTrainResult:
    net: HyperNet
    curve: list[dict[str, float]] = field(default_factory=list)
    best_step: int = 0
    seconds: float = 0.0
    resumed_from: int = 0
    world_size: int = 1
    rank_weight_sha256: list[str] = field(default_factory=list)
    train_captures: list[str] = field(default_factory=list)
    val_captures: list[str] = field(default_factory=list)


MIN_INPUT_BRIGHTNESS = 0.1
"""an input view whose radiance scale is below this fraction of its capture's pooled scale sees
mostly unlit surface (a point light behind the object): its radiance carries little about the
material and dividing the other views by its scale blows the cost up (measured: scale ratios up
to 1e6 in the hyper corpus, which made training diverge). Such views are not drawn as inputs."""


def load_hyper_capture(path: str | os.PathLike, pixels: int, seed: int = 0) -> HyperCapture:
    """Read every frame of a capture folder into a :class:`HyperCapture` (``pixels`` random covered
    pixels kept, drawn with ``seed``; input views as :data:`MIN_INPUT_BRIGHTNESS` says)."""
    cap = read_capture(path)
    crops, scales, vs, ns, cs = [], [], [], [], []
    for f in cap.frames:
        d = read_frame(cap, f, with_weights=False)
        vd = view_dir_world(d.position_world, f.camera_centre_world)
        fg = d.coverage > FOREGROUND_COVERAGE
        if not fg.any():
            continue
        crops.append(view_crop(d.radiance_lin, d.normal_world, vd, d.coverage).half())
        scales.append(radiance_scale_of(torch.from_numpy(d.radiance_lin[fg])))
        vs.append(vd[fg])
        ns.append(d.normal_world[fg])
        cs.append(d.radiance_lin[fg])
    if not crops:
        raise DamcapError(f"{path}: no frame has covered pixels")
    v, n, c = (np.concatenate(x).astype(np.float32) for x in (vs, ns, cs))
    pooled = radiance_scale_of(torch.from_numpy(c))
    lit = [k for k, sc in enumerate(scales) if sc >= MIN_INPUT_BRIGHTNESS * pooled] or [int(np.argmax(scales))]
    crops = [crops[k] for k in lit]
    keep = np.random.default_rng(seed).permutation(len(v))[:pixels]
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a[keep]))  # noqa: E731
    return HyperCapture(Path(path).name, crops, pooled, t(v), t(n), t(c))


def corpus_training_captures(corpus: str | os.PathLike) -> list[Path]:
    """The finished ``train``-split captures of a ``damcap synth-set`` corpus, in corpus order.

    Raises:
        DamcapError: no corpus.json, or no finished training capture.
    """
    corpus = Path(corpus)
    paths = [path for path, _ in finished_captures(corpus, "train", reader="train-hyper")]
    if not paths:
        raise DamcapError(f"{corpus}: no finished training capture yet (render some with `damcap synth-set {corpus} ...`)")
    return paths


def split_validation(paths: list[Path], fraction: float) -> tuple[list[Path], list[Path]]:
    """(train, validation): every round(1/fraction)-th capture validates (none when fraction is 0
    or there are fewer than 2 captures).

    >>> [len(x) for x in split_validation([Path(str(k)) for k in range(20)], 0.1)]
    [18, 2]
    """
    if fraction <= 0 or len(paths) < 2:
        return paths, []
    k = max(2, round(1 / fraction))
    val = paths[k - 1::k] or paths[-1:]
    return [p for p in paths if p not in val], val


def _step_generator(seed: int, rank: int, step: int) -> torch.Generator:
    return torch.Generator().manual_seed((seed * 1_000_003 + rank * 7_919 + step) % (2**63))


def draw_batch(captures: list[HyperCapture], n: int, opts: HyperTrainOptions, gen: torch.Generator
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """n augmented (image, view_dir, normal, radiance / scale) training examples.

    Returns:
        (n, 9, S, S) images; (n, K, 3) view directions, normals and normalised radiance.
    """
    imgs, vs, ns, ys = [], [], [], []
    for _ in range(n):
        c = captures[int(torch.randint(len(captures), (1,), generator=gen))]
        crop = c.crops[int(torch.randint(len(c.crops), (1,), generator=gen))].float()
        rot, mirror, gain = None, False, None
        if opts.augment:
            rot = rotation_y(float(torch.rand((), generator=gen)) * 2 * math.pi)
            mirror = bool(torch.rand((), generator=gen) < 0.5)
            gain = torch.exp((torch.rand(3, generator=gen) - 0.5))
        scale = c.radiance_scale * (float(gain.mean()) if gain is not None else 1.0)
        img, scale = predictor_image(crop, opts.input_size, rot, mirror, gain, radiance_scale=scale)
        idx = torch.randint(c.radiance_lin.shape[0], (opts.pixels,), generator=gen)
        v, nn_, y = c.view_dir_world[idx], c.normal_world[idx], c.radiance_lin[idx]
        if mirror:
            flip = torch.tensor([-1.0, 1.0, 1.0])
            v, nn_ = v * flip, nn_ * flip
        if rot is not None:
            v, nn_ = v @ rot.T, nn_ @ rot.T
        if gain is not None:
            y = y * gain
        imgs.append(img)
        vs.append(v)
        ns.append(nn_)
        ys.append(y / scale)
    return torch.stack(imgs), torch.stack(vs), torch.stack(ns), torch.stack(ys)


@torch.no_grad()
def validation_l1(net: HyperNet, captures: list[HyperCapture], pixels: int = 8192) -> float:
    """Mean L1 (radiance / capture scale) of predictions from each capture's best-covered view, without
    augmentation, over its first ``pixels`` kept pixels."""
    if not captures:
        return float("nan")
    was_training = net.training
    net.eval()
    device = next(net.parameters()).device
    total = 0.0
    for c in captures:
        img, scale = predictor_image(c.crops[c.best_view].float(), net.arch.input_size, radiance_scale=c.radiance_scale)
        w = net(img[None].to(device))
        k = slice(0, pixels)
        loss = predicted_loss(w, c.view_dir_world[None, k].to(device), c.normal_world[None, k].to(device),
                              (c.radiance_lin[None, k] / scale).to(device), net.arch.dam)
        total += float(loss)
    net.train(was_training)
    return total / len(captures)


def weights_sha256(net: torch.nn.Module) -> str:
    """Digest of a network's parameters (bitwise: equal digests = identical weights)."""
    h = hashlib.sha256()
    for k, v in sorted(net.state_dict().items()):
        h.update(k.encode())
        h.update(v.detach().float().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _distributed(device_kind: str) -> tuple[int, int, int]:
    """(rank, world size, local rank); initialises the process group under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1, 0
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device_kind == "cuda" else "gloo")
    return dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0"))


def _options_json(opts: HyperTrainOptions, names: list[str]) -> str:
    d = asdict(opts)
    d.pop("device")
    d["channels"] = list(opts.channels)
    return json.dumps({"options": d, "captures": names}, sort_keys=True)


def hyper_fingerprint(state_key: str, train: list[HyperCapture], val: list[HyperCapture]) -> str:
    """What a training run's result depends on: its options and capture names (``state_key``),
    every tensor of the loaded training and validation captures (bit for bit) and the damcap
    version. A ``.state`` checkpoint is resumed only by a run with the same fingerprint."""
    parts: list[Any] = ["train-hyper", damcap_version(), state_key]
    for c in [*train, *val]:
        parts += [c.name, float(c.radiance_scale), c.view_dir_world, c.normal_world, c.radiance_lin, *c.crops]
    return fingerprint(*parts)


def train_hyper(
    capture_paths: list[Path],
    opts: HyperTrainOptions,
    *,
    checkpoint_path: str | os.PathLike | None = None,
    progress: Callable[[int, int, dict[str, float]], None] | None = None,
    log: Callable[[str], None] | None = None,
) -> HyperTrainResult:
    """Train a predictor on capture folders (data-parallel under torchrun).

    Args:
        capture_paths: training capture folders (:func:`corpus_training_captures`).
        opts: options.
        checkpoint_path: checkpoint file; one with this run's :func:`hyper_fingerprint` (options,
            the captures' loaded content, damcap version) is resumed exactly; any other (other
            captures or content, options, version, or an old one without a fingerprint) is never
            loaded: rank 0 moves it to ``CKPT.stale``, says so through ``log`` and the run starts
            afresh. An interrupted run (KeyboardInterrupt propagates) leaves its last periodic
            checkpoint.
        progress: rank 0 only: progress(step, steps, stats).
        log: rank 0 only: one-line messages.

    Returns:
        the trained network (the weights with the lowest validation L1, or the last without a
        validation set), its curve and provenance. Every rank returns; only rank 0's result is
        meant to be written.
    """
    opts.validate()
    arch = opts.architecture
    device = resolve_device(opts.device)
    rank, world, local_rank = _distributed(device.type)
    if device.type == "cuda" and world > 1:
        device = torch.device("cuda", local_rank)
        torch.cuda.set_device(device)
    say = (lambda m: log(m)) if (log and rank == 0) else (lambda m: None)
    paths = list(capture_paths)[: opts.max_captures or None]
    train_paths, val_paths = split_validation(paths, opts.val_fraction)
    if not train_paths:
        raise DamcapError("no training captures")
    t_load = time.perf_counter()
    train = [load_hyper_capture(p, opts.pixels_per_capture, seed=k) for k, p in enumerate(train_paths)]
    val = [load_hyper_capture(p, opts.pixels_per_capture, seed=k) for k, p in enumerate(val_paths)] if rank == 0 else []
    say(f"loaded {len(train)} training and {len(val_paths)} validation captures in {time.perf_counter() - t_load:.1f} s")

    with torch.random.fork_rng(devices=[]):  # conv/linear default init, seeded without touching the global RNG
        torch.manual_seed(opts.seed)
        net = HyperNet(arch, torch.Generator().manual_seed(opts.seed))
    net.to(device).train()
    model: torch.nn.Module = net
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel as DDP

        model = DDP(net, device_ids=[device.index] if device.type == "cuda" else None)
    optim = torch.optim.Adam(net.parameters(), lr=opts.learning_rate)
    lr_at = lambda s: opts.learning_rate * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * s / opts.steps)))  # noqa: E731
    state_key = _options_json(opts, [p.name for p in paths])

    start, best_val, best_step, curve, elapsed_before = 0, math.inf, 0, [], 0.0
    best_state = {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}
    ckpt = Path(checkpoint_path) if checkpoint_path else None
    fp = ""
    if ckpt:
        fp = hyper_fingerprint(state_key, train, val)  # rank 0 alone holds the validation captures
        if world > 1:
            shared = [fp]
            dist.broadcast_object_list(shared, src=0)
            fp = str(shared[0])
    if ckpt and ckpt.is_file():
        state = load_checkpoint(ckpt)
        if world > 1:
            dist.barrier()  # every rank has read the file before rank 0 may move it aside
        if state.get(FINGERPRINT_KEY) == fp and state.get("key") == state_key:
            net.load_state_dict(state["net"])
            optim.load_state_dict(state["optim"])
            start, best_val, best_step = int(state["step"]), float(state["best_val"]), int(state["best_step"])
            best_state, curve, elapsed_before = state["best_net"], json.loads(state["curve"]), float(state["elapsed"])
            say(f"resuming from {ckpt} at step {start}")
        elif rank == 0:
            set_aside_stale(ckpt, "other inputs (captures, options or damcap version differ)" if state else "nothing readable", say)
    resumed_from = start

    per_rank = max(1, math.ceil(opts.batch_size / world))
    t0 = time.perf_counter()
    running = None
    for step in range(start, opts.steps):
        for g in optim.param_groups:
            g["lr"] = lr_at(step)
        gen = _step_generator(opts.seed, rank, step)
        img, v, n, y = draw_batch(train, per_rank, opts, gen)
        loss = predicted_loss(model(img.to(device)), v.to(device), n.to(device), y.to(device), arch.dam)
        optim.zero_grad()
        loss.backward()
        if opts.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(net.parameters(), opts.grad_clip)
        optim.step()
        done = step + 1
        lv = float(loss.detach())
        running = lv if running is None else 0.95 * running + 0.05 * lv
        stats = {"loss": running}
        if rank == 0 and (done % opts.eval_every == 0 or done == opts.steps):
            vl = validation_l1(net, val)
            curve.append({"step": done, "train_l1": running, "val_l1": vl, "seconds": elapsed_before + time.perf_counter() - t0})
            if not val or vl < best_val:
                best_val, best_step = (vl if val else math.inf), done
                best_state = {k: t.detach().cpu().clone() for k, t in net.state_dict().items()}
            stats["val"] = vl
            say(f"step {done}/{opts.steps}: train L1 {running:.4f}, validation L1 {vl:.4f}")
        if rank == 0 and progress:
            progress(done, opts.steps, stats)
        if rank == 0 and ckpt and opts.checkpoint_every and done % opts.checkpoint_every == 0 and done < opts.steps:
            save_checkpoint(ckpt, {FINGERPRINT_KEY: fp, "damcap_version": damcap_version(), "key": state_key, "step": done, "net": net.state_dict(), "optim": optim.state_dict(),
                               "best_val": best_val, "best_step": best_step, "best_net": best_state,
                               "curve": json.dumps(curve), "elapsed": elapsed_before + time.perf_counter() - t0})
    seconds = elapsed_before + time.perf_counter() - t0

    digests = [weights_sha256(net)]
    if world > 1:
        gathered: list[Any] = [None] * world
        dist.all_gather_object(gathered, digests[0])
        digests = [str(d) for d in gathered]
        dist.barrier()
    final = HyperNet(arch)
    final.load_state_dict(best_state if val else {k: t.detach().cpu() for k, t in net.state_dict().items()})
    final.eval()
    if rank == 0 and ckpt and ckpt.is_file():
        ckpt.unlink()
    if world > 1:
        dist.destroy_process_group()
    return HyperTrainResult(final, curve, best_step if val else opts.steps, seconds, resumed_from, world, digests,
                            [p.name for p in train_paths], [p.name for p in val_paths])
