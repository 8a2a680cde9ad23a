"""The one mesh type (common/mesh.py): readers, normals, signed volume, clean-up, normalisation."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.common.mesh import (
    Mesh, bounding_sphere, clean_mesh, face_normals_area, load_mesh, normalise_to_unit_sphere, read_mesh,
    signed_volume, to_open3d, vertex_normals_area_weighted,
)
from damcap.common.shapes import icosphere

#: a unit right tetrahedron, faces wound outward: volume 1/6
TETRA_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TETRA_T = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def test_mesh_validates_shapes():
    m = Mesh(TETRA_V, TETRA_T)
    assert m.vertex_normals is None and m.triangle_groups is None
    with pytest.raises(ValueError, match=r"vertices must be \(V, 3\), got \(4, 2\)"):
        Mesh(TETRA_V[:, :2], TETRA_T)
    with pytest.raises(ValueError, match=r"triangles must be \(T, 3\), got \(6,\)"):
        Mesh(TETRA_V, TETRA_T[:2].ravel())


def test_obj_quads_negative_indices_and_slashes(tmp_path):
    p = tmp_path / "quad.obj"
    p.write_text("# a unit square as one quad, plus a triangle with negative indices\n"
                 "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n"
                 "f 1/1/1 2/1/1 3/1/1 4/1/1\nf -4 -3 -1\n")
    m = read_mesh(p)
    assert m.vertices.shape == (4, 3) and m.vertices.dtype == np.float64 and m.triangles.dtype == np.int64
    np.testing.assert_array_equal(m.triangles, [[0, 1, 2], [0, 2, 3], [0, 1, 3]])


def test_ply_ascii_faces_and_binary_tristrips(tmp_path):
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 2, 0]], np.float32)
    ascii_ply = tmp_path / "a.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
                         "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                         + "".join(f"{x} {y} {z}\n" for x, y, z in verts) + "4 0 1 3 2\n")
    np.testing.assert_array_equal(read_mesh(ascii_ply).triangles, [[0, 1, 3], [0, 3, 2]])
    # binary little-endian with one strip 0 1 2 3, a restart (-1), then 2 3 4 (alternating winding)
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
              "property float z\nelement tristrips 1\nproperty list int int vertex_indices\nend_header\n").encode()
    strip = np.array([0, 1, 2, 3, -1, 2, 3, 4], np.int32)
    bin_ply = tmp_path / "b.ply"
    bin_ply.write_bytes(header + verts.tobytes() + np.int32(len(strip)).tobytes() + strip.tobytes())
    m = read_mesh(bin_ply)
    np.testing.assert_allclose(m.vertices, verts)
    np.testing.assert_array_equal(m.triangles, [[0, 1, 2], [2, 1, 3], [2, 3, 4]])


def test_read_mesh_errors_name_the_file(tmp_path):
    with pytest.raises(DamcapError, match="missing.obj: mesh file not found"):
        read_mesh(tmp_path / "missing.obj")
    (tmp_path / "m.stl").write_text("solid")
    with pytest.raises(DamcapError, match=r"m.stl: unknown mesh type '.stl'"):
        read_mesh(tmp_path / "m.stl")
    (tmp_path / "empty.obj").write_text("v 0 0 0\n")
    with pytest.raises(DamcapError, match="empty.obj: the mesh has no triangles"):
        read_mesh(tmp_path / "empty.obj")
    (tmp_path / "bad.obj").write_text("v 0 0 zero\nf 1 2 3\n")
    with pytest.raises(DamcapError, match="bad.obj: cannot parse"):
        read_mesh(tmp_path / "bad.obj")
    (tmp_path / "range.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 9\n")
    with pytest.raises(DamcapError, match="range.obj: face indices out of range"):
        read_mesh(tmp_path / "range.obj")
    (tmp_path / "empty.glb").write_bytes(b"glTF")
    with pytest.raises(DamcapError, match="empty.glb: the mesh has no triangles"):
        read_mesh(tmp_path / "empty.glb")


def _write_glb(path, vertices, triangles):
    """A minimal glTF 2.0 binary: one mesh, one primitive, POSITION and uint32 indices."""
    v = np.ascontiguousarray(vertices, np.float32)
    t = np.ascontiguousarray(triangles, np.uint32)
    blob = v.tobytes() + t.tobytes()
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 4}]}],
           "buffers": [{"byteLength": len(blob)}],
           "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": v.nbytes, "target": 34962},
                           {"buffer": 0, "byteOffset": v.nbytes, "byteLength": t.nbytes, "target": 34963}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": len(v), "type": "VEC3",
                          "min": v.min(0).tolist(), "max": v.max(0).tolist()},
                         {"bufferView": 1, "componentType": 5125, "count": t.size, "type": "SCALAR"}]}
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(blob), 0x004E4942) + blob
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)


def test_glb_gltf_and_off_are_read_through_open3d(tmp_path):
    """Both readers take glTF (binary or not) and OFF through Open3D: the same surface, to float32
    precision (Assimp may reorder the vertices of a GLB)."""
    import open3d as o3d

    s = icosphere(2)
    _write_glb(tmp_path / "s.glb", s.vertices, s.triangles)  # Open3D's own GLB writer gives files it cannot read
    for name in ("s.gltf", "s.off"):
        assert o3d.io.write_triangle_mesh(str(tmp_path / name), to_open3d(s))
    for name in ("s.glb", "s.gltf", "s.off"):
        m = read_mesh(tmp_path / name)
        assert m.vertices.dtype == np.float64 and m.triangles.shape == (320, 3), name
        np.testing.assert_allclose(np.linalg.norm(m.vertices, axis=1), 1.0, atol=1e-6)
        assert signed_volume(m.vertices, m.triangles) == pytest.approx(signed_volume(s.vertices, s.triangles), rel=1e-6)
        np.testing.assert_allclose(np.unique(np.round(m.vertices, 5), axis=0), np.unique(np.round(s.vertices, 5), axis=0), atol=1e-5)
        loaded = load_mesh(tmp_path / name)
        assert loaded.vertices.dtype == np.float32 and len(loaded.triangles) == 320, name


def test_signed_volume_closed_forms():
    assert signed_volume(TETRA_V, TETRA_T) == pytest.approx(1 / 6, rel=1e-15)
    assert signed_volume(TETRA_V, TETRA_T[:, ::-1]) == pytest.approx(-1 / 6, rel=1e-15)
    assert signed_volume(2.0 * TETRA_V + 5.0, TETRA_T) == pytest.approx(8 / 6, rel=1e-12)  # scale^3, translation-free
    s = icosphere(5)
    assert signed_volume(s.vertices, s.triangles) == pytest.approx(4 / 3 * np.pi, rel=1e-3)
    assert signed_volume(s.vertices.astype(np.float32), s.triangles) == pytest.approx(4 / 3 * np.pi, rel=1e-3)


def test_face_normals_are_twice_the_area():
    fn = face_normals_area(TETRA_V, TETRA_T)
    np.testing.assert_allclose(0.5 * np.linalg.norm(fn, axis=1), [0.5, 0.5, 0.5, np.sqrt(3) / 2])
    np.testing.assert_allclose(fn[3] / np.linalg.norm(fn[3]), np.ones(3) / np.sqrt(3))


def test_vertex_normals_of_a_sphere_are_radial():
    s = icosphere(3)
    n = vertex_normals_area_weighted(s.vertices, s.triangles)
    cos = (n * s.vertices).sum(-1)
    assert cos.min() > 0.999
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-12)
    assert n.dtype == np.float64
    # float32 input: same normals to float32 precision
    np.testing.assert_allclose(vertex_normals_area_weighted(s.vertices.astype(np.float32), s.triangles), n, atol=1e-6)


def test_vertex_normals_of_isolated_vertices():
    v = np.vstack([TETRA_V, [[5.0, 5, 5]], [[0.0, 0, 1e-12]]])  # an unreferenced vertex, then a tiny triangle's apex
    t = np.vstack([TETRA_T, [[0, 1, 5]]])  # degenerate-ish: area 5e-13
    n0 = vertex_normals_area_weighted(v, t)
    assert (n0[4] == 0).all()  # default: no area, zero normal
    np.testing.assert_allclose(np.linalg.norm(n0[5]), 1.0)  # scale-free: the tiny triangle still has a direction
    n1 = vertex_normals_area_weighted(v, t, eps=1e-20, isolated_normal=(0.0, 0.0, 1.0))
    np.testing.assert_array_equal(n1[4], [0, 0, 1])  # synth's convention: +z
    np.testing.assert_array_equal(n1[5], [0, 0, 1])  # |sum|^2 = 1e-24 <= eps
    np.testing.assert_array_equal(n0[:4], n1[:4])  # identical elsewhere


def test_clean_mesh_drops_degenerates_and_unused_vertices():
    v = np.vstack([TETRA_V, [[9.0, 9, 9]], [[0.5, 0, 0]]])
    t = np.vstack([TETRA_T, [[0, 0, 1]], [[0, 1, 5]]])  # repeated index; zero area (collinear)
    normals = np.arange(18, dtype=np.float64).reshape(6, 3)
    m = clean_mesh(Mesh(v, t, normals, np.arange(6, dtype=np.int32)))
    np.testing.assert_array_equal(m.vertices, TETRA_V)
    np.testing.assert_array_equal(m.triangles, TETRA_T)
    np.testing.assert_array_equal(m.vertex_normals, normals[:4])
    np.testing.assert_array_equal(m.triangle_groups, [0, 1, 2, 3])
    assert m.triangles.dtype == t.dtype


def test_normalise_centres_scales_and_winds_outward():
    """synth's normalisation (clean + fix_winding) makes an inward, moved, scaled sphere the unit one."""
    s = icosphere(2)
    inward = Mesh(s.vertices * 3.0 + [5.0, -2.0, 1.0], s.triangles[:, ::-1].copy())
    m = normalise_to_unit_sphere(inward, clean=True, fix_winding=True)
    assert np.linalg.norm(m.vertices, axis=-1).max() == pytest.approx(1.0)
    np.testing.assert_allclose(0.5 * (m.vertices.min(0) + m.vertices.max(0)), 0, atol=1e-12)
    assert signed_volume(m.vertices, m.triangles) == pytest.approx(signed_volume(s.vertices, s.triangles), rel=1e-9)  # outward again
    assert inward.vertices.max() > 5  # input untouched
    assert m.vertices.dtype == np.float64


def test_normalise_without_options_keeps_winding_vertices_and_dtype():
    """export's normalisation: no clean-up, winding as given, float32 stays float32, normals carried."""
    s = icosphere(1)
    inward = Mesh((s.vertices * 3.0 + 1.0).astype(np.float32), s.triangles[:, ::-1].copy(),
                  s.vertices.astype(np.float32), np.zeros(len(s.triangles), np.int32))
    m = normalise_to_unit_sphere(inward)
    assert m.vertices.dtype == np.float32 and len(m.vertices) == len(s.vertices)
    np.testing.assert_array_equal(m.triangles, inward.triangles)
    assert signed_volume(m.vertices, m.triangles) < 0
    np.testing.assert_allclose(m.vertices, s.vertices, atol=1e-6)  # the unit sphere's own vertices again
    assert m.vertex_normals is inward.vertex_normals
    flipped = normalise_to_unit_sphere(inward, fix_winding=True)
    np.testing.assert_array_equal(flipped.triangles, s.triangles)
    np.testing.assert_array_equal(flipped.vertex_normals, -inward.vertex_normals)


def test_normalise_refuses_a_mesh_with_nothing_left():
    with pytest.raises(DamcapError, match="no non-degenerate triangles"):
        normalise_to_unit_sphere(Mesh(np.zeros((3, 3)), np.array([[0, 1, 2]])), clean=True)


def test_bounding_sphere():
    c, r = bounding_sphere(TETRA_V + 1.0)
    np.testing.assert_allclose(c, [1.5, 1.5, 1.5])
    assert r == pytest.approx(np.sqrt(3 * 0.25))


def test_load_mesh_repairs_and_names_the_file(tmp_path):
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 1 0\nv 7 7 7\nf 1 2 3\nf 1 2 4\nf 1 1 2\n")
    m = load_mesh(tmp_path / "m.obj")  # welds 3 and 4, drops the duplicate, the degenerate and vertex 5
    assert m.vertices.dtype == np.float32 and m.triangles.dtype == np.int32 and len(m.triangles) == 1
    assert len(m.vertices) == 3
    np.testing.assert_allclose(m.vertex_normals, [[0, 0, 1]] * 3)
    with pytest.raises(DamcapError, match="nope.obj: mesh file not found"):
        load_mesh(tmp_path / "nope.obj")


def test_obj_material_groups_are_numbered_from_0_in_library_order(tmp_path):
    """Open3D numbers OBJ materials from 1 (0 is its default); damcap's parts start at 0, so three
    materials need three models."""
    from tests.conftest import write_tetra_obj_with_materials

    m = load_mesh(write_tetra_obj_with_materials(tmp_path))
    centroid = m.vertices[m.triangles].mean(axis=1)
    by_face = {tuple(np.round(c * 3).astype(int)): int(g) for c, g in zip(centroid, m.triangle_groups)}
    assert by_face == {(1, 1, 0): 0, (1, 0, 1): 1, (0, 1, 1): 2, (1, 1, 1): 2}


def test_shared_meshes_load(shared_data):
    counts = {"igea.ply": 268686, "stanford-bunny.obj": 69451, "beetle.obj": 2053}
    for name, faces in counts.items():
        m = normalise_to_unit_sphere(read_mesh(shared_data / "meshes" / name), clean=True, fix_winding=True)
        assert len(m.triangles) == faces, name
        assert np.linalg.norm(m.vertices, axis=-1).max() == pytest.approx(1.0)
        assert signed_volume(m.vertices, m.triangles) > 0.1, name


def test_file_vertex_order_undoes_the_obj_loaders_reordering(tmp_path):
    """Open3D splits OBJ vertices by (v, vt, vn) and renumbers them: per-vertex data written in the
    file's order (export --labels) is placed through file_vertex_order."""
    from damcap.common.mesh import file_vertex_order, load_mesh, read_mesh

    grid = [(x, y, 0.0) for y in range(3) for x in range(3)]
    faces = []
    for y in range(2):
        for x in range(2):
            a = y * 3 + x + 1
            faces += [(a + 4, a + 3, a), (a, a + 1, a + 4)]
    lines = [f"v {x:g} {y:g} {z:g}" for x, y, z in grid] + [f"vt {x / 2:g} {y / 2:g}" for x, y, _ in grid] + ["vn 0 0 1"]
    lines += ["f " + " ".join(f"{i}/{i}/1" for i in f) for f in reversed(faces)]
    path = tmp_path / "grid.obj"
    path.write_text("\n".join(lines) + "\n")
    loaded, in_file = load_mesh(path).vertices, read_mesh(path).vertices
    order, n_file = file_vertex_order(path, loaded)
    assert n_file == 9 and not np.array_equal(order, np.arange(len(loaded)))  # the loader did reorder
    assert np.array_equal(in_file[order].astype(np.float32), loaded)
    labels_in_file_order = (in_file[:, 0] > 0.5).astype(np.int64)
    assert np.array_equal(labels_in_file_order[order], (loaded[:, 0] > 0.5).astype(np.int64))
    with pytest.raises(DamcapError, match="match no vertex of the file"):
        file_vertex_order(path, loaded + 10)


def test_file_vertex_order_on_damcaps_own_torus(tmp_path):
    """The torus damcap writes (make demo's export shape): the two readers parse its numbers into
    floats that differ in the last bits, which must not stop per-vertex labels (it did: 37 of
    1440 vertices matched nothing when compared bit for bit)."""
    from damcap.common.mesh import file_vertex_order, load_mesh, read_mesh
    from damcap.common.shapes import write_shape

    write_shape("torus", tmp_path / "torus.obj")
    loaded, in_file = load_mesh(tmp_path / "torus.obj").vertices, read_mesh(tmp_path / "torus.obj").vertices
    order, n_file = file_vertex_order(tmp_path / "torus.obj", loaded)
    assert n_file == len(in_file) and np.abs(in_file[order] - loaded).max() < 1e-5
