"""Rendering a DAM into a frame's pixels (pure)."""

from __future__ import annotations

import numpy as np
import torch

from damcap.common.capture_folder import FrameData

from damcap.appearance.dam import DeepAppearanceMap
from damcap.appearance.normal_field import surface_normals
from damcap.appearance.pixels import view_dir_world
from damcap.appearance.spatial import albedo_at


@torch.no_grad()
def render_frame(model: DeepAppearanceMap, data: FrameData, camera_centre_world: np.ndarray, chunk: int = 1 << 16) -> np.ndarray:
    """Evaluate the DAM on every covered pixel (A > 0) of a frame, with the normals refined by the
    model's normal field (``model.normal_field``) and times its spatial factor (``model.spatial``)
    at the pixel's surface point, where it has them.

    Args:
        model: the DAM.
        data: the frame's geometry (radiance is not read).
        camera_centre_world: (3,) camera centre.
        chunk: pixels per forward pass.

    Returns:
        (H, W, 3) float32 linear radiance; 0 on background.
    """
    covered = data.coverage > 0
    out = np.zeros(data.coverage.shape + (3,), np.float32)
    if not covered.any():
        return out
    v = torch.from_numpy(view_dir_world(data.position_world[covered], camera_centre_world))
    n = torch.from_numpy(surface_normals(model.normal_field, data.normal_world[covered], data.position_world[covered]))
    dev = model.weights_flat.device
    parts = [model(v[s:s + chunk].to(dev), n[s:s + chunk].to(dev)).cpu() for s in range(0, v.shape[0], chunk)]
    rad = torch.cat(parts).numpy()
    if model.spatial is not None:
        rad = rad * albedo_at(model.spatial, data.position_world[covered])
    out[covered] = rad
    return out
