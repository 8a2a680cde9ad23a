"""Procedural shapes, as :class:`~damcap.common.mesh.Mesh`: sphere, icosphere, torus, bumpy blob.

``make demo`` exports its DAM onto one of them. Run ``damcap shape torus
OUT.obj`` (or ``sphere``) to write one as an OBJ that ``damcap export --mesh`` reads like any
user mesh.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from damcap.common.errors import DamcapError
from damcap.common.mesh import Mesh, midpoint_subdivision, signed_volume, to_open3d, vertex_normals_area_weighted

SHAPES = ("torus", "sphere")


def torus_mesh(major: float = 0.9, minor: float = 0.4, radial: int = 60, tubular: int = 24) -> Mesh:
    """A torus about the y axis (the capture contract's up axis), Open3D's tessellation.

    Its vertices satisfy ``(hypot(x, z) - major)^2 + y^2 = minor^2``.

    Args:
        major: distance from the centre to the tube's centre line, scene units.
        minor: tube radius, scene units (< major).
        radial: segments around the y axis.
        tubular: segments around the tube.

    Returns:
        ``radial * tubular`` float64 vertices centred at the origin, ``2 * radial * tubular``
        int32 triangles, no normals.
    """
    import open3d as o3d

    if not 0 < minor < major or radial < 3 or tubular < 3:
        raise DamcapError(f"a torus needs 0 < minor < major and >= 3 segments, got major={major}, minor={minor}, "
                          f"radial={radial}, tubular={tubular}")
    m = o3d.geometry.TriangleMesh.create_torus(torus_radius=major, tube_radius=minor, radial_resolution=radial,
                                               tubular_resolution=tubular)
    v = np.asarray(m.vertices)[:, [0, 2, 1]] * [1.0, 1.0, -1.0]  # Open3D's torus turns about z; ours about y
    return Mesh(v, np.asarray(m.triangles, np.int32).copy())


def _uv_sphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Open3D's UV sphere at resolution ``max(8, 2^subdivisions)``, vertices pushed onto the unit sphere.

    Returns:
        (V, 3) float64 unit vertices, (T, 3) int32 triangles.
    """
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=max(8, 2 ** subdivisions))
    v = np.asarray(m.vertices, np.float64).copy()
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v, np.asarray(m.triangles, np.int32).copy()


def sphere_mesh(centre: np.ndarray, radius: float, subdivisions: int = 6) -> Mesh:
    """A sphere (Open3D's UV tessellation) with exact (radial) vertex normals, wound outward.

    Args:
        centre: (3,) scene units.
        radius: scene units.
        subdivisions: resolution ``max(8, 2^subdivisions)`` segments.

    Returns:
        float32 vertices with ``|v - centre| = radius``, int32 triangles, float32 normals
        ``(v - centre) / radius``, zero groups.
    """
    v, t = _uv_sphere(subdivisions)
    if signed_volume(v, t) < 0:
        t = t[:, ::-1].copy()
    return Mesh((centre + radius * v).astype(np.float32), t, v.astype(np.float32), np.zeros(len(t), np.int32))


def icosphere(subdivisions: int) -> Mesh:
    """Unit sphere: an icosahedron subdivided ``subdivisions`` times (20 * 4^s faces), outward.

    Returns:
        float64 unit-length vertices, int64 triangles, no normals.

    >>> icosphere(2).triangles.shape
    (320, 3)
    """
    t = (1 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6),
         (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
         (8, 6, 7), (9, 8, 1)]
    pos = np.asarray(v, dtype=np.float64)
    pos /= np.linalg.norm(pos, axis=-1, keepdims=True)
    faces = np.asarray(f, dtype=np.int64)
    for _ in range(subdivisions):
        uniq, children = midpoint_subdivision(faces, len(pos))
        mid = pos[uniq[:, 0]] + pos[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=-1, keepdims=True)
        pos = np.concatenate([pos, mid])
        faces = children.transpose(1, 0, 2).reshape(-1, 3)  # every face's first child, then every second, ...
    return Mesh(pos, faces)


def _hash3(ijk: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) per integer lattice point (P, 3) -> (P,)."""
    h = (ijk[:, 0] * 73856093) ^ (ijk[:, 1] * 19349663) ^ (ijk[:, 2] * 83492791) ^ (seed * 2654435761)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float64) / float(0x1000000)


def value_noise(points: np.ndarray, frequency: float, seed: int) -> np.ndarray:
    """Trilinear lattice value noise in [0, 1] at (P, 3) points (smoothstep-interpolated).

    Args:
        points: (P, 3) scene units.
        frequency: lattice cells per scene unit.
        seed: lattice seed.

    Returns:
        (P,) float64 in [0, 1].
    """
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


def bumpy_blob(subdivisions: int = 5, amplitude: float = 0.12, seed: int = 0) -> Mesh:
    """A sphere with smooth radial bumps and one dent (not convex, not a sphere), radius about 1.

    Returns:
        float32 vertices (farthest at distance 1), int32 triangles, float32 area-weighted normals,
        zero groups.
    """
    v, t = _uv_sphere(subdivisions)
    r = 1 + amplitude * (2 * value_noise(v * 0.9 + 3.0, 1.5, seed + 5) - 1)
    r -= 0.25 * np.exp(-((v - np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])) ** 2).sum(1) / 0.08)
    v = v * r[:, None]
    v /= np.linalg.norm(v, axis=1).max()
    return Mesh(v.astype(np.float32), t, vertex_normals_area_weighted(v, t).astype(np.float32), np.zeros(len(t), np.int32))


def shape_mesh(name: str) -> Mesh:
    """The named shape (one of :data:`SHAPES`) in the unit sphere's scale (float64 vertices, no normals)."""
    import open3d as o3d

    if name == "torus":
        return torus_mesh()
    if name == "sphere":
        m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=48)
        return Mesh(np.asarray(m.vertices, np.float64).copy(), np.asarray(m.triangles, np.int32).copy())
    raise DamcapError(f"unknown shape {name!r}; choose one of {', '.join(SHAPES)}")


def write_shape(name: str, path: str | os.PathLike) -> Path:
    """Write the named shape as an OBJ or PLY file (by ``path``'s suffix), atomically."""
    import open3d as o3d

    from damcap.common.atomic import atomic_path

    path = Path(path)
    if path.suffix.lower() not in (".obj", ".ply"):
        raise DamcapError(f"{path}: write the shape as .obj or .ply")
    mesh = to_open3d(shape_mesh(name))
    with atomic_path(path, keep_name=True) as tmp:  # an OBJ names its object after the file
        if not o3d.io.write_triangle_mesh(str(tmp), mesh):
            raise DamcapError(f"{path}: Open3D could not write the mesh")
    return path

