"""The segmentation network Psi and :class:`SegmentationModel` (n DAMs, Psi, and the segmentation
carried onto the geometry as a weighted point set)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import nn

from damcap.common.errors import DamcapError
from damcap.common.mesh import bounding_sphere

from damcap.appearance.dam import DeepAppearanceMap
from damcap.appearance.views import ViewData
from damcap.appearance.pixels import FOREGROUND_COVERAGE, view_dir_world


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
    prior_choice: dict = field(default_factory=dict)
    """the predictor's prior (``SegmentOptions.prior``): the mode, whether it was used, and for
    'auto' the held-out scores and the mode kept"""

    @property
    def materials(self) -> int:
        return len(self.dams)

    @torch.no_grad()
    def weights_of(self, view: ViewData) -> np.ndarray:
        """(H, W, n) Psi's weights for a frame with colour (a training frame); 0 off the object."""
        if not self.has_psi:
            return self.weights_on(view)
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

    def weights_on(self, view: ViewData) -> np.ndarray:
        """(H, W, n) weights carried from the geometry onto a frame's covered pixels; 0 off the object.

        Only covered pixels are looked up: a background pixel's position (0 by the capture format)
        can lie far from every training point, where a k-d tree query costs about 150x a surface
        one (the demo's 320 px frames: 17 s a frame, against 0.02 s for the object's pixels).
        """
        cov = view.data.coverage > 0
        out = np.zeros(cov.shape + (self.materials,), np.float32)
        if cov.any():
            out[cov] = self.weights_at(view.data.position_world[cov])
        return out

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


def scene_bounds(views: list[ViewData]) -> tuple[np.ndarray, float]:
    """Centre and radius of the training foreground's world positions."""
    pts = np.concatenate([v.data.position_world[v.data.coverage > FOREGROUND_COVERAGE] for v in views])
    centre, radius = bounding_sphere(pts)
    return centre.astype(np.float32), max(radius, 1e-6)


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
