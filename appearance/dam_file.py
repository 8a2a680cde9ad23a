"""``.dam`` files: one safetensors file, the flat weights plus a JSON metadata block.

safetensors stores raw tensors and a JSON header only: opening a stranger's file executes
nothing. Layout: tensor ``weights`` (P,) float32; metadata key ``damcap`` holding JSON with
``format_version``, ``architecture``, ``radiance_scale``, ``colorspace``, ``made_by`` and
free-form ``provenance`` (options, loss, capture).

A model with a spatial factor (:mod:`.spatial`) adds the tensors ``spatial_keys`` (M,) int64 and
``spatial_log_albedo`` (M, 3) float32 and the metadata object ``spatial``
(``kind: "albedo_voxels"``, ``origin_world``, ``voxel_size``), and is written as format version 2
so that a damcap that cannot apply the factor refuses the file instead of rendering without it.
A model with a normal field (:mod:`.normal_field`) adds the tensors ``normal_keys`` (M,) int64 and
``normal_offset`` (M, 3) float32 and the metadata object ``normal_field``
(``kind: "normal_offset_voxels"``, ``origin_world``, ``voxel_size``), and is written as format
version 3 for the same reason. A model with neither stays version 1.

The optional metadata ``normal_histogram`` (a list of non-negative numbers, one per direction of
:func:`.coverage.fibonacci_directions`) records the world normals the model was trained on
(:mod:`.coverage`); ``damcap export`` reads it to say where a new shape leaves them. It changes
nothing in how the model renders, so it does not raise the format version.
"""

from __future__ import annotations

import dataclasses
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
from damcap.common.capture_folder import COLORSPACES
from damcap.common.errors import DamcapError
from damcap.common.validate import finite_in, loads_json

from damcap.appearance.dam import FLOAT32_TINY, DamArchitecture, DeepAppearanceMap, overflow_problem
from damcap.appearance.normal_field import NormalField
from damcap.appearance.spatial import SpatialAlbedo

DAM_FORMAT_VERSION = 3
"""the newest format this damcap reads and writes (1: the DAM alone; 2: with a spatial factor;
3: with a normal field, and a spatial factor or not)"""
SPATIAL_KIND = "albedo_voxels"
NORMAL_FIELD_KIND = "normal_offset_voxels"
SPATIAL_TENSORS = ("spatial_keys", "spatial_log_albedo")
NORMAL_TENSORS = ("normal_keys", "normal_offset")
METADATA_KEY = "damcap"


def save_dam(path: str | os.PathLike, model: DeepAppearanceMap, *, colorspace: str, made_by: str, provenance: dict[str, Any] | None = None,
             up_world: np.ndarray | None = None, normal_histogram: np.ndarray | None = None) -> None:
    """Write a model atomically as a ``.dam`` file.

    Args:
        path: destination.
        model: the DAM.
        colorspace: the capture's ``colorspace`` (e.g. ``lin_rec709``).
        made_by: ``fit``, ``predict`` or ``segment``.
        provenance: JSON-serialisable record of how it was made (options, seed, loss, ...).
        up_world: (3,) the capture's up direction (``Capture.up_world``), recorded as the
            metadata ``up_world`` (export orbits about it); None records none.
        normal_histogram: (k,) the training normals' histogram (:func:`.coverage.normal_histogram`),
            recorded as the metadata ``normal_histogram``; None records none.
    """
    tensors = {"weights": model.get_flat_weights().float().contiguous()}
    meta: dict[str, Any] = {
        "format_version": format_version_of(model),
        "architecture": model.arch.to_json(),
        "radiance_scale": model.radiance_scale,
        "colorspace": colorspace,
        "made_by": made_by,
        "provenance": provenance or {},
    }
    if up_world is not None:
        meta["up_world"] = [float(x) for x in np.asarray(up_world, np.float64) / np.linalg.norm(up_world)]
    if normal_histogram is not None:
        meta["normal_histogram"] = [float(x) for x in np.asarray(normal_histogram, np.float64).reshape(-1)]
    if model.spatial is not None:
        sa = model.spatial
        meta["spatial"] = {"kind": SPATIAL_KIND, "origin_world": [float(x) for x in sa.origin_world], "voxel_size": float(sa.voxel_size)}
        tensors["spatial_keys"] = torch.from_numpy(np.ascontiguousarray(sa.keys, np.int64))
        tensors["spatial_log_albedo"] = torch.from_numpy(np.ascontiguousarray(sa.log_albedo, np.float32))
    if model.normal_field is not None:
        nf = model.normal_field
        meta["normal_field"] = {"kind": NORMAL_FIELD_KIND, "origin_world": [float(x) for x in nf.origin_world],
                                "voxel_size": float(nf.voxel_size)}
        tensors["normal_keys"] = torch.from_numpy(np.ascontiguousarray(nf.keys, np.int64))
        tensors["normal_offset"] = torch.from_numpy(np.ascontiguousarray(nf.offset, np.float32))
    blob = st_save(tensors, metadata={METADATA_KEY: json.dumps(meta)})
    with atomic_path(path) as tmp:
        tmp.write_bytes(blob)


def recorded_normal_histogram(meta: dict[str, Any]) -> np.ndarray | None:
    """(k,) the training normals' histogram a loaded ``.dam``'s metadata records (None when none)."""
    h = meta.get("normal_histogram")
    return None if h is None else np.asarray(h, np.float64)


def recorded_up(meta: dict[str, Any]) -> np.ndarray | None:
    """(3,) unit up direction a loaded ``.dam``'s metadata records (None when it records none)."""
    up = meta.get("up_world")
    return None if up is None else np.asarray(up, np.float64) / np.linalg.norm(up)


def format_version_of(model: DeepAppearanceMap) -> int:
    """The oldest format that holds the model: 1, 2 (spatial factor) or 3 (normal field)."""
    return 3 if model.normal_field is not None else 2 if model.spatial is not None else 1


def integer_fields(cls: type) -> tuple[str, ...]:
    """The fields of an architecture dataclass annotated ``int``.

    >>> integer_fields(DamArchitecture)
    ('width', 'depth')
    """
    return tuple(f.name for f in dataclasses.fields(cls) if f.type in (int, "int"))


def require_integers(values: dict[str, Any], names: tuple[str, ...], path: Path, key: str) -> None:
    """Refuse a metadata value that is not a JSON integer: 32.0 or true is no layer width.

    Args:
        values: a metadata object (``architecture``).
        names: its integer keys (absent ones are skipped: a default or another check applies).
        path: the file, for the message.
        key: the object's key in the metadata (``"architecture"``).

    Raises:
        DamcapError: one line naming the file, the key and the value.
    """
    for name in names:
        if name in values and (type(values[name]) is not int):
            raise DamcapError(f"{path}: metadata '{key}.{name}' must be an integer, got {values[name]!r:.40}")


def load_dam(path: str | os.PathLike) -> tuple[DeepAppearanceMap, dict[str, Any]]:
    """Read a ``.dam`` file; refuses anything else with a clear error.

    Returns:
        the model (on CPU) and the metadata dictionary.

    Raises:
        DamcapError: missing file, not a safetensors file (random bytes, a pickle, truncated),
            missing or invalid metadata (an integer of the architecture given as 32.0 or true
            among them), a newer format version, weights that do not match the
            architecture, non-finite weights, weights whose output overflows float32, a colour
            space damcap does not know.
    """
    path = Path(path)
    tensors, meta_text = read_damcap_safetensors(path, "model", ".dam model")
    meta = loads_json(meta_text, path, "damcap metadata")
    try:
        version = meta["format_version"]
        arch_json = meta["architecture"]
        scale_raw = meta["radiance_scale"]
    except (KeyError, TypeError) as e:
        raise DamcapError(f"{path}: damcap metadata is invalid ({e!r})") from None
    if not isinstance(version, int) or version > DAM_FORMAT_VERSION:
        raise DamcapError(f"{path}: .dam format version {version!r} is newer than this damcap reads ({DAM_FORMAT_VERSION}); upgrade damcap")
    # every number is checked before anything is built from it: the architecture's bounds
    # (DamArchitecture), the scale in float32 (it multiplies float32 radiance)
    if isinstance(scale_raw, str):
        try:
            scale_raw = float(scale_raw)
        except ValueError:
            pass
    scale = finite_in(scale_raw, "float32", "radiance_scale", path)
    if not scale >= FLOAT32_TINY:
        raise DamcapError(f"{path}: radiance_scale must be positive (>= {FLOAT32_TINY:.4g} in float32), got {scale_raw!r}")
    colorspace = meta.get("colorspace", "lin_rec709")
    if colorspace not in COLORSPACES:
        raise DamcapError(f"{path}: colorspace {colorspace!r} is not one damcap knows; use one of {', '.join(COLORSPACES)}")
    if not isinstance(arch_json, dict):
        raise DamcapError(f"{path}: damcap metadata 'architecture' must be an object, got {type(arch_json).__name__}")
    require_integers(arch_json, integer_fields(DamArchitecture), path, "architecture")
    try:
        arch = DamArchitecture(**arch_json)
    except TypeError as e:
        raise DamcapError(f"{path}: unknown architecture fields ({e})") from None
    except DamcapError as e:
        raise DamcapError(f"{path}: invalid architecture: {e}") from None
    spatial_meta, normal_meta = meta.get("spatial"), meta.get("normal_field")
    expected = {"weights"} | (set() if spatial_meta is None else set(SPATIAL_TENSORS)) | (set() if normal_meta is None else set(NORMAL_TENSORS))
    if set(tensors) != expected:
        raise DamcapError(f"{path}: expected the tensors {sorted(expected)}, found {sorted(tensors)}")
    w = tensors["weights"]
    if w.dim() != 1 or w.shape[0] != arch.num_weights:
        raise DamcapError(f"{path}: weights have shape {tuple(w.shape)}, the stated architecture needs ({arch.num_weights},)")
    if not w.dtype.is_floating_point:
        raise DamcapError(f"{path}: weights are {w.dtype}, expected float32")
    if not torch.isfinite(w.float()).all():
        raise DamcapError(f"{path}: weights contain NaN or inf")
    model = DeepAppearanceMap(arch, scale, w)
    problem = overflow_problem(model)
    if problem:
        raise DamcapError(f"{path}: {problem}")
    if "up_world" in meta:
        up = meta["up_world"]
        ok = isinstance(up, list) and len(up) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in up)
        if not ok or not np.isfinite(up).all() or np.linalg.norm(up) < 1e-6:
            raise DamcapError(f"{path}: metadata 'up_world' must be 3 finite numbers of non-zero length, got {up!r:.80}")
    if "normal_histogram" in meta:
        h = meta["normal_histogram"]
        ok = isinstance(h, list) and len(h) >= 1 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in h)
        if not ok or not np.isfinite(h).all() or min(h) < 0:
            raise DamcapError(f"{path}: metadata 'normal_histogram' must be a list of finite non-negative numbers, got {h!r:.80}")
    if spatial_meta is not None:
        model.spatial = _spatial_from(path, spatial_meta, tensors)
    if normal_meta is not None:
        model.normal_field = _normal_field_from(path, normal_meta, tensors)
    return model, meta


def _voxel_grid_from(path: Path, key: str, kind: str, grid_meta: Any, tensors: dict[str, torch.Tensor],
                     names: tuple[str, str]) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """(origin, voxel size, keys, values) of a sparse voxel grid stored in a .dam file, their
    types checked (DamcapError naming the file otherwise)."""
    if not isinstance(grid_meta, dict) or grid_meta.get("kind") != kind:
        raise DamcapError(f"{path}: metadata {key!r} must be an object of kind {kind!r}, got {grid_meta!r:.80}")
    keys, values = tensors[names[0]], tensors[names[1]]
    if keys.dtype != torch.int64 or not values.dtype.is_floating_point:
        raise DamcapError(f"{path}: tensors {names[0]} and {names[1]} must be int64 and float, got {keys.dtype} and {values.dtype}")
    try:
        origin = np.asarray(grid_meta["origin_world"], np.float64)
        voxel = float(grid_meta["voxel_size"])
    except (KeyError, TypeError, ValueError) as e:
        raise DamcapError(f"{path}: metadata {key!r} is invalid ({e!r})") from None
    return origin, voxel, keys.numpy().copy(), values.float().numpy().copy()


def _spatial_from(path: Path, spatial_meta: Any, tensors: dict[str, torch.Tensor]) -> SpatialAlbedo:
    """The spatial factor stored in a .dam file, checked (DamcapError naming the file otherwise)."""
    sa = SpatialAlbedo(*_voxel_grid_from(path, "spatial", SPATIAL_KIND, spatial_meta, tensors, SPATIAL_TENSORS))
    problem = sa.problem()
    if problem:
        raise DamcapError(f"{path}: spatial factor: {problem}")
    return sa


def _normal_field_from(path: Path, normal_meta: Any, tensors: dict[str, torch.Tensor]) -> NormalField:
    """The normal field stored in a .dam file, checked (DamcapError naming the file otherwise)."""
    nf = NormalField(*_voxel_grid_from(path, "normal_field", NORMAL_FIELD_KIND, normal_meta, tensors, NORMAL_TENSORS))
    problem = nf.problem()
    if problem:
        raise DamcapError(f"{path}: normal field: {problem}")
    return nf


def read_damcap_safetensors(path: Path, noun: str, kind: str) -> tuple[dict[str, torch.Tensor], str]:
    """The tensors and the damcap metadata text (``METADATA_KEY``) of a damcap safetensors file.

    Args:
        path: the file.
        noun: what the file is called in 'NOUN file not found' (e.g. 'model').
        kind: what it is called in 'not a damcap KIND file' (e.g. '.dam model').

    Raises:
        DamcapError: a missing file, not safetensors (random bytes, a pickle, truncated), or no
            damcap metadata.
    """
    if not path.is_file():
        raise DamcapError(f"{path}: {noun} file not found")
    data = path.read_bytes()
    try:
        tensors = st_load(data)
        meta_raw = read_safetensors_metadata(data)
    except (SafetensorError, ValueError, OverflowError, UnicodeDecodeError, RecursionError) as e:
        raise DamcapError(f"{path}: not a damcap {kind} file (not valid safetensors: {str(e).splitlines()[0][:120]})") from None
    if METADATA_KEY not in meta_raw:
        raise DamcapError(f"{path}: a safetensors file without damcap metadata; not a {kind}")
    return tensors, meta_raw[METADATA_KEY]


def read_safetensors_metadata(data: bytes) -> dict[str, str]:
    """The ``__metadata__`` block of a safetensors blob (already validated by ``st_load``)."""
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8:8 + n].decode("utf-8"))
    meta = header.get("__metadata__") or {}
    if not isinstance(meta, dict):
        raise ValueError("__metadata__ is not an object")
    return meta
