"""A RAW bracket simulator: real HDR radiance through a camera model into real DNG files.

No real multi-exposure RAW bracket is available to the project, so RAW merging is tested and
benchmarked on brackets made here: linear Rec.709 radiance (e.g. an HDR environment map) is
converted to camera RGB with a colour matrix, sampled through a Bayer pattern, exposed
(photon shot noise: Poisson; read noise: Gaussian; full-well clipping), offset by a black
level, quantised to 12-14 bits and written as a DNG (pidng) with its exposure time, ISO and
f-number, ColorMatrix1, black and white levels. Reading the files back goes through rawpy like
any camera's.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from damcap.common.errors import DamcapError

#: XYZ -> camera matrix of a real camera (Canon EOS 550D, ColorMatrix1 of shared/data/raw's DNG)
CANON_550D_CAMERA_FROM_XYZ = ((0.6461, -0.1164, -0.0857), (-0.3825, 1.1597, 0.2534), (-0.0416, 0.1540, 0.6039))

#: linear Rec.709 (sRGB primaries, D65) -> XYZ, the matrix LibRaw inverts (IEC 61966-2-1 primaries)
XYZ_FROM_REC709 = ((0.412453, 0.357580, 0.180423), (0.212671, 0.715160, 0.072169), (0.019334, 0.119193, 0.950227))

#: CFA layouts: colour (0 = R, 1 = G, 2 = B) of the 2x2 repeat, row-major
CFA_PATTERNS = {"RGGB": (0, 1, 1, 2), "BGGR": (2, 1, 1, 0), "GRBG": (1, 0, 2, 1), "GBRG": (1, 2, 0, 1)}


@dataclass(frozen=True)
class CameraModel:
    """Sensor and colour parameters of the simulated camera."""

    bits: int = 14
    """ADC bit depth, 12..14; the white level is 2**bits - 1."""
    black_level: int = 512
    """Black level in ADU (added before quantisation)."""
    full_well_e: float = 30000.0
    """Full-well capacity in electrons; it maps to the white level."""
    read_noise_e: float = 3.0
    """Gaussian read noise, standard deviation in electrons."""
    cfa: str = "RGGB"
    """Bayer layout, one of :data:`CFA_PATTERNS`."""
    camera_from_xyz: tuple[tuple[float, float, float], ...] = CANON_550D_CAMERA_FROM_XYZ
    """(3, 3) XYZ -> camera RGB (the DNG ColorMatrix1, D65)."""

    @property
    def white_level(self) -> int:
        return (1 << self.bits) - 1

    @property
    def gain_e_per_adu(self) -> float:
        """Electrons per ADU, so that the full well lands on the white level."""
        return self.full_well_e / (self.white_level - self.black_level)


def camera_rgb_from_rec709(radiance_rec709: np.ndarray, camera_from_xyz: np.ndarray) -> np.ndarray:
    """Linear Rec.709 to the camera's linear RGB via XYZ (:data:`XYZ_FROM_REC709`).

    Args:
        radiance_rec709: (H, W, 3) float, linear, >= 0.
        camera_from_xyz: (3, 3) XYZ -> camera RGB.

    Returns:
        (H, W, 3) float64 camera RGB; negative values (outside the camera's gamut) set to 0.
    """
    m = np.asarray(camera_from_xyz, dtype=np.float64) @ np.asarray(XYZ_FROM_REC709)
    return np.maximum(np.asarray(radiance_rec709, dtype=np.float64) @ m.T, 0.0)


def cfa_map(shape: tuple[int, int], cfa: str) -> np.ndarray:
    """(H, W) uint8 colour of each photosite for a 2x2 Bayer layout.

    >>> cfa_map((2, 4), "RGGB").tolist()
    [[0, 1, 0, 1], [1, 2, 1, 2]]
    """
    if cfa not in CFA_PATTERNS:
        raise DamcapError(f"unknown CFA layout {cfa!r}; use one of {', '.join(CFA_PATTERNS)}")
    quad = np.array(CFA_PATTERNS[cfa], np.uint8).reshape(2, 2)
    h, w = shape
    return np.tile(quad, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


def mosaic(camera_rgb: np.ndarray, cfa: str) -> np.ndarray:
    """Sample camera RGB through a Bayer pattern: (H, W, 3) -> (H, W), one channel per photosite."""
    img = np.asarray(camera_rgb)
    colors = cfa_map(img.shape[:2], cfa)
    return np.take_along_axis(img, colors[..., None].astype(np.int64), axis=2)[..., 0]


def expose(
    photons_mosaic: np.ndarray, exposure: float, model: CameraModel, rng: np.random.Generator
) -> np.ndarray:
    """One exposure of the sensor: shot noise, read noise, full well, black level, quantisation.

    Args:
        photons_mosaic: (H, W) float >= 0, expected electrons per photosite at exposure 1.
        exposure: relative exposure H > 0 of this frame.
        model: the camera.
        rng: random generator.

    Returns:
        (H, W) uint16 raw values in [0, 2**bits - 1].
    """
    lam = np.maximum(np.asarray(photons_mosaic, dtype=np.float64) * exposure, 0.0)
    electrons = rng.poisson(np.minimum(lam, 1e12)).astype(np.float64)
    electrons = np.minimum(electrons, model.full_well_e)
    electrons += rng.normal(0.0, model.read_noise_e, size=electrons.shape)
    adu = np.round(electrons / model.gain_e_per_adu + model.black_level)
    return np.clip(adu, 0, model.white_level).astype(np.uint16)


def _rational(x: float, den: int = 10000) -> list[int]:
    return [int(round(x * den)), den]


def _exposure_rational(t: float) -> list[int]:
    """Exposure time as a TIFF rational (1/n for short times)."""
    if t < 1:
        return [1, int(round(1 / t))] if abs(1 / t - round(1 / t)) < 1e-6 else _rational(t, 1000000)
    return _rational(t, 1000)


def write_dng(
    path: str | os.PathLike,
    raw: np.ndarray,
    model: CameraModel,
    exposure_time_s: float,
    iso: int = 100,
    f_number: float = 8.0,
) -> Path:
    """Write raw sensor values as a Bayer DNG with exposure EXIF (pidng), atomically.

    Args:
        path: destination ``.dng``.
        raw: (H, W) uint16 values in [0, 2**bits - 1] (stored in 16-bit samples).
        model: the camera (pattern, levels, colour matrix).
        exposure_time_s: ExposureTime tag, seconds.
        iso: PhotographicSensitivity tag.
        f_number: FNumber tag.
    """
    from damcap.common.optional import require

    require("pidng", "writing simulated RAW brackets as DNG")
    from pidng.core import RAW2DNG
    from pidng.defs import CalibrationIlluminant, DNGVersion, Orientation, PhotometricInterpretation
    from pidng.dng import DNGTags, Tag

    from damcap.common.atomic import atomic_path

    raw = np.ascontiguousarray(raw, dtype=np.uint16)
    h, w = raw.shape
    xyz_d65 = np.array([0.95047, 1.0, 1.08883])
    neutral = np.asarray(model.camera_from_xyz, dtype=np.float64) @ xyz_d65
    t = DNGTags()
    t.set(Tag.ImageWidth, w)
    t.set(Tag.ImageLength, h)
    t.set(Tag.TileWidth, w)
    t.set(Tag.TileLength, h)
    t.set(Tag.Orientation, Orientation.Horizontal)
    t.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    t.set(Tag.SamplesPerPixel, 1)
    t.set(Tag.BitsPerSample, 16)
    t.set(Tag.CFARepeatPatternDim, [2, 2])
    t.set(Tag.CFAPattern, list(CFA_PATTERNS[model.cfa]))
    t.set(Tag.BlackLevel, model.black_level)
    t.set(Tag.WhiteLevel, model.white_level)
    t.set(Tag.ColorMatrix1, [_rational(v) for v in np.ravel(model.camera_from_xyz)])
    t.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    t.set(Tag.AsShotNeutral, [_rational(v / neutral.max()) for v in neutral])
    t.set(Tag.BaselineExposure, [[0, 1]])
    t.set(Tag.Make, "damcap")
    t.set(Tag.Model, "simulated bracket")
    t.set(Tag.ExposureTime, [_exposure_rational(exposure_time_s)])
    t.set(Tag.FNumber, [_rational(f_number, 100)])
    t.set(Tag.PhotographicSensitivity, [int(iso)])
    t.set(Tag.DNGVersion, DNGVersion.V1_4)
    t.set(Tag.DNGBackwardVersion, DNGVersion.V1_2)
    conv = RAW2DNG()
    conv.options(t, path="", compress=False)
    buf = conv.convert(raw)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(bytes(buf))
    return path


@dataclass
class SimulatedBracket:
    """The files of a simulated bracket and the truth they were made from."""

    files: list[Path]
    exposure_times_s: list[float]
    radiance_rec709: np.ndarray
    """(H, W, 3) float32 the truth, linear Rec.709, scaled so that 1 is the full well at the
    median exposure (the merged output's units up to one global factor, the green multiplier)."""
    clipped_in_shortest: np.ndarray
    """(H, W) bool: some channel's photosite exceeds the full well even in the shortest frame."""
    model: CameraModel = field(default_factory=CameraModel)


def bracket_times(n_frames: int, stops_apart: float = 2.0, longest_s: float = 1 / 15) -> list[float]:
    """Exposure times of a bracket, shortest first, ``stops_apart`` EV apart.

    >>> bracket_times(3, 2.0, 1.0)
    [0.0625, 0.25, 1.0]
    """
    return [longest_s * 2.0 ** (-stops_apart * (n_frames - 1 - k)) for k in range(n_frames)]


def simulate_raw_bracket(
    radiance_rec709: np.ndarray,
    out_dir: str | os.PathLike,
    exposure_times_s: Sequence[float],
    model: CameraModel | None = None,
    peak_fraction_shortest: float = 0.9,
    percentile: float = 99.9,
    iso: int = 100,
    f_number: float = 8.0,
    seed: int = 0,
    prefix: str = "sim",
) -> SimulatedBracket:
    """Simulate a RAW bracket of a radiance map and write it as DNG files.

    The light level is set so that the ``percentile`` of the photosites reaches
    ``peak_fraction_shortest`` of the full well in the shortest exposure (so brighter outliers
    such as a sun may clip in every frame, as they would in a real bracket).

    Args:
        radiance_rec709: (H, W, 3) float, linear Rec.709 radiance, >= 0, finite.
        out_dir: folder for ``{prefix}_{k}.dng``.
        exposure_times_s: 3 to 7 exposure times in seconds (any order).
        model: the camera (default :class:`CameraModel`).
        peak_fraction_shortest: see above, > 0.
        percentile: see above, in (0, 100].
        iso, f_number: written to every frame.
        seed: random seed of the noise.
        prefix: file name prefix.

    Returns:
        :class:`SimulatedBracket`; its truth is scaled to the merged output's units.

    Raises:
        DamcapError: non-finite or negative radiance, or a number of frames outside 3..7.
    """
    model = model or CameraModel()
    rad = np.asarray(radiance_rec709, dtype=np.float64)
    if rad.ndim != 3 or rad.shape[2] != 3 or not np.all(np.isfinite(rad)) or rad.min() < 0:
        raise DamcapError(f"radiance must be (H, W, 3), finite and >= 0; got shape {rad.shape}")
    if not 3 <= len(exposure_times_s) <= 7:
        raise DamcapError(f"simulate 3 to 7 exposures, got {len(exposure_times_s)}")
    if not 12 <= model.bits <= 16:
        raise DamcapError(f"bit depth must be 12..16, got {model.bits}")
    h, w = (rad.shape[0] // 2) * 2, (rad.shape[1] // 2) * 2
    rad = rad[:h, :w]
    cam = camera_rgb_from_rec709(rad, np.asarray(model.camera_from_xyz))
    site = mosaic(cam, model.cfa)
    times = np.asarray(exposure_times_s, dtype=np.float64)
    t_short = float(times.min())
    level = max(float(np.percentile(site, percentile)), 1e-30)
    photons_per_unit = peak_fraction_shortest * model.full_well_e / (level * t_short)
    photons = site * photons_per_unit  # expected electrons per second of exposure
    rng = np.random.default_rng(seed)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    files = []
    for k, t in enumerate(times):
        raw = expose(photons, float(t), model, rng)
        files.append(write_dng(out_dir / f"{prefix}_{k}.dng", raw, model, float(t), iso, f_number))
    # Truth in counts of the full well at the median exposure.
    t_ref = float(np.median(times))
    truth = rad * (photons_per_unit * t_ref / model.full_well_e)
    clipped = (cam * photons_per_unit * t_short >= model.full_well_e).any(axis=-1)
    return SimulatedBracket(files=files, exposure_times_s=[float(t) for t in times],
                            radiance_rec709=truth.astype(np.float32), clipped_in_shortest=clipped, model=model)
