"""Mesh reading, normalisation, smooth normals and material regions of the synthetic data set."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.synth.mesh import (
    TriangleMesh, icosphere, material_labels, normalise_to_unit_sphere, read_mesh, signed_volume,
    smooth_noise_fields, submesh, vertex_normals,
)


def test_obj_quads_negative_indices_and_slashes(tmp_path):
    p = tmp_path / "quad.obj"
    p.write_text("# a unit square as one quad, plus a triangle with negative indices\n"
                 "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n"
                 "f 1/1/1 2/1/1 3/1/1 4/1/1\nf -4 -3 -1\n")
    m = read_mesh(p)
    assert m.positions.shape == (4, 3)
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3], [0, 1, 3]])


def test_ply_ascii_faces_and_binary_tristrips(tmp_path):
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 2, 0]], np.float32)
    ascii_ply = tmp_path / "a.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
                         "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                         + "".join(f"{x} {y} {z}\n" for x, y, z in verts) + "4 0 1 3 2\n")
    np.testing.assert_array_equal(read_mesh(ascii_ply).faces, [[0, 1, 3], [0, 3, 2]])
    # binary little-endian with one strip 0 1 2 3, a restart (-1), then 2 3 4 (alternating winding)
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
              "property float z\nelement tristrips 1\nproperty list int int vertex_indices\nend_header\n").encode()
    strip = np.array([0, 1, 2, 3, -1, 2, 3, 4], np.int32)
    bin_ply = tmp_path / "b.ply"
    bin_ply.write_bytes(header + verts.tobytes() + np.int32(len(strip)).tobytes() + strip.tobytes())
    m = read_mesh(bin_ply)
    np.testing.assert_allclose(m.positions, verts)
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [2, 1, 3], [2, 3, 4]])


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


def test_normalise_centres_scales_and_winds_outward():
    s = icosphere(2)
    inward = TriangleMesh(s.positions * 3.0 + [5.0, -2.0, 1.0], s.faces[:, ::-1].copy())
    m = normalise_to_unit_sphere(inward)
    assert np.linalg.norm(m.positions, axis=-1).max() == pytest.approx(1.0)
    np.testing.assert_allclose(0.5 * (m.positions.min(0) + m.positions.max(0)), 0, atol=1e-12)
    assert signed_volume(m) == pytest.approx(signed_volume(icosphere(2)), rel=1e-9)  # outward again
    assert inward.positions.max() > 5  # input untouched


def test_vertex_normals_of_a_sphere_are_radial():
    s = icosphere(3)
    n = vertex_normals(s)
    cos = (n * s.positions).sum(-1)
    assert cos.min() > 0.999
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-12)


def test_material_regions_are_balanced_smooth_and_seeded():
    s = icosphere(4)
    labels = material_labels(s, 3, seed=11)
    area = 0.5 * np.linalg.norm(np.cross(*(s.positions[s.faces][:, 1:] - s.positions[s.faces][:, :1]).transpose(1, 0, 2)), axis=-1)
    frac = np.bincount(labels, weights=area, minlength=3) / area.sum()
    assert frac.min() >= 0.2 - 1e-9, frac
    np.testing.assert_array_equal(labels, material_labels(s, 3, seed=11))
    assert (labels != material_labels(s, 3, seed=12)).mean() > 0.2
    # smooth regions: far fewer label changes across edges than for random labels (about 2/3)
    e = np.concatenate([s.faces[:, [0, 1]], s.faces[:, [1, 2]], s.faces[:, [2, 0]]])
    key = np.sort(e, 1)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    faces_of_edge = np.argsort(inv, kind="stable").reshape(-1, 2)  # a closed mesh: two faces per edge
    f = np.tile(np.arange(len(s.faces)), 3)[faces_of_edge]
    assert (labels[f[:, 0]] != labels[f[:, 1]]).mean() < 0.1
    assert np.all(material_labels(s, 1, seed=0) == 0)


def test_noise_fields_are_smooth():
    p = np.random.default_rng(0).uniform(-1, 1, (200, 3))
    a = smooth_noise_fields(p, 3, seed=4)
    b = smooth_noise_fields(p + 1e-3, 3, seed=4)
    assert np.abs(a - b).max() < 0.05
    assert a.std() > 0.2


def test_submesh_keeps_normals():
    s = icosphere(1)
    n = vertex_normals(s)
    mask = np.arange(len(s.faces)) % 2 == 0
    sub, sub_n = submesh(s, n, mask)
    assert len(sub.faces) == mask.sum()
    np.testing.assert_allclose(sub.positions[sub.faces], s.positions[s.faces[mask]])
    np.testing.assert_allclose((sub_n * sub.positions).sum(-1), (n * s.positions).sum(-1)[np.unique(s.faces[mask])])


def test_shared_meshes_load(shared_data):
    counts = {"igea.ply": 268686, "stanford-bunny.obj": 69451, "beetle.obj": 2053}
    for name, faces in counts.items():
        m = normalise_to_unit_sphere(read_mesh(shared_data / "meshes" / name))
        assert len(m.faces) == faces, name
        assert np.linalg.norm(m.positions, axis=-1).max() == pytest.approx(1.0)
        assert signed_volume(m) > 0.1, name
