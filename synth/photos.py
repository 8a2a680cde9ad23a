"""Ordinary photos of a textured synthetic object, made by damcap itself (tests, samples, bench).

Structure from motion needs texture, which the appearance renderers (``synth``, ``closed_form``)
do not paint. Here a mesh gets a procedural albedo (multi-scale lattice noise plus sharp-edged
spots, a pure function of the 3D surface point, so it is consistent across views), Lambertian
shading under one distant light plus ambient light, and goes through a camera: exposure
``time_s * iso / f_number^2``, clipping, the sRGB curve, 8 bits. Files: JPEG photos with EXIF
exposure, PNG masks (white = object) and the ground-truth cameras as a nerfstudio
``transforms.json``.

Optionally the object stands in a static textured room (an inward-facing cube around it, painted
with another procedural texture, shaded alike) and is photographed in one of two motions:

* ``orbit``: the camera circles the object; object and room stay still.
* ``turntable``: the camera stays put (up to jitter) and the object turns about the vertical
  axis, so the room's features do not move between photos while the object's do (the turntable
  trap of structure from motion).

The ground-truth cameras are always the object's (``obj_from_cam``, OpenGL axes): the same
cameras for both motions, so that a correct reconstruction of the object agrees with them up to
a similarity. The masks cover the object only.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from damcap.common.atomic import write_json_atomic
from damcap.common.capture_folder import Intrinsics
from damcap.common.errors import DamcapError
from damcap.common.exr import write_image_u8

from damcap.common.cameras import focal_px_from_fov, look_at_world_from_cam, pixel_rays_world
from damcap.common.colour import linear_to_srgb
from damcap.common.mesh import Mesh
from damcap.common.raycast import MeshRaycaster
from damcap.common.shapes import bumpy_blob, value_noise
from damcap.common.validate import CAMERA_DISTANCE, ELEVATION_DEG, MAX_IMAGE_SIDE, SEED, check_ranges, in_range, require_resolution


def procedural_albedo(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """A colourful, feature-rich albedo as a function of the surface point.

    Args:
        points: (P, 3) surface points of an object of about unit size.
        seed: pattern seed, >= 0.

    Returns:
        (P, 3) float32 albedo in [0.05, 0.9].
    """
    p = np.asarray(points, dtype=np.float64)

    def lattice_seed(i: int) -> int:  # below 2^31: value_noise's hash multiplies it in int64
        return (seed * 31 + i) % 2 ** 31

    rgb = np.zeros((len(p), 3))
    for c in range(3):
        v = sum(value_noise(p, f, lattice_seed(c * 7 + k)) / (k + 1) for k, f in enumerate((4.0, 9.0, 20.0)))
        rgb[:, c] = v / sum(1 / (k + 1) for k in range(3))
    spots = value_noise(p, 24.0, lattice_seed(99)) > 0.72  # sharp-edged blobs: corners for SIFT
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


#: procedural texture units per room half-size (room_texture_scale = this / half-size): the
#: finest noise octave then has 32 lattice cells per half-size, about 10 px each on a wall two
#: camera distances away in a 384 px photo of 45 degrees field of view
ROOM_TEXTURE_CELLS = 1.6
#: room half-size per camera distance (walls about two camera distances from the object's centre)
ROOM_SIZE_PER_DISTANCE = 2.0


def lambert_ambient(albedo: np.ndarray, normal: np.ndarray, light_dir: np.ndarray, ambient: float) -> np.ndarray:
    """Radiance of a Lambertian surface under one distant light of unit irradiance plus ambient light.

    Args:
        albedo: (P, 3) float32 in [0, 1].
        normal: (P, 3) float32 unit normals, same frame as ``light_dir``.
        light_dir: (3,) unit direction toward the light.
        ambient: ambient irradiance relative to the light's, >= 0.

    Returns:
        (P, 3) float32 ``albedo * (ambient + max(0, n . l))``.
    """
    shade = ambient + np.clip(normal @ np.asarray(light_dir, np.float32), 0, None)
    return albedo * shade[:, None]


def cube_room(half_size: float) -> Mesh:
    """An axis-aligned cube centred at the origin, seen from inside: 6 faces of 2 triangles, each
    face with its own 4 vertices so that the vertex normals are the face's (pointing inward).

    Args:
        half_size: half the edge length, scene units, > 0.

    Returns:
        float32 vertices (24, 3), int32 triangles (12, 3) wound counter-clockwise seen from inside,
        float32 unit inward normals, zero groups.
    """
    h = float(half_size)
    verts, tris, normals = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u_ax, v_ax = (axis + 1) % 3, (axis + 2) % 3
            inward = np.zeros(3)
            inward[axis] = -sign
            quad = []
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[u_ax], p[v_ax] = sign * h, a * h, b * h
                quad.append(p)
            base = len(verts)
            e1, e2 = quad[1] - quad[0], quad[2] - quad[0]
            order = (0, 1, 2, 0, 2, 3) if np.dot(np.cross(e1, e2), inward) > 0 else (0, 2, 1, 0, 3, 2)
            verts += quad
            normals += [inward] * 4
            tris += [[base + order[0], base + order[1], base + order[2]], [base + order[3], base + order[4], base + order[5]]]
    return Mesh(np.array(verts, np.float32), np.array(tris, np.int32), np.array(normals, np.float32), np.zeros(len(tris), np.int32))


def room_albedo(points_room: np.ndarray, texture_scale: float, seed: int = 0) -> np.ndarray:
    """The room's albedo: :func:`procedural_albedo` at ``points_room * texture_scale`` with a seed
    of its own, so that the room's pattern differs from the object's.

    Args:
        points_room: (P, 3) points on the room's walls, room frame, scene units.
        texture_scale: procedural texture units per scene unit.
        seed: the photo set's seed.

    Returns:
        (P, 3) float32 albedo in [0.05, 0.9].
    """
    return procedural_albedo(np.asarray(points_room, np.float64) * texture_scale, seed + 1000)


def y_rotation(angle_deg: float) -> np.ndarray:
    """(4, 4) float64 rotation by ``angle_deg`` about +y (right-handed: +z turns toward +x).

    >>> np.round(y_rotation(90.0) @ np.array([0.0, 0.0, 1.0, 1.0]), 12).tolist()
    [1.0, 0.0, 0.0, 1.0]
    """
    a = math.radians(angle_deg)
    m = np.eye(4)
    m[0, 0], m[0, 2], m[2, 0], m[2, 2] = math.cos(a), math.sin(a), -math.sin(a), math.cos(a)
    return m


def render_room(room: MeshRaycaster, room_from_cam: np.ndarray, intr: Intrinsics, light_dir_room: np.ndarray, texture_scale: float,
                seed: int = 0, ambient: float = 0.25, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The room behind the object: distance along each pixel's centre ray and radiance averaged
    over a sub-pixel grid (:func:`lambert_ambient` of :func:`room_albedo`).

    Args:
        room: ray caster of an inward-facing room mesh (room frame); every ray must hit it.
        room_from_cam: (4, 4) OpenGL camera-to-room.
        intr: pinhole intrinsics.
        light_dir_room: (3,) unit direction toward the distant light, room frame.
        texture_scale: see :func:`room_albedo`.
        seed: the photo set's seed.
        ambient: ambient irradiance relative to the light's.
        supersample: sub-pixel grid per axis for the radiance (1 = pixel centres, as the object;
            2 costs 4x the time, mostly the procedural albedo).

    Returns:
        t_room: (h, w) float32 distance from the camera centre along the pixel-centre ray, inf on a miss.
        radiance_lin: (h, w, 3) float32 room radiance, 0 on a miss.
    """
    origin, d = pixel_rays_world(room_from_cam, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h)
    d = d.astype(np.float32)
    hit = room.cast(origin, d)
    t_room = hit["t_hit"]
    ss = int(supersample)
    if ss > 1:
        offs = (np.stack(np.meshgrid(np.arange(ss), np.arange(ss)), -1).reshape(-1, 2) + 0.5) / ss - 0.5
        _, d = pixel_rays_world(room_from_cam, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h, offsets=offs)
        d = d.astype(np.float32)
        hit = room.cast(origin, d)
    else:  # the pixel centres' rays, cast once
        d, hit = d[None], {k: v[None] for k, v in hit.items()}
    ok = np.isfinite(hit["t_hit"])
    dv = d[ok]
    pos = origin.astype(np.float32) + hit["t_hit"][ok][:, None] * dv
    n = hit["primitive_normals"][ok]
    n = n * -np.sign(np.einsum("pi,pi->p", n, dv))[:, None]  # face the camera
    sub = np.zeros(d.shape, np.float32)
    light = np.asarray(light_dir_room, np.float64)
    sub[ok] = lambert_ambient(room_albedo(pos, texture_scale, seed), n.astype(np.float32), light / np.linalg.norm(light), ambient)
    return t_room, sub.mean(0)


def render_textured(raycaster: MeshRaycaster, world_from_cam: np.ndarray, intr: Intrinsics, light_dir_world: np.ndarray,
                    exposure: PhotoExposure, seed: int = 0, ambient: float = 0.25, gain: float = 2.0,
                    background_srgb: float = 0.0, *, room: MeshRaycaster | None = None, room_from_obj: np.ndarray | None = None,
                    room_texture_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One photo of the textured mesh, on a flat background or in a room.

    With a room, the object (cast in its own frame with ``world_from_cam``) and the room (cast
    in the room's frame with ``room_from_obj @ world_from_cam``: the same rays, the same
    distances) are both ray cast and each pixel keeps the nearer surface; the object's partial
    coverage at its silhouette is blended with the room in linear radiance.

    Args:
        raycaster: the mesh's ray caster.
        world_from_cam: (4, 4) OpenGL camera-to-object (the object's frame is the "world").
        intr: pinhole intrinsics.
        light_dir_world: (3,) unit direction toward the distant light, object frame.
        exposure: camera settings; pixel = radiance * gain * exposure.factor.
        seed: texture seed.
        ambient: ambient irradiance relative to the light's.
        gain: scene-to-sensor scale.
        background_srgb: grey level of the background without a room, [0, 1].
        room: ray caster of an inward-facing room mesh (:func:`cube_room`), or None.
        room_from_obj: (4, 4) rigid object-to-room transform of this photo; None: identity.
        room_texture_scale: see :func:`room_albedo`.

    Returns:
        photo_u8: (h, w, 3) uint8 sRGB.
        mask_u8: (h, w) uint8 coverage of the object (255 = object), the room excluded.
        radiance_lin: (h, w, 3) float32 the object's scene radiance (before the camera), 0 off
            the object (the room is not included).
    """
    b = raycaster.buffers(world_from_cam, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h, supersample=3)
    cov = b.coverage
    hit = cov > 0
    radiance = np.zeros((intr.h, intr.w, 3), np.float32)
    radiance[hit] = lambert_ambient(procedural_albedo(b.position_world[hit], seed), b.normal_world[hit], light_dir_world, ambient)
    if room is None:
        sensor = radiance * gain * exposure.factor
        srgb = linear_to_srgb(sensor) * cov[..., None] + background_srgb * (1 - cov[..., None])
    else:
        room_from_obj = np.eye(4) if room_from_obj is None else np.asarray(room_from_obj, np.float64)
        light_room = room_from_obj[:3, :3] @ np.asarray(light_dir_world, np.float64)
        t_room, radiance_room = render_room(room, room_from_obj @ np.asarray(world_from_cam, np.float64), intr, light_room,
                                            room_texture_scale, seed, ambient)
        t_obj = np.full((intr.h, intr.w), np.inf, np.float32)
        t_obj[hit] = np.linalg.norm(b.position_world[hit] - np.asarray(world_from_cam, np.float32)[:3, 3], axis=1)
        hidden = hit & (t_room < t_obj)  # the room in front of the object
        cov = np.where(hidden, 0.0, cov).astype(np.float32)
        radiance[hidden] = 0.0
        sensor = (radiance * cov[..., None] + radiance_room * (1 - cov[..., None])) * gain * exposure.factor
        srgb = linear_to_srgb(sensor)
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


def turntable_cameras(n_views: int, distance: float, elevation_deg: float, jitter_deg: float = 0.0,
                      seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A fixed camera before an object that turns by -360 / n_views degrees about +y per photo
    (clockwise seen from above).

    The object-frame cameras are exactly :func:`orbit_cameras` ``(n_views, distance,
    (elevation_deg,), jitter_deg, seed)``; in the room the camera stays at azimuth 0 (up to the
    same azimuth and elevation jitter): ``room_from_obj_k = R_y(-360 k / n_views)``.

    Returns:
        obj_from_cam: (n_views, 4, 4) float64 OpenGL camera-to-object (the ground truth).
        room_from_obj: (n_views, 4, 4) float64 the object's pose in the room, per photo.
    """
    obj_from_cam = orbit_cameras(n_views, distance, (elevation_deg,), jitter_deg=jitter_deg, seed=seed)
    room_from_obj = np.stack([y_rotation(-360.0 * k / n_views) for k in range(n_views)])
    return obj_from_cam, room_from_obj


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
                    seed: int = 0, prefix: str = "IMG_", masks: bool = True, gain: float = 2.0, *,
                    room: Mesh | None = None, room_texture_scale: float = 1.0, room_from_obj: np.ndarray | None = None) -> list[str]:
    """Write ``out/images/*.jpg`` (EXIF exposure), ``out/masks/*.png`` and ``out/transforms.json``
    (ground-truth cameras, nerfstudio keys, OpenGL axes).

    Args:
        world_from_cams: (N, 4, 4) OpenGL camera-to-object, written as the ground truth.
        light_dir_world: (3,) direction toward the distant light, room frame (the object's frame
            when ``room_from_obj`` is None).
        room: an inward-facing room mesh (:func:`cube_room`, room frame) behind the object, or None
            (black background).
        room_texture_scale: see :func:`room_albedo`.
        room_from_obj: (N, 4, 4) the object's pose in the room per photo (a turntable,
            :func:`turntable_cameras`), or None (the object stands still: an orbit). When given,
            each frame also records ``room_from_cam``.

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
    room_rc = MeshRaycaster(room) if room is not None else None
    names, frames = [], []
    for k, (m, ex) in enumerate(zip(world_from_cams, exposures)):
        r_from_o = None if room_from_obj is None else np.asarray(room_from_obj[k], np.float64)
        light_obj = light if r_from_o is None else r_from_o[:3, :3].T @ light
        photo, mask, _ = render_textured(rc, m, intr, light_obj, ex, seed, gain=gain, room=room_rc, room_from_obj=r_from_o,
                                         room_texture_scale=room_texture_scale)
        name = f"{prefix}{k:04d}.jpg"
        write_jpeg(out / "images" / name, photo, ex)
        if masks:
            write_png(out / "masks" / f"{prefix}{k:04d}.png", mask)
        names.append(name)
        frame = {"file_path": f"images/{name}", "transform_matrix": np.asarray(m).tolist()}
        if r_from_o is not None:
            frame["room_from_cam"] = (r_from_o @ np.asarray(m, np.float64)).tolist()
        frames.append(frame)
    write_json_atomic(out / "transforms.json", {"camera_model": "OPENCV", **intr.to_json(), "frames": frames})
    return names


def default_intrinsics(size: int, fov_deg: float = 45.0, principal_dx_px: float = 0.0, principal_dy_px: float = 0.0) -> Intrinsics:
    """Square pinhole camera of ``size`` pixels with the given horizontal field of view and its
    principal point ``(size / 2 + principal_dx_px, size / 2 + principal_dy_px)`` (x right, y down)."""
    f = focal_px_from_fov(fov_deg, size)
    return Intrinsics(f, f, size / 2 + principal_dx_px, size / 2 + principal_dy_px, size, size)


@dataclass(frozen=True)
class PhotoSetOptions:
    """Options of ``damcap synth-photos`` (a textured bumpy blob photographed on one camera ring,
    or by a fixed camera while it turns, optionally in a textured room)."""

    views: int = field(default=24, metadata=in_range(1, 100_000))
    """photos, on one ring around the object (a turntable: one per 360 / views degrees of turn)"""
    size: int = field(default=256, metadata=in_range(8, MAX_IMAGE_SIDE))
    """photo width and height, pixels"""
    elevation_deg: float = field(default=25.0, metadata={**ELEVATION_DEG, "cli_flag": "--elevation"})
    """camera ring elevation (a turntable: the fixed camera's), degrees"""
    jitter_deg: float = field(default=5.0, metadata=in_range(0, 90, cli_flag="--jitter"))
    """random azimuth and elevation jitter of each camera, degrees (a turntable: of the fixed
    camera's place, photo by photo)"""
    distance: float = field(default=3.2, metadata=CAMERA_DISTANCE)
    """camera distance from the object's centre (object radius 1)"""
    seed: int = field(default=0, metadata=SEED)
    """seeds the shape, the texture, the jitter and the exposures"""
    motion: Literal["orbit", "turntable"] = "orbit"
    """'orbit': the camera circles the still object; 'turntable': the camera stays put and the
    object turns (the room, if any, stays still around the camera). The ground-truth cameras of
    transforms.json are the object's either way (the same for both motions)"""
    room: bool = False
    """put the object in a static textured room (walls, floor and ceiling of a cube about two
    camera distances away) instead of a black background; masks stay the object's"""
    principal_dx_px: float = field(default=0.0, metadata=in_range(-(MAX_IMAGE_SIDE // 4), MAX_IMAGE_SIDE // 4, cli_flag="--principal-dx", cli_panel="advanced"))
    """principal point offset from the photo's centre, pixels to the right (at most --size / 4)"""
    principal_dy_px: float = field(default=0.0, metadata=in_range(-(MAX_IMAGE_SIDE // 4), MAX_IMAGE_SIDE // 4, cli_flag="--principal-dy", cli_panel="advanced"))
    """principal point offset from the photo's centre, pixels down (at most --size / 4)"""

    def validate(self) -> None:
        """Raise DamcapError naming the first bad value."""
        check_ranges(self)
        require_resolution(self.size, self.size, 4 * 32, f"--size {self.size}: a photo")
        if self.motion not in ("orbit", "turntable"):
            raise DamcapError(f"--motion must be one of orbit, turntable, got {self.motion!r}")
        limit = self.size / 4
        if not (abs(self.principal_dx_px) <= limit and abs(self.principal_dy_px) <= limit):
            raise DamcapError(f"--principal-dx {self.principal_dx_px:g} --principal-dy {self.principal_dy_px:g}: the principal point "
                              f"must stay within a quarter of --size {self.size} ({limit:g} px) of the photo's centre on each axis")


def make_photo_set(out: str | os.PathLike, opts: PhotoSetOptions) -> list[str]:
    """Write the photo set of ``opts`` into ``out`` (:func:`write_photo_set`); returns the photo names."""
    opts.validate()
    mesh = bumpy_blob(seed=opts.seed)
    if opts.motion == "turntable":
        cams, room_from_obj = turntable_cameras(opts.views, opts.distance, opts.elevation_deg, opts.jitter_deg, opts.seed)
    else:
        cams = orbit_cameras(opts.views, opts.distance, (opts.elevation_deg,), jitter_deg=opts.jitter_deg, seed=opts.seed)
        room_from_obj = None
    half = ROOM_SIZE_PER_DISTANCE * opts.distance
    room = cube_room(half) if opts.room else None
    intr = default_intrinsics(opts.size, principal_dx_px=opts.principal_dx_px, principal_dy_px=opts.principal_dy_px)
    return write_photo_set(out, mesh, cams, intr, exposure_series(opts.views, opts.seed), seed=opts.seed,
                           room=room, room_texture_scale=ROOM_TEXTURE_CELLS / half, room_from_obj=room_from_obj)
