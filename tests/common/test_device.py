"""Device choice: auto picks CUDA only when torch sees it; a bad or unavailable device is a clear error."""

from __future__ import annotations

import pytest
import torch

from damcap.common.device import resolve_device
from damcap.common.errors import DamcapError


def test_explicit_cpu_and_auto_without_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device() == torch.device("cpu")
    assert resolve_device("auto").type == "cpu"


def test_auto_picks_cuda_when_available(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cuda:1") == torch.device("cuda", 1)


def test_cuda_without_a_gpu_is_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(DamcapError, match=r"device 'cuda:0' asked for, but this torch build sees no CUDA GPU; use --device cpu"):
        resolve_device("cuda:0")


@pytest.mark.parametrize("name", ["gpu", "cuda:x", ""])
def test_unknown_names_are_refused(name):
    with pytest.raises(DamcapError, match=rf"unknown device {name!r}: use auto, cpu or cuda"):
        resolve_device(name)
