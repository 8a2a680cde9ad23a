"""Pinhole cameras in the capture convention (OpenGL axes: x right, y up, looking down -z)."""

from __future__ import annotations

import functools
import math

import numpy as np


def look_at_world_from_cam(centre_world: np.ndarray, target_world: np.ndarray, up_world: np.ndarray) -> np.ndarray:
    """Camera-to-world matrix of a camera at ``centre_world`` looking at ``target_world``.

    Args:
        centre_world: (3,) camera centre.
        target_world: (3,) point the optical axis passes through.
        up_world: (3,) approximate up direction (must not be parallel to the viewing direction).

    Returns:
        (4, 4) float64 world_from_cam; its column 2 points backwards (away from the target).
    """
    centre = np.asarray(centre_world, dtype=np.float64)
    back = centre - np.asarray(target_world, dtype=np.float64)
    back /= np.linalg.norm(back)
    right = np.cross(np.asarray(up_world, dtype=np.float64), back)
    norm = np.linalg.norm(right)
    if norm < 1e-9:
        raise ValueError("up_world is parallel to the viewing direction")
    right /= norm
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, centre
    return m


def orbit_world_from_cam(n_views: int, distance: float, elevation_deg: float, azimuth0_deg: float = 0.0,
                         up_world: np.ndarray | None = None) -> np.ndarray:
    """Cameras equally spaced on a circle around the origin, all looking at the origin, turning
    about ``up_world`` (default +y).

    Args:
        n_views: number of cameras.
        distance: distance from the origin, scene units.
        elevation_deg: angle above the plane normal to up, degrees, in (-90, 90).
        azimuth0_deg: azimuth of the first camera, degrees (0: on +z for up +y; for another up,
            the +y orbit turned by the smallest rotation taking +y to it).
        up_world: (3,) the orbit's axis (any length but 0).

    Returns:
        (n_views, 4, 4) float64 world_from_cam; each camera's image up lies in the plane of its
        view direction and ``up_world``.
    """
    el = math.radians(elevation_deg)
    mats = []
    for k in range(n_views):
        az = math.radians(azimuth0_deg) + 2 * math.pi * k / n_views
        centre = distance * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        mats.append(look_at_world_from_cam(centre, np.zeros(3), np.array([0.0, 1.0, 0.0])))
    out = np.stack(mats)
    if up_world is not None:
        rot = np.eye(4)
        rot[:3, :3] = rotation_between(np.array([0.0, 1.0, 0.0]), np.asarray(up_world, np.float64))
        out = rot[None] @ out
    return out


def up_direction(world_from_cams: np.ndarray, planarity: float = 0.3) -> np.ndarray:
    """The capture's up direction: the normal of the camera ring when the cameras lie near a
    plane (an orbit), else the mean of the cameras' up axes.

    Args:
        world_from_cams: (N, 4, 4) OpenGL camera-to-world (camera y = up in the image).
        planarity: the ring's normal is used when the centres' smallest spread is below this
            fraction of the middle one and the normal is within 45 degrees of the mean up.

    Returns:
        (3,) unit vector.
    """
    m = np.asarray(world_from_cams, dtype=np.float64)
    mean_up = m[:, :3, 1].sum(0)
    mean_up /= max(np.linalg.norm(mean_up), 1e-12)
    centres = m[:, :3, 3]
    if len(centres) >= 4:
        _, s, vt = np.linalg.svd(centres - centres.mean(0), full_matrices=False)
        normal = vt[2] * np.sign(vt[2] @ mean_up or 1.0)
        if s[1] > 0 and s[2] < planarity * s[1] and normal @ mean_up > np.cos(np.radians(45)):
            return normal
    return mean_up


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) smallest rotation taking unit vector a to unit vector b.

    >>> np.round(rotation_between(np.array([1., 0, 0]), np.array([0., 1, 0])) @ [1, 0, 0], 6).tolist()
    [0.0, 1.0, 0.0]
    """
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-12:  # opposite: turn half-way around any axis perpendicular to a
        axis = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


def focal_px_from_fov(fov_deg: float, size_px: int) -> float:
    """Focal length in pixels of a pinhole with full field of view ``fov_deg`` over ``size_px``.

    >>> round(focal_px_from_fov(90.0, 256), 6)
    128.0
    """
    return 0.5 * size_px / math.tan(math.radians(fov_deg) / 2)


@functools.lru_cache(maxsize=8)
def _centre_dirs_cam(fl_x: float, fl_y: float, cx: float, cy: float, w: int, h: int) -> np.ndarray:
    """(H, W, 3) unit camera-space directions through pixel centres (cached per intrinsics)."""
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = np.stack([(j - cx) / fl_x, -(i - cy) / fl_y, -np.ones_like(j)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d.setflags(write=False)
    return d


def pixel_rays_world(
    world_from_cam: np.ndarray, fl_x: float, fl_y: float, cx: float, cy: float, w: int, h: int, offsets: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through pixel centres (or sub-pixel offsets from them).

    Args:
        world_from_cam: (4, 4) camera-to-world.
        fl_x, fl_y, cx, cy: pinhole intrinsics, pixels; pixel (i, j) centre is (j + 0.5, i + 0.5).
        w, h: image size, pixels.
        offsets: optional (S, 2) sub-pixel offsets (dx, dy) in pixels from the centre.

    Returns:
        origin_world: (3,) camera centre.
        dir_world: (H, W, 3) or (S, H, W, 3) unit ray directions.
    """
    if offsets is None:
        d_cam = _centre_dirs_cam(float(fl_x), float(fl_y), float(cx), float(cy), int(w), int(h))
        d_world = d_cam @ world_from_cam[:3, :3].T.astype(d_cam.dtype)
        return world_from_cam[:3, 3].copy(), d_world
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    offs = np.asarray(offsets, dtype=np.float64)
    u = j[None] + offs[:, 0, None, None]
    v = i[None] + offs[:, 1, None, None]
    return world_from_cam[:3, 3].copy(), rays_world_at(world_from_cam, fl_x, fl_y, cx, cy, u, v)


def rays_world_at(world_from_cam: np.ndarray, fl_x: float, fl_y: float, cx: float, cy: float, u: np.ndarray,
                  v: np.ndarray) -> np.ndarray:
    """Unit world-space ray directions through image points (u right, v down, pixels; pixel
    (i, j) spans [j, j+1] x [i, i+1]) of a pinhole camera with OpenGL axes.

    Args:
        world_from_cam: (4, 4) camera-to-world.
        fl_x, fl_y, cx, cy: pinhole intrinsics, pixels.
        u, v: (...) float image coordinates, pixels.

    Returns:
        (..., 3) float64 unit directions.

    >>> rays_world_at(np.eye(4), 10.0, 10.0, 5.0, 5.0, np.array([5.0]), np.array([5.0])).tolist()
    [[0.0, 0.0, -1.0]]
    """
    d_cam = np.stack([(u - cx) / fl_x, -(v - cy) / fl_y, -np.ones(np.shape(u))], axis=-1)
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    return d_cam @ world_from_cam[:3, :3].T
