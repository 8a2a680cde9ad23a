"""Learning-to-learn (Maximov et al. 2019, Sec. 3.3): a CNN that maps one image to a DAM's weights.

The predictor Theta(I | phi) reads a 9-channel image of the object (linear RGB, world-space
normal, world-space view direction; covered pixels only, 0 elsewhere) and outputs the flat weight
vector of a deep appearance map (:mod:`.dam`). Eight stride-2 convolutions halve the resolution
from 256 to 1, a fully-connected layer maps the last features to a *correction* of a learned mean
weight vector (so an untrained predictor already outputs a valid DAM: the mean appearance).
A predictor with ``input_views`` above 1 is a set encoder: it runs the convolutions on each of up
to that many views and averages their features before the output layer, so the prediction does
not depend on the views' order and works with any number of them (:func:`predictor_inputs`
chooses views that spread the cameras). A predictor whose ``orientation`` is 'light'
(:mod:`.orientation`) first turns the world so that its input's dominant light comes from +y, and turns the DAM it
predicts back.

Units: the RGB channels are the view's linear radiance divided by the *capture's* radiance
scale (95th percentile of the train views' foreground, :func:`.fit.radiance_scale_of`, the same
number a fit uses) and compressed with log1p; the predicted DAM outputs radiance in units of that
scale, which becomes its ``radiance_scale``. (Normalising by the input view's own scale instead
made targets from brighter views up to 1e6 times too large and training diverge: measured on the
hyper corpus, point lights behind the object.) Without other views, the input view's own scale
stands in. Everything here is pure (tensors in, tensors out); files live in
:mod:`.hyper_file`, training in :mod:`.hyper_train`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from damcap.common.errors import DamcapError
from damcap.common.validate import MAX_CHANNELS, MAX_CONV_LAYERS, MAX_IMAGE_SIDE, bounded_int, require_memory

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, dam_forward, encode_inputs, init_weights, rotated_world_weights
from damcap.appearance.hyper.orientation import ORIENTATIONS, Orientation, light_rotation, rotate_images
from damcap.appearance.views import ViewData, radiance_scale_of
from damcap.appearance.readout import solved_weights
from damcap.appearance.pixels import FOREGROUND_COVERAGE, view_dir_world

IN_CHANNELS = 9
"""RGB (log1p of radiance / scale), normal_world, view_dir_world"""


@dataclass(frozen=True)
class HyperArchitecture:
    """Shape of a predictor network."""

    input_size: int = 256
    """side of the square input image, pixels (the paper: 256)"""
    channels: tuple[int, ...] = (16, 32, 64, 64, 128, 128, 256, 256)
    """output channels of the stride-2 4x4 convolutions (8 layers: 256 -> 1 pixel)"""
    dam: DamArchitecture = field(default_factory=DamArchitecture)
    """the DAM whose weights it predicts"""
    input_views: int = 1
    """views it reads at once: each view's features are averaged before the output layer (a set
    encoder: the prediction does not depend on the order of the views); 1 = the paper's one view"""
    orientation: Orientation = "world"
    """coordinates the network reads and writes (:mod:`.orientation`): 'world' (v1-v8), or 'light'
    (v10), the world turned so that the input's dominant light comes from +y (the DAM is turned
    back). Predictor files store it as ``"orientation"``; older ones as ``"frame"`` (still read)"""

    def __post_init__(self) -> None:
        # bounded before any layer is built from them (a predictor file's metadata, an option)
        bounded_int(len(self.channels), 1, MAX_CONV_LAYERS, "number of predictor --channels layers")
        for c in self.channels:
            bounded_int(c, 1, MAX_CHANNELS, "predictor channels")
        bounded_int(self.input_size, 1, MAX_IMAGE_SIDE, "predictor --input-size")
        bounded_int(self.input_views, 1, 64, "predictor --input-views")
        if self.orientation not in ORIENTATIONS:
            raise DamcapError(f"unknown predictor orientation {self.orientation!r}; use one of {', '.join(ORIENTATIONS)}")
        if not isinstance(self.dam, DamArchitecture):
            raise DamcapError(f"predictor dam must be a DamArchitecture, got {type(self.dam).__name__}")
        dims = (IN_CHANNELS,) + tuple(self.channels)
        params = sum(16 * a * b + b for a, b in zip(dims[:-1], dims[1:])) + (dims[-1] + 1) * self.dam.num_weights
        require_memory(16.0 * params, f"a predictor of {params} parameters (weights, gradients, Adam state)")
        if self.input_size < 2 ** len(self.channels):
            raise DamcapError(f"an input of {self.input_size} px is too small for {len(self.channels)} stride-2 layers "
                              f"(needs >= {2 ** len(self.channels)} px); raise --input-size or use fewer --channels")

    def to_json(self) -> dict:
        d = asdict(self)
        d["channels"] = list(self.channels)
        return d

    @staticmethod
    def from_json(d: dict) -> HyperArchitecture:
        """Inverse of :meth:`to_json`; reads the ``"frame"`` key of files written before the
        field was called ``orientation``.

        >>> a = HyperArchitecture(input_size=64, channels=(4, 8))
        >>> HyperArchitecture.from_json(a.to_json()) == a
        True
        """
        d = dict(d)
        return HyperArchitecture(input_size=int(d["input_size"]), channels=tuple(int(c) for c in d["channels"]),
                                 dam=DamArchitecture(**d["dam"]), input_views=int(d.get("input_views", 1)),
                                 orientation=d.get("orientation", d.get("frame", "world")))


class HyperNet(nn.Module):
    """Theta: (B, 9, S, S) predictor images, or (B, V, 9, S, S) sets of views -> (B, P) flat DAM
    weights (world coordinates, whatever the architecture's ``orientation``)."""

    def __init__(self, arch: HyperArchitecture, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.arch = arch
        layers: list[nn.Module] = []
        c_in = IN_CHANNELS
        for c in arch.channels:
            layers += [nn.Conv2d(c_in, c, 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
            c_in = c
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(c_in, arch.dam.num_weights)
        self.base = nn.Parameter(init_weights(arch.dam, generator))
        with torch.no_grad():  # start at the mean DAM: small corrections
            self.head.weight.mul_(0.1)
            self.head.bias.zero_()

    def forward(self, images: torch.Tensor, view_mask: torch.Tensor | None = None, rotation: torch.Tensor | None = None) -> torch.Tensor:
        """Args:
            images: (B, 9, S, S), or (B, V, 9, S, S) with any V.
            view_mask: (B, V) bool, the views present (default all); each set needs one.
            rotation: (B, 3, 3) a light-orientation predictor's :func:`.orientation.light_rotation`
                of these images when the caller has found it already (default: found here;
                ignored by a world-orientation predictor).
        """
        if images.dim() == 4:
            images = images[:, None]
        if self.arch.orientation != "light":
            rotation = None
        elif rotation is None:
            with torch.no_grad():  # a change of coordinates, a constant of the step
                rotation = light_rotation(images, view_mask)
        if rotation is not None:
            images = rotate_images(images, rotation.to(images.device))
        b, v = images.shape[:2]
        f = F.adaptive_avg_pool2d(self.features(images.flatten(0, 1)), 1).reshape(b, v, -1)
        w = torch.ones(b, v, 1, device=f.device, dtype=f.dtype) if view_mask is None else view_mask[..., None].to(f.dtype)
        f = (f * w).sum(1) / w.sum(1).clamp_min(1.0)
        weights = self.base[None] + self.head(f)
        return weights if rotation is None else rotated_world_weights(weights, self.arch.dam, rotation)


def crop_box(foreground: np.ndarray, margin: float = 0.05) -> tuple[int, int, int]:
    """Square (top, left, side) around the foreground's bounding box, ``margin`` of its side on
    each edge (may reach outside the image: padded with background).

    >>> m = np.zeros((10, 20), bool); m[2:6, 4:12] = True
    >>> crop_box(m, margin=0.0)
    (0, 4, 8)
    """
    ys, xs = np.nonzero(foreground)
    if ys.size == 0:
        raise DamcapError("the input view has no covered pixels (coverage A > 0.5 nowhere)")
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    side = int(math.ceil(max(y1 - y0, x1 - x0) * (1 + 2 * margin)))
    cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
    return int(round(cy - side / 2)), int(round(cx - side / 2)), side


def view_crop(radiance_lin: np.ndarray, normal_world: np.ndarray, view_dir: np.ndarray, coverage: np.ndarray) -> torch.Tensor:
    """The object's square crop of one view as (10, s, s) float32: linear RGB (radiance units),
    normal_world, view_dir_world, foreground mask; all 0 off the foreground.

    Args:
        radiance_lin: (H, W, 3) linear radiance.
        normal_world: (H, W, 3) unit normals.
        view_dir: (H, W, 3) unit vectors from the surface toward the camera.
        coverage: (H, W) coverage A in [0, 1]; foreground = A > 0.5.

    Raises:
        DamcapError: a foreground value is NaN or inf.
    """
    fg = coverage > FOREGROUND_COVERAGE
    top, left, side = crop_box(fg)
    stack = np.concatenate([radiance_lin, normal_world, view_dir, fg[..., None]], -1).astype(np.float32)
    if not np.isfinite(stack[fg]).all():  # read_frame refuses such frames; a caller's own arrays may not
        raise DamcapError("the view's foreground has NaN or inf in its radiance, normals or view directions")
    stack = np.where(fg[..., None], stack, 0.0)  # off the foreground, whatever is there (even NaN) becomes 0
    out = np.zeros((side, side, 10), np.float32)
    h, w = fg.shape
    ys, xs = slice(max(top, 0), min(top + side, h)), slice(max(left, 0), min(left + side, w))
    out[ys.start - top:ys.stop - top, xs.start - left:xs.stop - left] = stack[ys, xs]
    return torch.from_numpy(out).permute(2, 0, 1).contiguous()


LIT_FRACTION = 0.1
"""a view is lit when its radiance scale is at least this fraction of the brightest train view's"""


def choose_input_view(covered_px: list[int], scales: list[float], min_brightness: float = LIT_FRACTION) -> int:
    """The default input view: the best covered among the *lit* views, those whose radiance scale
    is at least ``min_brightness`` times the brightest view's (a view of the unlit side of an
    object under a point light says little about its material).

    Args:
        covered_px: covered pixels (A > 0.5) per view.
        scales: radiance scale (95th foreground percentile) per view.

    >>> choose_input_view([900, 800, 700], [0.001, 1.0, 0.5])
    1
    """
    top = max(scales)
    lit = [k for k, s in enumerate(scales) if s >= min_brightness * top]
    return max(lit, key=lambda k: covered_px[k])


def spread_views(first: int, centres_world: np.ndarray, candidates: list[int], count: int) -> list[int]:
    """``first``, then up to ``count - 1`` more of ``candidates`` chosen greedily to spread the
    cameras' directions from the object (farthest-point: each next view maximises its smallest
    angle to those chosen).

    Args:
        first: the first view.
        centres_world: (N, 3) camera centres relative to the object's centre.
        candidates: the views that may be added.
        count: views wanted.

    >>> spread_views(0, np.array([[1.0, 0, 0], [0.9, 0.1, 0], [-1, 0, 0], [0, 1, 0]]), [1, 2, 3], 3)
    [0, 2, 3]
    """
    d = centres_world / np.maximum(np.linalg.norm(centres_world, axis=1, keepdims=True), 1e-12)
    chosen = [first]
    rest = [c for c in candidates if c != first]
    while rest and len(chosen) < count:
        nxt = min(rest, key=lambda c: (float(np.max(d[chosen] @ d[c])), c))
        chosen.append(nxt)
        rest.remove(nxt)
    return chosen


def predictor_inputs(train: list[ViewData], count: int = 1, name: str | None = None) -> tuple[list[int], list[torch.Tensor], float]:
    """What ``damcap predict`` feeds the network, from a capture's train views.

    Args:
        train: the train split's views.
        count: views wanted (the predictor's ``input_views``): the first as below, the others the
            lit views that spread the cameras most (:func:`spread_views`).
        name: the first input view's name (file stem); None = :func:`choose_input_view`.

    Returns:
        (indices of the input views, their :func:`view_crop` s, the capture's radiance scale over
        all train views' foreground, the fit's).

    Raises:
        DamcapError: ``name`` is not a train view.
    """
    fgs = [v.data.coverage > FOREGROUND_COVERAGE for v in train]
    pixels = [torch.from_numpy(v.data.radiance_lin[fg]) for v, fg in zip(train, fgs, strict=True)]
    scales = [radiance_scale_of(p) for p in pixels]
    covered = [int(fg.sum()) for fg in fgs]
    lit = [k for k, sc in enumerate(scales) if sc >= LIT_FRACTION * max(scales) and covered[k] > 0]
    if name is None:
        k = choose_input_view(covered, scales)
    else:
        names = [v.name for v in train]
        if name not in names:
            raise DamcapError(f"--view {name!r} is not a train-split frame; choose one of "
                              f"{', '.join(names[:12])}{' ...' if len(names) > 12 else ''}")
        k = names.index(name)
    pos = [v.data.position_world[fg] for v, fg in zip(train, fgs, strict=True) if fg.any()]
    centre = np.concatenate(pos).mean(0) if pos else np.zeros(3)
    centres = np.stack([np.asarray(v.centre_world, np.float64) - centre for v in train])
    ks = spread_views(k, centres, lit, count)
    crops = []
    for j in ks:
        d = train[j].data
        crops.append(view_crop(d.radiance_lin, d.normal_world, view_dir_world(d.position_world, train[j].centre_world), d.coverage))
    return ks, crops, radiance_scale_of(torch.cat(pixels))


def predictor_input(train: list[ViewData], name: str | None = None) -> tuple[int, torch.Tensor, float]:
    """:func:`predictor_inputs` with one view: (its index, its crop, the capture's radiance scale)."""
    ks, crops, scale = predictor_inputs(train, 1, name)
    return ks[0], crops[0], scale


def rotation_y(angle_rad: float) -> torch.Tensor:
    """(3, 3) rotation about world +y (the capture's up axis).

    >>> torch.allclose(rotation_y(math.pi / 2) @ torch.tensor([1., 0, 0]), torch.tensor([0., 0, -1]), atol=1e-6)
    True
    """
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def predictor_image(crop: torch.Tensor, size: int, rotation: torch.Tensor | None = None, mirror: bool = False,
                    rgb_gain: torch.Tensor | None = None, radiance_scale: float | None = None) -> tuple[torch.Tensor, float]:
    """Turn a :func:`view_crop` into the predictor's input, optionally augmented.

    The augmentations are exact re-renderings of another scene: rotating every world vector about
    +y is the same object under the rotated illumination; mirroring the image while reflecting the
    world (x -> -x) is the mirrored scene; per-channel gains are a tinted light.

    Args:
        crop: (10, s, s) from :func:`view_crop`.
        size: output side, pixels.
        rotation: optional (3, 3) world rotation applied to normals and view directions.
        mirror: flip the image left-right and reflect world x.
        rgb_gain: optional (3,) gains of the linear RGB.
        radiance_scale: the capture's radiance scale (after the gains); None = this view's own.

    Returns:
        (9, size, size) float32 image and the radiance scale its RGB was divided by.
    """
    x = F.interpolate(crop[None], size=(size, size), mode="bilinear", antialias=True, align_corners=False)[0]
    mask = x[9:10]
    fg = mask > 0.5
    vec = torch.where(fg, x[:9] / mask.clamp_min(1e-6), torch.zeros(()))  # un-premultiply at the silhouette
    rgb, n, v = vec[0:3], vec[3:6], vec[6:9]
    if rgb_gain is not None:
        rgb = rgb * rgb_gain[:, None, None]
    if mirror:
        rgb, n, v, fg = rgb.flip(-1), n.flip(-1), v.flip(-1), fg.flip(-1)
        n, v = n * torch.tensor([-1.0, 1, 1])[:, None, None], v * torch.tensor([-1.0, 1, 1])[:, None, None]
    if rotation is not None:
        n = torch.einsum("ij,jhw->ihw", rotation, n)
        v = torch.einsum("ij,jhw->ihw", rotation, v)
    scale = radiance_scale if radiance_scale is not None else radiance_scale_of(rgb.permute(1, 2, 0)[fg[0]])
    image = _normalised_image(torch.cat([rgb, n, v, fg.float()])[None], torch.tensor([scale], dtype=torch.float32))
    return image[0], scale


def predictor_images(stacks: torch.Tensor, size: int, radiance_scale: torch.Tensor, margin: float = 0.05) -> torch.Tensor:
    """:func:`view_crop` and :func:`predictor_image` (no augmentation) for a batch of whole views at
    once, on any device: each view is cropped to its foreground's square box (``margin`` of its side
    on each edge) and resampled to ``size`` bilinearly (meant for views rendered near ``size``, so
    no anti-aliasing is needed).

    Args:
        stacks: (N, 10, H, W) linear radiance, normal_world, view_dir_world, coverage.
        size: output side, pixels.
        radiance_scale: (N,) what each view's radiance is divided by (its capture's scale).

    Returns:
        (N, 9, size, size) images; a view without foreground gives zeros.
    """
    n, _, h, w = stacks.shape
    fg = stacks[:, 9] > FOREGROUND_COVERAGE
    rows, cols = fg.any(2), fg.any(1)
    ar_h, ar_w = torch.arange(h, device=stacks.device), torch.arange(w, device=stacks.device)
    y0 = torch.where(rows, ar_h, h).amin(1).float()
    y1 = torch.where(rows, ar_h + 1, 0).amax(1).float()
    x0 = torch.where(cols, ar_w, w).amin(1).float()
    x1 = torch.where(cols, ar_w + 1, 0).amax(1).float()
    side = torch.maximum(y1 - y0, x1 - x0).clamp_min(1.0) * (1 + 2 * margin)
    cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
    theta = torch.zeros(n, 2, 3, device=stacks.device)
    theta[:, 0, 0], theta[:, 0, 2] = side / w, 2 * cx / w - 1
    theta[:, 1, 1], theta[:, 1, 2] = side / h, 2 * cy / h - 1
    grid = F.affine_grid(theta, [n, 10, size, size], align_corners=False)
    x = F.grid_sample(torch.where(fg[:, None], stacks, torch.zeros(())), grid, mode="bilinear", padding_mode="zeros",
                      align_corners=False)
    return _normalised_image(x, radiance_scale)


def _normalised_image(x: torch.Tensor, radiance_scale: torch.Tensor) -> torch.Tensor:
    """(N, 10, S, S) resampled premultiplied stacks -> (N, 9, S, S) predictor images (un-premultiplied
    at the silhouette, unit vectors, log1p(radiance / scale), 0 off the foreground)."""
    mask = x[:, 9:10]
    fg = mask > 0.5
    vec = torch.where(fg, x[:, :9] / mask.clamp_min(1e-6), torch.zeros(()))
    rgb = torch.log1p(vec[:, 0:3].clamp_min(0) / radiance_scale[:, None, None, None]) * fg
    n = F.normalize(vec[:, 3:6], dim=1) * fg
    v = F.normalize(vec[:, 6:9], dim=1) * fg
    return torch.cat([rgb, n, v], 1).float()


def predicted_loss(weights: torch.Tensor, view_dir_world: torch.Tensor, normal_world: torch.Tensor, radiance_norm: torch.Tensor,
                   arch: DamArchitecture, sample_mask: torch.Tensor | None = None, readout_iterations: int = 0) -> torch.Tensor:
    """The training cost: mean L1 between the predicted DAMs' radiance and the capture's.

    Args:
        weights: (B, P) predicted flat weights.
        view_dir_world, normal_world: (B, K, 3) pixel samples of each capture.
        radiance_norm: (B, K, 3) their radiance divided by each capture's radiance scale.
        arch: the DAM architecture.
        sample_mask: optional (B, K) bool, the samples that count (default all).
        readout_iterations: above 0, each DAM's output layer is first solved
            (:func:`.readout.solved_weights`, differentiably) on the even-numbered samples, and
            the cost is the L1 on the odd-numbered ones: the predictor is trained for what
            ``damcap predict`` delivers after its readout solve, scored on pixels the solve did
            not see.

    Returns:
        scalar loss.
    """
    x = encode_inputs(view_dir_world, normal_world, arch.encoding)
    if readout_iterations:
        solve_mask = torch.ones_like(x[..., 0], dtype=torch.bool) if sample_mask is None else sample_mask
        weights = solved_weights(weights, arch, x[:, 0::2], radiance_norm[:, 0::2], solve_mask[:, 0::2].to(x.dtype), readout_iterations)
        x, radiance_norm = x[:, 1::2], radiance_norm[:, 1::2]
        sample_mask = None if sample_mask is None else sample_mask[:, 1::2]
    pred = dam_forward(weights, x, arch)
    err = (pred - radiance_norm).abs()
    if sample_mask is None:
        return err.mean()
    m = sample_mask[..., None].to(err.dtype)
    return (err * m).sum() / (3 * m.sum()).clamp_min(1.0)


def input_images(crops: torch.Tensor | list[torch.Tensor], size: int, radiance_scale: float | None = None) -> tuple[torch.Tensor, float]:
    """The set of :func:`predictor_image` s a predictor reads from one view's :func:`view_crop`
    or several views': (V, 9, size, size) and the radiance scale they are in units of (the
    capture's ``radiance_scale``; None = the first view's own)."""
    crops = [crops] if isinstance(crops, torch.Tensor) else list(crops)
    if not crops:
        raise DamcapError("predict needs at least one input view")
    first, scale = predictor_image(crops[0], size, radiance_scale=radiance_scale)
    return torch.stack([first] + [predictor_image(c, size, radiance_scale=scale)[0] for c in crops[1:]]), scale


@torch.no_grad()
def predict_dam(net: HyperNet, crops: torch.Tensor | list[torch.Tensor], radiance_scale: float | None = None) -> DeepAppearanceMap:
    """Predict a DAM from one view's :func:`view_crop`, or from several views' (a set).

    Args:
        crops: a (10, s, s) crop or a list of them (any sizes).
        radiance_scale: the capture's radiance scale (:func:`.fit.radiance_scale_of` over the train
            views' foreground); None = the (first) input view's own.
    """
    return predict_from_images(net, *input_images(crops, net.arch.input_size, radiance_scale))


@torch.no_grad()
def predict_from_images(net: HyperNet, images: torch.Tensor, scale: float, rotation: torch.Tensor | None = None) -> DeepAppearanceMap:
    """:func:`predict_dam` from its :func:`input_images` (V, 9, S, S), whose RGB is in units of
    ``scale`` (``rotation``: (3, 3), their light rotation when the caller has found it already)."""
    net.eval()
    device = next(net.parameters()).device
    weights = net(images[None].to(device), rotation=None if rotation is None else rotation[None])[0].float().cpu()
    if not torch.isfinite(weights).all():
        raise DamcapError("the predictor produced non-finite weights for this view (is its radiance finite and positive?)")
    return DeepAppearanceMap(net.arch.dam, scale, weights)
