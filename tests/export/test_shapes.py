"""The pot in three named parts: closed-form surfaces, watertight parts wound outward, exact
normals, a deterministic OBJ that load_mesh reads back in the same parts."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.mesh import load_mesh, signed_volume, vertex_normals_area_weighted
from damcap.export.shapes import (POT_MTL_KD, POT_PARTS, obj_part_names, obj_text, pot_mesh, superellipsoid_of_revolution, torus_z,
                                  write_parted_obj)


@pytest.fixture(scope="module")
def pot():
    return pot_mesh()


def _directed_edges(triangles: np.ndarray) -> np.ndarray:
    return np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])


def test_parts_are_named_and_each_is_watertight_and_wound_outward(pot):
    mesh, names = pot
    assert names == POT_PARTS == ("body", "lid", "handle")
    assert set(np.unique(mesh.triangle_groups)) == {0, 1, 2}
    for k in range(3):
        tris = mesh.triangles[mesh.triangle_groups == k]
        edges = _directed_edges(tris)
        # closed and consistently wound: every directed edge once, and its reverse once
        as_set = {tuple(e) for e in edges.tolist()}
        assert len(as_set) == len(edges), names[k]
        assert all((b, a) in as_set for a, b in as_set), names[k]
        assert signed_volume(mesh.vertices, tris) > 0, names[k]
    assert len(mesh.triangles) > 20_000  # smooth silhouettes at the export's 512 px


def test_normals_are_exact_unit_and_agree_with_the_tessellation(pot):
    mesh, _ = pot
    assert np.allclose(np.linalg.norm(mesh.vertex_normals, axis=1), 1, atol=1e-12)
    # the triangles' own (area-weighted) normals point the same way everywhere, outward
    area = vertex_normals_area_weighted(mesh.vertices, mesh.triangles)
    assert (area * mesh.vertex_normals).sum(1).min() > 0.99


def test_surfaces_satisfy_their_equations():
    a, b, e = 0.75, 0.55, 2.6
    body = superellipsoid_of_revolution(a, b, e, 24, 16)
    r, y = np.hypot(body.vertices[:, 0], body.vertices[:, 2]), body.vertices[:, 1]
    assert np.allclose((r / a) ** e + (np.abs(y) / b) ** e, 1, atol=1e-12)
    # the normal is the implicit function's gradient: at the equator radial, at the poles along y
    eq = np.abs(y) < 1e-9
    assert not eq.any() or np.allclose(body.vertex_normals[eq][:, 1], 0)
    assert np.allclose(body.vertex_normals[[0, -1]], [[0, -1, 0], [0, 1, 0]])
    ring = torus_z(0.32, 0.07, 12, 8, centre=(0.72, 0.05, 0.0))
    p = ring.vertices - [0.72, 0.05, 0.0]
    assert np.allclose((np.hypot(p[:, 0], p[:, 1]) - 0.32) ** 2 + p[:, 2] ** 2, 0.07 ** 2, atol=1e-12)
    line = 0.32 * np.stack([p[:, 0], p[:, 1], 0 * p[:, 2]], 1) / np.hypot(p[:, 0], p[:, 1])[:, None]
    assert np.allclose(ring.vertex_normals, (p - line) / 0.07, atol=1e-12)
    with pytest.raises(ValueError, match="exponent >= 2"):
        superellipsoid_of_revolution(1, 1, 1.5, 8, 8)


def test_the_obj_is_deterministic_and_reads_back_in_the_same_parts(pot, tmp_path):
    mesh, names = pot
    again, _ = pot_mesh()
    assert obj_text(mesh, names, "pot.mtl") == obj_text(again, names, "pot.mtl")
    obj, mtl = write_parted_obj(mesh, names, tmp_path / "pot.obj", POT_MTL_KD)
    assert mtl == tmp_path / "pot.mtl" and "mtllib pot.mtl" in obj.read_text()
    assert [ln.split()[1] for ln in mtl.read_text().splitlines() if ln.startswith("newmtl")] == list(names)
    assert obj_part_names(obj) == list(names)
    back = load_mesh(obj)
    assert np.array_equal(np.bincount(back.triangle_groups), np.bincount(mesh.triangle_groups))
    # the file's normals are kept (6 decimals)
    near = np.linalg.norm(back.vertices[:, None] - mesh.vertices[None, :50].astype(np.float32), axis=2).argmin(0)
    assert np.allclose(back.vertex_normals[near], mesh.vertex_normals[:50], atol=2e-6)
    with pytest.raises(Exception, match="written as .obj"):
        write_parted_obj(mesh, names, tmp_path / "pot.ply")


def test_part_names_of_other_files(tmp_path):
    from tests.conftest import write_tetra_obj_with_materials

    assert obj_part_names(write_tetra_obj_with_materials(tmp_path)) == ["a", "b", "c"]
    (tmp_path / "plain.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert obj_part_names(tmp_path / "plain.obj") is None
    (tmp_path / "lost.obj").write_text("mtllib nowhere.mtl\nusemtl a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert obj_part_names(tmp_path / "lost.obj") is None
    assert obj_part_names(tmp_path / "x.ply") is None
