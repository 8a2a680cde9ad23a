"""Helpers shared by the appearance tests."""

from __future__ import annotations

from pathlib import Path

import torch

from damcap.appearance.hyper.model import view_crop
from damcap.appearance.pixels import view_dir_world
from damcap.common.capture_folder import read_capture, read_frame


def _crop_of(capture: Path, k: int = 0) -> torch.Tensor:
    cap = read_capture(capture)
    f = cap.frames[k]
    d = read_frame(cap, f, with_weights=False)
    return view_crop(d.radiance_lin, d.normal_world, view_dir_world(d.position_world, f.camera_centre_world), d.coverage)
