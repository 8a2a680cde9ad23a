"""Checks for numbers that come from a file or an option, before anything is allocated from them.

Every check is NaN-proof (it asks whether the value is *inside* the allowed range, so NaN, which
compares false, is refused) and names the bound in its message. The bounds on architectures and
counts are generous limits of what a machine can hold, not of what is sensible; resolutions are
bounded by this machine's memory (:func:`require_memory`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import types
import typing
from pathlib import Path
from typing import Any

import numpy as np

from damcap.common.errors import DamcapError

#: largest width of a DAM hidden layer
MAX_DAM_WIDTH = 4096
#: most hidden layers of a DAM
MAX_DAM_DEPTH = 64
#: largest channel count of a convolution (predictor, segmenter)
MAX_CHANNELS = 4096
#: most convolution layers of a predictor
MAX_CONV_LAYERS = 16
#: most materials of a segmentation or a capture
MAX_MATERIALS = 64
#: longest side of an image, pixels (OpenEXR and JPEG both stop at 65535)
MAX_IMAGE_SIDE = 65535
#: most optimiser steps, views, frames, samples and similar counts
MAX_COUNT = 10 ** 9
#: most pixels in one optimiser step's batch
MAX_BATCH_PIXELS = 2 ** 24
#: largest JSON file damcap parses (transforms.json, pose files, records), bytes
MAX_JSON_BYTES = 256 * 2 ** 20
#: memory assumed when the machine's cannot be read, bytes
FALLBACK_MEMORY_BYTES = 16 * 2 ** 30

_FLOAT_DTYPES = {"float16": np.float16, "float32": np.float32, "float64": np.float64}


def _prefix(where: str | os.PathLike | None) -> str:
    return f"{where}: " if where else ""


def flag(name: str) -> str:
    """The CLI flag of an options field: ``learning_rate`` -> ``--learning-rate``."""
    return "--" + name.replace("_", "-")


def finite_in(value: Any, dtype: str, what: str, where: str | os.PathLike | None = None) -> float:
    """``value`` as a float that stays finite when cast to ``dtype`` (where it will be used).

    >>> finite_in(1e39, "float64", "scale")
    1e+39
    >>> try:
    ...     finite_in(1e39, "float32", "scale", "a.dam")
    ... except DamcapError as e:
    ...     print(e)
    a.dam: scale must be a finite float32 number (|x| <= 3.403e+38), got 1e+39

    Raises:
        DamcapError: not a number (bools count as not numbers), NaN, inf, or beyond ``dtype``'s range.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise DamcapError(f"{_prefix(where)}{what} must be a number, got {value!r}")
    try:
        v = float(value)
    except OverflowError:
        v = math.inf
    limit = float(np.finfo(_FLOAT_DTYPES[dtype]).max)
    if not (math.isfinite(v) and abs(v) <= limit):
        raise DamcapError(f"{_prefix(where)}{what} must be a finite {dtype} number (|x| <= {limit:.4g}), got {value!r}")
    return v


def bounded_int(value: Any, lo: int, hi: int, what: str, where: str | os.PathLike | None = None) -> int:
    """``value`` as an int in [lo, hi]; a float is accepted only when it is a whole number.

    >>> try:
    ...     bounded_int(10 ** 12, 1, 4096, "DAM width", "a.dam")
    ... except DamcapError as e:
    ...     print(e)
    a.dam: DAM width must be an integer in [1, 4096], got 1000000000000

    Raises:
        DamcapError: not an integer, or outside [lo, hi] (the message names both bounds).
    """
    shown = repr(value)
    if isinstance(value, (float, np.floating)) and math.isfinite(value) and float(value).is_integer():
        value = int(value)
    return check_value(value, Range(lo, hi), integer=True, what=what, shown=shown, where=where)


#: field metadata key of an option's allowed values (:class:`Range`)
RANGE = "range"


@dataclasses.dataclass(frozen=True)
class Range:
    """The values a number may take: between ``lo`` and ``hi`` (None: unbounded on that side),
    each end included unless ``lo_open`` / ``hi_open``.

    An options dataclass declares it once per field (``field(default=..., metadata=in_range(1,
    MAX_COUNT))``); the command line refuses a value outside it while parsing, and
    :func:`check_ranges` refuses it for callers of the library.
    """

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def contains(self, v: float) -> bool:
        """Whether ``v`` lies inside (NaN never does)."""
        above = self.lo is None or (v > self.lo if self.lo_open else v >= self.lo)
        below = self.hi is None or (v < self.hi if self.hi_open else v <= self.hi)
        return bool(above and below) and v == v

    def phrase(self) -> str:
        """What a message says after "must be a number": `` in [1, 10]``, `` >= 0``, or nothing
        for an unbounded range."""
        if self.lo is None and self.hi is None:
            return ""
        return f" in {self.text()}" if self.lo is not None and self.hi is not None else f" {self.text()}"

    def text(self) -> str:
        """``[1, 1000000000]``, ``(0, 1]``, ``>= 0``, ``> 0``."""
        lo, hi = _number_text(self.lo), _number_text(self.hi)
        if self.hi is None:
            return f"{'>' if self.lo_open else '>='} {lo}" if self.lo is not None else "any value"
        if self.lo is None:
            return f"{'<' if self.hi_open else '<='} {hi}"
        return f"{'(' if self.lo_open else '['}{lo}, {hi}{')' if self.hi_open else ']'}"


def _number_text(x: float | None) -> str:
    """A bound as a person writes it: whole numbers in full (1000000000), others as ``%g``."""
    if x is None:
        return ""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e16 else f"{x:g}"


def in_range(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
             **metadata: Any) -> dict[str, Any]:
    """Field metadata declaring a number's allowed values (plus any other metadata given)."""
    return {RANGE: Range(lo, hi, lo_open, hi_open), **metadata}


#: a count of steps, views, samples, ... (>= 1)
COUNT = in_range(1, MAX_COUNT)
#: a count where 0 means none / never
COUNT_OR_ZERO = in_range(0, MAX_COUNT)
#: a random seed: what numpy, torch, COLMAP and Mitsuba all accept
SEED = in_range(0, 2 ** 31 - 1)
#: a positive scale, rate or distance
POSITIVE = in_range(0, None, lo_open=True)
#: a weight where 0 is off
NON_NEGATIVE = in_range(0, None)
#: a fraction in (0, 1]
FRACTION = in_range(0, 1, lo_open=True)
#: an elevation strictly between the poles (at a pole the camera's up is its view), degrees
ELEVATION_DEG = in_range(-90, 90, lo_open=True, hi_open=True)
#: a field of view, degrees
FOV_DEG = in_range(0, 170, lo_open=True, hi_open=True)
#: an azimuth, degrees (up to one turn either way)
AZIMUTH_DEG = in_range(-360, 360)
#: a camera's distance from the centre of an object scaled into the unit sphere (outside it)
CAMERA_DISTANCE = in_range(1, 1000, lo_open=True)


def _shown(value: Any) -> str:
    return value if isinstance(value, str) else repr(value)


def check_value(value: Any, rng: Range | None, *, integer: bool, what: str, shown: str | None = None,
                where: str | os.PathLike | None = None) -> Any:
    """``value`` if it is a finite float32 number (``integer``: an int) inside ``rng``.

    Args:
        shown: the value as the user wrote it (the command line's text), for the message.

    >>> try:
    ...     check_value(0, Range(1, 10), integer=True, what="--steps", shown="0")
    ... except DamcapError as e:
    ...     print(e)
    --steps must be an integer in [1, 10], got 0

    Raises:
        DamcapError: naming ``what``, the allowed values and the value.
    """
    shown = shown if shown is not None else _shown(value)
    allowed = rng.phrase() if rng is not None else ""
    if integer:
        ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
        if not ok or (rng is not None and not rng.contains(int(value))):
            raise DamcapError(f"{_prefix(where)}{what} must be an integer{allowed}, got {shown}")
        return int(value)
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    try:
        v = float(value) if ok else math.nan
    except OverflowError:
        v = math.inf
    if not (ok and math.isfinite(v) and abs(v) <= float(np.finfo(np.float32).max)) or (rng is not None and not rng.contains(v)):
        raise DamcapError(f"{_prefix(where)}{what} must be a finite number{allowed}, got {shown}")
    return value


def number_kind(annotation: Any) -> type | None:
    """``int`` or ``float`` for a numeric annotation (``int``, ``float | None``, ``tuple[int, ...]``,
    ``list[float]``), else None."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if typing.get_origin(annotation) in (typing.Union, types.UnionType) and len(args) == 1:
        return number_kind(args[0])
    if typing.get_origin(annotation) in (list, tuple) and args:
        return number_kind(args[0])
    return annotation if annotation in (int, float) else None


def check_ranges(options: object) -> None:
    """Every numeric field of an options dataclass (nested ones included) inside its declared
    :class:`Range` and finite in float32; list and tuple fields item by item; None passes (not
    given).

    Raises:
        DamcapError: naming the first bad field's flag, its allowed values and the value.
    """
    hints = typing.get_type_hints(type(options))
    for f in dataclasses.fields(options):  # type: ignore[arg-type]
        value = getattr(options, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            check_ranges(value)
            continue
        kind = number_kind(hints[f.name])
        if kind is None or value is None:
            continue
        name = f.metadata.get("cli_flag", flag(f.name)).split("/")[0].split(",")[0]
        for v in value if isinstance(value, (list, tuple)) else [value]:
            check_value(v, f.metadata.get(RANGE), integer=kind is int, what=name)


def machine_memory_bytes() -> int:
    """Physical memory of this machine (cgroup limit where lower), bytes."""
    total = FALLBACK_MEMORY_BYTES
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        pass
    for cg in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(cg).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < total:
            total = int(text)
    return int(total)


def require_memory(nbytes: float, what: str, where: str | os.PathLike | None = None, fraction: float = 0.5) -> None:
    """Refuse a buffer that would need more than ``fraction`` of this machine's memory.

    Raises:
        DamcapError: naming the GiB it would need and the GiB allowed.
    """
    limit = machine_memory_bytes() * fraction
    if not (nbytes <= limit):
        raise DamcapError(f"{_prefix(where)}{what} would need {nbytes / 2 ** 30:.3g} GiB of memory; this machine allows "
                          f"{limit / 2 ** 30:.3g} GiB ({fraction:g} of its {machine_memory_bytes() / 2 ** 30:.3g} GiB)")


def require_resolution(width: Any, height: Any, bytes_per_pixel: int, what: str,
                       where: str | os.PathLike | None = None, copies: int = 1) -> tuple[int, int]:
    """A (width, height) bounded by :data:`MAX_IMAGE_SIDE` and by memory (``copies`` buffers of
    ``bytes_per_pixel`` bytes per pixel)."""
    w = bounded_int(width, 1, MAX_IMAGE_SIDE, f"{what} width", where)
    h = bounded_int(height, 1, MAX_IMAGE_SIDE, f"{what} height", where)
    require_memory(float(w) * h * bytes_per_pixel * copies, f"{what} of {w}x{h} pixels", where)
    return w, h


def load_json_file(path: str | os.PathLike, what: str = "JSON file", max_bytes: int = MAX_JSON_BYTES) -> Any:
    """Parse a JSON file with a size limit; too deep nesting, bad UTF-8 or bad JSON are one line.

    Raises:
        DamcapError: naming the file (missing, larger than ``max_bytes``, invalid, nested too deeply).
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise DamcapError(f"{path}: {what} is {size / 2 ** 20:.1f} MiB, larger than the {max_bytes / 2 ** 20:.0f} MiB damcap reads")
        text = path.read_bytes().decode("utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise DamcapError(f"{path}: cannot read {what} ({e})") from None
    return loads_json(text, path, what)


def loads_json(text: str | bytes, where: str | os.PathLike, what: str = "JSON") -> Any:
    """``json.loads`` whose failures (bad JSON, nesting deeper than Python's recursion limit,
    numbers too long to convert) are one line naming ``where``."""
    try:
        return json.loads(text)
    except RecursionError:
        raise DamcapError(f"{where}: {what} is nested too deeply (beyond Python's recursion limit "
                          f"{__import__('sys').getrecursionlimit()}); not a damcap file") from None
    except (ValueError, UnicodeDecodeError) as e:  # JSONDecodeError, int conversion limits
        raise DamcapError(f"{where}: invalid JSON ({str(e).splitlines()[0][:160]})") from None


# --------------------------------------------------------------------------------------------
# Cannot be right: values a file may hold that no physical input has
# --------------------------------------------------------------------------------------------

#: a camera centre this many times farther from the cameras' median centre than their median
#: distance to it lies beyond any scene the other cameras see
MAX_CAMERA_SPREAD = 1e6

#: a format's first bytes, by the suffix the contract names it with
MAGIC: dict[str, tuple[bytes, ...]] = {
    ".exr": (b"\x76\x2f\x31\x01",),
    ".png": (b"\x89PNG\r\n\x1a\n",),
    ".jpg": (b"\xff\xd8\xff",),
    ".jpeg": (b"\xff\xd8\xff",),
    ".tif": (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"),
    ".tiff": (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"),
    ".npy": (b"\x93NUMPY",),
}
_FORMAT_NAMES = {".exr": "OpenEXR", ".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".tif": "TIFF", ".tiff": "TIFF",
                 ".npy": "NumPy .npy"}


def content_format(head: bytes) -> str:
    """What a file's first bytes say it is (``"PNG"``, ``"OpenEXR"``, ...; ``"unknown"``).

    >>> content_format(b"\\x89PNG\\r\\n\\x1a\\n...")
    'PNG'
    """
    for suffix, magics in MAGIC.items():
        if any(head.startswith(m) for m in magics):
            return _FORMAT_NAMES[suffix]
    if head[:1] in (b"{", b"["):
        return "JSON text"
    return "empty" if not head else "unknown"


def check_format(path: str | os.PathLike) -> None:
    """Refuse a file whose first bytes are not the format its suffix names (a PNG named ``.exr``),
    before a decoder that reads any format by content accepts it; suffixes without a known
    signature pass.

    Raises:
        DamcapError: naming the file, the format its name says and what its content is.
    """
    path = Path(path)
    magics = MAGIC.get(path.suffix.lower())
    if magics is None:
        return
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError:
        return  # the reader's own error names what is wrong
    if not any(head.startswith(m) for m in magics):
        raise DamcapError(f"{path}: named {path.suffix} but its content is {content_format(head)}, not "
                          f"{_FORMAT_NAMES[path.suffix.lower()]}; convert it to {_FORMAT_NAMES[path.suffix.lower()]} "
                          f"(or give it the name of what it is)")


def check_camera_centres(centres_world: np.ndarray, names: list[str], where: str | os.PathLike) -> None:
    """Refuse camera centres no scene can have: beyond float32 (where the cameras are used), or
    farther from the cameras' median centre than :data:`MAX_CAMERA_SPREAD` times their median
    distance to it (a translation of 1e300 among cameras a few units apart).

    Args:
        centres_world: (N, 3) float64 camera centres, any world unit.
        names: N frame names, for the message.
        where: the file that holds them.

    Raises:
        DamcapError: naming the frame, its centre and the bound.
    """
    c = np.asarray(centres_world, dtype=np.float64).reshape(-1, 3)
    limit = float(np.finfo(np.float32).max)
    far = np.abs(c).max(axis=1)
    bad = np.flatnonzero(~(far <= limit))
    if bad.size:
        k = int(bad[0])
        raise DamcapError(f"{where}: {names[k]}: camera centre {c[k].tolist()} lies beyond float32's range ({limit:.4g}); "
                          f"no scene is that large: fix its transform_matrix")
    if len(c) < 3:
        return
    d = np.linalg.norm(c - np.median(c, axis=0), axis=1)
    scale = float(np.median(d))
    if scale > 0:
        k = int(np.argmax(d))
        if d[k] > MAX_CAMERA_SPREAD * scale:
            raise DamcapError(f"{where}: {names[k]}: camera centre {c[k].tolist()} is {d[k] / scale:.3g} times farther from the "
                              f"cameras' median centre than their median distance ({scale:.4g}; at most {MAX_CAMERA_SPREAD:g} "
                              f"times): no scene spans that; fix its transform_matrix")


def no_signal(values: np.ndarray, black: float, saturated: float | None) -> str | None:
    """Why an image (or a set of them) holds nothing to measure, or None.

    Args:
        values: any shape, the stored values (codes or radiance).
        black: values at or below this are black.
        saturated: values at or above this are saturated (None: no ceiling, e.g. radiance).

    Returns:
        ``"black everywhere (largest value 0)"``, ``"saturated everywhere (smallest value 255,
        saturation at 250)"`` or None.

    >>> no_signal(np.zeros((2, 2)), 0.0, None)
    'black everywhere (largest value 0)'
    >>> no_signal(np.full((2, 2), 255), 2, 250)
    'saturated everywhere (smallest value 255, saturation at 250)'
    """
    v = np.asarray(values)
    if v.size == 0:
        return "empty (no pixel)"
    hi = float(np.nanmax(v)) if np.issubdtype(v.dtype, np.floating) else float(v.max())
    if not (hi > black):
        return f"black everywhere (largest value {hi:g})"
    if saturated is not None:
        lo = float(v.min())
        if lo >= saturated:
            return f"saturated everywhere (smallest value {lo:g}, saturation at {saturated:g})"
    return None


def require_foreground(coverages: list[np.ndarray], threshold: float, where: str | os.PathLike) -> None:
    """Refuse a capture with no foreground pixel in any frame (nothing to fit, score or render).

    Args:
        coverages: per frame (H, W) coverage in [0, 1].
        threshold: coverage above which a pixel is foreground.

    Raises:
        DamcapError: naming the capture and the largest coverage found.
    """
    peak = max((float(c.max()) for c in coverages if c.size), default=0.0)
    if not (peak > threshold):
        raise DamcapError(f"{where}: no frame has a foreground pixel (largest coverage {peak:g}, foreground is above "
                          f"{threshold:g}); the capture shows no object: check its geometry and masks")
