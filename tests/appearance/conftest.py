"""Helpers shared by the appearance tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from damcap.appearance.hyper.model import view_crop
from damcap.appearance.pixels import view_dir_world
from damcap.common.capture_folder import read_capture, read_frame


def _crop_of(capture: Path, k: int = 0) -> torch.Tensor:
    cap = read_capture(capture)
    f = cap.frames[k]
    d = read_frame(cap, f, with_weights=False)
    return view_crop(d.radiance_lin, d.normal_world, view_dir_world(d.position_world, f.camera_centre_world), d.coverage)


def bumpy_normals(normal_world: np.ndarray, position_world: np.ndarray, amplitude: float = 0.35) -> np.ndarray:
    """The true normals: the sphere's tilted by a smooth tangent field of position (period ~1.3)."""
    p = position_world
    t = amplitude * np.stack([np.sin(5 * p[..., 1]), np.sin(5 * p[..., 2] + 1), np.sin(5 * p[..., 0] + 2)], -1)
    t = t - (t * normal_world).sum(-1, keepdims=True) * normal_world
    n = normal_world + t
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
