"""Per-pixel surface buffers of a triangle mesh by ray casting (Open3D), in the capture convention.

For each pixel centre: the first hit's world position, the smooth (vertex-interpolated) normal
turned to face the camera, and coverage A from a sub-pixel grid. Edge-on pixels (dot(N, V) <= 0
after interpolation) are background, as the contract requires.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damcap.common.errors import DamcapError

from .cameras import pixel_rays_world


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


@dataclass
class SurfaceBuffers:
    """What ray casting a mesh gives per pixel."""

    normal_world: np.ndarray
    """(H, W, 3) float32 unit normals facing the camera; 0 on background"""
    position_world: np.ndarray
    """(H, W, 3) float32 surface points; 0 on background"""
    coverage: np.ndarray
    """(H, W) float32 in [0, 1]"""
    triangle_id: np.ndarray
    """(H, W) int64 hit triangle, -1 on background"""


class MeshRaycaster:
    """An Open3D ray-casting scene of one mesh, reused across frames."""

    def __init__(self, mesh: Mesh) -> None:
        import open3d as o3d

        self.mesh = mesh
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(mesh.vertices), o3d.core.Tensor(mesh.triangles.astype(np.uint32)))

    def _cast(self, origin: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        import open3d as o3d

        flat = dirs.reshape(-1, 3).astype(np.float32)
        rays = np.concatenate([np.broadcast_to(origin.astype(np.float32), flat.shape), flat], axis=1)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        return {k: (a := ans[k].numpy()).reshape(dirs.shape[:-1] + a.shape[1:]) for k in ("t_hit", "primitive_ids", "primitive_uvs", "primitive_normals")}

    def buffers(self, world_from_cam: np.ndarray, fl_x: float, fl_y: float, cx: float, cy: float, w: int, h: int, supersample: int = 3) -> SurfaceBuffers:
        """Ray cast one pinhole camera (OpenGL axes) into surface buffers.

        Args:
            world_from_cam: (4, 4) camera-to-world.
            fl_x, fl_y, cx, cy: intrinsics, pixels.
            w, h: image size.
            supersample: sub-pixel grid per axis for coverage at silhouettes (1 = binary).
        """
        origin, d = pixel_rays_world(world_from_cam, fl_x, fl_y, cx, cy, w, h)
        d = d.astype(np.float32)
        hit = self._cast(origin, d)
        valid = np.isfinite(hit["t_hit"])
        # everything below runs on the hit pixels only
        dv = d[valid]
        tri_v = hit["primitive_ids"][valid].astype(np.int64)
        pos_v = origin.astype(np.float32) + hit["t_hit"][valid][:, None] * dv
        uv = hit["primitive_uvs"][valid]
        vn = self.mesh.vertex_normals[self.mesh.triangles[tri_v]]  # (P, 3 vertices, 3)
        n_v = (1 - uv[:, 0:1] - uv[:, 1:2]) * vn[:, 0] + uv[:, 0:1] * vn[:, 1] + uv[:, 1:2] * vn[:, 2]
        # a back-facing hit (open mesh, inconsistent winding): turn the shading frame around
        flip = np.einsum("pi,pi->p", hit["primitive_normals"][valid], dv) > 0
        n_v[flip] *= -1
        n_v /= np.maximum(np.sqrt(np.einsum("pi,pi->p", n_v, n_v))[:, None], 1e-12)
        front = np.einsum("pi,pi->p", n_v, dv) < 0  # dot(N, V) > 0 with V = -d
        visible = np.zeros((h, w), bool)
        visible[valid] = front
        normal = np.zeros((h, w, 3), np.float32)
        position = np.zeros((h, w, 3), np.float32)
        tri = np.full((h, w), -1, np.int64)
        normal[visible] = n_v[front]
        position[visible] = pos_v[front]
        tri[visible] = tri_v[front]
        coverage = visible.astype(np.float32)
        if supersample > 1:
            ss = supersample
            offs = (np.stack(np.meshgrid(np.arange(ss), np.arange(ss)), -1).reshape(-1, 2) + 0.5) / ss - 0.5
            pad = np.pad(visible, 1, mode="edge")
            edge = np.zeros_like(visible)
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    edge |= pad[1 + di:1 + di + h, 1 + dj:1 + dj + w] != visible
            edge &= visible
            if edge.any():
                _, d_sub = pixel_rays_world(world_from_cam, fl_x, fl_y, cx, cy, w, h, offsets=offs)
                sub = np.isfinite(self._cast(origin, d_sub[:, edge])["t_hit"]).mean(0)
                coverage[edge] = np.maximum(sub, 1.0 / ss**2)
        return SurfaceBuffers(normal_world=normal, position_world=position, coverage=coverage, triangle_id=tri)
