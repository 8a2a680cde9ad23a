"""Exposure metadata (time, ISO, f-number): the pure exposure arithmetic and the EXIF readers.

The exposure of a photo is ``H = time_s * (iso / 100) / f_number**2`` (the photometric exposure
up to a constant: sensor counts are proportional to radiance times H). Dividing a linearised
photo by H (relative to a reference H) makes values proportional to scene radiance across photos
(``docs/capture-format.md``: "exposure time, ISO and aperture are already divided out").

Readers: OpenImageIO's EXIF attributes first (JPEG, PNG, TIFF and every TIFF-based RAW, DNG
included); for RAW files OpenImageIO cannot open, LibRaw's parse via rawpy. A field that is
absent or zero (some files carry zeroed EXIF) counts as missing.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from damcap.common.errors import DamcapError

#: ISO speed that counts as gain 1 in :func:`exposure_factor`.
ISO_REFERENCE = 100.0

#: what to do when a bracket lacks exposure metadata
MISSING_EXPOSURE_HINT = "pass the times with --exposures, e.g. --exposures 1/250,1/60,1/15 (seconds, one per file)"

#: File extensions read through rawpy (LibRaw).
RAW_EXTENSIONS = frozenset({
    ".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf", ".rw2",
    ".pef", ".srw", ".kdc", ".dcr", ".mrw", ".3fr", ".iiq", ".x3f", ".erf", ".mef", ".mos", ".raw",
    ".rwl", ".k25",
})


def is_raw_path(path: str | os.PathLike) -> bool:
    """Whether a file is a camera RAW by its extension.

    >>> is_raw_path("IMG_0001.CR2"), is_raw_path("photo.jpg")
    (True, False)
    """
    return Path(path).suffix.lower() in RAW_EXTENSIONS


@dataclass(frozen=True)
class Exposure:
    """Exposure settings of one photo; ``None`` where the file does not say."""

    time_s: float | None
    """Exposure time in seconds, > 0."""
    iso: float | None = None
    """ISO speed (gain), > 0."""
    f_number: float | None = None
    """Aperture f-number N, > 0."""

    def to_json(self) -> dict[str, float]:
        """The capture folder's ``exposure`` record (docs/capture-format.md; only the known fields)."""
        out = {"time_s": self.time_s, "iso": self.iso, "f_number": self.f_number}
        return {k: float(v) for k, v in out.items() if v is not None}


def exposure_factor(time_s: float, iso: float | None = None, f_number: float | None = None) -> float:
    """Relative photometric exposure ``H = time_s * (iso / 100) / f_number**2``.

    A missing ``iso`` counts as 100 and a missing ``f_number`` as 1, so photos that all lack
    the same field stay comparable.

    Args:
        time_s: exposure time in seconds, > 0.
        iso: ISO speed, > 0, or None.
        f_number: f-number, > 0, or None.

    Returns:
        H in units of (s at ISO 100 and f/1), > 0.

    >>> exposure_factor(1 / 50, 200, 2.0)
    0.01
    """
    h = time_s * ((iso / ISO_REFERENCE) if iso else 1.0) / ((f_number**2) if f_number else 1.0)
    return float(h)


def _positive(value) -> float | None:
    """A finite positive float rounded to 7 significant digits (EXIF values arrive as float32),
    or None (absent, zero, negative, NaN, or not a number).

    >>> _positive(0.019999999552965164), _positive(0.0), _positive((100,))
    (0.02, None, 100.0)
    """
    if isinstance(value, (tuple, list, np.ndarray)):
        value = value[0] if len(value) else None
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return float(f"{v:.7g}") if math.isfinite(v) and v > 0 else None


def _exposure_from_oiio(path: Path) -> Exposure | None:
    """EXIF exposure via OpenImageIO attributes; None when OpenImageIO cannot open the file."""
    import OpenImageIO as oiio

    from damcap.common.exr import oiio_error

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio_error(oiio)  # clear the error state
        return None
    try:
        spec = inp.spec()
        time_s = _positive(spec.getattribute("ExposureTime"))
        f_number = _positive(spec.getattribute("FNumber"))
        iso = None
        for key in ("Exif:PhotographicSensitivity", "Exif:ISOSpeedRatings", "Exif:ISOSpeed"):
            iso = _positive(spec.getattribute(key))
            if iso:
                break
    finally:
        inp.close()
    return Exposure(time_s=time_s, iso=iso, f_number=f_number)


def _exposure_from_rawpy(path: Path) -> Exposure | None:
    """LibRaw's parse of the maker metadata; None when LibRaw cannot open the file.

    LibRaw reports 1.0 for a missing shutter or aperture, so its time and aperture are only
    trusted when it also found an ISO speed (a sign that it parsed the exposure block).
    """
    import rawpy

    try:
        with rawpy.imread(str(path)) as raw:
            other = raw.other
    except (rawpy.LibRawError, OSError):
        return None
    iso = _positive(other.iso_speed)
    if iso is None:
        return Exposure(time_s=None)
    return Exposure(time_s=_positive(other.shutter_speed), iso=iso, f_number=_positive(other.aperture))


def read_exposure(path: str | os.PathLike) -> Exposure:
    """Exposure time, ISO and f-number of one photo from its metadata.

    Args:
        path: a JPEG, PNG, TIFF or camera RAW file.

    Returns:
        The fields found; each is None where the file has none (or only zeros).

    Raises:
        DamcapError: the file does not exist.
    """
    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: file not found")
    exp = _exposure_from_oiio(path)
    if is_raw_path(path):
        fallback = _exposure_from_rawpy(path)
        if exp is None:
            exp = fallback
        elif fallback is not None:
            exp = Exposure(time_s=exp.time_s or fallback.time_s, iso=exp.iso or fallback.iso,
                           f_number=exp.f_number or fallback.f_number)
    return exp if exp is not None else Exposure(time_s=None)


_NUMBER = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(?:/\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?))?\s*$")


def parse_exposure_list(text: str) -> list[float]:
    """Parse ``--exposures``: comma-separated exposure times in seconds (fractions allowed).

    >>> parse_exposure_list("1/30, 0.25,2")
    [0.03333333333333333, 0.25, 2.0]

    Raises:
        DamcapError: an entry is not a positive number.
    """
    out = []
    for item in text.split(","):
        m = _NUMBER.match(item)
        value = None
        if m:
            num = float(m.group(1))
            den = float(m.group(2)) if m.group(2) else 1.0
            value = num / den if den > 0 else None
        if value is None or not math.isfinite(value) or value <= 0:
            raise DamcapError(
                f"--exposures: {item.strip()!r} is not a positive exposure time; give seconds "
                "separated by commas, e.g. --exposures 1/250,1/60,1/15"
            )
        out.append(value)
    return out


def read_hdr_image_list(path: str | os.PathLike) -> dict[str, float]:
    """Exposure times (seconds) by file name from an HDRShop-style image list (Debevec and
    Malik's ``*.hdr_image_list.txt``: one ``NAME 1/SHUTTER ...`` line per image file).

    Raises:
        DamcapError: the list cannot be read or a shutter value is not a positive number.
    """
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as e:
        raise DamcapError(f"{path}: cannot read the image list ({e.strerror})") from None
    times = {}
    for line in lines:
        parts = line.split()
        if len(parts) >= 2 and Path(parts[0]).suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
            try:
                inv = float(parts[1])  # the list gives 1 / shutter time
            except ValueError:
                inv = 0.0
            if not (inv > 0 and math.isfinite(inv)):
                raise DamcapError(f"{path}: {parts[1]!r} is not a positive 1/shutter value (line {line.strip()!r})")
            times[parts[0]] = 1.0 / inv
    return times


def resolve_exposure_factors(
    paths: Sequence[str | os.PathLike],
    exposures: Sequence[Exposure],
    given_times_s: Sequence[float] | None = None,
    missing_hint: str = MISSING_EXPOSURE_HINT,
) -> np.ndarray:
    """Relative exposure H of every frame of a bracket, from EXIF or from ``--exposures``.

    ``given_times_s`` (the ``--exposures`` list) replaces the metadata entirely: the values are
    exposure times in seconds at one common ISO and aperture. From EXIF, ISO and f-number must be
    known for all frames or for none (then they are assumed equal).

    Args:
        paths: the N frame files (for messages).
        exposures: N metadata records from :func:`read_exposure`.
        given_times_s: N exposure times in seconds, or None.
        missing_hint: what to do when a time is missing (appended to the error).

    Returns:
        (N,) float64 exposure factors H, > 0 (see :func:`exposure_factor`).

    Raises:
        DamcapError: a time is missing (the message names ``--exposures``), the list has the wrong
            length, or ISO / f-number are known for some frames only.
    """
    n = len(paths)
    if given_times_s is not None:
        if len(given_times_s) != n:
            raise DamcapError(
                f"--exposures lists {len(given_times_s)} value(s) for {n} file(s); give one exposure time per file, "
                "in the order of the files"
            )
        return np.array([exposure_factor(float(t)) for t in given_times_s])
    missing = [Path(p).name for p, e in zip(paths, exposures) if e.time_s is None]
    if missing:
        raise DamcapError(
            f"{missing[0]}: no exposure time in the file's metadata ({len(missing)} of {n} file(s) lack one); {missing_hint}"
        )
    fields = {}
    for name in ("iso", "f_number"):
        values = [getattr(e, name) for e in exposures]
        known = [v is not None for v in values]
        if any(known) and not all(known):
            lacking = Path(paths[known.index(False)]).name
            raise DamcapError(
                f"{lacking}: metadata has no {name.replace('_', '-')} while other frames do, so frames would not be "
                f"comparable; {missing_hint}"
            )
        fields[name] = values
    return np.array([exposure_factor(float(e.time_s), i, f)  # type: ignore[arg-type]
                     for e, i, f in zip(exposures, fields["iso"], fields["f_number"])])
