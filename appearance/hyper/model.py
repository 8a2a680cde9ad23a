"""Learning-to-learn (Maximov et al. 2019, Sec. 3.3): a CNN that maps one image to a DAM's weights.

The predictor Theta(I | phi) reads a 9-channel image of the object (linear RGB, world-space
normal, world-space view direction; covered pixels only, 0 elsewhere) and outputs the flat weight
vector of a deep appearance map (:mod:`.dam`). Eight stride-2 convolutions halve the resolution
from 256 to 1, a fully-connected layer maps the last features to a *correction* of a learned mean
weight vector (so an untrained predictor already outputs a valid DAM: the mean appearance).

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

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, dam_forward, encode_inputs, init_weights
from damcap.appearance.views import ViewData, radiance_scale_of
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

    def __post_init__(self) -> None:
        # bounded before any layer is built from them (a predictor file's metadata, an option)
        bounded_int(len(self.channels), 1, MAX_CONV_LAYERS, "number of predictor --channels layers")
        for c in self.channels:
            bounded_int(c, 1, MAX_CHANNELS, "predictor channels")
        bounded_int(self.input_size, 1, MAX_IMAGE_SIDE, "predictor --input-size")
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
        """Inverse of :meth:`to_json`.

        >>> a = HyperArchitecture(input_size=64, channels=(4, 8))
        >>> HyperArchitecture.from_json(a.to_json()) == a
        True
        """
        d = dict(d)
        return HyperArchitecture(input_size=int(d["input_size"]), channels=tuple(int(c) for c in d["channels"]),
                                 dam=DamArchitecture(**d["dam"]))


class HyperNet(nn.Module):
    """Theta: (B, 9, S, S) predictor images -> (B, P) flat DAM weights."""

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

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        f = self.features(images)
        f = F.adaptive_avg_pool2d(f, 1).flatten(1)
        return self.base[None] + self.head(f)


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


def choose_input_view(covered_px: list[int], scales: list[float], min_brightness: float = 0.1) -> int:
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


def predictor_input(train: list[ViewData], name: str | None = None) -> tuple[int, torch.Tensor, float]:
    """What ``damcap predict`` feeds the network, from a capture's train views.

    Args:
        train: the train split's views.
        name: the input view's name (file stem); None = :func:`choose_input_view`.

    Returns:
        (index of the input view, its :func:`view_crop`, the capture's radiance scale over all
        train views' foreground, the fit's).

    Raises:
        DamcapError: ``name`` is not a train view.
    """
    fgs = [v.data.coverage > FOREGROUND_COVERAGE for v in train]
    pixels = [torch.from_numpy(v.data.radiance_lin[fg]) for v, fg in zip(train, fgs, strict=True)]
    if name is None:
        k = choose_input_view([int(fg.sum()) for fg in fgs], [radiance_scale_of(p) for p in pixels])
    else:
        names = [v.name for v in train]
        if name not in names:
            raise DamcapError(f"--view {name!r} is not a train-split frame; choose one of "
                              f"{', '.join(names[:12])}{' ...' if len(names) > 12 else ''}")
        k = names.index(name)
    d = train[k].data
    crop = view_crop(d.radiance_lin, d.normal_world, view_dir_world(d.position_world, train[k].centre_world), d.coverage)
    return k, crop, radiance_scale_of(torch.cat(pixels))


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
    n = F.normalize(n, dim=0) * fg
    v = F.normalize(v, dim=0) * fg
    scale = radiance_scale if radiance_scale is not None else radiance_scale_of(rgb.permute(1, 2, 0)[fg[0]])
    rgb = torch.log1p(rgb.clamp_min(0) / scale) * fg
    return torch.cat([rgb, n, v]).float(), scale


def predicted_loss(weights: torch.Tensor, view_dir_world: torch.Tensor, normal_world: torch.Tensor, radiance_norm: torch.Tensor,
                   arch: DamArchitecture) -> torch.Tensor:
    """The training cost: mean L1 between the predicted DAMs' radiance and the capture's.

    Args:
        weights: (B, P) predicted flat weights.
        view_dir_world, normal_world: (B, K, 3) pixel samples of each capture.
        radiance_norm: (B, K, 3) their radiance divided by each capture's radiance scale.
        arch: the DAM architecture.

    Returns:
        scalar loss.
    """
    pred = dam_forward(weights, encode_inputs(view_dir_world, normal_world, arch.encoding), arch)
    return (pred - radiance_norm).abs().mean()


@torch.no_grad()
def predict_dam(net: HyperNet, crop: torch.Tensor, radiance_scale: float | None = None) -> DeepAppearanceMap:
    """Predict a DAM from one view's :func:`view_crop`.

    Args:
        radiance_scale: the capture's radiance scale (:func:`.fit.radiance_scale_of` over the train
            views' foreground); None = the input view's own.
    """
    net.eval()
    image, scale = predictor_image(crop, net.arch.input_size, radiance_scale=radiance_scale)
    device = next(net.parameters()).device
    weights = net(image[None].to(device))[0].float().cpu()
    if not torch.isfinite(weights).all():
        raise DamcapError("the predictor produced non-finite weights for this view (is its radiance finite and positive?)")
    return DeepAppearanceMap(net.arch.dam, scale, weights)
