"""Training the predictor (``damcap train-hyper``): data, the loop, checkpoints, data-parallel.

Cost (the paper's, Sec. 3.3): the L1 re-synthesis error of the predicted DAM over the capture's
pixels. Each step draws ``batch_size`` examples: a set of 1 to ``input_views`` input views of one
scene and ``pixels`` target samples from all of its views. Examples come from two sources:
- corpus captures (``damcap synth-set``), augmented exactly (:func:`.model.predictor_image`:
  rotation about +y, mirror, tinted light), drawn by DataLoader worker processes
  (``loader_workers``) ahead of the step, in step order;
- random closed-form scenes (``procedural``, a :data:`SceneSource`: ``damcap train-hyper`` passes
  render_scenes in synth/procedural.py, passed in by the CLI), rendered on the training device itself, batched.

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
from dataclasses import asdict, dataclass, field, replace
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
from damcap.appearance.hyper.orientation import Orientation
from damcap.common.fingerprint import FINGERPRINT_KEY, fingerprint
from damcap.common.version import package_version

from damcap.appearance.fit import load_checkpoint, save_checkpoint, set_aside_stale
from damcap.appearance.views import radiance_scale_of
from damcap.appearance.hyper.model import HyperArchitecture, HyperNet, predicted_loss, predictor_image, predictor_images, rotation_y, view_crop
from damcap.appearance.pixels import FOREGROUND_COVERAGE, view_dir_world


@dataclass(frozen=True)
class HyperTrainOptions:
    """Options of ``damcap train-hyper`` (each knob that trades speed for accuracy is here)."""

    steps: int = field(default=3000, metadata=COUNT)
    """optimiser steps (Adam)"""
    batch_size: int = field(default=8, metadata=in_range(1, 65536))
    """training examples per step, over all ranks together (a multiple of the number of processes)"""
    pixels: int = field(default=4096, metadata=in_range(1, MAX_BATCH_PIXELS, cli_panel="advanced"))
    """pixels per capture and step scored by the L1 cost"""
    learning_rate: float = field(default=5e-4, metadata=in_range(0, 10, lo_open=True))
    """initial Adam learning rate; cosine-decayed to 5% of it"""
    input_size: int = field(default=256, metadata=in_range(1, MAX_IMAGE_SIDE, cli_panel="advanced"))
    """side of the predictor's input image, pixels"""
    channels: tuple[int, ...] = field(default=(16, 32, 64, 64, 128, 128, 256, 256), metadata=in_range(1, MAX_CHANNELS, cli_panel="advanced"))
    """convolution channels (one stride-2 layer each)"""
    encoding: Encoding = field(default="nr", metadata={"cli_panel": "advanced"})
    """input encoding of the predicted DAM (32 x 4, no biases)"""
    orientation: Orientation = field(default="world", metadata={"cli_old_flags": "--frame"})
    """the predictor's coordinates (appearance/hyper/orientation.py): 'world', or 'light' (the world
    turned so that each input's dominant light comes from +y; the predicted DAM is turned back)"""
    augment: bool = field(default=True, metadata={"cli_panel": "advanced"})
    """exact augmentations: rotation about +y, mirror, tinted light"""
    max_captures: int = field(default=0, metadata={**COUNT_OR_ZERO, "cli_panel": "advanced"})
    """use at most this many training captures (0 = all): the training-set-size knob"""
    val_fraction: float = field(default=0.1, metadata=in_range(0, 1, hi_open=True, cli_panel="advanced"))
    """training captures kept out for the validation curve and the stopping rule"""
    eval_every: int = field(default=100, metadata=COUNT)
    """steps between validations"""
    pixels_per_capture: int = field(default=32768, metadata=in_range(1, MAX_BATCH_PIXELS, cli_panel="advanced"))
    """covered pixels kept in memory per capture (spread over all its views)"""
    seed: int = field(default=0, metadata=SEED)
    """seeds initialisation and every random draw"""
    device: str = "cpu"
    """'cpu', 'cuda' or 'auto' (under torchrun each rank uses its LOCAL_RANK GPU)"""
    snapshot_every: int = field(default=0, metadata={**COUNT_OR_ZERO, "cli_panel": "advanced"})
    """also write the predictor as it stands every this many steps (OUTPUT.stepN.safetensors; 0 =
    never): how error falls with training compute, measured afterwards on any captures"""
    checkpoint_every: int = field(default=100, metadata=COUNT_OR_ZERO)
    """steps between checkpoints (0 = never)"""
    input_views: int = field(default=1, metadata=in_range(1, 64))
    """views the predictor reads at once (a set encoder; 1 = the paper's single view); each
    training example gets 1 to this many, so the predictor works with any number up to it"""
    procedural: float = field(default=0.0, metadata=in_range(0, 1))
    """share of each batch drawn from random closed-form scenes rendered on the training device
    (``--procedural 1`` needs no corpus); the rest comes from the corpus's captures"""
    loader_workers: int = field(default=0, metadata=in_range(0, 256, cli_panel="advanced"))
    """DataLoader worker processes that draw and augment the corpus's examples ahead of the
    training step (0 = on the main thread)"""
    val_scenes: int = field(default=64, metadata=in_range(0, 100_000, cli_panel="advanced"))
    """random closed-form scenes (fixed, never trained on) scored by the validation curve when
    ``--procedural`` is above 0"""
    init: str = ""
    """predictor file, or a shipped one by name (v1, v10), whose weights start the run instead of a
    random initialisation: trains a predictor further (the architecture options must match it;
    the learning-rate schedule starts afresh). '' = random initialisation"""
    readout_iterations: int = field(default=0, metadata=in_range(0, 20, cli_panel="advanced"))
    """train (and validate) through ``damcap predict``'s readout solve: each predicted DAM's
    output layer is solved on half of its samples (this many unrolled reweighted Gauss-Newton
    steps, appearance/readout.py) and scored on the other half, so the hidden layers learn a basis
    the capture's own pixels can mix (0 = the paper's cost on the network's own output)"""
    grad_clip: float = field(default=1.0, metadata=in_range(0, 1e6, cli_panel="advanced"))
    """largest gradient norm of a step (0 = no clipping): a hypernetwork's output weights
    multiply through the DAM's layers, so one bad batch can otherwise throw it far off"""

    def validate(self) -> None:
        """Raise DamcapError naming the first value outside its range."""
        check_ranges(self)
        self.architecture  # channels and input size within HyperArchitecture's bounds (named in its error)

    @property
    def architecture(self) -> HyperArchitecture:
        return HyperArchitecture(self.input_size, tuple(self.channels), DamArchitecture(encoding=self.encoding), self.input_views,
                                 self.orientation)


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
    device: str = "cpu"
    """what trained it: 'cpu', or the GPU's name"""
    init: dict[str, Any] | None = None
    """the predictor the run started from (:func:`init_weights`'s record), None = random weights"""


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


def _step_seed(seed: int, rank: int, step: int) -> int:
    return (seed * 1_000_003 + rank * 7_919 + step) % (2**63)


def _step_generator(seed: int, rank: int, step: int, device: torch.device | str = "cpu") -> torch.Generator:
    return torch.Generator(device=device).manual_seed(_step_seed(seed, rank, step))


@dataclass
class Batch:
    """A training batch: sets of input views and each example's target samples."""

    images: torch.Tensor
    """(B, V, 9, S, S) predictor images"""
    view_mask: torch.Tensor
    """(B, V) bool"""
    view_dir_world: torch.Tensor
    """(B, K, 3)"""
    normal_world: torch.Tensor
    """(B, K, 3)"""
    radiance_norm: torch.Tensor
    """(B, K, 3) radiance / the example's radiance scale"""
    sample_mask: torch.Tensor
    """(B, K) bool"""

    def to(self, device: torch.device) -> Batch:
        return Batch(*(getattr(self, f).to(device, non_blocking=True) for f in self.__dataclass_fields__))

    @staticmethod
    def cat(parts: list[Batch]) -> Batch:
        parts = [p for p in parts if p.images.shape[0]]
        return Batch(*(torch.cat([getattr(p, f) for p in parts]) for f in Batch.__dataclass_fields__))


def draw_batch(captures: list[HyperCapture], n: int, opts: HyperTrainOptions, gen: torch.Generator) -> Batch:
    """n augmented training examples from corpus captures: a capture, 1 to ``opts.input_views`` of
    its lit views (all under one augmentation), and ``opts.pixels`` of its pixels."""
    vmax = opts.input_views
    imgs = torch.zeros(n, vmax, 9, opts.input_size, opts.input_size)
    vmask = torch.zeros(n, vmax, dtype=torch.bool)
    vs, ns, ys = [], [], []
    for i in range(n):
        c = captures[int(torch.randint(len(captures), (1,), generator=gen))]
        n_views = min(int(torch.randint(1, vmax + 1, (1,), generator=gen)), len(c.crops))
        picks = torch.randperm(len(c.crops), generator=gen)[:n_views].tolist()
        rot, mirror, gain = None, False, None
        if opts.augment:
            rot = rotation_y(float(torch.rand((), generator=gen)) * 2 * math.pi)
            mirror = bool(torch.rand((), generator=gen) < 0.5)
            gain = torch.exp((torch.rand(3, generator=gen) - 0.5))
        scale = c.radiance_scale * (float(gain.mean()) if gain is not None else 1.0)
        for j, k in enumerate(picks):
            imgs[i, j] = predictor_image(c.crops[k].float(), opts.input_size, rot, mirror, gain, radiance_scale=scale)[0]
            vmask[i, j] = True
        idx = torch.randint(c.radiance_lin.shape[0], (opts.pixels,), generator=gen)
        v, nn_, y = c.view_dir_world[idx], c.normal_world[idx], c.radiance_lin[idx]
        if mirror:
            flip = torch.tensor([-1.0, 1.0, 1.0])
            v, nn_ = v * flip, nn_ * flip
        if rot is not None:
            v, nn_ = v @ rot.T, nn_ @ rot.T
        if gain is not None:
            y = y * gain
        vs.append(v)
        ns.append(nn_)
        ys.append(y / scale)
    return Batch(imgs, vmask, torch.stack(vs), torch.stack(ns), torch.stack(ys), torch.ones(n, opts.pixels, dtype=torch.bool))


SceneSource = Callable[[torch.Generator, int, int, int], Any]
"""Random closed-form scenes: (generator, scenes, most input views, target samples) -> an object
with the fields of SceneBatch in synth/procedural.py (views, view_mask, view_dir_world,
normal_world, radiance_lin, sample_mask) on the generator's device. ``damcap train-hyper`` passes
its render_scenes; appearance never imports synth."""


def scene_batch(scenes: Any, input_size: int) -> Batch:
    """A :data:`SceneSource` batch as a training :class:`Batch`: each scene's radiance scale is the
    95th percentile of its target samples (as a capture's is of its train views' pixels), its views
    are cropped and normalised by :func:`.model.predictor_images`. A scene whose samples all miss
    or are black keeps no sample."""
    b, v = scenes.view_mask.shape
    rad = torch.where(scenes.sample_mask[..., None], scenes.radiance_lin, torch.full_like(scenes.radiance_lin, math.nan))
    scale = torch.nanquantile(rad.reshape(b, -1), 0.95, dim=1)
    ok = torch.isfinite(scale) & (scale > 0)
    scale = torch.where(ok, scale, torch.ones_like(scale))
    has_fg = (scenes.views[:, :, 9] > FOREGROUND_COVERAGE).flatten(2).any(2)
    images = predictor_images(scenes.views.flatten(0, 1), input_size, scale.repeat_interleave(v)).reshape(b, v, 9, input_size, input_size)
    vmask = scenes.view_mask & has_fg
    smask = scenes.sample_mask & ok[:, None] & vmask.any(1, keepdim=True)
    vmask = vmask | ~vmask.any(1, keepdim=True)  # a set needs a view; such an example keeps no sample
    return Batch(images, vmask, scenes.view_dir_world, scenes.normal_world, scenes.radiance_lin / scale[:, None, None], smask)


class CorpusDraws(torch.utils.data.IterableDataset):
    """The corpus part of steps ``start .. steps - 1``, in step order, for a DataLoader: with W
    workers, worker w draws steps w, w + W, ... and the loader returns them in order, so a run with
    workers draws exactly what one without draws (and resumes exactly)."""

    def __init__(self, captures: list[HyperCapture], n: int, opts: HyperTrainOptions, rank: int, start: int) -> None:
        self.captures, self.n, self.opts, self.rank, self.start = captures, n, opts, rank, start

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        w, nw = (info.id, info.num_workers) if info else (0, 1)
        torch.set_num_threads(1) if info else None
        for step in range(self.start + w, self.opts.steps, nw):
            yield draw_batch(self.captures, self.n, self.opts, _step_generator(self.opts.seed, self.rank, step))


def corpus_loader(captures: list[HyperCapture], n: int, opts: HyperTrainOptions, rank: int, start: int, pin: bool):
    """An iterator over the corpus part of each step (``n`` examples; empty batches when n is 0)."""
    if n == 0 or not captures:
        empty = Batch(torch.zeros(0, opts.input_views, 9, opts.input_size, opts.input_size), torch.zeros(0, opts.input_views, dtype=torch.bool),
                      torch.zeros(0, opts.pixels, 3), torch.zeros(0, opts.pixels, 3), torch.zeros(0, opts.pixels, 3),
                      torch.zeros(0, opts.pixels, dtype=torch.bool))
        return iter(lambda: empty, None)
    ds = CorpusDraws(captures, n, opts, rank, start)
    if opts.loader_workers == 0:
        return iter(ds)
    return iter(torch.utils.data.DataLoader(ds, batch_size=None, num_workers=opts.loader_workers, pin_memory=pin,
                                            prefetch_factor=4, persistent_workers=False))


def batch_loss(model: torch.nn.Module, batch: Batch, arch: DamArchitecture, readout_iterations: int = 0) -> torch.Tensor:
    return predicted_loss(model(batch.images, batch.view_mask), batch.view_dir_world, batch.normal_world, batch.radiance_norm,
                          arch, batch.sample_mask, readout_iterations)


def validation_inputs(c: HyperCapture, views: int) -> list[int]:
    """The validation input views of a corpus capture: its ``views`` best-covered lit views."""
    cov = [float(x[9].float().sum()) for x in c.crops]
    return sorted(range(len(cov)), key=lambda k: -cov[k])[:views]


@torch.no_grad()
def validation_l1(net: HyperNet, captures: list[HyperCapture], pixels: int = 8192, readout_iterations: int = 0) -> float:
    """Mean L1 (radiance / capture scale) of predictions from each capture's best-covered views
    (:func:`validation_inputs`, up to the predictor's ``input_views``), without augmentation, over
    its first ``pixels`` kept pixels (with ``readout_iterations``: the cost of
    :func:`.model.predicted_loss` after the readout solve)."""
    if not captures:
        return float("nan")
    was_training = net.training
    net.eval()
    device = next(net.parameters()).device
    total = 0.0
    for c in captures:
        imgs = [predictor_image(c.crops[k].float(), net.arch.input_size, radiance_scale=c.radiance_scale)[0]
                for k in validation_inputs(c, net.arch.input_views)]
        w = net(torch.stack(imgs)[None].to(device))
        k = slice(0, pixels)
        loss = predicted_loss(w, c.view_dir_world[None, k].to(device), c.normal_world[None, k].to(device),
                              (c.radiance_lin[None, k] / c.radiance_scale).to(device), net.arch.dam, readout_iterations=readout_iterations)
        total += float(loss)
    net.train(was_training)
    return total / len(captures)


@torch.no_grad()
def validation_scenes_l1(net: HyperNet, batches: list[Batch], readout_iterations: int = 0) -> float:
    """Mean L1 over fixed validation scene batches."""
    if not batches:
        return float("nan")
    was_training = net.training
    net.eval()
    device = next(net.parameters()).device
    total = sum(float(batch_loss(net, b.to(device), net.arch.dam, readout_iterations)) for b in batches) / len(batches)
    net.train(was_training)
    return total


def held_out_l1(corpus_l1: float | None, scenes_l1: float | None) -> float:
    """The validation number the best step is chosen by: the mean of the validation sets the run
    has (None = the run has no such set), NaN when any of them is not finite (a diverged net).

    >>> held_out_l1(0.2, None), held_out_l1(0.2, 0.4), held_out_l1(float("nan"), 0.4), held_out_l1(None, None)
    (0.2, 0.30000000000000004, nan, nan)
    """
    present = [x for x in (corpus_l1, scenes_l1) if x is not None]
    if not present or not all(math.isfinite(x) for x in present):
        return math.nan
    return float(np.mean(present))


def init_weights(choice: str, arch: HyperArchitecture) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The weights a run starts from (``--init``) and their record for the recipe: file, weight
    digest, and the steps and seconds of training already in them (so compute adds up).

    Raises:
        DamcapError: the file is not a readable predictor, or its architecture is not ``arch``.
    """
    from damcap.appearance.hyper.file import load_predictor, predictor_path

    path = predictor_path(choice)
    net, meta = load_predictor(path)
    if replace(net.arch, orientation=arch.orientation) != arch:  # the orientation is no tensor's shape: a run may change it
        raise DamcapError(f"{path}: --init predictor has architecture {net.arch.to_json()}, but the options ask for {arch.to_json()}; "
                          f"give the same --input-size, --channels, --encoding and --input-views as it was trained with")
    training = meta.get("training") or {}
    prior = training.get("init") or {}
    steps = int((training.get("options") or {}).get("steps", 0)) + int(prior.get("steps", 0))
    seconds = float(training.get("seconds", 0.0)) + float(prior.get("seconds", 0.0))
    record = {"file": path.name, "weights_sha256": weights_sha256(net), "steps": steps, "seconds": seconds, "orientation": net.arch.orientation}
    return {k: v.detach().clone() for k, v in net.state_dict().items()}, record


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
    parts: list[Any] = ["train-hyper", package_version(), state_key]
    for c in [*train, *val]:
        parts += [c.name, float(c.radiance_scale), c.view_dir_world, c.normal_world, c.radiance_lin, *c.crops]
    return fingerprint(*parts)


def train_hyper(
    capture_paths: list[Path],
    opts: HyperTrainOptions,
    *,
    checkpoint_path: str | os.PathLike | None = None,
    scenes: SceneSource | None = None,
    snapshot: Callable[[int, HyperNet], None] | None = None,
    progress: Callable[[int, int, dict[str, float]], None] | None = None,
    log: Callable[[str], None] | None = None,
) -> HyperTrainResult:
    """Train a predictor on capture folders (data-parallel under torchrun).

    Args:
        capture_paths: training capture folders (:func:`corpus_training_captures`).
        opts: options.
        scenes: the random closed-form scenes that ``opts.procedural`` of each batch is drawn from
            (and the validation scenes), rendered on the training device.
        snapshot: rank 0 only: snapshot(step, net, init) every ``opts.snapshot_every`` steps, with
            ``init`` the record of the predictor the run started from (``--init``; None without), so
            a snapshot can say how many steps of training it holds in all.
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
    if opts.procedural > 0 and scenes is None:
        raise DamcapError("--procedural above 0 needs a scene source (damcap train-hyper passes one)")
    if opts.procedural < 1 and not capture_paths:
        raise DamcapError("no training captures: give a corpus, or train on random scenes alone with --procedural 1")
    arch = opts.architecture
    device = resolve_device(opts.device)
    rank, world, local_rank = _distributed(device.type)
    if opts.batch_size % world:
        raise DamcapError(f"--batch-size {opts.batch_size} does not split evenly over {world} processes: the effective batch "
                          f"would not be the one asked for; use a multiple of {world}")
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True  # the DAM's small matrix products; convolutions use TF32 already
        torch.backends.cudnn.benchmark = True
    if device.type == "cuda" and world > 1:
        device = torch.device("cuda", local_rank)
        torch.cuda.set_device(device)
    say = (lambda m: log(m)) if (log and rank == 0) else (lambda m: None)
    paths = list(capture_paths)[: opts.max_captures or None]
    train_paths, val_paths = split_validation(paths, opts.val_fraction) if opts.procedural < 1 else ([], [])
    t_load = time.perf_counter()
    train = [load_hyper_capture(p, opts.pixels_per_capture, seed=k) for k, p in enumerate(train_paths)]
    val = [load_hyper_capture(p, opts.pixels_per_capture, seed=k) for k, p in enumerate(val_paths)] if rank == 0 else []
    say(f"loaded {len(train)} training and {len(val_paths)} validation captures in {time.perf_counter() - t_load:.1f} s")
    val_scenes: list[Batch] = []
    if rank == 0 and opts.procedural > 0 and opts.val_scenes:
        vgen = _step_generator(opts.seed + 1, 1_000_003, 0, device)  # a stream no training step draws
        for k in range(0, opts.val_scenes, 16):
            val_scenes.append(scene_batch(scenes(vgen, min(16, opts.val_scenes - k), opts.input_views, opts.pixels), opts.input_size))

    with torch.random.fork_rng(devices=[]):  # conv/linear default init, seeded without touching the global RNG
        torch.manual_seed(opts.seed)
        net = HyperNet(arch, torch.Generator().manual_seed(opts.seed))
    init_record = None
    if opts.init:  # every rank reads the same file before the DDP wrap, so ranks start identical
        init_state, init_record = init_weights(opts.init, arch)
        net.load_state_dict(init_state)
    net.to(device).train()
    model: torch.nn.Module = net
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel as DDP

        model = DDP(net, device_ids=[device.index] if device.type == "cuda" else None)
    optim = torch.optim.Adam(net.parameters(), lr=opts.learning_rate)
    lr_at = lambda s: opts.learning_rate * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * s / opts.steps)))  # noqa: E731
    state_key = _options_json(opts, [p.name for p in paths]) + (init_record["weights_sha256"] if init_record else "")

    start, best_val, best_step, curve, elapsed_before = 0, math.inf, 0, [], 0.0
    best_state = {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}
    ckpt = Path(checkpoint_path) if checkpoint_path else None
    fp = ""
    if ckpt:
        fp = hyper_fingerprint(state_key, train, val)  # rank 0 alone holds the validation captures
        if val_scenes:
            fp = fingerprint(fp, *[x for b in val_scenes for x in (b.images, b.radiance_norm)])
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

    per_rank = opts.batch_size // world
    n_scenes = round(per_rank * opts.procedural) if train else per_rank
    corpus_part = corpus_loader(train, per_rank - n_scenes, opts, rank, start, pin=device.type == "cuda")
    def validate() -> tuple[float, float, float]:
        """(corpus L1, scenes L1, the L1 the best step is chosen by)."""
        v_corpus = validation_l1(net, val, readout_iterations=opts.readout_iterations)
        v_scenes = validation_scenes_l1(net, val_scenes, opts.readout_iterations)
        return v_corpus, v_scenes, held_out_l1(v_corpus if val else None, v_scenes if val_scenes else None)

    t0 = time.perf_counter()
    if rank == 0 and init_record and start == 0 and (val or val_scenes):  # the start is a candidate: never worse than --init
        v_corpus, v_scenes, best_val = validate()
        curve.append({"step": 0, "train_l1": math.nan, "val_l1": best_val, "val_corpus_l1": v_corpus, "val_scenes_l1": v_scenes, "seconds": 0.0})
        say(f"step 0 (--init {init_record['file']}): validation L1 {best_val:.4f}")
    running = None
    for step in range(start, opts.steps):
        for g in optim.param_groups:
            g["lr"] = lr_at(step)
        parts = [next(corpus_part).to(device)]
        if n_scenes:
            gen = _step_generator(opts.seed, rank + 65_537, step, device)
            parts.append(scene_batch(scenes(gen, n_scenes, opts.input_views, opts.pixels), opts.input_size))
        loss = batch_loss(model, Batch.cat(parts), arch.dam, opts.readout_iterations)
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
            v_corpus, v_scenes, vl = validate()
            curve.append({"step": done, "train_l1": running, "val_l1": vl, "val_corpus_l1": v_corpus, "val_scenes_l1": v_scenes,
                          "seconds": elapsed_before + time.perf_counter() - t0})
            if not (val or val_scenes) or vl < best_val:  # a NaN (diverged) validation never replaces the best
                best_val, best_step = (vl if (val or val_scenes) else math.inf), done
                best_state = {k: t.detach().cpu().clone() for k, t in net.state_dict().items()}
            elif not math.isfinite(vl):
                say(f"step {done}: validation L1 is {vl}: training diverged; the result stays the best step so far ({best_step})")
            stats["val"] = vl
            say(f"step {done}/{opts.steps}: train L1 {running:.4f}, validation L1 {vl:.4f}")
        if rank == 0 and progress:
            progress(done, opts.steps, stats)
        if rank == 0 and snapshot and opts.snapshot_every and done % opts.snapshot_every == 0:
            snapshot(done, net, init_record)
        if rank == 0 and ckpt and opts.checkpoint_every and done % opts.checkpoint_every == 0 and done < opts.steps:
            save_checkpoint(ckpt, {FINGERPRINT_KEY: fp, "damcap_package_version": package_version(), "key": state_key, "step": done, "net": net.state_dict(), "optim": optim.state_dict(),
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
    validated = bool(val or val_scenes)  # only rank 0 validates; the other ranks return their last weights
    final.load_state_dict(best_state if validated else {k: t.detach().cpu() for k, t in net.state_dict().items()})
    final.eval()
    if rank == 0 and ckpt and ckpt.is_file():
        ckpt.unlink()
    if world > 1:
        dist.destroy_process_group()
    device_name = torch.cuda.get_device_name(device) if device.type == "cuda" else device.type
    return HyperTrainResult(final, curve, best_step if validated else opts.steps, seconds, resumed_from, world, digests,
                            [p.name for p in train_paths], [p.name for p in val_paths], device_name,
                            init_record)
