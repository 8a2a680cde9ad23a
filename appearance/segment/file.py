"""Saving and loading a segmentation: n ``.dam`` files, Psi and the 3D points, in one folder.

Layout of OUT/: ``material_0.dam .. material_{n-1}.dam``, ``segmenter.safetensors`` (Psi's
tensors, the 3D point set and JSON metadata), ``segment.json`` (options, history, choice of n).
safetensors only: nothing in the folder is executable.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save

from damcap.common.atomic import atomic_path
from damcap.common.errors import DamcapError

from damcap.appearance.dam_file import load_dam, read_safetensors_metadata, save_dam
from damcap.appearance.segment.model import SegmentationModel, SegmentationNet

SEGMENTER_FILE = "segmenter.safetensors"
SEGMENT_FORMAT_VERSION = 1


def save_segmentation(folder: str | os.PathLike, model: SegmentationModel, *, colorspace: str, provenance: dict[str, Any]) -> list[Path]:
    """Write the n DAMs and the segmenter; returns the DAM paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, dam in enumerate(model.dams):
        p = folder / f"material_{k}.dam"
        save_dam(p, dam, colorspace=colorspace, made_by="segment", provenance={**provenance, "material": k, "materials": model.materials})
        paths.append(p)
    tensors = {f"psi.{k}": v.detach().cpu().contiguous() for k, v in model.psi.state_dict().items()}
    tensors["points_world"] = torch.from_numpy(np.ascontiguousarray(model.points_world))
    tensors["point_weights"] = torch.from_numpy(np.ascontiguousarray(model.point_weights))
    meta = {"format_version": SEGMENT_FORMAT_VERSION, "materials": model.materials, "channels": model.psi.channels, "resolution": model.psi.resolution,
            "radiance_scale": model.radiance_scale, "scene_centre": [float(x) for x in model.scene_centre],
            "scene_radius": model.scene_radius}
    with atomic_path(folder / SEGMENTER_FILE) as tmp:
        tmp.write_bytes(st_save(tensors, metadata={"damcap_segmenter": json.dumps(meta)}))
    return paths


def load_segmentation(folder: str | os.PathLike) -> SegmentationModel:
    """Read a folder written by :func:`save_segmentation`.

    Raises:
        DamcapError: missing or damaged files, a newer format, inconsistent material counts.
    """
    folder = Path(folder)
    path = folder / SEGMENTER_FILE
    if not path.is_file():
        raise DamcapError(f"{folder}: not a segmentation folder (no {SEGMENTER_FILE}); make one with damcap segment")
    data = path.read_bytes()
    try:
        tensors = st_load(data)
        meta = json.loads(read_safetensors_metadata(data)["damcap_segmenter"])
        n = int(meta["materials"])
        version = int(meta["format_version"])
    except (SafetensorError, ValueError, KeyError, TypeError, json.JSONDecodeError) as e:
        raise DamcapError(f"{path}: damaged segmenter file ({str(e)[:100]})") from None
    if version > SEGMENT_FORMAT_VERSION:
        raise DamcapError(f"{path}: format version {version} is newer than this damcap reads; upgrade damcap")
    psi = SegmentationNet(n, channels=int(meta["channels"]), resolution=int(meta.get("resolution", 64)))
    try:
        psi.load_state_dict({k[4:]: v for k, v in tensors.items() if k.startswith("psi.")})
    except RuntimeError as e:
        raise DamcapError(f"{path}: segmenter weights do not match its architecture ({str(e)[:100]})") from None
    dams = [load_dam(folder / f"material_{k}.dam")[0] for k in range(n)]
    return SegmentationModel(
        dams=dams, psi=psi.eval(), radiance_scale=float(meta["radiance_scale"]),
        scene_centre=np.asarray(meta["scene_centre"], np.float32), scene_radius=float(meta["scene_radius"]),
        points_world=tensors["points_world"].numpy(), point_weights=tensors["point_weights"].numpy(),
    )
