"""The photo folder at the edge of ``damcap reconstruct``: listing, masks, EXIF exposure, linear radiance.

Photos are ordinary 8-bit JPEG/PNG/TIFF files in one folder; masks (optional) are grey images with
the same base name (``IMG_5881.JPG`` <-> ``IMG_5881.png``, or COLMAP's ``IMG_5881.JPG.png``),
white = object. Everything that touches a file is here; the math is in small pure functions.

Linearisation is the capture stage's (:func:`damcap.capture.linearize.linearize_photo`): the
tone curve is undone and the exposure ``time_s * (iso / 100) / f_number^2`` from EXIF is divided
out, relative to the median exposure of the photo set (:func:`exposure_factors`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from damcap.common.errors import DamcapError

#: file suffixes read as photos (case-insensitive)
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
#: mask value (0..1) above which a pixel belongs to the object
MASK_THRESHOLD = 0.5


# --------------------------------------------------------------------------------------------
# Listing photos and masks
# --------------------------------------------------------------------------------------------

def list_photos(folder: str | os.PathLike) -> list[str]:
    """Sorted file names of the photos in ``folder`` (not recursive; hidden files skipped).

    Raises:
        DamcapError: the folder is missing or holds no photo.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DamcapError(f"{folder}: photo folder not found")
    names = sorted(p.name for p in folder.iterdir()
                   if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in PHOTO_SUFFIXES)
    if not names:
        others = sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))[:5]
        raise DamcapError(
            f"{folder}: no photos found (looked for {', '.join(PHOTO_SUFFIXES)}); "
            f"the folder holds {others or 'nothing'}. Point damcap reconstruct at the folder of JPEG/PNG photos"
        )
    stems = [Path(n).stem for n in names]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise DamcapError(f"{folder}: several photos share the base name {dup[0]!r} (e.g. .jpg and .png); keep one")
    return names


def match_masks(photo_names: list[str], mask_folder: str | os.PathLike) -> dict[str, Path]:
    """The mask file of every photo: ``stem.*`` or COLMAP's ``name.png``.

    Raises:
        DamcapError: the folder is missing, or some photo has no mask (names the first ones and
            the masks that were found instead, so a naming mismatch is obvious).
    """
    mask_folder = Path(mask_folder)
    if not mask_folder.is_dir():
        raise DamcapError(f"{mask_folder}: mask folder not found")
    files = [p for p in mask_folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES]
    by_name = {p.name: p for p in files}
    by_stem: dict[str, Path] = {}
    for p in files:
        by_stem.setdefault(p.stem, p)
    found: dict[str, Path] = {}
    missing: list[str] = []
    for name in photo_names:
        m = by_name.get(name + ".png") or by_stem.get(Path(name).stem)
        if m is None:
            missing.append(name)
        else:
            found[name] = m
    if missing:
        have = sorted(by_name)[:3]
        raise DamcapError(
            f"{mask_folder}: no mask for {len(missing)} of {len(photo_names)} photo(s), e.g. {missing[:3]}; "
            f"masks must share the photo's base name (IMG_1.JPG -> IMG_1.png); found {have or 'no images'}"
        )
    return found


# --------------------------------------------------------------------------------------------
# Pure math: masks
# --------------------------------------------------------------------------------------------

def mask_to_unit(mask_pixels: np.ndarray) -> np.ndarray:
    """A mask image (any bit depth, grey or RGB(A)) as (H, W) float32 in [0, 1].

    Args:
        mask_pixels: (H, W) or (H, W, C) uint8/uint16/float array; the first channel is used
            (alpha when there are 2 or 4 channels: a cut-out PNG).
    """
    m = np.asarray(mask_pixels)
    if m.ndim == 3:
        m = m[..., -1] if m.shape[2] in (2, 4) else m[..., 0]
    if m.dtype == np.uint8:
        return m.astype(np.float32) / 255.0
    if m.dtype == np.uint16:
        return m.astype(np.float32) / 65535.0
    return np.clip(m.astype(np.float32), 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# File readers
# --------------------------------------------------------------------------------------------

def _spec_attributes(path: Path) -> tuple[int, int, dict[str, Any]]:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise DamcapError(f"{path}: cannot read image ({oiio.geterror().strip()})")
    try:
        spec = inp.spec()
        attrs = {a.name: a.value for a in spec.extra_attribs}
        return spec.width, spec.height, attrs
    finally:
        inp.close()


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file in pixels (header only)."""
    w, h, _ = _spec_attributes(Path(path))
    return w, h


def exposure_factors(paths: list[Path], ignore_exposure: bool = False) -> tuple[np.ndarray, list[Any], float, str]:
    """Exposure factors of a photo set from EXIF (the capture stage's reader and rules).

    Args:
        paths: the photos.
        ignore_exposure: use factor 1 for every photo (only the tone curve is undone).

    Returns:
        factors: (N,) float64 exposure ``time_s * (iso / 100) / f_number^2`` (1 when ignored).
        exposures: N :class:`damcap.capture.exif.Exposure` records.
        reference: the median factor; radiance is relative to a photo taken at it.
        note: one line saying what was divided out.

    Raises:
        DamcapError: some photos have an exposure time and others not (or ISO / f-number for
            some only); the message suggests ``--ignore-exposure``.
    """
    from damcap.capture.exif import read_exposure, resolve_exposure_factors

    exposures = [read_exposure(p) for p in paths]
    have_time = [e.time_s is not None for e in exposures]
    if ignore_exposure or not any(have_time):
        why = "--ignore-exposure" if ignore_exposure else "no photo has an EXIF exposure time"
        return (np.ones(len(paths)), exposures, 1.0,
                f"tone curve (sRGB) undone; exposure not divided out ({why}): radiance is comparable across "
                "photos only if they share one exposure")
    hint = "or pass --ignore-exposure if all photos were taken at one fixed exposure"
    factors = resolve_exposure_factors(paths, exposures, None, hint)
    ref = float(np.median(factors))
    return factors, exposures, ref, (f"tone curve (sRGB) undone, EXIF exposure time x ISO/100 / f-number^2 divided out, "
                                     f"relative to the median exposure {ref:.6g} (factors {factors.min():.4g}..{factors.max():.4g})")


def read_photo_u8(path: str | os.PathLike) -> np.ndarray:
    """A photo as (H, W, 3) uint8 (grey expanded, alpha dropped; 16-bit scaled down)."""
    from damcap.common.exr import read_image_u8

    px = read_image_u8(path)
    if px.shape[2] == 1 or px.shape[2] == 2:
        px = np.repeat(px[..., :1], 3, axis=2)
    return np.ascontiguousarray(px[..., :3])


def read_photo_linear(path: str | os.PathLike, factor: float, reference: float) -> np.ndarray:
    """A photo as linear radiance (:func:`damcap.capture.linearize.linearize_photo`).

    Args:
        path: the photo.
        factor: its exposure factor (from :func:`exposure_factors`), > 0.
        reference: the exposure factor the result is relative to, > 0.

    Returns:
        (H, W, 3) float32 linear Rec.709 radiance, proportional across photos, >= 0.
    """
    from damcap.capture.linearize import linearize_photo

    return linearize_photo(read_photo_u8(path), float(factor), float(reference))


def read_mask(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """A mask file as (H, W) float32 in [0, 1].

    Args:
        path: mask image.
        size: (width, height) it must have (the photo's), or None.

    Raises:
        DamcapError: unreadable, or a size different from the photo's.
    """
    from damcap.common.exr import read_image_u8

    m = mask_to_unit(read_image_u8(path))
    if size is not None and (m.shape[1], m.shape[0]) != tuple(size):
        raise DamcapError(f"{path}: mask is {m.shape[1]}x{m.shape[0]} but its photo is {size[0]}x{size[1]}; masks must match the photos' size")
    return m
