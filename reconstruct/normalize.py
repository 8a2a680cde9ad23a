"""Scene normalisation: the object at the origin, a sensible scale, an up axis (pure functions).

Registration leaves the world frame arbitrary (COLMAP: the first pair's frame, any scale).
:func:`normalization_transform` returns one similarity ``norm_from_world`` (scale s, rotation R,
translation t; ``x_norm = s R x + t``) that puts the point the cameras look at on the origin,
the cameras' common up direction on +y, the first camera on the +z side, and the object's radius
at ``target_radius``. Cameras stay rigid (:func:`transform_world_from_cam`).
"""

from __future__ import annotations

import numpy as np

from damcap.common.cameras import rotation_between, up_direction
from damcap.common.errors import DamcapError
from damcap.common.mesh import Mesh, bounding_sphere


def similarity(scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) float64 ``[s R | t]``.

    Args:
        scale: s > 0.
        rotation: (3, 3) rotation.
        translation: (3,).
    """
    m = np.eye(4)
    m[:3, :3] = scale * np.asarray(rotation, dtype=np.float64)
    m[:3, 3] = translation
    return m


def similarity_scale(norm_from_world: np.ndarray) -> float:
    """s of a similarity ``[s R | t]`` (cube root of the determinant).

    >>> round(similarity_scale(similarity(2.0, np.eye(3), np.zeros(3))), 12)
    2.0
    """
    return float(np.cbrt(np.linalg.det(np.asarray(norm_from_world)[:3, :3])))


def transform_points(norm_from_world: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """(P, 3) points mapped by a (4, 4) affine transform."""
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    return p @ norm_from_world[:3, :3].T + norm_from_world[:3, 3]


def transform_world_from_cam(norm_from_world: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """A camera-to-world matrix in the new frame, kept rigid (the scale moves the centre only).

    Args:
        norm_from_world: (4, 4) similarity.
        world_from_cam: (4, 4) or (N, 4, 4) rigid camera-to-world.

    Returns:
        Same shape, rigid, ``norm_from_cam``.
    """
    s = similarity_scale(norm_from_world)
    rot = norm_from_world[:3, :3] / s
    m = np.array(world_from_cam, dtype=np.float64)
    out = m.copy()
    out[..., :3, :3] = rot @ m[..., :3, :3]
    out[..., :3, 3] = m[..., :3, 3] @ norm_from_world[:3, :3].T + norm_from_world[:3, 3]
    return out


def optical_axes_focus(world_from_cams: np.ndarray) -> tuple[np.ndarray, float]:
    """The point nearest (least squares) to every camera's optical axis: what an object-centred
    capture looks at.

    Args:
        world_from_cams: (N, 4, 4) OpenGL camera-to-world (cameras look down -z).

    Returns:
        focus_world: (3,).
        conditioning: smallest / largest eigenvalue of the normal matrix, in [0, 1]; near 0 when
            the axes are (almost) parallel and the focus is ill defined.
    """
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for m in np.asarray(world_from_cams, dtype=np.float64):
        d = -m[:3, 2] / np.linalg.norm(m[:3, 2])
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ m[:3, 3]
    ev = np.linalg.eigvalsh(a)
    return np.linalg.lstsq(a, b, rcond=None)[0], float(ev[0] / max(ev[-1], 1e-12))


def object_radius(centre_world: np.ndarray, world_from_cams: np.ndarray, points_world: np.ndarray | None = None,
                  percentile: float = 90.0, camera_fraction: float = 0.35) -> float:
    """A robust radius of the object around ``centre_world``.

    From sparse points when there are at least 20 closer to the centre than the nearest camera
    (their ``percentile``); else ``camera_fraction`` of the median camera distance.
    """
    dist_cam = np.linalg.norm(np.asarray(world_from_cams)[:, :3, 3] - centre_world, axis=1)
    if points_world is not None and len(points_world):
        d = np.linalg.norm(np.asarray(points_world) - centre_world, axis=1)
        d = d[d < 0.9 * dist_cam.min()]
        if len(d) >= 20:
            return float(np.percentile(d, percentile))
    return float(camera_fraction * np.median(dist_cam))


def normalization_transform(world_from_cams: np.ndarray, points_world: np.ndarray | None = None,
                            target_radius: float = 1.0) -> np.ndarray:
    """The similarity that normalises a capture: focus -> origin, up -> +y, first camera on +z,
    object radius -> ``target_radius``.

    Args:
        world_from_cams: (N, 4, 4) OpenGL camera-to-world, N >= 1.
        points_world: optional (P, 3) sparse points (improve the radius and an ill-defined focus).
        target_radius: the object's radius after normalisation, scene units.

    Returns:
        (4, 4) float64 norm_from_world.

    Raises:
        DamcapError: the radius is 0 (no absolute floor: the scale must not depend on the units).
    """
    m = np.asarray(world_from_cams, dtype=np.float64)
    focus, cond = optical_axes_focus(m) if len(m) >= 2 else (m[0, :3, 3] - m[0, :3, 2], 0.0)
    if cond < 1e-3:  # parallel axes (a forward-facing capture): the points' median, else 1 unit ahead
        if points_world is not None and len(points_world) >= 20:
            focus = np.median(np.asarray(points_world), axis=0)
        else:
            focus = m[:, :3, 3].mean(0) - m[:, :3, 2].mean(0)
    up = up_direction(m)
    rot = rotation_between(up, np.array([0.0, 1.0, 0.0]))
    c0 = rot @ (m[0, :3, 3] - focus)
    az = np.arctan2(c0[0], c0[2])  # turn about +y so the first camera has azimuth 0 (+z side)
    ry = np.array([[np.cos(-az), 0, np.sin(-az)], [0, 1, 0], [-np.sin(-az), 0, np.cos(-az)]])
    rot = ry @ rot
    radius = object_radius(focus, m, points_world)
    if not (np.isfinite(radius) and radius > 0):  # no absolute floor: 1e-12 is a valid radius in other units
        raise DamcapError(f"cannot normalise the scene: the object's radius is {radius} (the cameras sit at the point "
                          "they look at)")
    s = target_radius / radius
    return similarity(s, rot, -s * rot @ focus)


def recentre_transform(vertices: np.ndarray, target_radius: float = 1.0) -> np.ndarray:
    """(4, 4) similarity (no rotation) putting a mesh's bounding sphere at the origin with
    ``target_radius``: the final normalisation once the geometry is known."""
    centre, radius = bounding_sphere(vertices)
    s = target_radius / max(radius, 1e-12)
    return similarity(s, np.eye(3), -s * centre)


def umeyama_similarity(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> np.ndarray:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991, Eq. 40-42).

    Args:
        src, dst: (N, 3) corresponding points, N >= 3 not collinear.
        with_scale: estimate s (else s = 1).

    Returns:
        (4, 4) float64 dst_from_src.

    >>> p = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> (np.round(umeyama_similarity(p, 2 * p + 1), 6)[:3] + 0.0).tolist()
    [[2.0, 0.0, 0.0, 1.0], [0.0, 2.0, 0.0, 1.0], [0.0, 0.0, 2.0, 1.0]]
    """
    a = np.asarray(src, dtype=np.float64)
    b = np.asarray(dst, dtype=np.float64)
    ma, mb = a.mean(0), b.mean(0)
    ac, bc = a - ma, b - mb
    cov = bc.T @ ac / len(a)
    u, d, vt = np.linalg.svd(cov)
    e = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        e[2, 2] = -1
    rot = u @ e @ vt
    s = float(np.trace(np.diag(d) @ e) / (ac ** 2).sum(1).mean()) if with_scale else 1.0
    return similarity(s, rot, mb - s * rot @ ma)


def rotation_angle_deg(rotation: np.ndarray) -> np.ndarray:
    """Angle of (..., 3, 3) rotations in degrees (numerically safe near 0).

    >>> round(float(rotation_angle_deg(np.eye(3))), 9)
    0.0
    """
    r = np.asarray(rotation, dtype=np.float64)
    tr = np.trace(r, axis1=-2, axis2=-1)
    skew = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    return np.degrees(np.arctan2(np.linalg.norm(skew, axis=-1), tr - 1))


def rotation_agreement_deg(world_from_cams: np.ndarray, ref_world_from_cams: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How well camera rotations agree with reference cameras of the same photos.

    Args:
        world_from_cams: (N, 4, 4) estimated camera-to-world (any world frame and scale).
        ref_world_from_cams: (N, 4, 4) reference camera-to-world, same camera axes.

    Returns:
        absolute: (N,) degrees, after a similarity alignment of the camera centres (Umeyama):
            angle of R_ref_i^T R_align R_i.
        relative: (N (N-1) / 2,) degrees, alignment-free: angle between R_i^T R_j and
            R_ref_i^T R_ref_j for every pair.
    """
    est = np.asarray(world_from_cams, dtype=np.float64)
    ref = np.asarray(ref_world_from_cams, dtype=np.float64)
    t = umeyama_similarity(est[:, :3, 3], ref[:, :3, 3])
    r_align = t[:3, :3] / similarity_scale(t)
    absolute = rotation_angle_deg(np.swapaxes(ref[:, :3, :3], -1, -2) @ r_align @ est[:, :3, :3])
    i, j = np.triu_indices(len(est), 1)
    rel_est = np.swapaxes(est[i, :3, :3], -1, -2) @ est[j, :3, :3]
    rel_ref = np.swapaxes(ref[i, :3, :3], -1, -2) @ ref[j, :3, :3]
    relative = rotation_angle_deg(np.swapaxes(rel_ref, -1, -2) @ rel_est)
    return absolute, relative


def rotation_aligned_errors_deg(world_from_cams: np.ndarray, ref_world_from_cams: np.ndarray) -> np.ndarray:
    """Per-camera rotation error after the best global rotation (chordal L2 mean of
    R_ref_i R_i^T, closed form by SVD); independent of the camera centres' layout.

    Args:
        world_from_cams, ref_world_from_cams: (N, 4, 4) or (N, 3, 3).

    Returns:
        (N,) degrees.
    """
    est = np.asarray(world_from_cams, dtype=np.float64)[:, :3, :3]
    ref = np.asarray(ref_world_from_cams, dtype=np.float64)[:, :3, :3]
    m = np.einsum("nij,nkj->ik", ref, est)
    u, _, vt = np.linalg.svd(m)
    align = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return rotation_angle_deg(np.swapaxes(ref, -1, -2) @ align @ est)


def transform_mesh_similarity(mesh: Mesh, t: np.ndarray) -> Mesh:
    """The mesh under a similarity ``t`` (4, 4): vertices transformed, normals rotated (float32)."""
    s = similarity_scale(t)
    v = transform_points(t, mesh.vertices).astype(np.float32)
    n = (mesh.vertex_normals.astype(np.float64) @ (t[:3, :3] / s).T).astype(np.float32)
    return Mesh(v, mesh.triangles, n, mesh.triangle_groups)
