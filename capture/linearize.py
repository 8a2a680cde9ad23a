"""Single-exposure photos to radiance comparable across photos (``damcap linearize``; ``reconstruct`` calls it).

An auto-exposure camera changes exposure time and ISO from photo to photo, and its JPEGs carry a
tone curve. :func:`linearize_photo` undoes the curve (sRGB, or a response recovered by
``damcap hdr``) and divides by the photo's exposure ``H = time_s * (iso / 100) / f_number**2``
relative to a reference exposure, so equal radiance gives equal values in every photo.
"""

from __future__ import annotations

import functools
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Literal, Sequence

import numpy as np

from damcap.common.errors import DamcapError
from damcap.common.native_stderr import native_stderr_caught
from damcap.common.validate import FRACTION, POSITIVE, check_ranges

from damcap.capture.exif import Exposure, exposure_factor, is_raw_path, read_exposure, resolve_exposure_factors
from damcap.common.colour import srgb_to_linear
from damcap.capture.working_space import CAMERA_RGB, COLORSPACES, rec709_to_working

#: file extensions ``damcap linearize`` picks up in a folder (RAW files too)
PHOTO_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff"})
#: encoded value at or above which a channel counts as clipped
CLIP_LEVEL = 0.99


def linearize_photo(
    srgb: np.ndarray,
    exposure: Exposure | float,
    reference_exposure: float = 1.0,
    log_response: np.ndarray | None = None,
) -> np.ndarray:
    """Linear radiance of one photo: undo the tone curve, divide by the relative exposure.

    Args:
        srgb: (H, W, 3) encoded photo: float in [0, 1], or uint8 / uint16 codes.
        exposure: the photo's :class:`~damcap.capture.exif.Exposure` (time_s required) or its
            exposure factor H directly, > 0.
        reference_exposure: exposure factor H_ref the result is relative to, > 0.
        log_response: (3, L) response table ``ln(linear)`` per code (from ``damcap hdr``);
            None: the sRGB curve.

    Returns:
        (H, W, 3) float32, linear Rec.709 (the photo's primaries), >= 0: what a photo taken at
        the reference exposure would record after linearisation.

    Raises:
        DamcapError: no exposure time, a non-positive exposure, or a wrongly shaped image.

    >>> img = np.full((1, 1, 3), 0.5)
    >>> round(float(linearize_photo(img, Exposure(time_s=0.02, iso=400, f_number=2.0), 0.005)[0, 0, 0]), 6)
    0.05351
    """
    h = _factor(exposure)
    if not (np.isfinite(reference_exposure) and reference_exposure > 0):
        raise DamcapError(f"reference exposure must be positive, got {reference_exposure!r}")
    img = np.asarray(srgb)
    if img.ndim != 3 or img.shape[2] != 3:
        raise DamcapError(f"a photo must be (H, W, 3), got shape {img.shape}")
    if log_response is None and np.issubdtype(img.dtype, np.integer):
        # integer codes: the curve once per code, then a table look-up (the same values, ~10x faster)
        return (_srgb_table(int(np.iinfo(img.dtype).max) + 1) * (reference_exposure / h)).astype(np.float32)[img]
    encoded = _encoded(img)
    if log_response is None:
        lin = srgb_to_linear(encoded)
    else:
        g = np.asarray(log_response, dtype=np.float64)
        if g.ndim != 2 or g.shape[0] != 3:
            raise DamcapError(f"log_response must be (3, L), got shape {g.shape}")
        pos = encoded * (g.shape[1] - 1)
        grid = np.arange(g.shape[1])
        lin = np.stack([np.exp(np.interp(pos[..., c], grid, g[c])) for c in range(3)], axis=-1)
    return (lin * (reference_exposure / h)).astype(np.float32)


def clipped_mask(srgb: np.ndarray, level: float = CLIP_LEVEL) -> np.ndarray:
    """(H, W) bool: some channel at or above ``level`` of full scale (its radiance is a lower bound).

    >>> clipped_mask(np.array([[[255, 10, 10], [200, 200, 200]]], np.uint8)).tolist()
    [[True, False]]
    """
    return (_encoded(np.asarray(srgb)) >= level).any(axis=-1)


@functools.lru_cache(maxsize=2)
def _srgb_table(levels: int) -> np.ndarray:
    """(levels,) float64: the sRGB decoding curve at each integer code ``z / (levels - 1)``."""
    return srgb_to_linear(np.arange(levels) / float(levels - 1))


def _encoded(img: np.ndarray) -> np.ndarray:
    if np.issubdtype(img.dtype, np.integer):
        return img.astype(np.float64) / float(np.iinfo(img.dtype).max)
    return np.clip(img.astype(np.float64), 0.0, 1.0)


def _factor(exposure: Exposure | float) -> float:
    if isinstance(exposure, Exposure):
        if exposure.time_s is None:
            raise DamcapError("the photo has no exposure time; cannot divide out its exposure")
        h = exposure_factor(exposure.time_s, exposure.iso, exposure.f_number)
    else:
        h = float(exposure)
    if not (np.isfinite(h) and h > 0):
        raise DamcapError(f"exposure must be positive, got {h!r}")
    return h


# --------------------------------------------------------------------------------------------
# Folder of photos (the command's body)
# --------------------------------------------------------------------------------------------

@dataclass
class LinearizeOptions:
    """Options of ``damcap linearize`` (the CLI mirrors them one to one)."""

    colorspace: Literal["lin_rec709", "acescg"] = "lin_rec709"
    """Working colour space of the output."""
    reference_exposure: float | None = field(default=None, metadata=POSITIVE)
    """Exposure factor H (s at ISO 100, f/1) the outputs are relative to; None: the median of the photos."""
    ignore_exposure: bool = False
    """Only undo the tone curve (for photos without exposure metadata taken at one fixed exposure)."""
    dtype: Literal["float", "half"] = "half"
    """EXR storage of the outputs."""
    clip_level: float = field(default=CLIP_LEVEL, metadata={**FRACTION, "cli_panel": "advanced"})
    """Encoded value at or above which a pixel is flagged clipped, in (0, 1]."""

    def validate(self) -> None:
        """Raise DamcapError on values outside their documented ranges (NaN and inf included)."""
        check_ranges(self)
        if self.colorspace not in COLORSPACES:
            raise DamcapError(f"--colorspace must be one of {', '.join(COLORSPACES)}, got {self.colorspace!r}")
        if self.dtype not in ("float", "half"):
            raise DamcapError(f"--dtype must be float or half, got {self.dtype!r}")


def list_photos(folder: str | os.PathLike) -> list[Path]:
    """Photos in a folder (not recursive), sorted by name: JPEG, PNG, TIFF and camera RAW.

    Raises:
        DamcapError: not a folder, or no photos in it.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DamcapError(f"{folder}: not a folder of photos")
    entries = [p for p in folder.iterdir() if p.suffix.lower() in PHOTO_EXTENSIONS or is_raw_path(p)]
    not_files = sorted(p for p in entries if not p.is_file())
    if not_files:
        raise DamcapError(f"{not_files[0]}: named like a photo but is not a file (a folder?); move it out of the photo folder")
    photos = sorted(entries)
    if not photos:
        raise DamcapError(f"{folder}: no photos found (looked for {', '.join(sorted(PHOTO_EXTENSIONS))} and RAW files)")
    return photos


def linearize_files(photos: Sequence[Path], out_dir: Path, opts: LinearizeOptions,
                    progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Linearise every photo into ``out_dir/<stem>.exr`` (R, G, B, clipped) and return the record
    (``progress(stage, done, total)`` after each photo).

    Raises:
        DamcapError: unreadable photos, missing exposure metadata (names --ignore-exposure),
            two photos with one base name, values beyond half precision.
    """
    opts.validate()
    stems = [p.stem for p in photos]
    dup = {s for s in stems if stems.count(s) > 1}
    if dup:
        raise DamcapError(f"{photos[0].parent}: several photos share the base name {sorted(dup)[0]!r}; outputs would collide")
    exposures = [_read_exposure_quietly(p) for p in photos]
    if opts.ignore_exposure:
        factors = np.ones(len(photos))
    else:
        factors = resolve_exposure_factors(photos, exposures, missing_hint=(
            "if all photos were taken at one exposure, pass --ignore-exposure to only undo the tone curve"))
    ref = float(opts.reference_exposure) if opts.reference_exposure else float(np.median(factors))
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    # outputs are staged in a hidden folder and moved into place only once every photo has been
    # read: a bad photo late in the list leaves no partial set of EXRs behind
    stage = Path(tempfile.mkdtemp(prefix=".linearize-", dir=out_dir))
    try:
        try:
            records = _linearize_into(photos, exposures, factors, ref, stage, opts, progress)
        except OSError as e:  # the error names the file in OUT it was writing, not the hidden stage
            name = None if e.filename is None else Path(os.fsdecode(e.filename))
            if name is not None and stage in name.parents:
                raise OSError(e.errno, e.strerror or str(e), str(out_dir / name.relative_to(stage))) from None
            raise
        except DamcapError as e:
            raise DamcapError(str(e).replace(str(stage), str(out_dir))) from None
        for rec in records:
            os.replace(stage / rec["output"], out_dir / rec["output"])
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if created:
            try:
                out_dir.rmdir()  # only when empty: the folder this call made
            except OSError:
                pass
        raise
    shutil.rmtree(stage, ignore_errors=True)
    return {"command": "linearize", "options": asdict(opts), "reference_exposure": ref, "photos": records}


def _linearize_into(photos: Sequence[Path], exposures: list[Exposure], factors: np.ndarray, ref: float, out_dir: Path,
                    opts: LinearizeOptions, progress: Callable[[str, int, int], None] | None = None) -> list[dict]:
    """Write every photo's EXR into ``out_dir``; the per-photo records."""
    from damcap.common.exr import CLIPPED_CHANNEL, write_exr

    from damcap.capture.hdr import HALF_MAX, read_ldr_codes

    records = []
    for path, exp, h in zip(photos, exposures, factors):
        colorspace = opts.colorspace
        if is_raw_path(path):
            rgb, clipped, converted = _linear_raw(path)
            radiance = rgb * np.float32(ref / h)
            colorspace = opts.colorspace if converted else CAMERA_RGB
        else:
            with native_stderr_caught():  # libpng prints its own lines on a damaged PNG; the error names the file
                codes, _ = read_ldr_codes(path)
            radiance = linearize_photo(codes, float(h), ref)
            clipped = clipped_mask(codes, opts.clip_level)
            converted = True
        if converted:
            radiance = np.maximum(rec709_to_working(radiance, opts.colorspace), 0.0)
        if opts.dtype == "half" and float(radiance.max()) > HALF_MAX:
            raise DamcapError(f"{path}: radiance reaches {float(radiance.max()):.4g}, beyond half precision; use --dtype float")
        out = out_dir / f"{path.stem}.exr"
        write_exr(out, np.concatenate([radiance, clipped[..., None].astype(np.float32)], axis=-1),
                  ("R", "G", "B", CLIPPED_CHANNEL), dtype=opts.dtype,
                  attributes={"damcap:colorspace": colorspace, "damcap:exposure_factor": float(h),
                              "damcap:reference_exposure": ref, "damcap:source": path.name})
        records.append({"file": path.name, "output": out.name, "exposure": exp.to_json(), "factor": float(h),
                        "scale": ref / float(h), "colorspace": colorspace, "clipped_fraction": float(clipped.mean())})
        if progress:
            progress("linearize", len(records), len(photos))
    return records


def _read_exposure_quietly(path: Path) -> Exposure:
    """:func:`damcap.capture.exif.read_exposure`, with what libpng prints itself on a damaged PNG caught."""
    with native_stderr_caught():
        return read_exposure(path)


def _linear_raw(path: Path) -> tuple[np.ndarray, np.ndarray, bool]:
    """One RAW photo as linear Rec.709 (or camera RGB), clipped mask, whether a matrix was applied."""
    import warnings

    from damcap.capture.raw import CaptureWarning, read_raw_rgb

    with warnings.catch_warnings():
        warnings.simplefilter("always", CaptureWarning)
        return read_raw_rgb(path)
