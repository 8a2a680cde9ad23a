"""Triangle meshes: the one mesh type every stage uses, reading (Open3D), normals, normalisation.

Everything here is pure numpy except :func:`load_mesh` (the one file reader).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damcap.common.errors import DamcapError


@dataclass
class Mesh:
    """A triangle mesh as plain arrays."""

    vertices: np.ndarray
    """(V, 3) float32 world-space positions"""
    triangles: np.ndarray
    """(T, 3) int32 vertex indices"""
    vertex_normals: np.ndarray
    """(V, 3) float32 unit normals (area-weighted, recomputed when the file has none)"""
    triangle_groups: np.ndarray
    """(T,) int32 part index per triangle (OBJ material groups; 0 when none)"""


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Read an OBJ/PLY/OFF/GLB mesh with Open3D; repair what can be repaired.

    Degenerate and duplicate triangles and unreferenced vertices are removed; vertex normals are
    (re)computed when missing or non-finite.

    Raises:
        DamcapError: missing file, unreadable file, or no triangles left.
    """
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise DamcapError(f"{path}: mesh file not found")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise DamcapError(f"{path}: no triangles could be read (empty mesh or unsupported format; use OBJ or PLY)")
    groups = np.asarray(mesh.triangle_material_ids, np.int32) if mesh.has_triangle_material_ids() else None
    if groups is not None and len(groups) == len(mesh.triangles):
        # Open3D's clean-up below reorders triangles; carry groups through as a triangle attribute
        mesh.triangle_material_ids = o3d.utility.IntVector(groups.tolist())
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    mesh.remove_unreferenced_vertices()
    tris = np.asarray(mesh.triangles, np.int32)
    verts = np.asarray(mesh.vertices, np.float64)
    if len(tris) == 0:
        raise DamcapError(f"{path}: every triangle is degenerate; nothing to render")
    if not np.isfinite(verts).all():
        raise DamcapError(f"{path}: vertex positions contain NaN or inf")
    area = np.linalg.norm(np.cross(verts[tris[:, 1]] - verts[tris[:, 0]], verts[tris[:, 2]] - verts[tris[:, 0]]), axis=1)
    if area.max() <= 0:
        raise DamcapError(f"{path}: all triangles have zero area")
    normals = np.asarray(mesh.vertex_normals, np.float64) if mesh.has_vertex_normals() else np.zeros((0, 3))
    if normals.shape != verts.shape or not np.isfinite(normals).all() or (np.linalg.norm(normals, axis=1) < 1e-6).any():
        normals = vertex_normals_area_weighted(verts, tris)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    g = np.asarray(mesh.triangle_material_ids, np.int32) if mesh.has_triangle_material_ids() else np.zeros(len(tris), np.int32)
    if len(g) != len(tris):
        g = np.zeros(len(tris), np.int32)
    return Mesh(verts.astype(np.float32), tris, normals.astype(np.float32), g)


def vertex_normals_area_weighted(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(V, 3) unit vertex normals: the sum of adjacent face normals weighted by face area.

    Scale-free: the sum has units of area (square scene units, as small as 1e-24 for a mesh of
    size 1e-11), so it is divided by its own length without an absolute floor; a vertex without
    area (unreferenced, or only degenerate triangles) gets a zero normal.

    Args:
        vertices: (V, 3).
        triangles: (T, 3) counter-clockwise (outward) vertex indices.
    """
    v = vertices.astype(np.float64)
    fn = np.cross(v[triangles[:, 1]] - v[triangles[:, 0]], v[triangles[:, 2]] - v[triangles[:, 0]])  # length = 2 area
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, triangles[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


def normalise_to_unit_sphere(mesh: Mesh) -> Mesh:
    """Centre the mesh's bounding box at the origin and scale it into the unit sphere."""
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    centre = (lo + hi) / 2
    radius = float(np.linalg.norm(mesh.vertices - centre, axis=1).max())
    return Mesh(((mesh.vertices - centre) / max(radius, 1e-12)).astype(np.float32), mesh.triangles, mesh.vertex_normals, mesh.triangle_groups)


def bounding_sphere(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (of the bounding box) and radius (farthest vertex) of a vertex set.

    Args:
        vertices: (V, 3).

    Returns:
        centre: (3,); radius: scene units.
    """
    v = np.asarray(vertices, dtype=np.float64)
    centre = (v.min(0) + v.max(0)) / 2
    return centre, float(np.linalg.norm(v - centre, axis=1).max())
