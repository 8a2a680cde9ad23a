"""Per-pixel surface buffers of a triangle mesh by ray casting (Open3D), in the capture convention.

For each pixel centre: the first hit's world position, the smooth (vertex-interpolated) normal
turned to face the camera, and coverage A from a sub-pixel grid. Edge-on pixels (dot(N, V) <= 0
after interpolation) are background, as the contract requires.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from damcap.common.cameras import pixel_rays_world, rays_world_at
from damcap.common.mesh import Mesh


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
    """An Open3D (Embree) ray-casting scene of one mesh, reused across frames.

    The scene holds the mesh in float32 (Embree's precision) whatever the mesh's dtype.
    """

    def __init__(self, mesh: Mesh) -> None:
        import open3d as o3d

        self.mesh = mesh
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                                 o3d.core.Tensor(mesh.triangles.astype(np.uint32)))

    def cast(self, origin: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        """First hits of rays from one origin (origin and directions are cast to float32).

        Args:
            origin: (3,) ray origin, world space.
            dirs: (..., 3) ray directions (unit length: then ``t_hit`` is a distance).

        Returns:
            arrays shaped like ``dirs``' leading dimensions: ``t_hit`` (...) float32, inf on a
            miss; ``primitive_ids`` (...) uint32 hit triangle (invalid on a miss);
            ``primitive_uvs`` (..., 2) float32 barycentrics (u, v) of vertices 1 and 2 (vertex 0
            has 1 - u - v); ``primitive_normals`` (..., 3) float32 unit geometric normals.
        """
        import open3d as o3d

        flat = dirs.reshape(-1, 3).astype(np.float32)
        rays = np.concatenate([np.broadcast_to(np.asarray(origin, np.float32), flat.shape), flat], axis=1)
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
        hit = self.cast(origin, d)
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
                ii, jj = np.nonzero(edge)  # sub-pixel rays of the silhouette pixels only
                d_sub = rays_world_at(world_from_cam, fl_x, fl_y, cx, cy, jj[None] + 0.5 + offs[:, :1],
                                      ii[None] + 0.5 + offs[:, 1:])
                sub = np.isfinite(self.cast(origin, d_sub)["t_hit"]).mean(0)
                coverage[edge] = np.maximum(sub, 1.0 / ss**2)
        return SurfaceBuffers(normal_world=normal, position_world=position, coverage=coverage, triangle_id=tri)
