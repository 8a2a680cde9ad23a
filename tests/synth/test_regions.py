"""Material regions of the synthetic data set (synth/regions.py): noise fields, labels, sub-meshes."""

from __future__ import annotations

import numpy as np

from damcap.common.mesh import vertex_normals_area_weighted
from damcap.common.shapes import icosphere
from damcap.synth.regions import (
    SYNTH_ISOLATED_NORMAL, SYNTH_NORMAL_EPS, material_labels, smooth_noise_fields, submesh,
)


def test_material_regions_are_balanced_smooth_and_seeded():
    s = icosphere(4)
    labels = material_labels(s, 3, seed=11)
    area = 0.5 * np.linalg.norm(np.cross(*(s.vertices[s.triangles][:, 1:] - s.vertices[s.triangles][:, :1]).transpose(1, 0, 2)), axis=-1)
    frac = np.bincount(labels, weights=area, minlength=3) / area.sum()
    assert frac.min() >= 0.2 - 1e-9, frac
    np.testing.assert_array_equal(labels, material_labels(s, 3, seed=11))
    assert (labels != material_labels(s, 3, seed=12)).mean() > 0.2
    # smooth regions: far fewer label changes across edges than for random labels (about 2/3)
    e = np.concatenate([s.triangles[:, [0, 1]], s.triangles[:, [1, 2]], s.triangles[:, [2, 0]]])
    key = np.sort(e, 1)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    faces_of_edge = np.argsort(inv, kind="stable").reshape(-1, 2)  # a closed mesh: two faces per edge
    f = np.tile(np.arange(len(s.triangles)), 3)[faces_of_edge]
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
    n = vertex_normals_area_weighted(s.vertices, s.triangles, SYNTH_NORMAL_EPS, SYNTH_ISOLATED_NORMAL)
    mask = np.arange(len(s.triangles)) % 2 == 0
    sub, sub_n = submesh(s, n, mask)
    assert len(sub.triangles) == mask.sum()
    np.testing.assert_allclose(sub.vertices[sub.triangles], s.vertices[s.triangles[mask]])
    np.testing.assert_allclose((sub_n * sub.vertices).sum(-1), (n * s.vertices).sum(-1)[np.unique(s.triangles[mask])])
