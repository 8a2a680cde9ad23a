"""Rendering a DAM into a frame: covered pixels only, in closed form for an all-zero DAM."""

from __future__ import annotations

import math

import numpy as np
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.appearance.pixels import view_dir_world
from damcap.appearance.render import render_frame
from damcap.common.capture_folder import FrameData


def _frame(h: int = 6, w: int = 5, seed: int = 0) -> FrameData:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(h, w, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    cov = np.zeros((h, w), np.float32)
    cov[1:5, 1:4] = 1.0
    cov[0, 0] = 0.2  # partially covered: rendered too (A > 0)
    return FrameData(np.full((h, w, 3), -1.0, np.float32), n.astype(np.float32), rng.normal(size=(h, w, 3)).astype(np.float32), cov)


def test_all_zero_dam_renders_softplus_0_times_the_scale():
    """With every weight 0 the network outputs softplus(0) = ln 2 per channel, times the radiance scale."""
    arch = DamArchitecture()
    model = DeepAppearanceMap(arch, radiance_scale=2.0, weights_flat=torch.zeros(arch.num_weights))
    data = _frame()
    out = render_frame(model, data, np.array([0.0, 0.0, 5.0]))
    assert out.shape == (6, 5, 3) and out.dtype == np.float32
    covered = data.coverage > 0
    np.testing.assert_allclose(out[covered], 2.0 * math.log(2.0), rtol=1e-6)
    assert np.all(out[~covered] == 0)  # background is 0, and the frame's radiance is never read


def test_render_equals_the_model_on_the_covered_pixels_in_any_chunks():
    model = DeepAppearanceMap(DamArchitecture(width=8, depth=3), radiance_scale=1.5, generator=torch.Generator().manual_seed(3))
    data = _frame(seed=1)
    centre = np.array([1.0, 2.0, 3.0])
    covered = data.coverage > 0
    with torch.no_grad():
        want = model(torch.from_numpy(view_dir_world(data.position_world[covered], centre)),
                     torch.from_numpy(data.normal_world[covered])).numpy()
    full = render_frame(model, data, centre)
    np.testing.assert_allclose(full[covered], want, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(render_frame(model, data, centre, chunk=4), full, rtol=1e-6, atol=1e-7)  # batch size changes the float32 sums
    assert int(covered.sum()) == 13


def test_a_frame_without_coverage_renders_black():
    model = DeepAppearanceMap(DamArchitecture(width=4, depth=2))
    data = _frame()
    empty = FrameData(data.radiance_lin, data.normal_world, data.position_world, np.zeros_like(data.coverage))
    out = render_frame(model, empty, np.zeros(3))
    assert out.shape == (6, 5, 3) and not out.any()


def test_spatial_factor_multiplies_the_render_at_each_surface_point():
    """Albedo 2 in red at the voxel corners around all covered points but one: red doubles
    wherever a point has a stored corner, and nothing changes where it has none."""
    from damcap.appearance.spatial import SpatialAlbedo, trilinear_corners

    model = DeepAppearanceMap(DamArchitecture(width=8, depth=2), radiance_scale=1.0, generator=torch.Generator().manual_seed(1))
    data = _frame(seed=2)
    centre = np.array([0.0, 0.0, 5.0])
    plain = render_frame(model, data, centre)
    covered = data.coverage > 0
    origin, h = np.full(3, -10.0), 0.5
    corners = lambda p: trilinear_corners(np.asarray(p, np.float64).reshape(-1, 3), origin, h)[0]  # noqa: E731
    keys = np.setdiff1d(np.unique(corners(data.position_world[covered])), corners(data.position_world[1, 1]))
    sa = SpatialAlbedo(origin, h, keys, np.tile(np.array([[np.log(2.0), 0.0, 0.0]], np.float32), (keys.size, 1)))
    textured = render_frame(model.with_spatial(sa), data, centre)
    found = np.array([[np.isin(corners(data.position_world[i, j]), keys).any() for j in range(5)] for i in range(6)])
    assert not found[1, 1] and found[covered].sum() >= covered.sum() - 3
    np.testing.assert_allclose(textured[..., 0], np.where(found & covered, 2.0, 1.0) * plain[..., 0], rtol=1e-5)
    np.testing.assert_allclose(textured[..., 1:], plain[..., 1:], rtol=1e-6)
    assert np.all(textured[~covered] == 0)


def test_normal_field_tilts_the_normals_the_dam_sees():
    """A constant offset at every stored corner: each covered pixel renders as the DAM evaluated
    at n + the offset's tangent part, normalised (closed form); a pixel whose corners are not
    stored keeps its normal; the spatial factor still multiplies on top."""
    from damcap.appearance.normal_field import NormalField
    from damcap.appearance.spatial import trilinear_corners

    model = DeepAppearanceMap(DamArchitecture(width=8, depth=2), radiance_scale=1.0, generator=torch.Generator().manual_seed(4))
    data = _frame(seed=3)
    centre = np.array([0.0, 0.0, 5.0])
    covered = data.coverage > 0
    origin, h = np.full(3, -10.0), 0.5
    corners = lambda p: trilinear_corners(np.asarray(p, np.float64).reshape(-1, 3), origin, h)[0]  # noqa: E731
    keys = np.setdiff1d(np.unique(corners(data.position_world[covered])), corners(data.position_world[2, 2]))
    found = np.array([[np.isin(corners(data.position_world[i, j]), keys).any() for j in range(5)] for i in range(6)])
    # every stored corner has the same offset: wherever a point finds any corner, the
    # renormalised trilinear mean is that offset itself
    offset = np.array([0.3, -0.2, 0.1], np.float32)
    nf = NormalField(origin, h, keys, np.tile(offset, (keys.size, 1)))
    got = render_frame(model.with_normal_field(nf), data, centre)
    n = data.normal_world.astype(np.float64)
    t = offset[None, None] - (n * offset).sum(-1, keepdims=True) * n
    n_want = np.where(found[..., None], n + t, n)
    n_want /= np.linalg.norm(n_want, axis=-1, keepdims=True)
    v = view_dir_world(data.position_world[covered], centre)
    want = model(torch.from_numpy(v), torch.from_numpy(n_want[covered].astype(np.float32))).detach().numpy()
    np.testing.assert_allclose(got[covered], want, rtol=1e-4, atol=1e-6)
    assert not found[2, 2] and found[covered].sum() >= covered.sum() - 3
    np.testing.assert_array_equal(got[2, 2], render_frame(model, data, centre)[2, 2])
    assert np.all(got[~covered] == 0)
