"""Other tools' dataset folders as ``damcap reconstruct``'s input.

``damcap reconstruct FOLDER`` takes a folder of photos, and also:
- a nerfstudio / instant-ngp dataset: ``FOLDER/transforms.json`` whose frames' ``file_path`` name
  photos in one folder under FOLDER (``images/``); its cameras become ``--poses`` and, when every
  frame has a ``mask_path`` in one folder, those masks become ``--masks``;
- a COLMAP project: ``FOLDER/images/`` and a model in ``FOLDER/sparse/0/`` (or ``FOLDER/sparse/``),
  whose cameras become ``--poses colmap:...``.
A ``--poses`` or ``--masks`` given on the command line wins over the dataset's.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from damcap.common.errors import DamcapError
from damcap.reconstruct.photos import PHOTO_SUFFIXES

DatasetKind = Literal["photos", "nerfstudio", "colmap"]


@dataclass(frozen=True)
class DatasetInputs:
    """What reconstruct reads from a folder it was given."""

    kind: DatasetKind
    photos: Path
    """the folder of photos"""
    poses: str | None
    """a ``--poses`` value, or None (register the photos)"""
    masks: Path | None
    """a ``--masks`` folder, or None"""

    def describe(self) -> str:
        if self.kind == "photos":
            return f"photos in {self.photos}"
        return (f"{self.kind} dataset: photos in {self.photos}, cameras from {self.poses}"
                + (f", masks in {self.masks}" if self.masks else ", no masks"))


def _holds_photos(folder: Path) -> bool:
    return any(p.suffix.lower() in PHOTO_SUFFIXES and not p.name.startswith(".") for p in folder.iterdir() if p.is_file())


def _one_parent(root: Path, paths: list[str], key: str, where: Path) -> Path:
    parents = sorted({str(Path(p).parent) for p in paths})
    if len(parents) != 1:
        raise DamcapError(f"{where}: the frames' {key} entries lie in {len(parents)} folders ({', '.join(parents[:3])}); "
                          f"damcap reads one folder: give it with {'the photo folder' if key == 'file_path' else '--masks'}")
    return (root / parents[0]).resolve()


def colmap_model_dir(folder: Path) -> Path | None:
    """The COLMAP model of a project folder (``sparse/0`` or ``sparse``), or None."""
    for d in (folder / "sparse" / "0", folder / "sparse"):
        if any((d / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return d
    return None


def dataset_inputs(folder: str | Path) -> DatasetInputs:
    """What ``damcap reconstruct FOLDER`` reads (see the module docstring).

    Raises:
        DamcapError: a missing folder; a transforms.json that is not JSON or whose frames' photos
            (or masks) lie in several folders, or only some frames with a mask; a folder with
            neither photos, a transforms.json nor a COLMAP project.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DamcapError(f"{folder}: photo folder not found")
    if _holds_photos(folder):
        return DatasetInputs("photos", folder, None, None)
    tj = folder / "transforms.json"
    if tj.is_file():
        try:
            doc = json.loads(tj.read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError) as e:
            raise DamcapError(f"{tj}: not JSON ({e})") from None
        frames = doc.get("frames") if isinstance(doc, dict) else None
        if not isinstance(frames, list) or not frames or not all(isinstance(f, dict) and "file_path" in f for f in frames):
            raise DamcapError(f"{tj}: needs a non-empty 'frames' list whose entries have a 'file_path'")
        photos = _one_parent(folder, [str(f["file_path"]) for f in frames], "file_path", tj)
        with_mask = [str(f["mask_path"]) for f in frames if "mask_path" in f]
        if with_mask and len(with_mask) != len(frames):
            raise DamcapError(f"{tj}: {len(with_mask)} of {len(frames)} frames have a mask_path; give masks for all of them "
                              "or none (or --masks FOLDER)")
        masks = _one_parent(folder, with_mask, "mask_path", tj) if with_mask else None
        return DatasetInputs("nerfstudio", photos, str(tj), masks)
    model = colmap_model_dir(folder)
    if model is not None and (folder / "images").is_dir():
        return DatasetInputs("colmap", folder / "images", f"colmap:{model}", None)
    raise DamcapError(f"{folder}: holds no photos, no transforms.json (nerfstudio / instant-ngp) and no COLMAP project "
                      "(images/ + sparse/0/); give a folder of photos")
