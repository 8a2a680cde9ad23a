"""Ordinary photos of a textured synthetic object, made by damcap itself (tests, samples, bench).

Structure from motion needs texture, which the appearance renderers (``synth``, ``closed_form``)
do not paint. Here a mesh gets a procedural albedo (multi-scale lattice noise plus sharp-edged
spots, a pure function of the 3D surface point, so it is consistent across views), Lambertian
shading under one distant light plus ambient light, and goes through a camera: exposure
``time_s * iso / f_number^2``, clipping, the sRGB curve, 8 bits. Files: JPEG photos with EXIF
exposure, PNG masks (white = object) and the ground-truth cameras as a nerfstudio
``transforms.json``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from damcap.common.atomic import write_json_atomic
from damcap.common.capture_folder import Intrinsics
from damcap.common.exr import write_image_u8

from damcap.common.cameras import focal_px_from_fov, look_at_world_from_cam
from damcap.common.colour import linear_to_srgb
from damcap.common.mesh import Mesh
from damcap.common.raycast import MeshRaycaster
from damcap.common.shapes import bumpy_blob, value_noise
from damcap.common.validate import CAMERA_DISTANCE, ELEVATION_DEG, MAX_IMAGE_SIDE, SEED, check_ranges, in_range, require_resolution


def procedural_albedo(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """A colourful, feature-rich albedo as a function of the surface point.

    Args:
        points: (P, 3) surface points of an object of about unit size.
        seed: pattern seed.

    Returns:
        (P, 3) float32 albedo in [0.05, 0.9].
    """
    p = np.asarray(points, dtype=np.float64)
    rgb = np.zeros((len(p), 3))
    for c in range(3):
        v = sum(value_noise(p, f, seed * 31 + c * 7 + k) / (k + 1) for k, f in enumerate((4.0, 9.0, 20.0)))
        rgb[:, c] = v / sum(1 / (k + 1) for k in range(3))
    spots = value_noise(p, 24.0, seed * 31 + 99) > 0.72  # sharp-edged blobs: corners for SIFT
    rgb = np.where(spots[:, None], 1.0 - rgb, rgb)
    return (0.05 + 0.85 * np.clip((rgb - 0.3) / 0.4, 0, 1)).astype(np.float32)


@dataclass(frozen=True)
class PhotoExposure:
    """A camera's exposure settings."""

    time_s: float
    iso: float
    f_number: float

    @property
    def factor(self) -> float:
        """time_s * iso / f_number^2 (what linear pixel values are proportional to)."""
        return self.time_s * self.iso / self.f_number ** 2


def render_textured(raycaster: MeshRaycaster, world_from_cam: np.ndarray, intr: Intrinsics, light_dir_world: np.ndarray,
                    exposure: PhotoExposure, seed: int = 0, ambient: float = 0.25, gain: float = 2.0,
                    background_srgb: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One photo of the textured mesh.

    Args:
        raycaster: the mesh's ray caster.
        world_from_cam: (4, 4) OpenGL camera-to-world.
        intr: pinhole intrinsics.
        light_dir_world: (3,) unit direction toward the distant light.
        exposure: camera settings; pixel = radiance * gain * exposure.factor.
        seed: texture seed.
        ambient: ambient irradiance relative to the light's.
        gain: scene-to-sensor scale.
        background_srgb: grey level of the background, [0, 1].

    Returns:
        photo_u8: (h, w, 3) uint8 sRGB.
        mask_u8: (h, w) uint8 coverage (255 = object).
        radiance_lin: (h, w, 3) float32 scene radiance (before the camera), 0 on background.
    """
    b = raycaster.buffers(world_from_cam, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h, supersample=3)
    cov = b.coverage
    hit = cov > 0
    radiance = np.zeros((intr.h, intr.w, 3), np.float32)
    alb = procedural_albedo(b.position_world[hit], seed)
    shade = ambient + np.clip(b.normal_world[hit] @ np.asarray(light_dir_world, np.float32), 0, None)
    radiance[hit] = alb * shade[:, None]
    sensor = radiance * gain * exposure.factor
    srgb = linear_to_srgb(sensor) * cov[..., None] + background_srgb * (1 - cov[..., None])
    photo = np.round(srgb * 255).astype(np.uint8)
    return photo, np.round(cov * 255).astype(np.uint8), radiance


def orbit_cameras(n_views: int, distance: float, elevations_deg: tuple[float, ...] = (20.0,), jitter_deg: float = 0.0,
                  seed: int = 0) -> np.ndarray:
    """Cameras on rings around the origin looking at it (y up), in ring order, with optional
    random jitter of azimuth and elevation.

    Returns:
        (n_views, 4, 4) float64 world_from_cam.
    """
    rng = np.random.default_rng(seed)
    mats = []
    per_ring = -(-n_views // len(elevations_deg))
    for k in range(n_views):
        ring, pos = divmod(k, per_ring)
        el = math.radians(elevations_deg[ring] + rng.uniform(-jitter_deg, jitter_deg))
        az = 2 * math.pi * pos / per_ring + math.radians(rng.uniform(-jitter_deg, jitter_deg) + 17 * ring)
        c = distance * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        mats.append(look_at_world_from_cam(c, np.zeros(3), np.array([0.0, 1.0, 0.0])))
    return np.stack(mats)


def write_jpeg(path: str | os.PathLike, photo_u8: np.ndarray, exposure: PhotoExposure | None, quality: int = 92) -> None:
    """An 8-bit sRGB JPEG with EXIF exposure tags (OpenImageIO), written atomically."""
    attributes: dict[str, str | int | float] = {"Compression": f"jpeg:{quality}", "Make": "damcap", "Model": "textured_photos"}
    if exposure is not None:
        attributes.update({"ExposureTime": float(exposure.time_s), "FNumber": float(exposure.f_number),
                           "Exif:PhotographicSensitivity": int(round(exposure.iso))})
    write_image_u8(path, photo_u8, attributes)


def exposure_series(n: int, seed: int = 0, target_factor: float = 0.25) -> list[PhotoExposure]:
    """Auto-exposure-like settings at f/4: ISO 100..400 and a shutter time (1/N s) that keeps
    ``time_s * iso / f_number^2`` within about 25% of ``target_factor``, as a camera on auto would."""
    rng = np.random.default_rng(seed + 1)
    out = []
    for _ in range(n):
        iso = float(rng.choice([100, 200, 400]))
        t = target_factor * 16.0 / iso * rng.uniform(0.8, 1.25)
        out.append(PhotoExposure(1.0 / round(1.0 / t), iso, 4.0))
    return out


def write_photo_set(out: str | os.PathLike, mesh: Mesh, world_from_cams: np.ndarray, intr: Intrinsics,
                    exposures: list[PhotoExposure] | None = None, light_dir_world: np.ndarray = np.array([0.4, 0.8, 0.45]),
                    seed: int = 0, prefix: str = "IMG_", masks: bool = True, gain: float = 2.0) -> list[str]:
    """Write ``out/images/*.jpg`` (EXIF exposure), ``out/masks/*.png`` and ``out/transforms.json``
    (ground-truth cameras, nerfstudio keys, OpenGL axes).

    Returns:
        the photo file names.
    """
    from damcap.common.exr import write_png

    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    if masks:
        (out / "masks").mkdir(parents=True, exist_ok=True)
    exposures = exposures or exposure_series(len(world_from_cams), seed)
    light = np.asarray(light_dir_world, np.float64) / np.linalg.norm(light_dir_world)
    rc = MeshRaycaster(mesh)
    names, frames = [], []
    for k, (m, ex) in enumerate(zip(world_from_cams, exposures)):
        photo, mask, _ = render_textured(rc, m, intr, light, ex, seed, gain=gain)
        name = f"{prefix}{k:04d}.jpg"
        write_jpeg(out / "images" / name, photo, ex)
        if masks:
            write_png(out / "masks" / f"{prefix}{k:04d}.png", mask)
        names.append(name)
        frames.append({"file_path": f"images/{name}", "transform_matrix": np.asarray(m).tolist()})
    write_json_atomic(out / "transforms.json", {"camera_model": "OPENCV", **intr.to_json(), "frames": frames})
    return names


def default_intrinsics(size: int, fov_deg: float = 45.0) -> Intrinsics:
    """Square pinhole camera of ``size`` pixels with the given horizontal field of view."""
    f = focal_px_from_fov(fov_deg, size)
    return Intrinsics(f, f, size / 2, size / 2, size, size)


@dataclass(frozen=True)
class PhotoSetOptions:
    """Options of ``damcap synth-photos`` (a textured bumpy blob photographed on one camera ring)."""

    views: int = field(default=24, metadata=in_range(1, 100_000))
    """photos, on one ring around the object"""
    size: int = field(default=256, metadata=in_range(8, MAX_IMAGE_SIDE))
    """photo width and height, pixels"""
    elevation_deg: float = field(default=25.0, metadata={**ELEVATION_DEG, "cli_flag": "--elevation"})
    """camera ring elevation, degrees"""
    jitter_deg: float = field(default=5.0, metadata=in_range(0, 90, cli_flag="--jitter"))
    """random azimuth and elevation jitter of each camera, degrees"""
    distance: float = field(default=3.2, metadata=CAMERA_DISTANCE)
    """camera distance from the object's centre (object radius 1)"""
    seed: int = field(default=0, metadata=SEED)
    """seeds the shape, the texture, the jitter and the exposures"""

    def validate(self) -> None:
        """Raise DamcapError naming the first bad value."""
        check_ranges(self)
        require_resolution(self.size, self.size, 4 * 32, f"--size {self.size}: a photo")


def make_photo_set(out: str | os.PathLike, opts: PhotoSetOptions) -> list[str]:
    """Write the photo set of ``opts`` into ``out`` (:func:`write_photo_set`); returns the photo names."""
    opts.validate()
    mesh = bumpy_blob(seed=opts.seed)
    cams = orbit_cameras(opts.views, opts.distance, (opts.elevation_deg,), jitter_deg=opts.jitter_deg, seed=opts.seed)
    return write_photo_set(out, mesh, cams, default_intrinsics(opts.size), exposure_series(opts.views, opts.seed), seed=opts.seed)
