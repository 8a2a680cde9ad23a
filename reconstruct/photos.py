"""The photo folder at the edge of ``damcap reconstruct``: listing, masks, exposure, linear radiance.

Photos are the files of one folder, all of one kind (:func:`photo_kind`):

- ``display``: 8/16-bit JPEG/PNG/TIFF. The tone curve is undone (sRGB, or a response curve that
  ``damcap hdr`` recovered) and the EXIF exposure ``time_s * (iso / 100) / f_number^2`` divided
  out, relative to the median exposure of the set (:func:`damcap.capture.linearize.linearize_photo`).
  A pixel with a channel at the top codes (:func:`damcap.capture.linearize.clipped_mask`, the
  level ``damcap linearize`` flags) is flagged clipped: its radiance is only a lower bound.
- ``linear``: OpenEXR (the output of ``damcap hdr`` and ``damcap linearize``) or Radiance ``.hdr``;
  the values are linear already. An EXR written by damcap records in its header the exposure its
  values are relative to (``damcap:reference_exposure``); the values are rescaled to the median of
  the set, so EXRs of several ``linearize`` runs or brackets compare. Without that attribute (other
  tools, ``.hdr``) the factor is 1 and the values are used as stored. A ``clipped`` channel (both
  commands write one) flags pixels whose radiance is only a lower bound.
- ``raw``: camera RAW files (:data:`damcap.capture.exif.RAW_EXTENSIONS`), decoded linearly as the
  capture stage does (:func:`damcap.capture.raw.read_raw_rgb`), EXIF exposure divided out as for
  display photos; saturated photosites are flagged clipped.

A folder mixing kinds is refused: an sRGB-decoded JPEG, a RAW file (1 = the sensor's white level)
and a merged EXR (1 = the middle code of a recovered response) have no common scale.

Photos and masks are read upright, as a viewer shows them: a display photo or mask with an EXIF
Orientation other than 1 (a phone's portrait photo is stored sideways with 6) is turned by it
(:func:`damcap.common.exr.upright`), so sizes, cameras, frames and masks are all in the upright
frame; RAW files are turned by LibRaw's flip as decoded.

Masks (optional) are grey images with the same base name (``IMG_5881.JPG`` <-> ``IMG_5881.png``,
or COLMAP's ``IMG_5881.JPG.png``), white = object. COLMAP reads only display images well, and
them as stored, so linear and RAW photos, and display photos stored turned, are registered through
8-bit upright proxies (:func:`write_registration_proxies`).
Everything that touches a file is here; the math is in small pure functions.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from damcap.common.errors import DamcapError
from damcap.common.validate import no_signal

from damcap.capture.exif import RAW_EXTENSIONS

PhotoKind = Literal["display", "linear", "raw"]

#: display photos: 8/16-bit, tone-mapped (case-insensitive suffixes)
DISPLAY_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
#: linear radiance files (OpenEXR, Radiance RGBE)
LINEAR_SUFFIXES = (".exr", ".hdr")
#: camera RAW files (read through LibRaw)
RAW_SUFFIXES = tuple(sorted(RAW_EXTENSIONS))
#: file suffixes read as photos
PHOTO_SUFFIXES = DISPLAY_SUFFIXES + LINEAR_SUFFIXES + RAW_SUFFIXES
#: file suffixes read as masks
MASK_SUFFIXES = DISPLAY_SUFFIXES
#: mask value (0..1) above which a pixel belongs to the object
MASK_THRESHOLD = 0.5
#: EXR header attribute: the exposure factor the values are relative to (damcap hdr / linearize)
EXR_REFERENCE_EXPOSURE = "damcap:reference_exposure"
#: EXR header attribute: the colour space of the values
EXR_COLORSPACE = "damcap:colorspace"
#: registration proxies: this percentile of the per-pixel largest channel maps to display white
PROXY_PERCENTILE = 99.0
#: version of the proxy encoding (a change makes every proxy be written again)
PROXY_VERSION = 1

_KIND_WORDS = {"display": "8-bit photos", "linear": "linear EXR/HDR files", "raw": "RAW files"}


# --------------------------------------------------------------------------------------------
# Listing photos and masks
# --------------------------------------------------------------------------------------------

def photo_kind(name: str | os.PathLike) -> PhotoKind:
    """The kind of a photo file by its suffix.

    >>> photo_kind("IMG_1.JPG"), photo_kind("IMG_1.exr"), photo_kind("IMG_1.CR2")
    ('display', 'linear', 'raw')

    Raises:
        DamcapError: not a photo suffix.
    """
    suffix = Path(name).suffix.lower()
    if suffix in DISPLAY_SUFFIXES:
        return "display"
    if suffix in LINEAR_SUFFIXES:
        return "linear"
    if suffix in RAW_EXTENSIONS:
        return "raw"
    raise DamcapError(f"{name}: not a photo (suffixes {', '.join(DISPLAY_SUFFIXES + LINEAR_SUFFIXES)} and camera RAW)")


def photo_set_kind(names: list[str] | list[Path], where: str | os.PathLike = "") -> PhotoKind:
    """The one kind of a photo set.

    Raises:
        DamcapError: the set is empty or mixes kinds (names one file of each).
    """
    if not names:
        raise DamcapError(f"{where}: no photos")
    by_kind: dict[str, str] = {}
    for n in names:
        by_kind.setdefault(photo_kind(n), Path(n).name)
    if len(by_kind) > 1:
        which = " and ".join(f"{_KIND_WORDS[k]} (e.g. {v})" for k, v in sorted(by_kind.items()))
        raise DamcapError(f"{where or Path(names[0]).parent}: the folder mixes {which}; their radiance scales are not comparable, "
                          "so keep one kind per folder (damcap linearize turns 8-bit and RAW photos into linear EXRs)")
    return next(iter(by_kind))  # type: ignore[return-value]


def list_photos(folder: str | os.PathLike) -> list[str]:
    """Sorted file names of the photos in ``folder`` (not recursive; hidden files skipped), all of one kind.

    Raises:
        DamcapError: the folder is missing, holds no photo, mixes kinds (:func:`photo_set_kind`)
            or has two photos with one base name.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DamcapError(f"{folder}: photo folder not found")
    entries = [p for p in folder.iterdir() if not p.name.startswith(".") and p.suffix.lower() in PHOTO_SUFFIXES]
    not_files = sorted(p.name for p in entries if not p.is_file())
    if not_files:
        raise DamcapError(f"{folder / not_files[0]}: named like a photo but is not a file (a folder?); "
                          "move it out of the photo folder")
    names = sorted(p.name for p in entries)
    if not names:
        others = sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))[:5]
        raise DamcapError(
            f"{folder}: no photos found (looked for {', '.join(DISPLAY_SUFFIXES + LINEAR_SUFFIXES)} and camera RAW); "
            f"the folder holds {others or 'nothing'}. Point damcap reconstruct at the folder of photos"
        )
    stems = [Path(n).stem for n in names]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise DamcapError(f"{folder}: several photos share the base name {dup[0]!r} (e.g. .jpg and .png); keep one")
    photo_set_kind(names, folder)
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
    files = [p for p in mask_folder.iterdir() if p.is_file() and p.suffix.lower() in MASK_SUFFIXES]
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
# Pure math
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


def proxy_srgb_u8(radiance_lin: np.ndarray, percentile: float = PROXY_PERCENTILE) -> np.ndarray:
    """The 8-bit display encoding of linear radiance that feature extraction sees.

    The radiance is scaled so that the ``percentile`` of the per-pixel largest channel maps to 1
    (a per-photo exposure, as a camera's auto exposure would choose), clipped to [0, 1] and
    sRGB-encoded. A pure function of the photo: the same file always gives the same proxy.

    Args:
        radiance_lin: (H, W, 3) float, linear, >= 0 (negative values count as 0).
        percentile: in (0, 100].

    Returns:
        (H, W, 3) uint8 sRGB.

    >>> proxy_srgb_u8(np.array([[[0.18, 0.18, 0.18], [1.0, 2.0, 0.5]]]), 100.0).tolist()
    [[[85, 85, 85], [188, 255, 137]]]
    """
    from damcap.common.colour import display_srgb8

    rad = np.maximum(np.asarray(radiance_lin, dtype=np.float64), 0.0)
    white = float(np.percentile(rad.max(axis=-1), percentile)) if rad.size else 0.0
    return display_srgb8(rad, 1.0 / white if white > 0 else 1.0)


# --------------------------------------------------------------------------------------------
# Headers and exposure
# --------------------------------------------------------------------------------------------

def _spec_attributes(path: Path) -> tuple[int, int, dict[str, Any]]:
    import OpenImageIO as oiio

    from damcap.common.exr import oiio_error
    from damcap.common.native_stderr import native_stderr_caught

    with native_stderr_caught() as printed:  # libpng prints its own lines on a damaged PNG
        inp = oiio.ImageInput.open(str(path))
        if inp is not None:
            try:
                spec = inp.spec()
                attrs = {a.name: a.value for a in spec.extra_attribs}
            finally:
                inp.close()
    if inp is None:
        msg = (oiio_error(oiio).strip() or "\n".join(printed)).splitlines()
        raise DamcapError(f"{path}: cannot read image ({msg[-1] if msg else 'unknown format'})")
    return spec.width, spec.height, attrs


def _raw_size(path: Path) -> tuple[int, int]:
    """(width, height) of a RAW file as :func:`damcap.capture.raw.read_raw_rgb` decodes it (upright)."""
    import rawpy

    try:
        with rawpy.imread(str(path)) as raw:
            w, h, flip = int(raw.sizes.width), int(raw.sizes.height), int(raw.sizes.flip)
    except (rawpy.LibRawError, OSError, ValueError) as e:
        raise DamcapError(f"{path}: cannot read as a camera RAW file ({type(e).__name__}: {e}); "
                          "is the file complete and a RAW format?") from None
    return (h, w) if flip in (5, 6) else (w, h)


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of a photo in pixels, upright (header only): display photos turned by their
    EXIF Orientation (:func:`damcap.common.exr.upright_size`), RAW files as decoded; linear files
    as stored."""
    from damcap.common.exr import exif_orientation, upright_size

    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: file not found")
    if path.suffix.lower() in RAW_EXTENSIONS:
        return _raw_size(path)
    w, h, attrs = _spec_attributes(path)
    if path.suffix.lower() in DISPLAY_SUFFIXES:
        return upright_size(w, h, exif_orientation(attrs.get("Orientation", 1)))
    return w, h


def _reference_exposure_of(path: Path) -> float | None:
    """The exposure factor an EXR's values are relative to (its header), or None."""
    _, _, attrs = _spec_attributes(path)
    value = attrs.get(EXR_REFERENCE_EXPOSURE)
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return float(f"{v:.7g}") if np.isfinite(v) and v > 0 else None  # stored as float32


def exposure_factors(paths: list[Path], ignore_exposure: bool = False,
                     tone_curve: str = "sRGB") -> tuple[np.ndarray, list[Any], float, str]:
    """Exposure factors of a photo set: what each photo's linear values are divided by.

    Display and RAW photos: ``time_s * (iso / 100) / f_number^2`` from EXIF (the capture stage's
    reader and rules). Linear EXRs: the header's ``damcap:reference_exposure`` (the exposure
    ``damcap hdr`` / ``damcap linearize`` made the values relative to), or 1 for every photo when
    no EXR has one.

    Args:
        paths: the photos, all of one kind.
        ignore_exposure: use factor 1 for every photo (values are only linearised).
        tone_curve: what undoes the tone curve of display photos, for the note.

    Returns:
        factors: (N,) float64 exposure factors (1 when ignored or unknown).
        exposures: N :class:`damcap.capture.exif.Exposure` records (time unknown for linear files).
        reference: the median factor; radiance is relative to a photo taken at it.
        note: one line saying how the photos were linearised and what was divided out.

    Raises:
        DamcapError: mixed kinds; some photos have an exposure (EXIF time, ISO, f-number, or an
            EXR reference exposure) and others not; the message suggests ``--ignore-exposure``.
    """
    from damcap.capture.exif import Exposure, read_exposure, resolve_exposure_factors
    from damcap.common.native_stderr import native_stderr_caught

    kind = photo_set_kind(paths)
    hint = "or pass --ignore-exposure if all photos were taken at one fixed exposure"
    if kind == "linear":
        exposures = [Exposure(time_s=None) for _ in paths]
        how = "linear EXR/HDR radiance, no tone curve undone"
        refs = [None] * len(paths) if ignore_exposure else [_reference_exposure_of(Path(p)) for p in paths]
        if ignore_exposure or not any(r is not None for r in refs):
            why = ("--ignore-exposure" if ignore_exposure
                   else f"no file's header has {EXR_REFERENCE_EXPOSURE}, which damcap hdr / linearize write")
            return (np.ones(len(paths)), exposures, 1.0,
                    f"{how}; values used as stored, exposure factor 1 for every photo ({why}): radiance is comparable "
                    "across photos only if they share one scale")
        lacking = next(Path(p).name for p, r in zip(paths, refs) if r is None) if None in refs else None
        if lacking is not None:
            raise DamcapError(f"{lacking}: its header has no {EXR_REFERENCE_EXPOSURE} while other photos' do, so they "
                              f"would not be comparable; {hint}")
        factors = np.array(refs, dtype=np.float64)
        ref = float(np.median(factors))
        return factors, exposures, ref, (
            f"{how}; each file's values, relative to its {EXR_REFERENCE_EXPOSURE}, rescaled to the median {ref:.6g} "
            f"(factors {factors.min():.4g}..{factors.max():.4g})")
    how = (f"tone curve ({tone_curve}) undone" if kind == "display"
           else "RAW sensor values decoded linearly (black level subtracted, white level 1, demosaiced, colour matrix to Rec.709)")
    with native_stderr_caught():  # libpng prints its own lines on a damaged PNG
        exposures = [read_exposure(p) for p in paths]
    have_time = [e.time_s is not None for e in exposures]
    if ignore_exposure or not any(have_time):
        why = "--ignore-exposure" if ignore_exposure else "no photo has an EXIF exposure time"
        return (np.ones(len(paths)), exposures, 1.0,
                f"{how}; exposure not divided out ({why}): radiance is comparable across "
                "photos only if they share one exposure")
    factors = resolve_exposure_factors(paths, exposures, None, hint)
    ref = float(np.median(factors))
    return factors, exposures, ref, (f"{how}, EXIF exposure time x ISO/100 / f-number^2 divided out, "
                                     f"relative to the median exposure {ref:.6g} (factors {factors.min():.4g}..{factors.max():.4g})")


# --------------------------------------------------------------------------------------------
# File readers
# --------------------------------------------------------------------------------------------

@dataclass
class PhotoRadiance:
    """One photo as linear radiance."""

    radiance_lin: np.ndarray
    """(H, W, 3) float32, linear Rec.709, proportional across the photo set (exposure divided out), >= 0
    up to noise"""
    clipped: np.ndarray | None
    """(H, W) bool, radiance only a lower bound (saturated: a display photo's top codes, a RAW
    file's white level, an EXR's ``clipped`` channel); None when the file does not say (an EXR or
    ``.hdr`` without that channel)"""


def verify_photos(folder: str | os.PathLike, names: list[str],
                  progress: Callable[[str, int, int], None] | None = None) -> None:
    """Decode every display photo once, so that a damaged or truncated file is refused before any
    work (registration would only drop it as unregistered); linear and RAW photos are decoded
    when their registration proxies are written, which refuses them the same way.

    Raises:
        DamcapError: the first unreadable or truncated photo, named (as ``damcap hdr`` and
            ``damcap linearize`` refuse it).
    """
    folder = Path(folder)
    display = [n for n in names if photo_kind(n) == "display"]
    empty: list[tuple[str, str]] = []
    for k, name in enumerate(display):
        if progress:
            progress("checking photos", k, len(display))
        codes = _read_display_codes(folder / name)
        if (why := display_photo_signal(codes)) is not None:
            empty.append((name, why))
    if progress and display:
        progress("checking photos", len(display), len(display))
    if display and len(empty) == len(display):
        name, why = empty[0]
        raise DamcapError(f"{folder / name}: {why}, as is every photo in {folder} ({len(display)}); they show nothing to "
                          f"reconstruct: photograph the object with an exposure that shows it")


#: display codes at or below this fraction of full scale are black (JPEG noise of a black frame)
BLACK_FRACTION = 0.02
#: display codes at or above this fraction of full scale are saturated
SATURATED_FRACTION = 0.98


def display_photo_signal(codes: np.ndarray) -> str | None:
    """Why a display photo shows nothing (black or saturated everywhere, in codes), or None.

    >>> display_photo_signal(np.full((4, 4, 3), 255, np.uint8))
    'saturated everywhere (smallest value 255, saturation at 249.9)'
    >>> display_photo_signal(np.arange(48, dtype=np.uint8).reshape(4, 4, 3)) is None
    True
    """
    full = float(np.iinfo(codes.dtype).max) if np.issubdtype(codes.dtype, np.integer) else 1.0
    return no_signal(codes, BLACK_FRACTION * full, SATURATED_FRACTION * full)


def _read_display_codes(path: Path) -> np.ndarray:
    """(H, W, 3) uint8/uint16 codes of a display photo, upright (:func:`damcap.capture.hdr.read_ldr_codes`),
    with what libpng prints itself on a damaged PNG caught (the error names the file instead)."""
    from damcap.capture.hdr import read_ldr_codes
    from damcap.common.native_stderr import native_stderr_caught

    with native_stderr_caught():
        codes, _ = read_ldr_codes(path)
    return codes


def read_photo_u8(path: str | os.PathLike) -> np.ndarray:
    """A display photo as (H, W, 3) uint8, upright (grey expanded, alpha dropped; 16-bit scaled down)."""
    from damcap.common.exr import read_image_u8

    px = read_image_u8(path)
    if px.shape[2] == 1 or px.shape[2] == 2:
        px = np.repeat(px[..., :1], 3, axis=2)
    return np.ascontiguousarray(px[..., :3])


def read_linear_rgb(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """A linear EXR/HDR file as Rec.709 radiance, as stored (no exposure applied).

    Channels R, G, B (a single channel is grey); ``damcap:colorspace`` ``acescg`` is converted
    back to Rec.709; a ``clipped`` channel (> 0.5) is returned as the clipped mask.

    Returns:
        rgb: (H, W, 3) float32, linear Rec.709.
        clipped: (H, W) bool, or None without a ``clipped`` channel.

    Raises:
        DamcapError: unreadable or truncated file, no colour channels, NaN or infinite values,
            radiance in a camera's own RGB or an unknown colour space.
    """
    from damcap.common.exr import CLIPPED_CHANNEL, read_exr

    from damcap.capture.working_space import COLORSPACES, working_from_rec709

    path = Path(path)
    pixels, names = read_exr(path)
    if all(c in names for c in ("R", "G", "B")):
        rgb = np.stack([pixels[..., names.index(c)] for c in ("R", "G", "B")], axis=-1)
    elif len(names) == 1 or (len(names) == 2 and CLIPPED_CHANNEL in names):
        grey = pixels[..., [i for i, n in enumerate(names) if n != CLIPPED_CHANNEL][0]]
        rgb = np.repeat(grey[..., None], 3, axis=-1)
    else:
        raise DamcapError(f"{path}: no R, G, B channels (the file has {', '.join(names)})")
    bad = int((~np.isfinite(rgb)).sum())
    if bad:
        raise DamcapError(f"{path}: {bad} pixel value(s) are NaN or infinite; a photo must hold finite radiance")
    _, _, attrs = _spec_attributes(path)
    space = attrs.get(EXR_COLORSPACE, "lin_rec709")
    if space not in COLORSPACES:
        raise DamcapError(f"{path}: radiance is in {space!r} (a RAW file without a colour matrix?); damcap reconstruct "
                          f"needs one of {', '.join(COLORSPACES)}")
    if space != "lin_rec709":
        rgb = rgb @ np.linalg.inv(working_from_rec709(space)).astype(np.float32).T
    clipped = pixels[..., names.index(CLIPPED_CHANNEL)] > 0.5 if CLIPPED_CHANNEL in names else None
    return np.ascontiguousarray(rgb, dtype=np.float32), clipped


def _read_raw(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import warnings

    from damcap.capture.raw import CaptureWarning, read_raw_rgb

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CaptureWarning)
        rgb, clipped, converted = read_raw_rgb(path)
    if not converted:
        raise DamcapError(f"{path}: the RAW file has no colour matrix, so its camera RGB cannot be converted to the "
                          "capture's lin_rec709")
    return rgb, clipped


def read_photo_radiance(path: str | os.PathLike, factor: float, reference: float,
                        log_response: np.ndarray | None = None) -> PhotoRadiance:
    """A photo of any kind as linear radiance, comparable across the photo set.

    Display photos go through :func:`damcap.capture.linearize.linearize_photo` (8/16-bit codes,
    tone curve undone); linear files through :func:`read_linear_rgb`; RAW files through
    :func:`damcap.capture.raw.read_raw_rgb`. The result is multiplied by ``reference / factor``.

    Args:
        path: the photo.
        factor: its exposure factor (from :func:`exposure_factors`), > 0.
        reference: the exposure factor the result is relative to, > 0.
        log_response: display photos only: (3, L) ``ln`` linear value per code, the curve
            ``damcap hdr`` recovered (:func:`damcap.capture.hdr.read_response`); None: sRGB.

    Returns:
        :class:`PhotoRadiance`.

    Raises:
        DamcapError: an unreadable or truncated file (named), a bad factor, a response curve
            given for a linear or RAW photo.
    """
    from damcap.capture.linearize import clipped_mask, linearize_photo

    path = Path(path)
    if not (np.isfinite(factor) and factor > 0 and np.isfinite(reference) and reference > 0):
        raise DamcapError(f"{path}: exposure factor and reference must be positive, got {factor!r}, {reference!r}")
    kind = photo_kind(path)
    if kind != "display" and log_response is not None:
        raise DamcapError(f"{path}: a response curve undoes the tone curve of 8-bit photos; this photo is a {kind} file")
    if kind == "display":
        codes = _read_display_codes(path)
        return PhotoRadiance(linearize_photo(codes, float(factor), float(reference), log_response), clipped_mask(codes))
    rgb, clipped = read_linear_rgb(path) if kind == "linear" else _read_raw(path)
    return PhotoRadiance((rgb * np.float32(reference / factor)).astype(np.float32), clipped)


def read_photo_linear(path: str | os.PathLike, factor: float, reference: float,
                      log_response: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) float32 linear radiance of a photo (:func:`read_photo_radiance` without the clipped mask)."""
    return read_photo_radiance(path, factor, reference, log_response).radiance_lin


def read_mask(path: str | os.PathLike, size: tuple[int, int] | None = None, photo_name: str = "") -> np.ndarray:
    """A mask file as (H, W) float32 in [0, 1], upright (turned by its own EXIF Orientation, if any).

    Args:
        path: mask image.
        size: (width, height) it must have (the photo's, upright: :func:`image_size`), or None.
        photo_name: the photo the mask belongs to, named in the size error.

    Raises:
        DamcapError: unreadable, or an upright size different from the photo's.
    """
    from damcap.common.exr import image_header, read_image_u8, upright_size

    if size is not None:  # from the header: a mask of another size is refused before it is decoded
        w, h, _, orientation = image_header(path)
        _check_mask_size(path, upright_size(w, h, orientation), tuple(size), photo_name)
    m = mask_to_unit(read_image_u8(path, working_bytes_per_pixel=MASK_WORKING_BYTES))
    if size is not None:
        _check_mask_size(path, (m.shape[1], m.shape[0]), tuple(size), photo_name)
    return m


#: bytes per pixel a mask needs beside its decoded pixels (its float32 copy and the comparisons made of it)
MASK_WORKING_BYTES = 8


def _check_mask_size(path: str | os.PathLike, mask: tuple[int, int], photo: tuple[int, int], photo_name: str) -> None:
    if mask == photo:
        return
    of = f"its photo {photo_name + ' ' if photo_name else ''}is {photo[0]}x{photo[1]}"
    if mask == photo[::-1] and mask[0] != mask[1]:
        raise DamcapError(f"{path}: mask is {mask[0]}x{mask[1]} but {of}, both upright as a viewer shows them (EXIF "
                          f"Orientation applied): the mask is turned by 90 degrees to its photo; draw or turn the mask "
                          f"to the photo as a viewer shows it")
    raise DamcapError(f"{path}: mask is {mask[0]}x{mask[1]} but {of}; masks must match the photos' size")


# --------------------------------------------------------------------------------------------
# Registration proxies
# --------------------------------------------------------------------------------------------

def proxy_name(photo_name: str) -> str:
    """The file name of a photo's registration proxy: same base name, PNG.

    >>> proxy_name("IMG_0001.exr")
    'IMG_0001.png'
    """
    return f"{Path(photo_name).stem}.png"


def turned_photos(folder: str | os.PathLike, names: list[str]) -> dict[str, int]:
    """The display photos stored turned: name -> EXIF Orientation (2..8), from their headers."""
    from damcap.common.exr import image_header

    folder = Path(folder)
    out = {}
    for n in names:
        if photo_kind(n) == "display" and (o := image_header(folder / n)[3]) != 1:
            out[n] = o
    return out


def needs_registration_proxies(folder: str | os.PathLike, names: list[str]) -> bool:
    """Whether COLMAP must read proxies (:func:`write_registration_proxies`) instead of the photos:
    linear or RAW photos, or display photos of which some are stored turned (COLMAP reads pixels as
    stored, ignoring EXIF Orientation)."""
    return photo_set_kind(names, folder) != "display" or bool(turned_photos(folder, names))


#: header attributes a display photo's upright proxy keeps: what COLMAP's focal-length prior reads
#: (in 35 mm terms, or in mm with the camera's make and model or the focal plane's resolution)
PROXY_EXIF = ("Make", "Model", "Exif:FocalLength", "Exif:FocalLengthIn35mmFilm", "Exif:FocalPlaneXResolution",
              "Exif:FocalPlaneYResolution", "Exif:FocalPlaneResolutionUnit")


def proxy_exif(path: str | os.PathLike) -> dict[str, str | int | float]:
    """The header attributes of a display photo its upright proxy carries (:data:`PROXY_EXIF`;
    numbers and text only), so that COLMAP's focal-length prior, computed from the EXIF focal length
    and the image's diagonal, is the one the photo gives (a turn keeps the diagonal)."""
    _, _, attrs = _spec_attributes(Path(path))
    return {k: v for k, v in attrs.items() if k in PROXY_EXIF and isinstance(v, (str, int, float))}


def _link(target: Path, source: Path) -> None:
    """``target`` made a symbolic link to ``source`` (a copy where links cannot be made), atomically."""
    from damcap.common.atomic import atomic_path

    with atomic_path(target, keep_name=True) as tmp:  # a fresh name in a staging folder: nothing there yet
        try:
            os.symlink(source.resolve(), tmp)
        except OSError:
            shutil.copyfile(source, tmp)


def write_registration_proxies(photos_dir: str | os.PathLike, names: list[str], proxy_dir: str | os.PathLike,
                               progress: Callable[[str, int, int], None] | None = None) -> dict[str, str]:
    """8-bit upright proxies for COLMAP, which reads display images only, and those as stored.

    Linear and RAW photos: COLMAP's reader would clamp linear floats to 8 bits without a display
    encoding and cannot decode RAW files, so each photo is decoded to linear radiance
    (:func:`read_photo_radiance`) and written as :func:`proxy_srgb_u8` PNG under its base name.
    Display photos stored turned (EXIF Orientation other than 1, :func:`turned_photos`): COLMAP
    ignores the tag, so each is written upright (:func:`read_photo_u8`) as PNG under its base name,
    with its EXIF focal length, make and model (:func:`proxy_exif`); the other display photos are
    linked under their own names (copied where links cannot be made). Same pixel grid as the photo
    as damcap reads it (upright), so cameras and keypoints are the photo's. A proxy is written again
    only when its photo's size or modification time changed (``proxy_dir/manifest.json``); the
    encoding is deterministic.

    Args:
        photos_dir: the photo folder (read only).
        names: photo file names (unique base names, see :func:`list_photos`).
        proxy_dir: where the proxies go (inside the capture's work folder).
        progress: called as (stage, done, total).

    Returns:
        photo name -> proxy file name (in ``proxy_dir``).

    Raises:
        DamcapError: an unreadable photo (named).
    """
    from damcap.common.atomic import write_json_atomic
    from damcap.common.exr import write_image_u8, write_png

    photos_dir, proxy_dir = Path(photos_dir), Path(proxy_dir)
    proxy_dir.mkdir(parents=True, exist_ok=True)
    progress = progress or (lambda stage, done, total: None)
    manifest_path = proxy_dir / "manifest.json"
    try:
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        manifest = {}
    turned = turned_photos(photos_dir, names)
    out: dict[str, str] = {}
    for k, name in enumerate(names):
        progress("registration proxies", k, len(names))
        st = (photos_dir / name).stat()
        key: dict[str, Any] = {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "version": PROXY_VERSION, "percentile": PROXY_PERCENTILE}
        display = photo_kind(name) == "display"
        if display:
            key = {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "version": PROXY_VERSION,
                   "upright_from": turned[name] if name in turned else "linked"}
        target = proxy_dir / (name if display and name not in turned else proxy_name(name))
        if manifest.get(name) != key or not target.is_file():
            if not display:
                write_png(target, proxy_srgb_u8(read_photo_radiance(photos_dir / name, 1.0, 1.0).radiance_lin))
            elif name in turned:
                write_image_u8(target, read_photo_u8(photos_dir / name), proxy_exif(photos_dir / name))
            else:
                _link(target, photos_dir / name)
            manifest[name] = key
            write_json_atomic(manifest_path, manifest)
        out[name] = target.name
    progress("registration proxies", len(names), len(names))
    return out


def file_digests(folder: str | os.PathLike, names: list[str]) -> dict[str, str]:
    """SHA-256 (16 hex digits) of each file's bytes: what identifies a proxy's content."""
    folder = Path(folder)
    return {n: hashlib.sha256((folder / n).read_bytes()).hexdigest()[:16] for n in names}
