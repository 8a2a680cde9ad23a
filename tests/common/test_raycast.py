"""The one ray caster (common/raycast.py): raw hits and per-pixel surface buffers, against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.cameras import look_at_world_from_cam
from damcap.common.mesh import Mesh
from damcap.common.raycast import MeshRaycaster
from damcap.common.shapes import icosphere, sphere_mesh

#: a square of side 4 in the z = 0 plane, facing +z
SQUARE = Mesh(np.array([[-2.0, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]]), np.array([[0, 1, 2], [0, 2, 3]]),
              np.tile([0.0, 0.0, 1.0], (4, 1)), np.zeros(2, np.int32))


def test_cast_hits_a_plane_at_the_closed_form_distance():
    rc = MeshRaycaster(SQUARE)  # float64 vertices are cast to float32 for Embree
    d = np.array([[0.0, 0, -1], [0.6, 0.0, -0.8], [0.0, 0.0, 1.0], [0.8, 0.0, -0.6]])
    ans = rc.cast(np.array([0.0, 0.0, 2.0]), d)
    assert ans["t_hit"].shape == (4,) and ans["primitive_uvs"].shape == (4, 2)
    np.testing.assert_allclose(ans["t_hit"][:2], [2.0, 2.5], rtol=1e-6)  # t = z0 / cos
    assert np.isinf(ans["t_hit"][2:]).all()  # away from the plane; past its edge (x = 2.67 > 2)
    np.testing.assert_allclose(np.abs(ans["primitive_normals"][:2, 2]), 1.0, atol=1e-6)
    # barycentrics reproduce the hit point: (1 - u - v) v0 + u v1 + v v2
    tri = SQUARE.triangles[ans["primitive_ids"][1]]
    u, v = ans["primitive_uvs"][1]
    p = (1 - u - v) * SQUARE.vertices[tri[0]] + u * SQUARE.vertices[tri[1]] + v * SQUARE.vertices[tri[2]]
    np.testing.assert_allclose(p, [1.5, 0.0, 0.0], atol=1e-5)


def test_cast_keeps_leading_batch_dimensions():
    rc = MeshRaycaster(SQUARE)
    d = np.broadcast_to(np.array([0.0, 0.0, -1.0]), (2, 3, 5, 3))
    ans = rc.cast(np.array([0.0, 0.0, 1.0]), d)
    assert ans["t_hit"].shape == (2, 3, 5) and ans["primitive_normals"].shape == (2, 3, 5, 3)


def test_buffers_of_a_sphere_are_radial():
    """Normals of a sphere are its positions (radius 1): the closed form the buffers must meet."""
    mesh = sphere_mesh(np.zeros(3), 1.0, subdivisions=6)
    w = h = 48
    f = 60.0
    cam = look_at_world_from_cam(np.array([0.0, 0.0, 3.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    b = MeshRaycaster(mesh).buffers(cam, f, f, w / 2, h / 2, w, h)
    hit = b.coverage > 0
    assert b.normal_world.dtype == np.float32 and b.triangle_id.dtype == np.int64
    np.testing.assert_allclose(np.linalg.norm(b.position_world[hit], axis=1), 1.0, atol=2e-3)
    cos = np.einsum("pc,pc->p", b.normal_world[hit], b.position_world[hit]) / np.linalg.norm(b.position_world[hit], axis=1)
    assert cos.min() > 0.999
    assert (b.triangle_id[~hit] == -1).all() and (b.normal_world[~hit] == 0).all()
    # the disc's area in pixels: a sphere at distance 3 subtends tan(a) = 1 / sqrt(8)
    r_px = f * np.tan(np.arcsin(1 / 3))
    assert b.coverage.sum() == pytest.approx(np.pi * r_px ** 2, rel=0.02)
    assert ((b.coverage > 0) & (b.coverage < 1)).any()  # soft silhouette from the sub-pixel grid


def test_float64_mesh_gives_the_float32_mesh_hits():
    s = icosphere(3)
    d = np.random.default_rng(0).normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.zeros(3)
    a = MeshRaycaster(s).cast(o, d)
    b = MeshRaycaster(Mesh(s.vertices.astype(np.float32), s.triangles.astype(np.int32))).cast(o, d)
    for k in ("t_hit", "primitive_ids", "primitive_uvs"):
        np.testing.assert_array_equal(a[k], b[k])
    np.testing.assert_allclose(a["t_hit"], 1.0, atol=0.02)  # from the centre, every ray hits the inscribed polyhedron near 1
