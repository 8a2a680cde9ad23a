"""The one place that decides torch devices and dtypes."""

from __future__ import annotations

import torch

from damcap.common.errors import DamcapError


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cpu``/``cuda``/``cuda:N`` as given.

    Raises:
        DamcapError: an unknown name, or CUDA asked for where none is available.
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise DamcapError(f"unknown device {name!r}: use auto, cpu or cuda") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DamcapError(f"device {name!r} asked for, but this torch build sees no CUDA GPU; use --device cpu")
    return dev
