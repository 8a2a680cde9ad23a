"""The normal field: offsets tilt normals by their tangent part only, in closed form."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from damcap.appearance.normal_field import NormalField, apply_offsets, empty_field, field_share, refined_normals, surface_normals


def test_zero_offsets_and_normal_components_change_nothing():
    n = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    idx, w = torch.zeros(50, 8, dtype=torch.long), torch.full((50, 8), 0.125)
    assert torch.allclose(apply_offsets(n, torch.zeros(1, 3), idx, w), n, atol=1e-6)
    # an offset along the normal itself is dropped: only its tangent part tilts the normal
    z = torch.tensor([[0.0, 0.0, 1.0]])
    assert torch.allclose(apply_offsets(z, torch.tensor([[0.0, 0.0, 3.0]]), idx[:1], w[:1]), z)
    nf = empty_field(np.random.default_rng(0).uniform(-1, 1, (200, 3)), 0.25)
    assert nf.keys.size > 0 and (nf.offset == 0).all()
    pts = np.random.default_rng(1).uniform(-1, 1, (20, 3))
    nrm = np.tile(np.array([[0.0, 1.0, 0.0]], np.float32), (20, 1))
    assert np.allclose(refined_normals(nf, nrm, pts), nrm, atol=1e-6)


def test_share_and_surface_normals():
    pts = np.random.default_rng(2).uniform(-1, 1, (100, 3))
    nf = empty_field(pts[:50], 0.1)
    assert field_share(nf, pts[:50]) == 1.0 and field_share(nf, pts[:50] + 100.0) == 0.0 and field_share(nf, pts[:0]) == 0.0
    n = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (50, 1))
    assert np.array_equal(surface_normals(None, n, pts[:50]), n)
    tilted = NormalField(nf.origin_world, nf.voxel_size, nf.keys, np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (nf.keys.size, 1)))
    np.testing.assert_allclose(surface_normals(tilted, n, pts[:50]), np.tile([[2 ** -0.5, 0.0, 2 ** -0.5]], (50, 1)), atol=1e-6)


@pytest.mark.parametrize("change, needle", [
    (lambda f: NormalField(f.origin_world, f.voxel_size, f.keys[::-1].copy(), f.offset), "sorted"),
    (lambda f: NormalField(f.origin_world, -1.0, f.keys, f.offset), "voxel size"),
    (lambda f: NormalField(f.origin_world, f.voxel_size, f.keys, f.offset[:1]), "must be (M,) and (M, 3)"),
    (lambda f: NormalField(f.origin_world, f.voxel_size, f.keys, np.full_like(f.offset, np.nan)), "NaN"),
    (lambda f: NormalField(f.origin_world, f.voxel_size, f.keys, np.full_like(f.offset, 1e3)), "more than"),
])
def test_problem_names_what_is_wrong(change, needle):
    f = empty_field(np.random.default_rng(3).uniform(-1, 1, (30, 3)), 0.3)
    assert f.problem() is None
    assert needle in change(f).problem()


def test_resampled_offsets_carry_a_field_onto_other_corners():
    from damcap.appearance.normal_field import corner_positions, empty_field, resampled_offsets

    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (500, 3))
    a = empty_field(pts, 0.25)
    a.offset[:] = (corner_positions(a) * [0.1, -0.2, 0.05]).astype(np.float32)  # linear in position
    b = empty_field(pts[:300] + 0.0, 0.25)  # other points: another origin, other corners
    got = resampled_offsets(a, b)
    # trilinear interpolation reproduces a linear field where all 8 corners exist
    inner = np.abs(corner_positions(b)).max(1) < 0.6
    assert np.allclose(got[inner], (corner_positions(b) * [0.1, -0.2, 0.05])[inner], atol=1e-5)
    assert np.array_equal(resampled_offsets(a, a), a.offset)
