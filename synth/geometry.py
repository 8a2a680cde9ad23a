"""Per-pixel geometry of a synthetic capture by ray casting (renderer-independent).

The geometry buffers are not taken from the renderer's AOVs: rays through the exact pixel
centres of the capture's pinhole (docs/capture-format.md: pixel (i, j) has its centre at
(j + 0.5, i + 0.5)) are cast against the very triangles and vertex normals that the renderer
gets, with the common ray caster (Embree through Open3D's ``RaycastingScene``), or analytically for the sphere. This avoids the
pitfalls of Mitsuba's AOVs (box-filtered normals and positions averaged across silhouettes, a
``shape_index`` whose meaning depends on the variant) and gives the contract's values exactly:

* ``P``: the surface point seen through the pixel centre; ``N``: the interpolated shading
  normal there (the one the renderer shades with), unit, turned toward the camera when a back
  face is seen (the renderer's BSDFs are two-sided);
* pixels whose centre ray misses, or sees the surface edge-on (``dot(N, V) <= eps``), are
  background: ``A = 0``, ``N = 0``, ``P = 0``, weights 0;
* coverage ``A`` on the other pixels: the fraction of a ``k x k`` stratified sub-pixel grid of
  rays (cell centres) that hit the object, at least ``1 / k^2``;
* material weights ``W``: among the sub-pixel rays that hit, the fraction that hit each
  material's faces (so they sum to 1 on covered pixels and are soft where a pixel straddles a
  material boundary, like the rendered radiance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from damcap.common.capture_folder import Intrinsics

from damcap.common.cameras import pixel_rays_world
from damcap.common.mesh import Mesh
from damcap.common.raycast import MeshRaycaster
from damcap.synth.closed_form import intersect_sphere


@dataclass(frozen=True)
class SceneGeometry:
    """The object as the ray caster sees it: a mesh with smooth normals and face materials,
    or the analytic unit sphere (``mesh is None``) with a single material."""

    mesh: Mesh | None
    """normalised mesh, or None for the analytic unit sphere at the origin"""
    vertex_normals: np.ndarray | None
    """(V, 3) unit vertex normals of ``mesh``"""
    face_material: np.ndarray | None
    """(F,) int64 material index per face of ``mesh``"""
    n_materials: int
    """number of materials (weight channels)"""


@dataclass
class RayHits:
    """First hits of a batch of rays."""

    hit: np.ndarray
    """(...) bool"""
    position_world: np.ndarray
    """(..., 3) hit points (0 where no hit)"""
    normal_world: np.ndarray
    """(..., 3) unit interpolated shading normals, oriented like the faces (0 where no hit)"""
    geo_normal_world: np.ndarray
    """(..., 3) unit geometric (face) normals (0 where no hit)"""
    material: np.ndarray
    """(...) int64 material index (0 where no hit)"""


class RayCaster:
    """Casts rays against a :class:`SceneGeometry`: the common ray caster
    (:class:`~damcap.common.raycast.MeshRaycaster`, Embree through Open3D) for meshes, the
    closed-form intersection for the analytic sphere."""

    def __init__(self, geometry: SceneGeometry) -> None:
        self.geometry = geometry
        self._scene = MeshRaycaster(geometry.mesh) if geometry.mesh is not None else None

    def cast(self, origin_world: np.ndarray, dir_world: np.ndarray) -> RayHits:
        """First hits of rays from one origin.

        Hit points, shading and face normals are interpolated in float64 on the mesh's own
        vertices from the float32 hit's triangle and barycentrics.

        Args:
            origin_world: (3,) ray origin (the camera centre).
            dir_world: (..., 3) unit directions.

        Returns:
            the hits, arrays shaped like ``dir_world``'s leading dimensions.
        """
        shape = dir_world.shape[:-1]
        if self._scene is None:
            hit, pos, nrm = intersect_sphere(np.asarray(origin_world, np.float64), dir_world.astype(np.float64))
            nrm = np.where(hit[..., None], nrm, 0.0)
            return RayHits(hit, np.where(hit[..., None], pos, 0.0), nrm, nrm.copy(), np.zeros(shape, np.int64))
        g = self.geometry
        ans = self._scene.cast(np.asarray(origin_world, np.float64), dir_world.reshape(-1, 3))
        t = ans["t_hit"]
        hit = np.isfinite(t)
        face = np.where(hit, ans["primitive_ids"].astype(np.int64), 0)
        uv = ans["primitive_uvs"].astype(np.float64)
        bary = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], -1)  # (1-u-v) v0 + u v1 + v v2
        tri = g.mesh.triangles[face]  # type: ignore[union-attr]
        pos = np.einsum("rk,rkc->rc", bary, g.mesh.vertices[tri])  # type: ignore[union-attr]
        nrm = np.einsum("rk,rkc->rc", bary, g.vertex_normals[tri])  # type: ignore[index]
        nrm /= np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-12)
        p = g.mesh.vertices[tri]  # type: ignore[union-attr]
        geo = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        geo /= np.maximum(np.linalg.norm(geo, axis=-1, keepdims=True), 1e-30)
        mat = g.face_material[face] if g.face_material is not None else np.zeros_like(face)
        m = hit[:, None]
        return RayHits(hit.reshape(shape), np.where(m, pos, 0.0).reshape(shape + (3,)),
                       np.where(m, nrm, 0.0).reshape(shape + (3,)), np.where(m, geo, 0.0).reshape(shape + (3,)),
                       np.where(hit, mat, 0).reshape(shape))


def subpixel_offsets(k: int) -> np.ndarray:
    """Centres of a k x k grid of cells inside a pixel, as offsets (dx, dy) from its centre.

    >>> subpixel_offsets(2).tolist()
    [[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]]
    """
    g = (np.arange(k) + 0.5) / k - 0.5
    dx, dy = np.meshgrid(g, g)
    return np.stack([dx.ravel(), dy.ravel()], -1)


@dataclass
class GeometryBuffers:
    """One frame's geometry, as the capture contract stores it."""

    normal_world: np.ndarray
    """(H, W, 3) float32 unit normals facing the camera on covered pixels, 0 elsewhere"""
    position_world: np.ndarray
    """(H, W, 3) float32 surface points seen through pixel centres, 0 on background"""
    coverage: np.ndarray
    """(H, W) float32 in [0, 1], 0 on background"""
    weights: np.ndarray
    """(H, W, n) float32 material weights, sum 1 on covered pixels, 0 elsewhere"""


def frame_geometry(caster: RayCaster, world_from_cam: np.ndarray, intr: Intrinsics, supersample: int = 4,
                   eps_facing: float = 1e-4) -> GeometryBuffers:
    """Geometry buffers of one view (module docstring: how each buffer is defined).

    Args:
        caster: the object's ray caster.
        world_from_cam: (4, 4) camera-to-world, OpenGL camera axes.
        intr: pinhole intrinsics, pixels.
        supersample: k; coverage and weights use k x k sub-pixel rays.
        eps_facing: least dot(N, V) of a covered pixel (smaller is edge-on, hence background).

    Returns:
        the frame's buffers.
    """
    origin, d = pixel_rays_world(world_from_cam, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h)
    centre = caster.cast(origin, d)
    view = origin - centre.position_world
    view /= np.maximum(np.linalg.norm(view, axis=-1, keepdims=True), 1e-12)
    back = (centre.geo_normal_world * view).sum(-1) < 0  # a back face: the renderer's BSDFs are two-sided
    normal = np.where(back[..., None], -centre.normal_world, centre.normal_world)
    covered = centre.hit & ((normal * view).sum(-1) > eps_facing)
    _, d_sub = pixel_rays_world(world_from_cam, intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.w, intr.h,
                                offsets=subpixel_offsets(supersample))
    sub = caster.cast(origin, d_sub)  # (S, H, W)
    n_mat = caster.geometry.n_materials
    counts = np.stack([(sub.hit & (sub.material == k)).sum(0) for k in range(n_mat)], -1).astype(np.float64)
    # the centre ray counts for its material too, so a covered pixel always has >= 1 hit
    counts[covered, centre.material[covered]] += 1
    hits = counts.sum(-1)
    frac = sub.hit.mean(0)
    coverage = np.where(covered, np.maximum(frac, 1.0 / len(sub.hit)), 0.0)
    weights = np.where(covered[..., None], counts / np.maximum(hits, 1)[..., None], 0.0)
    m = covered[..., None]
    return GeometryBuffers(
        normal_world=np.where(m, normal, 0.0).astype(np.float32),
        position_world=np.where(m, centre.position_world, 0.0).astype(np.float32),
        coverage=coverage.astype(np.float32),
        weights=weights.astype(np.float32),
    )
