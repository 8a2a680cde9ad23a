"""Procedural shapes (common/shapes.py): closed-form surfaces, winding, normals, files."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.common.errors import DamcapError
from damcap.common.mesh import Mesh, signed_volume, vertex_normals_area_weighted
from damcap.common.shapes import bumpy_blob, icosphere, shape_mesh, sphere_mesh, torus_mesh, value_noise


def test_procedural_shapes_are_the_closed_form_surfaces(tmp_path, capsys):
    """The demo's new shapes: every torus vertex lies on (sqrt(x^2 + z^2) - 0.9)^2 + y^2 = 0.4^2
    (axis y, as the capture contract's up), every sphere vertex on |v| = 1; both come back through
    damcap's own mesh reader, and bad requests are refused with a message."""
    from damcap.common.shapes import write_shape
    from damcap.common.mesh import load_mesh

    v = np.asarray(torus_mesh(0.9, 0.4).vertices)
    assert np.allclose((np.hypot(v[:, 0], v[:, 2]) - 0.9) ** 2 + v[:, 1] ** 2, 0.16, atol=1e-9)
    assert np.ptp(v[:, 1]) == pytest.approx(0.8, abs=1e-6)  # the tube's height along y
    torus = load_mesh(write_shape("torus", tmp_path / "torus.obj"))
    assert len(torus.vertices) == 60 * 24 and len(torus.triangles) == 2 * 60 * 24
    sphere = load_mesh(write_shape("sphere", tmp_path / "sphere.ply"))
    assert np.allclose(np.linalg.norm(sphere.vertices, axis=1), 1.0, atol=1e-5)
    with pytest.raises(DamcapError, match="0 < minor < major"):
        torus_mesh(0.4, 0.9)
    with pytest.raises(DamcapError, match=r"\.obj or \.ply"):
        write_shape("torus", tmp_path / "torus.stl")


def test_icosphere_is_the_unit_sphere_wound_outward():
    for s in range(4):
        m = icosphere(s)
        assert isinstance(m, Mesh) and m.vertices.dtype == np.float64 and m.triangles.dtype == np.int64
        assert m.triangles.shape == (20 * 4 ** s, 3) and len(m.vertices) == 10 * 4 ** s + 2  # Euler: V = F / 2 + 2
        np.testing.assert_allclose(np.linalg.norm(m.vertices, axis=1), 1.0, rtol=0, atol=1e-15)
    # inscribed polyhedron: its volume approaches 4/3 pi from below
    vol = [signed_volume(icosphere(s).vertices, icosphere(s).triangles) for s in (2, 3, 4)]
    assert vol[0] < vol[1] < vol[2] < 4 / 3 * np.pi
    assert vol[2] == pytest.approx(4 / 3 * np.pi, rel=3e-3)  # 2.2e-3 short at 5120 faces
    # every face normal points away from the centre
    m = icosphere(2)
    p = m.vertices[m.triangles]
    assert (np.einsum("fc,fc->f", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p.mean(1)) > 0).all()


def test_sphere_mesh_exact_radius_and_radial_normals():
    centre, radius = np.array([0.05, -0.03, 0.02]), 0.8
    m = sphere_mesh(centre, radius, subdivisions=4)
    assert m.vertices.dtype == np.float32 and m.triangles.dtype == np.int32
    np.testing.assert_allclose(np.linalg.norm(m.vertices - centre, axis=1), radius, rtol=1e-6)
    np.testing.assert_allclose(m.vertex_normals, (m.vertices - centre) / radius, atol=1e-6)
    assert signed_volume(m.vertices - centre, m.triangles) == pytest.approx(4 / 3 * np.pi * radius ** 3, rel=0.02)
    assert (m.triangle_groups == 0).all() and len(m.triangle_groups) == len(m.triangles)


def test_bumpy_blob_is_not_a_sphere_and_fits_the_unit_sphere():
    b = bumpy_blob(subdivisions=4)
    r = np.linalg.norm(b.vertices, axis=1)
    assert r.max() == pytest.approx(1.0, abs=1e-6) and r.min() < 0.8  # the dent
    assert b.vertices.dtype == np.float32 and b.vertex_normals.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(b.vertex_normals, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(b.vertex_normals, vertex_normals_area_weighted(b.vertices, b.triangles), atol=1e-6)
    assert signed_volume(b.vertices, b.triangles) > 0
    np.testing.assert_array_equal(b.vertices, bumpy_blob(subdivisions=4).vertices)  # deterministic
    assert not np.array_equal(b.vertices, bumpy_blob(subdivisions=4, seed=1).vertices)


def test_value_noise_range_and_lattice_values():
    p = np.random.default_rng(0).uniform(-3, 3, (500, 3))
    v = value_noise(p, 2.0, seed=3)
    assert v.shape == (500,) and 0 <= v.min() and v.max() < 1 and v.std() > 0.05
    # on lattice points the smoothstep weights are 0 / 1: the value is the lattice hash itself
    q = np.array([[1.0, 2.0, 3.0]])
    assert value_noise(q, 1.0, 3)[0] == pytest.approx(value_noise(q + 1e-9, 1.0, 3)[0], abs=1e-6)


def test_shape_mesh_returns_meshes():
    t, s = shape_mesh("torus"), shape_mesh("sphere")
    assert isinstance(t, Mesh) and isinstance(s, Mesh) and t.vertex_normals is None
    assert len(t.vertices) == 60 * 24
    np.testing.assert_allclose(np.linalg.norm(s.vertices, axis=1), 1.0, atol=1e-12)
    with pytest.raises(DamcapError, match="unknown shape 'cube'"):
        shape_mesh("cube")
