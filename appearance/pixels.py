"""From a frame's arrays to the DAM's per-pixel inputs (pure)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from damcap.common.capture_folder import FrameData

#: coverage above which a pixel counts as foreground (docs/capture-format.md: A > 0.5)
FOREGROUND_COVERAGE = 0.5


def view_dir_world(position_world: np.ndarray, camera_centre_world: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """V = normalize(camera_centre - P), the unit vector from the surface toward the camera.

    Args:
        position_world: (..., 3) surface points.
        camera_centre_world: (3,) camera centre.
        eps: floor of the length (a point at the camera centre gives V = 0).

    Returns:
        (..., 3) float32 unit vectors.

    >>> view_dir_world(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 2.0])).tolist()
    [0.0, 0.0, 1.0]
    """
    d = np.asarray(camera_centre_world, np.float64) - np.asarray(position_world, np.float64)
    return (d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), eps)).astype(np.float32)


def normal_cam(normal_world: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """World normals in camera axes: n_cam = R^T n_world with R = world_from_cam[:3, :3].

    Args:
        normal_world: (..., 3).
        world_from_cam: (4, 4).

    Returns:
        (..., 3) float32.
    """
    return (np.asarray(normal_world, np.float64) @ np.asarray(world_from_cam, np.float64)[:3, :3]).astype(np.float32)


@dataclass
class PixelSamples:
    """Foreground pixels of several frames, flattened."""

    view_dir_world: torch.Tensor
    """(N, 3) float32 unit vectors toward the camera"""
    normal_world: torch.Tensor
    """(N, 3) float32 unit normals"""
    radiance_lin: torch.Tensor
    """(N, 3) float32 linear radiance"""
    weight: torch.Tensor
    """(N,) float32 per-sample weight W of the data cost (Maximov et al. 2019, Eq. 3)"""
    frame_index: torch.Tensor
    """(N,) int64 index of the frame each sample came from"""

    def __len__(self) -> int:
        return int(self.weight.shape[0])

    def subset(self, mask: torch.Tensor) -> "PixelSamples":
        return PixelSamples(self.view_dir_world[mask], self.normal_world[mask], self.radiance_lin[mask], self.weight[mask], self.frame_index[mask])


def gather_samples(frames: list[FrameData], camera_centres_world: list[np.ndarray], weights: list[np.ndarray] | None = None, threshold: float = FOREGROUND_COVERAGE) -> PixelSamples:
    """Collect the foreground pixels (A > threshold) of frames into flat tensors.

    Args:
        frames: per-frame arrays.
        camera_centres_world: (3,) centre per frame.
        weights: optional (H, W) per-pixel data-cost weights per frame (default 1).
        threshold: coverage above which a pixel is used.
    """
    vs, ns, cs, ws, fs = [], [], [], [], []
    for k, (d, centre) in enumerate(zip(frames, camera_centres_world, strict=True)):
        fg = d.coverage > threshold
        vs.append(view_dir_world(d.position_world[fg], centre))
        ns.append(d.normal_world[fg])
        cs.append(d.radiance_lin[fg])
        ws.append(np.ones(int(fg.sum()), np.float32) if weights is None else weights[k][fg].astype(np.float32))
        fs.append(np.full(int(fg.sum()), k, np.int64))
    cat = lambda xs: torch.from_numpy(np.ascontiguousarray(np.concatenate(xs)))  # noqa: E731
    return PixelSamples(cat(vs), cat(ns), cat(cs), cat(ws), cat(fs))
