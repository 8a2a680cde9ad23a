"""Registered cameras, from SfM or from known poses, and the one place where camera axes change.

Every camera that enters damcap ends up as :class:`RegisteredPhoto`: a ``world_from_cam`` with the
contract's OpenGL camera axes (x right, y up, looking down -z) plus the photo's (possibly
distorted) :class:`~damcap.reconstruct.undistort.PhotoCamera`. The axis conventions met at the edge:

- COLMAP: ``cam_from_world``, camera axes x right, y down, looking down +z.
- LLFF ``poses_bounds.npy``: rows of 17 = a 3x5 matrix ``[R | t | (h, w, f)]`` (camera-to-world,
  columns of R = the camera's (down, right, backwards) axes in world space) + near/far bounds;
  h, w, f at the resolution the poses were computed at; rows follow the sorted image names.
- nerfstudio / instant-ngp ``transforms.json``: camera-to-world with OpenGL axes already.

Known poses from files are read by :mod:`damcap.reconstruct.known_poses`; a COLMAP model by
:mod:`damcap.reconstruct.colmap.model`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from damcap.common.errors import DamcapError

from damcap.reconstruct.undistort import PhotoCamera


#: OpenGL camera axes from COLMAP's (and back): flip y and z. Its own inverse.
GL_FROM_CV_CAM = np.diag([1.0, -1.0, -1.0, 1.0])


#: camera centres whose spread is at most this fraction of their largest distance from the world
#: origin count as one position (relative, so that any unit works; float64 resolves about 1e-16)
COINCIDENT_CENTRES_REL = 1e-9


@dataclass
class RegisteredPhoto:
    """One photo with a camera."""

    name: str
    """file name in the photo folder"""
    world_from_cam: np.ndarray
    """(4, 4) float64 camera-to-world, OpenGL camera axes"""
    camera: PhotoCamera
    observations_px: np.ndarray | None = None
    """(M, 3) float64 rows (x, y, reprojection error) of its sparse points' observations, photo
    pixels; None when the cameras came without points"""


@dataclass
class Registration:
    """Cameras for a photo set plus the sparse points that came with them (if any)."""

    photos: list[RegisteredPhoto]
    """registered photos, sorted by name"""
    unregistered: dict[str, str] = field(default_factory=dict)
    """photo name -> why it has no camera"""
    points_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(P, 3) float64 sparse 3D points, same world frame as the cameras"""
    points_seen_from: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.int64))
    """(P,) int64 index into ``photos`` of one photo that observes each point"""
    source: str = ""
    """'sfm', 'transforms.json', 'llff' or 'colmap'"""
    stats: dict[str, Any] = field(default_factory=dict)
    """numbers worth reporting (registered count, mean reprojection error px, timings s)"""

    @property
    def world_from_cams(self) -> np.ndarray:
        """(N, 4, 4) float64 camera-to-world of every registered photo."""
        return np.stack([p.world_from_cam for p in self.photos]) if self.photos else np.zeros((0, 4, 4))


def registration_without(reg: Registration, names: set[str]) -> Registration:
    """The registration without the photos in ``names``; the sparse points whose observing photo
    (``points_seen_from``) is left out go with it, the others keep their photo's new index.

    >>> from damcap.reconstruct.undistort import PhotoCamera
    >>> cam = PhotoCamera(4, 4, 2.0, 2.0, 2.0, 2.0)
    >>> reg = Registration([RegisteredPhoto(n, np.eye(4), cam) for n in "abc"], points_world=np.arange(9.0).reshape(3, 3),
    ...                    points_seen_from=np.array([0, 1, 2]))
    >>> out = registration_without(reg, {"b"})
    >>> [p.name for p in out.photos], out.points_world[:, 0].tolist(), out.points_seen_from.tolist()
    (['a', 'c'], [0.0, 6.0], [0, 1])
    """
    keep = [k for k, p in enumerate(reg.photos) if p.name not in names]
    new_index = np.full(len(reg.photos), -1, np.int64)
    new_index[keep] = np.arange(len(keep))
    seen = new_index[np.asarray(reg.points_seen_from, np.int64)] if len(reg.points_seen_from) else np.zeros(0, np.int64)
    points = np.asarray(reg.points_world)[seen >= 0] if len(seen) else reg.points_world
    return replace(reg, photos=[reg.photos[k] for k in keep], points_world=points, points_seen_from=seen[seen >= 0])


def nearest_facing_camera(points_world: np.ndarray, world_from_cams: np.ndarray) -> np.ndarray:
    """For points that come without observations (a dataset's point cloud), the camera each one is
    taken to be seen from: the nearest camera that has it in front (OpenGL axes: camera z < 0),
    else the nearest camera.

    Args:
        points_world: (P, 3).
        world_from_cams: (N, 4, 4) OpenGL camera-to-world.

    Returns:
        (P,) int64 camera index.

    >>> cams = np.stack([np.eye(4), np.diag([-1.0, 1, -1, 1])]); cams[:, 2, 3] = [2.0, -2.0]
    >>> nearest_facing_camera(np.array([[0.0, 0, 1], [0.0, 0, -1]]), cams).tolist()  # both see both; nearest wins
    [0, 1]
    """
    pts = np.asarray(points_world, np.float64)
    cams = np.asarray(world_from_cams, np.float64)
    out = np.zeros(len(pts), np.int64)
    if len(cams) == 0:
        return out
    chunk = max(1, (1 << 22) // len(cams))  # (chunk, N, 3) stays near 100 MB whatever the cloud's size
    for a in range(0, len(pts), chunk):
        rel = pts[a:a + chunk, None, :] - cams[None, :, :3, 3]  # (p, N, 3)
        z_cam = np.einsum("pnk,nk->pn", rel, cams[:, :3, 2])
        dist = np.linalg.norm(rel, axis=2)
        out[a:a + chunk] = np.argmin(np.where(z_cam < 0, dist, dist + 1e12), axis=1)
    return out


def world_from_cam_of_colmap(cam_from_world_cv: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world from COLMAP's world-to-camera.

    Args:
        cam_from_world_cv: (3, 4) or (4, 4) float64 ``[R | t]``, COLMAP camera axes
            (x right, y down, looking down +z).

    Returns:
        (4, 4) float64 world_from_cam, OpenGL camera axes.

    >>> world_from_cam_of_colmap(np.eye(4)).diagonal().tolist()
    [1.0, -1.0, -1.0, 1.0]
    """
    m = np.eye(4)
    m[:3, :4] = np.asarray(cam_from_world_cv, dtype=np.float64)[:3, :4]
    return np.linalg.inv(m) @ GL_FROM_CV_CAM


def colmap_of_world_from_cam(world_from_cam: np.ndarray) -> np.ndarray:
    """COLMAP's (3, 4) cam_from_world (camera axes x right, y down, +z forward) of an OpenGL
    camera-to-world; inverse of :func:`world_from_cam_of_colmap`."""
    m = np.asarray(world_from_cam, dtype=np.float64) @ GL_FROM_CV_CAM
    return np.linalg.inv(m)[:3, :4]


def world_from_cam_of_llff(llff_3x4: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world from an LLFF camera-to-world ``[R | t]``.

    Args:
        llff_3x4: (3, 4) float64; columns of R are the camera's (down, right, backwards) axes.

    Returns:
        (4, 4) float64 world_from_cam with columns (right, up, backwards, centre).
    """
    a = np.asarray(llff_3x4, dtype=np.float64)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = a[:, 1], -a[:, 0], a[:, 2], a[:, 3]
    return m


def llff_of_world_from_cam(world_from_cam: np.ndarray) -> np.ndarray:
    """(3, 4) LLFF ``[R | t]`` (down, right, backwards) of an OpenGL camera-to-world."""
    m = np.asarray(world_from_cam, dtype=np.float64)
    return np.stack([-m[:3, 1], m[:3, 0], m[:3, 2], m[:3, 3]], axis=1)


def orthonormalize_rotation(world_from_cam: np.ndarray) -> np.ndarray:
    """Nearest rigid transform (SVD projection of the rotation part): files store 6-8 digits,
    and a rotation read back is orthonormal only to that precision.

    Raises:
        ValueError: the rotation part is far from a rotation (scale, shear or reflection).
    """
    m = np.array(world_from_cam, dtype=np.float64)
    u, s, vt = np.linalg.svd(m[:3, :3])
    if np.abs(s - 1).max() > 1e-2 or np.linalg.det(u @ vt) < 0:
        raise ValueError(f"not a rotation: singular values {np.round(s, 4).tolist()}")
    m[:3, :3] = u @ vt
    m[3] = (0, 0, 0, 1)
    return m


def coincident_centres(world_from_cams: np.ndarray, rel: float = COINCIDENT_CENTRES_REL) -> str | None:
    """Why cameras cannot see an object from different sides, or None: all their centres at one
    point (translations scaled by 0, one matrix repeated, a panorama turned about its centre).

    Args:
        world_from_cams: (N, 4, 4) camera-to-world.
        rel: spread (largest distance from the centres' mean) at or below ``rel`` times the
            largest centre's distance from the origin counts as one position.

    >>> coincident_centres(np.stack([np.eye(4)] * 3))
    'all 3 cameras are at the same position [0.0, 0.0, 0.0] (spread 0)'
    """
    c = np.asarray(world_from_cams, dtype=np.float64)[:, :3, 3]
    if len(c) < 2:
        return None
    spread = float(np.linalg.norm(c - c.mean(0), axis=1).max())
    if spread > rel * float(np.linalg.norm(c, axis=1).max()):
        return None
    where = [float(f"{x:.6g}") + 0.0 for x in c[0]]  # + 0.0: no '-0.0'
    return f"all {len(c)} cameras are at the same position {where} (spread {spread:.3g})"


def photos_by_stem(photo_names: list[str]) -> dict[str, str]:
    return {Path(n).stem: n for n in photo_names}


def finish_registration(source: str, path: Path, found: dict[str, RegisteredPhoto], photo_names: list[str],
            missing_reason: str, extra: dict[str, Any]) -> Registration:
    if not found:
        raise DamcapError(
            f"{path}: none of its entries matches a photo by base name (photos: {photo_names[:3]}...); "
            "the pose file must describe these photos"
        )
    unregistered = {n: missing_reason for n in photo_names if n not in found}
    photos = [found[n] for n in sorted(found)]
    same = coincident_centres(np.stack([p.world_from_cam for p in photos]))
    if same:
        raise DamcapError(f"{path}: {same}; the photos must be taken from different positions around the object "
                          "(translations scaled by 0, or one matrix repeated?)")
    return Registration(photos=photos, unregistered=unregistered, source=source,
                        stats={"registered": len(photos), "photos": len(photo_names), **extra})
