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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damcap.common.atomic import write_json_atomic
from damcap.common.capture_folder import Intrinsics
from damcap.common.exr import write_image_u8

from damcap.common.cameras import focal_px_from_fov, look_at_world_from_cam
from damcap.common.mesh import Mesh, vertex_normals_area_weighted
from damcap.common.raycast import MeshRaycaster


def _hash3(ijk: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) per integer lattice point (P, 3) -> (P,)."""
    h = (ijk[:, 0] * 73856093) ^ (ijk[:, 1] * 19349663) ^ (ijk[:, 2] * 83492791) ^ (seed * 2654435761)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float64) / float(0x1000000)


def value_noise(points: np.ndarray, frequency: float, seed: int) -> np.ndarray:
    """Trilinear lattice value noise in [0, 1] at (P, 3) points (smoothstep-interpolated)."""
    q = np.asarray(points, dtype=np.float64) * frequency
    base = np.floor(q).astype(np.int64)
    f = q - base
    f = f * f * (3 - 2 * f)
    out = np.zeros(len(q))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) * (f[:, 2] if dz else 1 - f[:, 2])
                out += w * _hash3(base + np.array([dx, dy, dz]), seed)
    return out


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


def linear_to_srgb(lin: np.ndarray) -> np.ndarray:
    """The sRGB inverse EOTF on [0, 1] (values clipped first).

    >>> round(float(linear_to_srgb(np.array(0.18))), 6)
    0.461356
    """
    x = np.clip(np.asarray(lin, dtype=np.float64), 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


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


def bumpy_blob(subdivisions: int = 5, amplitude: float = 0.12, seed: int = 0) -> Mesh:
    """A sphere with smooth radial bumps and one dent (not convex, not a sphere), radius about 1."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=max(8, 2 ** subdivisions))
    v = np.asarray(m.vertices, np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    t = np.asarray(m.triangles, np.int32)
    r = 1 + amplitude * (2 * value_noise(v * 0.9 + 3.0, 1.5, seed + 5) - 1)
    r -= 0.25 * np.exp(-((v - np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])) ** 2).sum(1) / 0.08)
    v = v * r[:, None]
    v /= np.linalg.norm(v, axis=1).max()
    return Mesh(v.astype(np.float32), t, vertex_normals_area_weighted(v, t).astype(np.float32), np.zeros(len(t), np.int32))


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


def main(argv: list[str] | None = None) -> int:
    """``python -m damcap.synth.photos OUT``: write a textured photo set (samples/)."""
    import argparse

    ap = argparse.ArgumentParser(description="Write JPEG photos (EXIF exposure), masks and ground-truth cameras of a textured synthetic object.")
    ap.add_argument("out", type=Path)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--size", type=int, default=256, help="photo width and height, pixels")
    ap.add_argument("--elevation", type=float, default=25.0, help="camera ring elevation, degrees")
    ap.add_argument("--jitter", type=float, default=5.0, help="random azimuth/elevation jitter, degrees")
    ap.add_argument("--distance", type=float, default=3.2, help="camera distance (object radius 1)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if (args.out / "images").exists():
        raise SystemExit(f"{args.out}/images exists; choose a new folder")
    mesh = bumpy_blob(seed=args.seed)
    cams = orbit_cameras(args.views, args.distance, (args.elevation,), jitter_deg=args.jitter, seed=args.seed)
    names = write_photo_set(args.out, mesh, cams, default_intrinsics(args.size), exposure_series(args.views, args.seed), seed=args.seed)
    print(f"wrote {len(names)} photos, masks and transforms.json (ground truth) to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
