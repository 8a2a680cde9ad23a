"""A DAM as an ONNX model: inputs ``view_dir_world`` (N, 3) and ``normal_world`` (N, 3) float32,
output ``radiance_lin`` (N, 3) float32 (the capture's linear units)."""

from __future__ import annotations

import logging
import os
import warnings

import torch

from damcap.appearance.dam import DeepAppearanceMap
from damcap.common.atomic import atomic_path


class _DamModule(torch.nn.Module):
    def __init__(self, model: DeepAppearanceMap) -> None:
        super().__init__()
        self.model = model

    def forward(self, view_dir_world: torch.Tensor, normal_world: torch.Tensor) -> torch.Tensor:
        return self.model(view_dir_world, normal_world)


def export_onnx(model: DeepAppearanceMap, path: str | os.PathLike, opset: int = 18) -> None:
    """Write the DAM as an ONNX graph with a dynamic batch size (torch's exporter), atomically."""
    from damcap.common.optional import require

    for name in ("onnx", "onnxscript"):  # torch's exporter imports them
        require(name, "damcap export --format onnx")
    module = _DamModule(model.cpu().eval())
    example = (torch.randn(4, 3), torch.randn(4, 3))
    n = torch.export.Dim("n")
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)  # the exporter logs every torchvision op it cannot register
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(
            module, example, input_names=["view_dir_world", "normal_world"], output_names=["radiance_lin"],
            dynamic_shapes=({0: n}, {0: n}), dynamo=True, opset_version=opset, verbose=False,
        )
    logger.setLevel(level)
    with atomic_path(path) as tmp:
        program.save(str(tmp))
