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

from damcap.common.atomic import atomic_path, write_json_atomic
from damcap.common.capture_folder import weight_channels
from damcap.common.errors import DamcapError
from damcap.common.exr import read_exr_channels, write_exr, write_png
from damcap.common.validate import (MAX_CHANNELS, MAX_IMAGE_SIDE, MAX_MATERIALS, bounded_int, finite_in, load_json_file,
                                    loads_json)

from damcap.appearance.coverage import normal_histogram
from damcap.appearance.dam_file import load_dam, read_safetensors_metadata, save_dam
from damcap.appearance.pixels import FOREGROUND_COVERAGE
from damcap.appearance.segment.model import SegmentationModel, SegmentationNet
from damcap.appearance.segment.preview import false_colour, legend_entries, legend_image
from damcap.appearance.views import ViewData

SEGMENTER_FILE = "segmenter.safetensors"
SUMMARY_FILE = "segment.json"
WEIGHTS_FOLDER = "weights"
SEGMENT_FORMAT_VERSION = 1


def save_segmentation(folder: str | os.PathLike, model: SegmentationModel, *, colorspace: str, provenance: dict[str, Any],
                      up_world: np.ndarray | None = None, normal_histograms: list[np.ndarray] | None = None) -> list[Path]:
    """Write the n DAMs and the segmenter (``up_world``: the capture's, recorded in each DAM;
    ``normal_histograms``: per material, its training normals' histogram); returns the DAM paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, dam in enumerate(model.dams):
        p = folder / f"material_{k}.dam"
        save_dam(p, dam, colorspace=colorspace, made_by="segment", provenance={**provenance, "material": k, "materials": model.materials},
                 up_world=up_world, normal_histogram=normal_histograms[k] if normal_histograms is not None else None)
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


def save_segmentation_folder(folder: str | os.PathLike, model: SegmentationModel, views: list[ViewData], names: list[str], *,
                             colorspace: str, provenance: dict[str, Any], summary: dict[str, Any],
                             up_world: np.ndarray | None = None) -> None:
    """Write everything ``damcap segment`` writes into ``folder`` (normally a staging folder).

    The DAMs and segmenter (:func:`save_segmentation`), per training view ``weights/NAME.exr``
    ((H, W, n) half, channels ``W.0..``) and ``preview/NAME.png``, the previews' legend
    ``preview/legend.png`` and ``preview/legend.json`` (per material its colour and DAM file;
    ``legend_`` ... if a frame is named ``legend``), and ``segment.json``: ``provenance`` +
    ``summary`` + the material count, the frames and their output names.

    Args:
        views: the training views, in the order of ``names`` (one output name each).
    """
    folder = Path(folder)
    weights = [model.weights_of(v) for v in views]  # (H, W, n) each
    fg = [v.data.coverage > FOREGROUND_COVERAGE for v in views]
    normals = np.concatenate([v.data.normal_world[m] for v, m in zip(views, fg)])
    # each pixel counts for the material it is assigned to: the soft weights' tails would mark
    # directions as shown that only other materials' pixels show
    label = np.concatenate([w[m].argmax(-1) for w, m in zip(weights, fg)])
    histograms = [normal_histogram(normals, (label == k).astype(np.float64)) for k in range(model.materials)]
    save_segmentation(folder, model, colorspace=colorspace, provenance=provenance, up_world=up_world, normal_histograms=histograms)
    for v, name, w in zip(views, names, weights):
        write_exr(folder / WEIGHTS_FOLDER / f"{name}.exr", w, weight_channels(model.materials), dtype="half")
        write_png(folder / "preview" / f"{name}.png", false_colour(w, v.data.coverage))
    legend = legend_stem(names)
    write_png(folder / "preview" / f"{legend}.png", legend_image(model.materials))
    write_json_atomic(folder / "preview" / f"{legend}.json", legend_entries(model.materials))
    write_json_atomic(folder / SUMMARY_FILE, {**provenance, **summary, "materials": model.materials,
                                              "frames": [v.name for v in views], "outputs": list(names)})


def legend_stem(names: list[str]) -> str:
    """The name of the previews' legend files: ``legend``, with ``_`` appended while a frame's preview has that name.

    >>> legend_stem(["0001", "legend", "legend_"])
    'legend__'
    """
    stem = "legend"
    while stem in names:
        stem += "_"
    return stem


def _weight_files(folder: Path, summary: dict[str, Any], where: Path) -> list[Path]:
    """The weight maps segment.json lists (``outputs``), each inside ``weights/``.

    Raises:
        DamcapError: ``outputs`` not a list of names, a name that leaves the folder, no weights folder.
    """
    weights = folder / WEIGHTS_FOLDER
    if not weights.is_dir():
        raise DamcapError(f"{weights}: missing weights folder of the segmentation (weights/*.exr); "
                          f"the folder is incomplete, run damcap segment again")
    names = summary.get("outputs")
    if names is None:  # written before segment.json listed its outputs: every map in the folder
        files = sorted(weights.rglob("*.exr"))
        if not files:
            raise DamcapError(f"{weights}: no weight maps (*.exr); the folder is incomplete, run damcap segment again")
        return files
    if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
        raise DamcapError(f"{where}: 'outputs' must be a non-empty list of frame names, got {str(names)[:80]}")
    root = weights.resolve()
    files = []
    for n in names:
        f = weights / f"{n}.exr"
        if Path(n).is_absolute() or ".." in Path(n).parts or root not in f.resolve().parents:
            raise DamcapError(f"{where}: output name {n!r} leaves the segmentation folder")
        files.append(f)
    return files


def check_segmentation_folder(folder: str | os.PathLike, materials: int) -> None:
    """Check the parts of a segmentation folder beside the segmenter: ``segment.json`` (a JSON
    object whose ``materials`` is ``materials``) and one readable ``weights/NAME.exr`` with the
    channels ``W.0 .. W.{n-1}`` per listed frame.

    Raises:
        DamcapError: naming the missing, damaged or inconsistent file.
    """
    folder = Path(folder)
    path = folder / SUMMARY_FILE
    summary = load_json_file(path, "segmentation summary")
    if not isinstance(summary, dict):
        raise DamcapError(f"{path}: a segmentation summary must be a JSON object, got {type(summary).__name__}")
    if "materials" not in summary:
        raise DamcapError(f"{path}: no 'materials' count; not a segment.json written by damcap segment")
    n = bounded_int(summary["materials"], 1, MAX_MATERIALS, "materials", path)
    if n != materials:
        raise DamcapError(f"{path}: materials = {n}, but {SEGMENTER_FILE} holds {materials}; the folder's files do not belong together")
    for f in _weight_files(folder, summary, path):
        read_exr_channels(f, weight_channels(n))


def load_segmentation(folder: str | os.PathLike) -> SegmentationModel:
    """Read a folder written by ``damcap segment`` (:func:`save_segmentation_folder`): the DAMs and
    segmenter, with segment.json and the weight maps checked (:func:`check_segmentation_folder`).

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
        meta = loads_json(read_safetensors_metadata(data)["damcap_segmenter"], path, "segmenter metadata")
        version = int(meta["format_version"])
        raw = {k: meta[k] for k in ("materials", "channels", "radiance_scale", "scene_centre", "scene_radius")}
        raw_resolution = meta.get("resolution", 64)
    except (SafetensorError, ValueError, KeyError, TypeError, AttributeError, RecursionError) as e:
        raise DamcapError(f"{path}: damaged segmenter file ({str(e)[:100]})") from None
    if version > SEGMENT_FORMAT_VERSION:
        raise DamcapError(f"{path}: format version {version} is newer than this damcap reads; upgrade damcap")
    # every number is bounded before Psi is built from it
    n = bounded_int(raw["materials"], 1, MAX_MATERIALS, "materials", path)
    channels = bounded_int(raw["channels"], 1, MAX_CHANNELS, "channels", path)
    resolution = bounded_int(raw_resolution, 1, MAX_IMAGE_SIDE, "resolution", path)
    radiance_scale = finite_in(raw["radiance_scale"], "float32", "radiance_scale", path)
    scene_radius = finite_in(raw["scene_radius"], "float32", "scene_radius", path)
    if not (radiance_scale > 0 and scene_radius > 0):
        raise DamcapError(f"{path}: radiance_scale and scene_radius must be positive, got {radiance_scale}, {scene_radius}")
    centre = raw["scene_centre"]
    if not isinstance(centre, list) or len(centre) != 3:
        raise DamcapError(f"{path}: scene_centre must be 3 numbers, got {centre!r}")
    scene_centre = np.array([finite_in(c, "float32", "scene_centre", path) for c in centre], np.float32)
    for key, width in (("points_world", 3), ("point_weights", n)):
        t = tensors.get(key)
        if t is None or not t.dtype.is_floating_point or (width and (t.dim() != 2 or t.shape[1] != width)):
            raise DamcapError(f"{path}: tensor {key!r} is missing or has the wrong shape/dtype "
                              f"({None if t is None else (tuple(t.shape), str(t.dtype))})")
    if len(tensors["point_weights"]) != len(tensors["points_world"]):
        raise DamcapError(f"{path}: {len(tensors['point_weights'])} point weights for {len(tensors['points_world'])} points")
    bad = [k for k, v in tensors.items() if v.dtype.is_floating_point and not torch.isfinite(v.float()).all()]
    if bad:
        raise DamcapError(f"{path}: tensor(s) {bad[:3]} contain NaN or inf")
    psi = SegmentationNet(n, channels=channels, resolution=resolution)
    expected = {k: tuple(v.shape) for k, v in psi.state_dict().items()}
    found = {k[4:]: tuple(v.shape) for k, v in tensors.items() if k.startswith("psi.")}
    if expected != found:
        diff = sorted(set(expected.items()) ^ set(found.items()))[:3]
        raise DamcapError(f"{path}: segmenter weights do not match its architecture (first differences: {diff})")
    psi.load_state_dict({k[4:]: v.float() for k, v in tensors.items() if k.startswith("psi.")})
    check_segmentation_folder(folder, n)
    dams = [load_dam(folder / f"material_{k}.dam")[0] for k in range(n)]
    return SegmentationModel(
        dams=dams, psi=psi.eval(), radiance_scale=radiance_scale,
        scene_centre=scene_centre, scene_radius=scene_radius,
        points_world=tensors["points_world"].numpy(), point_weights=tensors["point_weights"].numpy(),
    )
