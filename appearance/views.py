"""A capture's frames as the appearance tasks see them: :class:`ViewData` (the I/O edge loads
them) and the radiance scale every model works in."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from damcap.common.capture_folder import Capture, FrameData, Split, read_frame

from damcap.appearance.pixels import FOREGROUND_COVERAGE, PixelSamples, gather_samples


@dataclass
class ViewData:
    """A frame's arrays plus its camera (what the baselines need)."""

    name: str
    data: FrameData
    world_from_cam: np.ndarray
    """(4, 4) camera-to-world"""

    @property
    def centre_world(self) -> np.ndarray:
        return self.world_from_cam[:3, 3]


def radiance_scale_of(radiance_lin: torch.Tensor, weight: torch.Tensor | None = None) -> float:
    """95th percentile of the pooled channels of (N, 3) radiance over samples with weight > 0
    (1 if that is 0)."""
    if weight is not None:
        radiance_lin = radiance_lin[weight > 0]
    if radiance_lin.numel() == 0:
        return 1.0
    x = radiance_lin.reshape(-1).float()
    if x.numel() > 1_000_000:
        x = x[torch.linspace(0, x.numel() - 1, 1_000_000).long()]
    p = float(torch.quantile(x, 0.95))
    return p if p > 0 and math.isfinite(p) else 1.0


def load_views(capture: Capture, split: Split) -> list[ViewData]:
    """Read (and validate) every frame of a split."""
    return [ViewData(f.name, read_frame(capture, f), f.world_from_cam) for f in capture.split(split)]


def samples_of(views: list[ViewData]) -> PixelSamples:
    """Foreground pixels of the views (frame_index = position in ``views``)."""
    return gather_samples([v.data for v in views], [v.centre_world for v in views])


def positions_of(views: list[ViewData]) -> np.ndarray:
    """(N, 3) float32 surface points of the pixels :func:`samples_of` returns, in its order."""
    parts = [v.data.position_world[v.data.coverage > FOREGROUND_COVERAGE] for v in views]
    return np.concatenate(parts).astype(np.float32) if parts else np.zeros((0, 3), np.float32)
