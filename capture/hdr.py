"""``damcap hdr``: one bracket of files to one linear radiance map (load, pure math, save).

RAW brackets go through :mod:`damcap.capture.raw` and the Poisson-optimal merge; LDR brackets
(JPEG, PNG, 8/16-bit TIFF) through a response curve (:mod:`damcap.capture.response`) and the
reliability-weighted merge. The output is linear, relative to a reference exposure (by default
the median exposure of the bracket): a value is what the reference frame would have recorded,
with 1 the saturation level of a RAW sensor or the value of the middle code for a recovered LDR
response.
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import numpy as np

from damcap.common.errors import DamcapError
from damcap.common.validate import FRACTION, POSITIVE, check_ranges, in_range, no_signal

from damcap.capture.align import chain_shifts, preview_u8, shift_image
from damcap.capture.exif import Exposure, is_raw_path, parse_exposure_list, read_exposure, resolve_exposure_factors
from damcap.capture.merge import PoissonAccumulator, merge_ldr
from damcap.capture.raw import (
    SATURATION_FRACTION,
    CaptureWarning,
    RawMosaic,
    apply_flip,
    camera_rgb_from_mosaic,
    dilate_mask,
    read_raw,
    to_rec709,
)
from damcap.capture.response import ResponseCurve, recover_response, sample_pixels_for_response
from damcap.capture.working_space import CAMERA_RGB, COLORSPACES, rec709_to_working

#: largest finite half-float value
HALF_MAX = 65504.0
#: code levels used for the response of 16-bit LDR images (codes are binned to this many)
LEVELS_16BIT = 1024
#: most sample pixels of a response recovery (its least-squares system grows with them)
MAX_RESPONSE_SAMPLES = 10 ** 6
#: most reweighting rounds of a response recovery
MAX_ITERATIONS = 100


@dataclass
class HdrOptions:
    """Options of ``damcap hdr`` (the CLI mirrors them one to one)."""

    exposures_s: list[float] | None = field(default=None, metadata=in_range(0, None, lo_open=True, cli_flag="--exposures", cli_parse=parse_exposure_list))
    """Exposure time of each file in seconds (same ISO and aperture), overriding EXIF; None: EXIF."""
    align: bool = False
    """Align frames by translation (median threshold bitmaps) before merging."""
    colorspace: Literal["lin_rec709", "acescg"] = "lin_rec709"
    """Working colour space of the output."""
    response: Literal["debevec", "srgb"] = "debevec"
    """LDR only: recover the camera response (Debevec & Malik 1997) or assume the sRGB curve."""
    reference_exposure: float | None = field(default=None, metadata=POSITIVE)
    """Exposure factor H (s at ISO 100, f/1; or seconds with ``exposures_s``) the output is relative to; None: the bracket's median."""
    saturation_fraction: float = field(default=SATURATION_FRACTION, metadata={**FRACTION, "cli_panel": "advanced"})
    """RAW only: fraction of the black-to-white range above which a raw value counts as clipped."""
    response_samples: int = field(default=2000, metadata=in_range(16, MAX_RESPONSE_SAMPLES, cli_panel="advanced"))
    """LDR only: sample pixels for the response recovery."""
    smoothness: float = field(default=12.0, metadata=in_range(0, 1e6, cli_panel="advanced"))
    """LDR only: Debevec smoothness weight (scaled by sqrt(observations / levels))."""
    flat_fraction: float = field(default=0.1, metadata={**FRACTION, "cli_panel": "advanced"})
    """LDR only: sample pixels are taken among this fraction of flattest pixels, in (0, 1]."""
    sample_phase: float = field(default=0.0, metadata=in_range(0, 1, hi_open=True, cli_panel="advanced"))
    """LDR only: shift of the sample pixels' brightness ranks, a fraction of their spacing. Another
    phase is another equally valid sample (to see how much a result depends on it)."""
    iterations: int = field(default=2, metadata=in_range(0, MAX_ITERATIONS, cli_panel="advanced"))
    """LDR only: reweighting rounds of the response and code reliabilities."""
    dtype: Literal["float", "half"] = "float"
    """EXR storage: float (32-bit) or half (16-bit, values up to 65504)."""

    def validate(self) -> None:
        """Raise DamcapError on values outside their declared ranges (NaN and inf included)."""
        check_ranges(self)
        if self.colorspace not in COLORSPACES:
            raise DamcapError(f"--colorspace must be one of {', '.join(COLORSPACES)}, got {self.colorspace!r}")
        if self.response not in ("debevec", "srgb"):
            raise DamcapError(f"--response must be debevec or srgb, got {self.response!r}")
        if self.dtype not in ("float", "half"):
            raise DamcapError(f"--dtype must be float or half, got {self.dtype!r}")


@dataclass
class HdrResult:
    """A merged bracket and how it was made."""

    radiance_lin: np.ndarray
    """(H, W, 3) float32, linear, in ``colorspace``, relative to ``reference_exposure``, >= 0."""
    clipped: np.ndarray
    """(H, W) bool: some channel saturated in every frame (its value is a lower bound)."""
    colorspace: str
    """``lin_rec709``, ``acescg`` or ``camera_rgb`` (RAW without a colour matrix)."""
    kind: Literal["raw", "ldr"]
    files: list[str]
    exposures: list[Exposure]
    exposure_factors: np.ndarray
    """(P,) relative exposures H used for the merge."""
    reference_exposure: float
    shifts: list[tuple[int, int]] = field(default_factory=list)
    """(dy, dx) applied to each frame (all zero without ``align``)."""
    response: ResponseCurve | None = None
    warnings: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------------------------
# LDR files
# --------------------------------------------------------------------------------------------

def read_ldr_codes(path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """Integer code values of an 8- or 16-bit image (JPEG, PNG, TIFF), as RGB, turned upright by
    its EXIF Orientation (:func:`damcap.common.exr.upright`; a phone's portrait photo is stored
    sideways with Orientation 6), as a viewer shows it.

    Args:
        path: the image file.

    Returns:
        codes: (H, W, 3) uint8 or uint16 (grey is repeated, alpha dropped), upright.
        max_code: 255 or 65535.

    Raises:
        DamcapError: missing, unreadable or truncated file, or a floating-point image.
    """
    import OpenImageIO as oiio

    from damcap.common.exr import check_header_size, oiio_error, upright

    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: file not found")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        msg = oiio_error(oiio).strip().splitlines()
        raise DamcapError(f"{path}: cannot read image ({msg[-1] if msg else 'unknown format'})")
    try:
        spec = inp.spec()
        fmt = str(spec.format)
        if fmt not in ("uint8", "uint16"):
            raise DamcapError(f"{path}: pixel format {fmt}; damcap hdr merges 8/16-bit photos or RAW files "
                              "(a floating-point image is already linear)")
        check_header_size(path, spec.width, spec.height, spec.nchannels, 2)
        pixels = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        err = oiio_error(inp)
        orientation = spec.get_int_attribute("Orientation", 1)
    finally:
        inp.close()
    if pixels is None or err:
        raise DamcapError(f"{path}: cannot read pixels, the file is damaged or truncated ({err.strip() or 'no data'})")
    codes = np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)
    if codes.shape[2] in (1, 2):
        codes = np.repeat(codes[..., :1], 3, axis=2)
    return upright(np.ascontiguousarray(codes[..., :3]), orientation), (255 if fmt == "uint8" else 65535)


def code_levels(codes: np.ndarray, max_code: int) -> tuple[np.ndarray, int]:
    """Map codes to response-table indices: 8-bit codes as they are, 16-bit codes binned.

    Args:
        codes: (...) uint8/uint16 codes in [0, max_code].
        max_code: 255 or 65535.

    Returns:
        indices: (...) uint16 in [0, L); L: 256 for 8-bit, :data:`LEVELS_16BIT` for 16-bit.

    >>> code_levels(np.array([0, 65535, 32768], np.uint16), 65535)[0].tolist()
    [0, 1023, 512]
    """
    if max_code <= 255:
        return codes.astype(np.uint16), 256
    levels = LEVELS_16BIT
    idx = np.round(codes.astype(np.float32) * ((levels - 1) / max_code)).astype(np.uint16)
    return idx, levels


# --------------------------------------------------------------------------------------------
# The command's body
# --------------------------------------------------------------------------------------------

def _check_files(paths: Sequence[Path]) -> Literal["raw", "ldr"]:
    if len(paths) < 2:
        which = paths[0] if paths else "(none)"
        raise DamcapError(f"{which}: a bracket needs at least 2 exposures, got {len(paths)}; for single photos "
                          "use damcap linearize")
    kinds = {is_raw_path(p) for p in paths}
    if len(kinds) > 1:
        raw = next(p for p in paths if is_raw_path(p))
        other = next(p for p in paths if not is_raw_path(p))
        raise DamcapError(f"{raw} is a RAW file but {other} is not: the bracket mixes RAW and non-RAW files; "
                          "merge one kind at a time")
    seen: dict[Path, Path] = {}
    for p in paths:
        if not p.is_file():
            raise DamcapError(f"{p}: file not found")
        key = p.resolve()
        if key in seen:
            raise DamcapError(f"{p}: given twice in the bracket (as {seen[key]} too); a bracket needs distinct exposures, "
                              "one file each")
        seen[key] = p
    return "raw" if kinds.pop() else "ldr"


def _check_distinct_exposures(paths: Sequence[Path], factors: np.ndarray, given_times_s: Sequence[float] | None) -> None:
    """Refuse two frames of (numerically) the same exposure: they add no range, and the LDR
    response recovery needs distinct exposures to be determined.

    Args:
        factors: (P,) exposure factors H of ``paths``.
        given_times_s: the ``--exposures`` list (named in the message) or None (EXIF).
    """
    order = np.argsort(factors, kind="stable")
    for i, j in zip(order[:-1], order[1:]):
        if np.isclose(factors[i], factors[j], rtol=1e-6, atol=0.0):
            what = (f"--exposures gives both {given_times_s[i]:g} s" if given_times_s is not None
                    else f"their metadata gives both the exposure factor {factors[i]:.6g}")
            raise DamcapError(f"{paths[i]} and {paths[j]}: {what}; a bracket needs distinct exposures "
                              "(e.g. 1-2 stops apart)")


def _reference(factors: np.ndarray, opts: HdrOptions) -> float:
    return float(opts.reference_exposure) if opts.reference_exposure else float(np.median(factors))


def _check_same_sensor(path: Path, m: RawMosaic, ref_path: Path, ref: RawMosaic) -> None:
    if m.counts.shape != ref.counts.shape:
        raise DamcapError(f"{path}: sensor area {m.counts.shape[1]}x{m.counts.shape[0]} differs from {ref_path.name}'s "
                          f"{ref.counts.shape[1]}x{ref.counts.shape[0]}; a bracket must come from one camera at one size")
    if (m.cfa is None) != (ref.cfa is None) or (m.cfa is not None and not np.array_equal(m.cfa, ref.cfa)):
        raise DamcapError(f"{path}: colour-filter pattern differs from {ref_path.name}'s")


def _raw_preview(m: RawMosaic) -> np.ndarray:
    """Grey preview of a frame for alignment (mosaics: 2x2 quads summed, half resolution), float32;
    saturated quads are +inf, so they stay white (bright, as they truly are) at every exposure."""
    if m.counts.ndim == 2:
        return np.where(_bin2(m.saturated.astype(np.float32)) > 0, np.inf, _bin2(m.counts))
    return np.where(m.saturated.any(axis=-1), np.inf, m.counts.mean(axis=-1))


def _raw_shifts(paths: list[Path], factors: np.ndarray, ref_idx: int, ref: RawMosaic, opts: HdrOptions) -> list[tuple[int, int]]:
    """Alignment pass: previews of every frame on one exposure-normalised scale, chained MTB shifts."""
    previews = []
    for j, (path, h) in enumerate(zip(paths, factors)):
        m = ref if j == ref_idx else read_raw(path, opts.saturation_fraction)
        _check_same_sensor(path, m, paths[ref_idx], ref)
        previews.append(_raw_preview(m) / np.float32(h))
        del m
    finite = previews[ref_idx][np.isfinite(previews[ref_idx])]
    scale = 0.18 / max(float(np.median(finite)) if finite.size else 1.0, 1e-12)
    previews_u8 = [preview_u8(p * scale, normalize=False) for p in previews]
    step = 2 if ref.counts.ndim == 2 else 1  # mosaics: shift by whole colour quads
    return [(dy * step, dx * step) for dy, dx in chain_shifts(previews_u8, factors, ref_idx)]


def _merge_raw(paths: list[Path], factors: np.ndarray, ref_h: float, opts: HdrOptions, result_warnings: list[str]):
    """RAW bracket -> (image in the working space, clipped mask, colour space, shifts)."""
    ref_idx = int(np.argsort(factors)[len(factors) // 2])
    ref = read_raw(paths[ref_idx], opts.saturation_fraction)
    mosaic_2d = ref.counts.ndim == 2
    shifts = _raw_shifts(paths, factors, ref_idx, ref, opts) if opts.align else [(0, 0)] * len(paths)
    acc = PoissonAccumulator(ref.counts.shape)
    acc.add(ref.counts, float(factors[ref_idx] / ref_h), ref.saturated)
    for j, path in enumerate(paths):
        if j == ref_idx:
            continue
        m = read_raw(path, opts.saturation_fraction)
        _check_same_sensor(path, m, paths[ref_idx], ref)
        if shifts[j] != (0, 0):
            counts, valid = shift_image(m.counts, *shifts[j], 0.0)
            saturated, _ = shift_image(m.saturated, *shifts[j], False)
            if not mosaic_2d:
                valid = np.repeat(valid[..., None], counts.shape[2], axis=2)
            acc.add(counts, float(factors[j] / ref_h), saturated, valid)
        else:
            acc.add(m.counts, float(factors[j] / ref_h), m.saturated)
        del m
    merged = acc.result()
    clipped = merged.clipped.any(axis=-1)
    if mosaic_2d:
        clipped = dilate_mask(clipped, 2)  # demosaicing spreads a clipped photosite over its 5x5 neighbourhood
    # Smallest resolvable signal: one ADU of the merged mosaic with every frame contributing.
    floor = 1.0 / (ref.white_level - max(ref.black_level)) / float(np.sum(factors / ref_h))
    mosaic = merged.radiance_lin[..., 0] if mosaic_2d else merged.radiance_lin
    camera_rgb = camera_rgb_from_mosaic(mosaic, ref.cfa, floor)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CaptureWarning)
        rec709, converted = to_rec709(camera_rgb, ref.rgb_from_camera, paths[ref_idx].name)
    for w in caught:
        result_warnings.append(str(w.message))
        warnings.warn(str(w.message), CaptureWarning, stacklevel=3)
    colorspace = opts.colorspace if converted else CAMERA_RGB
    img = rec709_to_working(rec709, opts.colorspace) if converted else rec709
    return np.maximum(apply_flip(img, ref.flip), 0.0).astype(np.float32), apply_flip(clipped, ref.flip), colorspace, shifts


def _bin2(mosaic: np.ndarray) -> np.ndarray:
    """Sum of each 2x2 block of a mosaic (one colour quad per output pixel)."""
    h, w = (mosaic.shape[0] // 2) * 2, (mosaic.shape[1] // 2) * 2
    m = mosaic[:h, :w]
    return m[0::2, 0::2] + m[0::2, 1::2] + m[1::2, 0::2] + m[1::2, 1::2]


def _merge_ldr(paths: list[Path], factors: np.ndarray, ref_h: float, opts: HdrOptions):
    frames = []
    max_code = None
    for p in paths:
        codes, mc = read_ldr_codes(p)
        if frames and codes.shape != frames[0].shape:
            raise DamcapError(f"{p}: image is {codes.shape[1]}x{codes.shape[0]} but {paths[0].name} is "
                              f"{frames[0].shape[1]}x{frames[0].shape[0]}; all frames of a bracket must have one size")
        if max_code is not None and mc != max_code:
            raise DamcapError(f"{p}: bit depth differs from {paths[0].name}'s; use frames of one bit depth")
        max_code = mc
        frames.append(codes)
    ref_idx = int(np.argsort(factors)[len(factors) // 2])
    shifts: list[tuple[int, int]] = [(0, 0)] * len(paths)
    if opts.align:
        previews = [f if max_code == 255 else (f >> 8).astype(np.uint8) for f in frames]
        shifts = chain_shifts(previews, factors, ref_idx)
        for j, (dy, dx) in enumerate(shifts):
            if (dy, dx) != (0, 0):
                frames[j], _ = shift_image(frames[j], dy, dx, 0)  # code 0 has no weight: the border is ignored
    stack = np.stack(frames)
    del frames
    levels_idx, levels = code_levels(stack, max_code)  # type: ignore[arg-type]
    del stack
    lnh = np.log(factors / ref_h)
    rows, cols = sample_pixels_for_response(levels_idx, opts.response_samples, opts.flat_fraction, opts.sample_phase)
    samples = np.transpose(levels_idx[:, rows, cols, :], (1, 0, 2))
    curve = recover_response(samples, lnh, levels, opts.response, opts.smoothness, opts.iterations)
    merged = merge_ldr(levels_idx, lnh, curve.log_response, curve.level_weight)
    img = rec709_to_working(merged.radiance_lin, opts.colorspace)
    return np.maximum(img, 0.0).astype(np.float32), merged.clipped.any(axis=-1), shifts, curve


def merge_bracket_files(files: Sequence[str | os.PathLike], opts: HdrOptions | None = None) -> HdrResult:
    """Merge one bracket of RAW or LDR files into one linear radiance map (the inputs are only read).

    Args:
        files: P >= 2 files of one kind (all RAW, or all 8/16-bit images), one scene, one size.
        opts: options (defaults: EXIF exposures, no alignment, lin_rec709, Debevec response).

    Returns:
        :class:`HdrResult`.

    Raises:
        DamcapError: fewer than 2 files, mixed kinds, missing exposure metadata (the message
            names ``--exposures``), different sizes, unreadable or damaged files.
    """
    opts = opts or HdrOptions()
    opts.validate()
    paths = [Path(f) for f in files]
    kind = _check_files(paths)
    exposures = [read_exposure(p) for p in paths]
    factors = resolve_exposure_factors(paths, exposures, opts.exposures_s)
    _check_distinct_exposures(paths, factors, opts.exposures_s)
    ref_h = _reference(factors, opts)
    result_warnings: list[str] = []
    curve = None
    if kind == "raw":
        img, clipped, colorspace, shifts = _merge_raw(paths, factors, ref_h, opts, result_warnings)
    else:
        img, clipped, shifts, curve = _merge_ldr(paths, factors, ref_h, opts)
        colorspace = opts.colorspace
    if clipped.all():
        raise DamcapError(f"{paths[0]}: every pixel is saturated in every frame; nothing can be measured. "
                          "Add a shorter exposure to the bracket")
    exposed = np.where(clipped[..., None], 0.0, img)  # the pixels not saturated in every frame
    if no_signal(exposed, 0.0, None) is not None:
        raise DamcapError(f"{paths[0]}: no pixel of the bracket is exposed: every frame is black where it is not saturated "
                          f"(largest merged radiance {float(exposed.max()):g}); nothing can be measured. Add a longer exposure "
                          "to the bracket")
    if clipped.any():
        result_warnings.append(f"{int(clipped.sum())} pixel(s) saturated in every frame; flagged in the 'clipped' channel "
                               "(their values are lower bounds)")
    return HdrResult(radiance_lin=img, clipped=clipped, colorspace=colorspace, kind=kind, files=[str(p) for p in paths],
                     exposures=exposures, exposure_factors=factors, reference_exposure=ref_h, shifts=shifts,
                     response=curve, warnings=result_warnings)


def write_hdr(path: str | os.PathLike, result: HdrResult, opts: HdrOptions) -> Path:
    """Write the merged map as an EXR (R, G, B, clipped) and the record ``<path>.json`` beside it.

    Both are complete on disk before either replaces an earlier pair: the record is staged, the
    EXR written and renamed into place, then the record renamed beside it (only a kill between
    these two back-to-back renames leaves the new EXR beside the earlier record).

    EXR header attributes: ``damcap:colorspace``, ``damcap:exposures`` (JSON: file, time_s, iso,
    f_number, factor), ``damcap:reference_exposure``, ``damcap:clipped_pixels``, ``damcap:version``.

    Returns:
        The path of the JSON record.

    Raises:
        DamcapError: half storage asked for values beyond 65504 (the message names --dtype float).
    """
    from damcap.common.atomic import atomic_path
    from damcap.common.exr import CLIPPED_CHANNEL, write_exr
    from damcap.common.version import package_version

    path = Path(path)
    peak = float(result.radiance_lin.max()) if result.radiance_lin.size else 0.0
    if opts.dtype == "half" and peak > HALF_MAX:
        raise DamcapError(f"{path}: radiance reaches {peak:.4g}, beyond half precision's {HALF_MAX:g}; use --dtype float, "
                          "or a larger --reference-exposure to scale values down")
    records = [{"file": Path(f).name, **e.to_json(), "factor": float(h)}
               for f, e, h in zip(result.files, result.exposures, result.exposure_factors)]
    pixels = np.concatenate([result.radiance_lin, result.clipped[..., None].astype(np.float32)], axis=-1)
    record = {
        "damcap_package_version": package_version(),
        "command": "hdr",
        "options": asdict(opts),
        "kind": result.kind,
        "colorspace": result.colorspace,
        "reference_exposure": result.reference_exposure,
        "frames": [{**r, "shift_px": list(s)} for r, s in zip(records, result.shifts)],
        "clipped_pixels": int(result.clipped.sum()),
        "warnings": result.warnings,
    }
    if result.response is not None:
        record["response"] = {"method": result.response.method, "levels": result.response.levels,
                               "log_response": result.response.log_response.round(6).tolist(),
                               "level_weight": result.response.level_weight.round(6).tolist()}
    side = hdr_record_path(path)
    with atomic_path(side) as staged_record:  # staged first, renamed right after the EXR
        staged_record.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
        write_exr(path, pixels, ("R", "G", "B", CLIPPED_CHANNEL), dtype=opts.dtype, attributes={
            "damcap:colorspace": result.colorspace,
            "damcap:exposures": json.dumps(records),
            "damcap:reference_exposure": float(result.reference_exposure),
            "damcap:clipped_pixels": int(result.clipped.sum()),
            "damcap:version": package_version(),
        })
    return side


def hdr_record_path(path: str | os.PathLike) -> Path:
    """The record :func:`write_hdr` writes beside a merged map: ``NAME.exr`` -> ``NAME.exr.json``.

    >>> hdr_record_path("out/merged.exr").as_posix()
    'out/merged.exr.json'
    """
    path = Path(path)
    return path.with_name(path.name + ".json")


def read_response(path: str | os.PathLike) -> ResponseCurve:
    """The response curve ``damcap hdr`` recovered from an LDR bracket, read back from its record.

    Args:
        path: the record ``NAME.exr.json`` that :func:`write_hdr` wrote, or the merged ``NAME.exr``
            itself (its record beside it is read).

    Returns:
        The :class:`~damcap.capture.response.ResponseCurve` (``log_response``: (3, L), ln of the
        linear value per code, a single-channel table repeated; ``level_weight`` zeros when the
        record has none).

    Raises:
        DamcapError: the file is missing or not JSON, the record has no response (a RAW bracket has
            none), or the table is not a finite (C, L) array with C in {1, 3} and L >= 2.
    """
    path = Path(path)
    record_path = hdr_record_path(path) if path.suffix.lower() == ".exr" else path
    if not record_path.is_file():
        raise DamcapError(f"{record_path}: response file not found (give the NAME.exr.json record damcap hdr writes "
                          "beside its output, or that NAME.exr)")
    try:
        record = json.loads(record_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DamcapError(f"{record_path}: cannot read the damcap hdr record ({type(e).__name__}: {e})") from None
    response = record.get("response") if isinstance(record, dict) else None
    if not isinstance(response, dict) or "log_response" not in response:
        kind = record.get("kind") if isinstance(record, dict) else None
        why = "a RAW bracket has none" if kind == "raw" else "not a damcap hdr record of an LDR bracket"
        raise DamcapError(f"{record_path}: no response curve in this file ({why})")
    try:
        g = np.asarray(response["log_response"], dtype=np.float64)
        w = np.asarray(response.get("level_weight", np.zeros_like(g)), dtype=np.float64)
    except (TypeError, ValueError):
        raise DamcapError(f"{record_path}: the response table is not numeric") from None
    if g.ndim != 2 or g.shape[0] not in (1, 3) or g.shape[1] < 2 or not np.all(np.isfinite(g)):
        raise DamcapError(f"{record_path}: the response table must be finite, (3, L) with L >= 2 code levels; got shape {g.shape}")
    if w.shape != g.shape:
        w = np.zeros_like(g)
    if g.shape[0] == 1:
        g, w = np.repeat(g, 3, axis=0), np.repeat(w, 3, axis=0)
    return ResponseCurve(log_response=g, level_weight=w, method=str(response.get("method", "debevec")))
