"""Loading a capture's frames into the arrays the appearance tasks work on (the I/O edge)."""

from __future__ import annotations

import numpy as np
import torch

from damcap.common.capture_folder import Capture, Split, read_frame

from .baselines import ViewData
from .dam import Encoding, encode_inputs
from .fit import FitOptions, TrainingFrame, radiance_scale_of
from .pixels import FOREGROUND_COVERAGE, PixelSamples, gather_samples, view_dir_world


def load_views(capture: Capture, split: Split) -> list[ViewData]:
    """Read (and validate) every frame of a split."""
    return [ViewData(f.name, read_frame(capture, f), f.world_from_cam) for f in capture.split(split)]


def samples_of(views: list[ViewData]) -> PixelSamples:
    """Foreground pixels of the views (frame_index = position in ``views``)."""
    return gather_samples([v.data for v in views], [v.centre_world for v in views])


def training_frames(views: list[ViewData], encoding: Encoding, radiance_scale: float) -> list[TrainingFrame]:
    """Whole frames for the adversarial cost."""
    out = []
    for v in views:
        fg = v.data.coverage > FOREGROUND_COVERAGE
        vd = torch.from_numpy(view_dir_world(v.data.position_world, v.centre_world))
        nd = torch.from_numpy(v.data.normal_world)
        x = torch.where(torch.from_numpy(fg)[..., None], encode_inputs(vd, nd, encoding), torch.zeros(()))
        rad = torch.from_numpy(np.where(fg[..., None], v.data.radiance_lin, 0) / radiance_scale).float().permute(2, 0, 1)
        out.append(TrainingFrame(rad, x, torch.from_numpy(fg)))
    return out


def adversarial_frames(views: list[ViewData], samples: PixelSamples, opts: FitOptions) -> list[TrainingFrame] | None:
    """The whole frames ``fit_dam`` needs for ``opts``' adversarial cost (None when it is off):
    :func:`training_frames` of ``views`` at the radiance scale of their pixels ``samples``."""
    if not opts.adversarial:
        return None
    return training_frames(views, opts.encoding, radiance_scale_of(samples.radiance_lin))
