"""Joint material estimation and segmentation (Maximov et al. 2019, Sec. 3.4).

n deep appearance maps and a segmentation network Psi are trained jointly and unsupervised.
Psi, a small encoder-decoder with skip connections shared among materials, maps a frame's
per-pixel colour, normal and position to soft weights W over the n materials; the weights
enter the data cost of every material (the W of Eq. 3):

    c_d = mean_x sum_k W_k(x) |DAM_k(V(x), N(x)) - L(x)|
    c_s = mean_x (1 - sum_k W_k(x)^2)         (zero when every pixel picks one material)
    cost = c_d + beta c_s

Training starts from k-means clusters of the lit pixels' chromaticity (colour without the amount
of light, so clusters follow materials rather than lit and unlit sides), taken from each surface
point's darkest observation among the training views (specular highlights only add light, and
move with the view), with the illumination's tint modelled as a function of the normal; pixels
too dim to shape the clusters are assigned to the nearest one. Psi is first taught these labels
and each DAM its cluster, then everything is refined jointly. (The paper's k-means baseline,
clusters in RGB + normal space with one DAM fitted per cluster, is :func:`kmeans_baseline`.)

The segmentation is carried onto the geometry: the training pixels' world positions with their
weights form a point set, and any new view (or new shape in the same frame) gets weights by
nearest-neighbour lookup, without ground truth.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Literal, get_args

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from torch import nn

from damcap.common.device import resolve_device
from damcap.common.errors import DamcapError
from damcap.common.mesh import bounding_sphere

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, Encoding, dam_forward, encode_inputs, init_weights
from damcap.appearance.views import ViewData, radiance_scale_of
from damcap.appearance.pixels import FOREGROUND_COVERAGE, view_dir_world

# --------------------------------------------------------------------------------------------
# Options
# --------------------------------------------------------------------------------------------

InitColour = Literal["pixel", "darkest-view"]
BRIGHT_FRACTION = 0.02
"""pixels whose mean radiance exceeds this fraction of the radiance scale shape the initial clusters"""


@dataclass(frozen=True)
class SegmentOptions:
    """Options of ``damcap segment``."""

    materials: int = 2
    """number of materials n"""
    steps: int = 1200
    """joint optimisation steps (after the initialisation)"""
    init_steps: int = 300
    """steps that teach Psi the initial (chromaticity k-means) labels and each DAM its cluster"""
    batch_pixels: int = 4096
    """pixels per step"""
    frames_per_step: int = 1
    """training frames Psi sees per step"""
    learning_rate: float = 5e-3
    """Adam learning rate of the DAMs (Psi uses a fifth of it)"""
    sparsity_beta: float = 0.05
    """weight beta of the sparsity cost c_s"""
    prior_weight: float = 1.0
    """weight of the initial labels' cross-entropy during the joint phase (0 = the paper's cost
    alone). The labels are the chromaticity k-means of the same frames, so the fit stays
    unsupervised; keeping them as a soft prior stops the DAMs from trading a material boundary
    for a shading one (measured: bench/segment.md)"""
    illumination_degree: int = 2
    """the initial clustering models the illumination's colour as a polynomial of this degree in
    the world normal (0, 1 or 2; 0 = plain chromaticity k-means): under a tinted environment map
    one material is redder where it faces the sun and bluer where it faces the sky, and plain
    k-means splits it by orientation (measured on the segment-dev captures: bench/segment.md)"""
    init_colour: InitColour = "darkest-view"
    """the colour the initial clustering sees per pixel: 'pixel' (its own) or 'darkest-view' (the
    least bright observation of the same surface point among the training views). Specular
    reflection only adds light and moves with the view, so the darkest observation is the closest
    to the diffuse colour; a material's highlights (tinted by what they reflect) otherwise cluster
    with another material (measured on the segment-dev captures: bench/segment.md)"""
    colour_floor: float = 2e-5
    """pixels whose mean radiance is below this fraction of the radiance scale (the capture's
    95th percentile) show no usable colour and start unlabelled. The clusters are always fitted to
    the pixels above BRIGHT_FRACTION (0.02); dimmer ones down to this floor (e.g. lit only by interreflection) are
    assigned to the nearest cluster"""
    psi_resolution: int = 128
    """Psi runs on frames area-downsampled to at most this many pixels per side; its weights are
    upsampled bilinearly. Speed vs accuracy, measured on the segment-dev captures (128 px): 64
    takes about 0.6x the time of 128 and loses about 0.02 mean IoU (bench/segment.md)"""
    psi_channels: int = 8
    """Psi's base channel count (doubles at each of its two levels)"""
    width: int = 32
    """DAM hidden units"""
    depth: int = 4
    """DAM hidden layers"""
    encoding: Encoding = "nr"
    """DAM input encoding (see DamArchitecture)"""
    seed: int = 0
    """seeds k-means, initialisation and sampling"""
    device: str = "cpu"
    """'cpu', 'cuda' or 'auto'"""

    def validate(self) -> None:
        if self.materials < 1 or self.materials > 16:
            raise DamcapError(f"--materials must be between 1 and 16, got {self.materials}")
        for name in ("steps", "batch_pixels", "frames_per_step"):
            if getattr(self, name) < 1:
                raise DamcapError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if self.init_steps < 0 or self.sparsity_beta < 0 or self.prior_weight < 0:
            raise DamcapError("--init-steps, --sparsity-beta and --prior-weight must be >= 0")
        if self.init_colour not in get_args(InitColour):
            raise DamcapError(f"--init-colour must be one of {', '.join(get_args(InitColour))}, got {self.init_colour!r}")
        if not 0 < self.colour_floor <= BRIGHT_FRACTION:
            raise DamcapError(f"--colour-floor must be in (0, {BRIGHT_FRACTION}], got {self.colour_floor}")
        if self.illumination_degree not in (0, 1, 2):
            raise DamcapError(f"--illumination-degree must be 0, 1 or 2, got {self.illumination_degree}")

    @property
    def architecture(self) -> DamArchitecture:
        return DamArchitecture(width=self.width, depth=self.depth, encoding=self.encoding)


# --------------------------------------------------------------------------------------------
# Features and k-means (the paper's baseline)
# --------------------------------------------------------------------------------------------


def kmeans_features(radiance_lin: np.ndarray, normal_world: np.ndarray, radiance_scale: float, eps: float = 1e-6) -> np.ndarray:
    """Per-pixel features for k-means: RGB and normal, both groups scaled to the same spread.

    RGB is divided by the radiance scale and compressed with x / (1 + x) (HDR highlights would
    otherwise dominate); then each group (3 RGB, 3 normal components) is centred and divided by
    its own root-mean-square spread, so colour and orientation weigh equally in the distance.

    Args:
        radiance_lin: (P, 3) linear radiance.
        normal_world: (P, 3) unit normals.
        radiance_scale: > 0.
        eps: floor of a group's spread (a constant colour stays constant).

    Returns:
        (P, 6) float32.
    """
    rgb = radiance_lin / radiance_scale
    rgb = rgb / (1 + rgb)

    def standardise(x: np.ndarray) -> np.ndarray:
        x = x - x.mean(0)
        return x / max(float(np.sqrt((x * x).sum(1).mean())), eps)

    return np.concatenate([standardise(rgb), standardise(normal_world)], axis=1).astype(np.float32)


def chromaticity_features(radiance_lin: np.ndarray, radiance_scale: float, dark_fraction: float = BRIGHT_FRACTION, eps: float = 1e-8) -> tuple[np.ndarray, np.ndarray]:
    """Shading-invariant colour features for initialising the joint segmentation.

    Chromaticity rgb / (r + g + b) does not change with the amount of light a pixel receives,
    so clusters follow materials rather than lit and unlit sides.

    Args:
        radiance_lin: (P, 3) linear radiance.
        radiance_scale: > 0 (the capture's 95th percentile).
        dark_fraction: pixels darker than this fraction of the scale carry no usable colour.
        eps: floor of the denominator.

    Returns:
        features: (P, 3) float32 chromaticities; bright: (P,) bool, the pixels with usable colour.
    """
    total = radiance_lin.sum(1, keepdims=True)
    chroma = radiance_lin / np.maximum(total, eps)
    return chroma.astype(np.float32), lit_mask(radiance_lin, radiance_scale, dark_fraction)


def lit_mask(radiance_lin: np.ndarray, radiance_scale: float, fraction: float) -> np.ndarray:
    """(P,) bool: pixels whose mean radiance over the channels exceeds ``fraction`` of the scale.

    Args:
        radiance_lin: (P, 3) linear radiance.
        radiance_scale: > 0 (the capture's 95th percentile).
        fraction: of the scale.
    """
    return radiance_lin.sum(1) > 3 * fraction * radiance_scale


def darkest_observation(position_world: np.ndarray, normal_world: np.ndarray, frame_index: np.ndarray, brightness: np.ndarray,
                        radius_world: float, min_cos: float = 0.9) -> np.ndarray:
    """For every pixel, the least bright observation of the same surface point in any frame.

    Two pixels of different frames observe the same surface point when their world positions lie
    within ``radius_world`` of each other and their normals agree (cosine above ``min_cos``; a
    thin part's far side does not count). Each frame contributes its nearest pixel; the pixel
    itself is always a candidate.

    Args:
        position_world: (P, 3) world positions of the pixels of all frames.
        normal_world: (P, 3) their unit normals.
        frame_index: (P,) int, the frame each pixel belongs to.
        brightness: (P,) e.g. r + g + b of the linear radiance.
        radius_world: world units, about half the pixel footprint (see :func:`pixel_spacing`).
        min_cos: normals' agreement.

    Returns:
        (P,) int64 index of the darkest observation of each pixel's surface point.
    """
    pos = np.asarray(position_world, np.float64)
    nrm = np.asarray(normal_world, np.float64)
    best = np.arange(len(pos))
    best_b = np.asarray(brightness, np.float64).copy()
    for f in np.unique(frame_index):
        idx_f = np.flatnonzero(frame_index == f)
        dist, j = cKDTree(pos[idx_f]).query(pos, k=1, distance_upper_bound=radius_world)
        found = np.isfinite(dist)
        cand = idx_f[j[found]]
        rows = np.flatnonzero(found)
        same = (nrm[cand] * nrm[rows]).sum(1) > min_cos
        rows, cand = rows[same], cand[same]
        darker = brightness[cand] < best_b[rows]
        best[rows[darker]] = cand[darker]
        best_b[rows[darker]] = brightness[cand[darker]]
    return best.astype(np.int64)


def pixel_spacing(position_world: list[np.ndarray]) -> float:
    """World distance between neighbouring pixels: median over frames of the median distance
    from a pixel to its nearest neighbour in the same frame.

    Args:
        position_world: per frame, (P_f, 3) the foreground pixels' world positions.
    """
    meds = [float(np.median(cKDTree(p).query(p, k=2)[0][:, 1])) for p in position_world if len(p) > 1]
    return float(np.median(meds)) if meds else 0.0


def kmeans(features: np.ndarray, k: int, seed: int, iterations: int = 50, restarts: int = 4) -> np.ndarray:
    """Lloyd's k-means with k-means++ seeding; the best of ``restarts`` runs.

    Args:
        features: (P, D) float32.
        k: clusters.
        seed: random seed.

    Returns:
        (P,) int64 labels in [0, k).
    """
    x = torch.from_numpy(np.ascontiguousarray(features)).float()
    gen = torch.Generator().manual_seed(seed)
    best, best_cost = None, math.inf
    sub = x[torch.randperm(x.shape[0], generator=gen)[:20000]]
    for _ in range(restarts):
        centres = sub[torch.randint(0, sub.shape[0], (1,), generator=gen)]
        for _ in range(1, k):  # k-means++
            d2 = torch.cdist(sub, centres).min(1).values ** 2
            centres = torch.cat([centres, sub[torch.multinomial(d2 + 1e-12, 1, generator=gen)]])
        for _ in range(iterations):
            lab = torch.cdist(sub, centres).argmin(1)
            new = torch.stack([sub[lab == j].mean(0) if (lab == j).any() else centres[j] for j in range(k)])
            if torch.allclose(new, centres):
                break
            centres = new
        cost = float((torch.cdist(sub, centres).min(1).values ** 2).sum())
        if cost < best_cost:
            best, best_cost = centres, cost
    labels = torch.cat([torch.cdist(x[s:s + 65536], best).argmin(1) for s in range(0, x.shape[0], 65536)])
    return labels.numpy().astype(np.int64)


def normal_polynomial(normal_world: np.ndarray, degree: int) -> np.ndarray:
    """Polynomial basis of a unit normal without the constant term (the real spherical harmonics'
    shapes: degree 1 adds x, y, z; degree 2 adds xy, xz, yz, x^2 - y^2, 3z^2 - 1).

    Args:
        normal_world: (P, 3) unit normals.
        degree: 0, 1 or 2.

    Returns:
        (P, D) float64, D = 0, 3 or 8.

    >>> normal_polynomial(np.array([[0.0, 0.0, 1.0]]), 2).tolist()
    [[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 2.0]]
    """
    n = np.asarray(normal_world, dtype=np.float64)
    if degree == 0:
        return np.zeros((len(n), 0))
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    cols = [x, y, z]
    if degree >= 2:
        cols += [x * y, x * z, y * z, x * x - y * y, 3 * z * z - 1]
    return np.stack(cols, axis=1)


def illumination_aware_kmeans(chroma: np.ndarray, normal_world: np.ndarray, k: int, seed: int, degree: int = 2,
                              iterations: int = 30, ridge: float = 1e-2, eps: float = 1e-6, fit: np.ndarray | None = None) -> np.ndarray:
    """Cluster colours into materials while a smooth illumination colour varies with the normal.

    Model: ``log chroma_i = a_{label_i} + B(n_i) theta + s_i``: a log-chromaticity per material
    ``a``, an illumination tint that is a polynomial ``B`` of the world normal shared by all
    materials (the diffuse irradiance of a distant environment is smooth in the normal), and a
    per-pixel grey level ``s`` (removed by centring over the channels). Alternates labels (nearest
    ``a``), the materials' ``a`` (means) and ``theta`` (ridge least squares), starting from plain
    k-means on the log chromaticity. Degree 0 is that k-means alone.

    Args:
        chroma: (P, 3) chromaticities (see :func:`chromaticity_features`) of lit pixels.
        normal_world: (P, 3) their unit normals.
        k: clusters.
        seed: k-means seed.
        degree: polynomial degree, 0..2.
        iterations: alternation rounds at most (stops when the labels settle).
        ridge: ridge on theta, relative to the number of pixels.
        eps: floor of a chromaticity before the log.
        fit: (P,) bool, the pixels the clusters and the tint are fitted to (default: all). The
            others (e.g. too dim to shape the clusters) are only assigned: nearest material
            after removing the fitted tint.

    Returns:
        (P,) int64 labels in [0, k).
    """
    f_all = np.log(np.maximum(np.asarray(chroma, dtype=np.float64), eps))
    f_all -= f_all.mean(axis=1, keepdims=True)
    fit = np.ones(len(f_all), bool) if fit is None else np.asarray(fit, bool)
    f = f_all[fit]
    labels = kmeans(f.astype(np.float32), k, seed)
    basis_all = normal_polynomial(normal_world, degree)
    basis_mean = basis_all[fit].mean(axis=0) if fit.any() else np.zeros(basis_all.shape[1])
    basis = basis_all[fit] - basis_mean
    theta = np.zeros((basis.shape[1], 3))
    if basis.shape[1] == 0:
        return _assign_rest(labels, fit, f_all, _cluster_means(f, labels, k))
    normal_eq = basis.T @ basis + ridge * len(basis) * np.eye(basis.shape[1])
    tint = np.zeros_like(f)
    for _ in range(iterations):
        untinted = f - tint
        centres = np.stack([untinted[labels == j].mean(0) if (labels == j).any() else np.zeros(3) for j in range(k)])
        theta = np.linalg.solve(normal_eq, basis.T @ (f - centres[labels]))
        tint = basis @ theta
        d2 = (((f - tint)[:, None, :] - centres[None]) ** 2).sum(-1)
        new = d2.argmin(1)
        if np.array_equal(new, labels):
            break
        labels = new
    return _assign_rest(labels, fit, f_all - (basis_all - basis_mean) @ theta, centres)


def _cluster_means(features: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """(k, D) mean feature per label; an empty cluster's centre is infinitely far."""
    return np.stack([features[labels == j].mean(0) if (labels == j).any() else np.full(features.shape[1], np.inf) for j in range(k)])


def _assign_rest(fit_labels: np.ndarray, fit: np.ndarray, features: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(P,) labels: ``fit_labels`` on the fitted pixels, the nearest centre elsewhere."""
    labels = np.empty(len(fit), np.int64)
    labels[fit] = fit_labels
    rest = ~fit
    if rest.any():
        labels[rest] = (((features[rest][:, None, :] - centres[None]) ** 2).sum(-1)).argmin(1)
    return labels


# --------------------------------------------------------------------------------------------
# The segmentation network Psi
# --------------------------------------------------------------------------------------------


class SegmentationNet(nn.Module):
    """Psi: a small U-Net. (B, 9, H, W) colour/normal/position -> (B, n, H, W) logits.

    Frames larger than ``resolution`` are area-downsampled before the network and its logits
    upsampled bilinearly back to the frame's size.
    """

    def __init__(self, materials: int, channels: int = 8, in_channels: int = 9, resolution: int = 64) -> None:
        super().__init__()
        c = channels
        block = lambda i, o: nn.Sequential(nn.Conv2d(i, o, 3, padding=1), nn.LeakyReLU(0.1), nn.Conv2d(o, o, 3, padding=1), nn.LeakyReLU(0.1))  # noqa: E731
        self.enc0, self.enc1, self.enc2 = block(in_channels, c), block(c, 2 * c), block(2 * c, 4 * c)
        self.dec1, self.dec0 = block(6 * c, 2 * c), block(3 * c, c)
        self.head = nn.Conv2d(c, materials, 1)
        self.materials = materials
        self.channels = channels
        self.resolution = resolution

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        full = x.shape[-2:]
        factor = max(1, math.ceil(max(full) / self.resolution))
        if factor > 1:
            x = F.avg_pool2d(x, factor, ceil_mode=True)
        logits = self._unet(x)
        if factor > 1:
            logits = F.interpolate(logits, scale_factor=float(factor), mode="bilinear", align_corners=False)[..., : full[0], : full[1]]
        return logits

    def _unet(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        ph, pw = (-h) % 4, (-w) % 4
        x = F.pad(x, (0, pw, 0, ph))
        e0 = self.enc0(x)
        e1 = self.enc1(F.avg_pool2d(e0, 2))
        e2 = self.enc2(F.avg_pool2d(e1, 2))
        d1 = self.dec1(torch.cat([F.interpolate(e2, scale_factor=2.0, mode="bilinear", align_corners=False), e1], 1))
        d0 = self.dec0(torch.cat([F.interpolate(d1, scale_factor=2.0, mode="bilinear", align_corners=False), e0], 1))
        return self.head(d0)[..., :h, :w]


def psi_inputs(view: ViewData, radiance_scale: float, scene_centre: np.ndarray, scene_radius: float) -> torch.Tensor:
    """Psi's input image: (9, H, W) = tone-mapped RGB, normal, normalised position; 0 off the object."""
    d = view.data
    fg = (d.coverage > FOREGROUND_COVERAGE)[..., None]
    rgb = d.radiance_lin / radiance_scale
    rgb = 2 * rgb / (1 + rgb) - 1
    pos = (d.position_world - scene_centre) / scene_radius
    img = np.concatenate([rgb, d.normal_world, pos], -1) * fg
    return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))).float()


# --------------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------------


@dataclass
class _Frames:
    images: torch.Tensor  # (F, 9, H, W)
    fg_index: list[torch.Tensor]  # per frame: (P_f,) flat pixel indices of the foreground
    dam_inputs: list[torch.Tensor]  # per frame: (P_f, C)
    targets: list[torch.Tensor]  # per frame: (P_f, 3) radiance / scale


@dataclass
class SegmentationModel:
    """What ``segment`` produces: n DAMs, Psi, and the segmentation carried onto the geometry."""

    dams: list[DeepAppearanceMap]
    psi: SegmentationNet
    radiance_scale: float
    scene_centre: np.ndarray
    scene_radius: float
    points_world: np.ndarray
    """(M, 3) float32 training-pixel positions"""
    point_weights: np.ndarray
    """(M, n) float32 their material weights"""
    history: list[dict[str, float]] = field(default_factory=list)
    seconds: float = 0.0
    has_psi: bool = True
    """False for the k-means baseline: its weights always come from the geometry"""

    @property
    def materials(self) -> int:
        return len(self.dams)

    @torch.no_grad()
    def weights_of(self, view: ViewData) -> np.ndarray:
        """(H, W, n) Psi's weights for a frame with colour (a training frame); 0 off the object."""
        if not self.has_psi:
            return self.weights_at(view.data.position_world) * (view.data.coverage > 0)[..., None]
        x = psi_inputs(view, self.radiance_scale, self.scene_centre, self.scene_radius)[None]
        w = torch.softmax(self.psi(x), 1)[0].permute(1, 2, 0).numpy()
        return w * (view.data.coverage > 0)[..., None]

    def point_tree(self) -> cKDTree:
        """The k-d tree of ``points_world`` (built once per point set)."""
        cached = self.__dict__.get("_point_tree")
        if cached is None or cached[0] is not self.points_world:
            cached = (self.points_world, cKDTree(self.points_world))
            self.__dict__["_point_tree"] = cached
        return cached[1]

    def weights_at(self, position_world: np.ndarray, k: int = 4) -> np.ndarray:
        """(..., n) weights carried from the geometry: mean of the k nearest training points."""
        tree = self.point_tree()
        flat = position_world.reshape(-1, 3)
        _, idx = tree.query(flat, k=min(k, len(self.points_world)))
        idx = idx.reshape(len(flat), -1)
        return self.point_weights[idx].mean(1).reshape(position_world.shape[:-1] + (self.materials,))

    @torch.no_grad()
    def render(self, view: ViewData, weights: np.ndarray) -> np.ndarray:
        """(H, W, 3) radiance sum_k W_k DAM_k(V, N) on covered pixels."""
        d = view.data
        cov = d.coverage > 0
        out = np.zeros(cov.shape + (3,), np.float32)
        if not cov.any():
            return out
        v = torch.from_numpy(view_dir_world(d.position_world[cov], view.centre_world))
        n = torch.from_numpy(np.ascontiguousarray(d.normal_world[cov]))
        w = torch.from_numpy(np.ascontiguousarray(weights[cov])).float()
        rad = sum(w[:, k:k + 1] * dam(v, n) for k, dam in enumerate(self.dams))
        out[cov] = rad.numpy()
        return out


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


def scene_bounds(views: list[ViewData]) -> tuple[np.ndarray, float]:
    """Centre and radius of the training foreground's world positions."""
    pts = np.concatenate([v.data.position_world[v.data.coverage > FOREGROUND_COVERAGE] for v in views])
    centre, radius = bounding_sphere(pts)
    return centre.astype(np.float32), max(radius, 1e-6)


def initial_labels(views: list[ViewData], radiance_scale: float, opts: SegmentOptions) -> list[np.ndarray]:
    """The clustering the joint training starts from: one material label per foreground pixel.

    k-means on the chromaticity of the bright pixels (of each pixel's own colour or of its
    surface point's darkest observation, ``opts.init_colour``), with the illumination's tint
    modelled as a polynomial of the normal (``opts.illumination_degree``); pixels between
    ``opts.colour_floor`` and the bright level are assigned to the nearest cluster.

    Args:
        views: training views.
        radiance_scale: the capture's radiance scale (:func:`.fit.radiance_scale_of`).
        opts: materials, seed, init_colour, colour_floor, illumination_degree.

    Returns:
        per view, (P_f,) int64 labels of its foreground pixels (row-major order) in [0, n);
        -1 where a pixel is too dark to show its colour.
    """
    opts.validate()
    n = opts.materials
    fgs = [v.data.coverage > FOREGROUND_COVERAGE for v in views]
    rad = np.concatenate([v.data.radiance_lin[fg] for v, fg in zip(views, fgs)])
    nrm = np.concatenate([v.data.normal_world[fg] for v, fg in zip(views, fgs)])
    chroma, bright = chromaticity_features(rad, radiance_scale)
    usable = np.flatnonzero(lit_mask(rad, radiance_scale, opts.colour_floor))  # includes the bright pixels
    if opts.init_colour == "darkest-view" and len(usable):
        fg_pos = [v.data.position_world[fg] for v, fg in zip(views, fgs)]
        frame = np.concatenate([np.full(len(p), i) for i, p in enumerate(fg_pos)])
        darkest = darkest_observation(np.concatenate(fg_pos)[usable], nrm[usable], frame[usable], rad[usable].sum(1),
                                      0.5 * pixel_spacing(fg_pos))
        chroma = chroma.copy()
        chroma[usable] = chroma[usable][darkest]
    labels = np.full(len(chroma), -1, np.int64)
    fit = bright[usable]  # the clusters are fitted to the bright pixels; dim ones are only assigned
    if fit.sum() < n:  # nothing lit enough to tell colours apart
        labels[:] = np.arange(len(chroma)) % n
    elif opts.illumination_degree == 0:
        fit_labels = kmeans(chroma[usable][fit], n, opts.seed)
        labels[usable] = _assign_rest(fit_labels, fit, chroma[usable], _cluster_means(chroma[usable][fit], fit_labels, n))
    else:
        labels[usable] = illumination_aware_kmeans(chroma[usable], nrm[usable], n, opts.seed, opts.illumination_degree, fit=fit)
    return np.split(labels, np.cumsum([int(fg.sum()) for fg in fgs])[:-1])


def segment_materials(views: list[ViewData], opts: SegmentOptions, progress: Callable[[int, int, dict[str, float]], None] | None = None) -> SegmentationModel:
    """Train n DAMs and Psi jointly on training views (unsupervised).

    Args:
        views: training views (colour, normals, positions).
        opts: options.
        progress: progress(step, total, stats) after every step.
    """
    opts.validate()
    if not views:
        raise DamcapError("segment needs at least one training view")
    t0 = time.perf_counter()
    device = resolve_device(opts.device)
    arch = opts.architecture
    n = opts.materials
    gen = torch.Generator().manual_seed(opts.seed)
    scale = radiance_scale_of(torch.from_numpy(np.concatenate([v.data.radiance_lin[v.data.coverage > FOREGROUND_COVERAGE] for v in views])))
    centre, radius = scene_bounds(views)
    frames = _prepare(views, arch.encoding, scale, centre, radius)
    init_labels = [torch.from_numpy(lab) for lab in initial_labels(views, scale, opts)]

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(opts.seed)
        psi = SegmentationNet(n, channels=opts.psi_channels, resolution=opts.psi_resolution).to(device)
    dam_w = nn.Parameter(torch.stack([init_weights(arch, gen) for _ in range(n)]).to(device))
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
        opt.zero_grad()
        loss.backward()
        opt.step()
        if (step + 1) % 100 == 0 or step + 1 == total:
            history.append({"step": step + 1, **stats, "seconds": time.perf_counter() - t0})
        if progress:
            progress(step + 1, total, stats)

    psi = psi.cpu().eval()
    dams = [DeepAppearanceMap(arch, scale, dam_w.detach()[k].cpu()) for k in range(n)]
    model = SegmentationModel(dams, psi, scale, centre, radius, np.zeros((0, 3), np.float32), np.zeros((0, n), np.float32), history)
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


def mesh_material_weights(model: SegmentationModel, vertices: np.ndarray, align: str = "sphere") -> np.ndarray:
    """Material weights for the vertices of any mesh, carried from the segmentation's 3D points.

    Args:
        model: a segmentation (its training pixels' positions and weights).
        vertices: (V, 3) mesh vertices.
        align: 'none': the mesh is in the capture's world frame (e.g. the reconstruction's own
            geometry); 'sphere': a new shape, whose bounding sphere (bounding-box centre, largest
            distance) is mapped onto that of the training pixels, so materials land at the same
            place relative to the object (exact for the captured shape when the training views
            saw all of it).

    Returns:
        (V, n) float32 weights (mean of the 4 nearest training points).
    """
    if align not in ("none", "sphere"):
        raise DamcapError(f"--align must be 'none' or 'sphere', got {align!r}")
    v = np.asarray(vertices, np.float64)
    if align == "sphere":
        centre, radius = bounding_sphere(v)
        v = (v - centre) / max(radius, 1e-30) * model.scene_radius + model.scene_centre
    return model.weights_at(v.astype(np.float32)).astype(np.float32)


# --------------------------------------------------------------------------------------------
# The k-means baseline: clusters in RGB + normal space, one DAM fitted per cluster
# --------------------------------------------------------------------------------------------


def kmeans_baseline(views: list[ViewData], materials: int, steps: int = 1500, seed: int = 0, encoding: Encoding = "nr") -> SegmentationModel:
    """The paper's baseline as a :class:`SegmentationModel` (hard weights; Psi unused)."""
    from damcap.appearance.fit import FitOptions, fit_dam
    from damcap.appearance.pixels import PixelSamples

    t0 = time.perf_counter()
    fgs = [v.data.coverage > FOREGROUND_COVERAGE for v in views]
    rad = np.concatenate([v.data.radiance_lin[fg] for v, fg in zip(views, fgs)])
    nrm = np.concatenate([v.data.normal_world[fg] for v, fg in zip(views, fgs)])
    pos = np.concatenate([v.data.position_world[fg] for v, fg in zip(views, fgs)])
    vd = np.concatenate([view_dir_world(v.data.position_world[fg], v.centre_world) for v, fg in zip(views, fgs)])
    fidx = np.concatenate([np.full(int(fg.sum()), k) for k, fg in enumerate(fgs)])
    scale = radiance_scale_of(torch.from_numpy(rad))
    labels = kmeans(kmeans_features(rad, nrm, scale), materials, seed)
    dams = []
    for k in range(materials):
        w = torch.from_numpy((labels == k).astype(np.float32))
        samples = PixelSamples(torch.from_numpy(vd), torch.from_numpy(nrm), torch.from_numpy(rad), w, torch.from_numpy(fidx))
        if w.sum() == 0:
            dams.append(DeepAppearanceMap(DamArchitecture(encoding=encoding), scale))
            continue
        # the same DAM architecture as the joint segmentation's
        opts = FitOptions(steps=steps, seed=seed, holdout_views=0).for_architecture(DamArchitecture(encoding=encoding))
        dams.append(fit_dam(samples, opts).model)
    centre, radius = scene_bounds(views)
    onehot = np.eye(materials, dtype=np.float32)[labels]
    keep = np.random.default_rng(seed).choice(len(pos), min(len(pos), 200_000), replace=False)
    model = SegmentationModel(dams, SegmentationNet(materials), scale, centre, radius, pos[keep].astype(np.float32), onehot[keep], has_psi=False)
    model.seconds = time.perf_counter() - t0
    return model


# --------------------------------------------------------------------------------------------
# Scores
# --------------------------------------------------------------------------------------------


def match_materials(pred_weights: np.ndarray, true_weights: np.ndarray) -> tuple[np.ndarray, float]:
    """Match predicted to true materials by maximum total IoU of the arg-max labels (Hungarian).

    Args:
        pred_weights: (P, n_pred) weights on foreground pixels.
        true_weights: (P, n_true) weights on the same pixels.

    Returns:
        perm: (n_true,) predicted material index for each true material (-1 = none),
        mean IoU over the true materials.
    """
    p = pred_weights.argmax(1)
    t = true_weights.argmax(1)
    n_p, n_t = pred_weights.shape[1], true_weights.shape[1]
    iou = np.zeros((n_t, n_p))
    for i in range(n_t):
        for j in range(n_p):
            inter = np.sum((t == i) & (p == j))
            union = np.sum((t == i) | (p == j))
            iou[i, j] = inter / union if union else 0.0
    rows, cols = linear_sum_assignment(-iou)
    perm = np.full(n_t, -1)
    perm[rows] = cols
    return perm, float(np.mean([iou[i, perm[i]] if perm[i] >= 0 else 0.0 for i in range(n_t)]))


def options_json(opts: SegmentOptions) -> dict:
    return asdict(opts)




def novel_view_dssim(model: SegmentationModel, views: list[ViewData], seen_only: bool = False, seen_radius: float = 0.02) -> float:
    """Mean DSSIM of the model on views, weights carried from the geometry (no ground truth).

    Args:
        seen_only: score only the pixels whose surface point the training views saw (within
            ``seen_radius`` x the scene radius of a training pixel's position). Elsewhere the
            weights are extrapolated by nearest neighbour and the DAMs' inputs were never
            observed, so errors there mostly measure extrapolation luck, not the materials.
    """
    from damcap.appearance.evaluate import score_view
    from damcap.appearance.metrics import dssim

    scores = []
    tree = model.point_tree() if seen_only else None
    for v in views:
        pred = model.render(v, model.weights_at(v.data.position_world))
        if tree is None:
            scores.append(score_view(v, pred))
            continue
        dist, _ = tree.query(v.data.position_world.reshape(-1, 3))
        seen = (dist < seen_radius * model.scene_radius).reshape(v.data.coverage.shape)
        scores.append(dssim(v.data.radiance_lin, pred, v.data.coverage * seen))
    vals = [s for s in scores if s is not None]
    return float(np.mean(vals)) if vals else float("nan")


def material_shares(model: SegmentationModel, views: list[ViewData]) -> np.ndarray:
    """(n,) fraction of the views' foreground pixels whose largest weight is each material's."""
    labels = np.concatenate([model.weights_of(v)[v.data.coverage > FOREGROUND_COVERAGE].argmax(-1) for v in views])
    return np.bincount(labels, minlength=model.materials) / max(len(labels), 1)


@dataclass
class MaterialChoice:
    """The outcome of ``--materials auto`` (or of a target accuracy)."""

    model: SegmentationModel
    materials: int
    curve: list[dict[str, Any]]
    """per n tried: materials, heldout_dssim (the best restart's), per-restart errors, shares, seconds"""
    margin: float
    reason: str
    """why this n, in words"""


def choose_materials(train: list[ViewData], heldout: list[ViewData], opts: SegmentOptions, max_materials: int = 4, margin: float = 0.1,
                     min_gain: float = 0.01, restarts: int = 2, min_share: float = 0.01, target_dssim: float | None = None,
                     progress: Callable[[int, int, dict[str, float]], None] | None = None,
                     log: Callable[[str], None] | None = None) -> MaterialChoice:
    """The smallest n whose held-out error stops improving: n is kept when n + 1 materials lower
    the held-out DSSIM by less than ``margin`` (relative) or less than ``min_gain`` (absolute),
    or when ``max_materials`` is reached.
    With ``target_dssim``: the smallest n whose held-out DSSIM is at most the target.

    The held-out error is the test split's DSSIM on the surface the training views saw
    (:func:`novel_view_dssim` with ``seen_only``), the best of ``restarts`` runs with different
    seeds: measured on closed-form captures, one run's novel-view DSSIM varies by up to 2x with
    the seed (the DAMs extrapolate to unseen inputs differently), more than one material more
    or less changes it. Near-perfect fits (DSSIM ~0.005) change by tens of percent between
    seeds, hence the absolute floor ``min_gain``. An n + 1 whose run leaves a material (almost)
    unused (largest weight on less than ``min_share`` of the training pixels) is no n + 1
    material model and never counts as an improvement.

    Args:
        train: views to fit.
        heldout: views to score (the test split), weights carried from the geometry.
        opts: segment options (``materials`` is ignored; ``seed`` is the first restart's).
        max_materials: the largest n tried.
        margin: relative improvement that justifies one more material (0.1 = 10 %).
        min_gain: absolute DSSIM improvement that one more material must also bring.
        restarts: runs per n (seeds ``seed``, ``seed + 1``, ...); the best is kept.
        min_share: smallest share of the training pixels a material must win.
        target_dssim: stop at the first n that reaches this held-out DSSIM instead.
        log: called with one line per n tried.
    """
    if not heldout:
        raise DamcapError("--materials auto needs held-out views (a non-empty test split)")
    if restarts < 1 or max_materials < 1:
        raise DamcapError(f"--restarts and --max-materials must be >= 1, got {restarts} and {max_materials}")
    if target_dssim is not None and not 0 < target_dssim < 1:
        raise DamcapError(f"--target-dssim must lie in (0, 1), got {target_dssim}")
    curve: list[dict[str, Any]] = []
    best: SegmentationModel | None = None
    best_err = math.inf
    for n in range(1, max_materials + 1):
        runs = []
        for r in range(restarts):
            model = segment_materials(train, SegmentOptions(**{**asdict(opts), "materials": n, "seed": opts.seed + r}), progress)
            runs.append((novel_view_dssim(model, heldout, seen_only=True), model))
        err, model = min(runs, key=lambda t: t[0])
        shares = material_shares(model, train)
        used = bool(shares.min() >= min_share)
        curve.append({"materials": n, "heldout_dssim": err, "restarts": [e for e, _ in runs], "shares": shares.round(4).tolist(),
                      "all_used": used, "seconds": sum(m.seconds for _, m in runs)})
        if log:
            log(f"n = {n}: held-out DSSIM (seen surface) {err:.4f}, best of {restarts} run(s), "
                f"material shares {', '.join(f'{x:.2f}' for x in shares)}, {curve[-1]['seconds']:.0f} s")
        if target_dssim is not None:
            if used and err <= target_dssim:
                return MaterialChoice(model, n, curve, margin, f"the fewest materials whose held-out DSSIM {err:.4f} <= {target_dssim}")
            if best is None or (used and err < best_err):
                best, best_err = model, err
            continue
        if best is not None and not (used and err < best_err - max(margin * best_err, min_gain)):
            why = "left a material unused" if not used else f"improved held-out DSSIM by less than {margin:.0%} or {min_gain}"
            return MaterialChoice(best, best.materials, curve, margin, f"n = {n} {why}")
        best, best_err = model, err
    assert best is not None
    if target_dssim is not None:
        return MaterialChoice(best, best.materials, curve, margin, f"no n up to {max_materials} reached {target_dssim}; kept the most accurate")
    return MaterialChoice(best, best.materials, curve, margin, f"every n up to --max-materials {max_materials} improved")


#: false colours of the preview images (material k -> RGB in [0, 1])
PALETTE = np.array([[0.90, 0.30, 0.25], [0.25, 0.60, 0.95], [0.95, 0.80, 0.20], [0.40, 0.80, 0.40],
                    [0.70, 0.40, 0.85], [0.95, 0.55, 0.10], [0.30, 0.85, 0.85], [0.85, 0.85, 0.85]], np.float32)


def false_colour(weights: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 preview: each pixel the weight-blend of its materials' palette colours."""
    pal = PALETTE[np.arange(weights.shape[-1]) % len(PALETTE)]
    rgb = weights @ pal * (coverage > 0)[..., None]
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def segmentation_scores(model: SegmentationModel, train: list[ViewData], targets: list[ViewData], same_view: bool) -> dict[str, dict[str, float | None]]:
    """Per-frame DSSIM of a segmentation on targets, by where the weights come from.

    Returns:
        ``{"estimated weights": {...}}`` always (Psi's weights on training frames when
        ``same_view``), plus ``{"true weights": {...}}`` when the targets carry ground-truth
        weights (materials matched to the truth on the training frames by IoU).
    """
    from damcap.appearance.evaluate import score_view

    out: dict[str, dict[str, float | None]] = {"estimated weights": {}}
    for v in targets:
        w = model.weights_of(v) if same_view else model.weights_at(v.data.position_world)
        out["estimated weights"][v.name] = score_view(v, model.render(v, w))
    if all(v.data.weights is not None for v in train + targets):
        fgs = [v.data.coverage > FOREGROUND_COVERAGE for v in train]
        pw = np.concatenate([model.weights_at(v.data.position_world[fg]) for v, fg in zip(train, fgs)])
        tw = np.concatenate([v.data.weights[fg] for v, fg in zip(train, fgs)])
        perm, _ = match_materials(pw, tw)
        out["true weights"] = {}
        for v in targets:
            w = np.zeros(v.data.weights.shape[:-1] + (model.materials,), np.float32)
            for i, j in enumerate(perm):
                if j >= 0:
                    w[..., j] += v.data.weights[..., i]
            out["true weights"][v.name] = score_view(v, model.render(v, w))
    return out
