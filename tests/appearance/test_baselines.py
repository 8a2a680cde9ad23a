"""RM and RM++ on cases with a known answer."""

from __future__ import annotations

import numpy as np
import pytest

from damcap.appearance.baselines import ReflectanceMap, nearest_source, rm_oracle, rm_plus_plus
from damcap.appearance.views import ViewData
from damcap.appearance.evaluate import score_view
from damcap.appearance.pixels import normal_cam
from damcap.common.capture_folder import FrameData
from damcap.common.cameras import focal_px_from_fov, orbit_world_from_cam, pixel_rays_world
from damcap.synth.closed_form import intersect_sphere


def sphere_view(name, world_from_cam, shade, res=40):
    """A sphere seen by a camera, coloured by shade(n_cam, n_world)."""
    f = focal_px_from_fov(40, res)
    o, d = pixel_rays_world(world_from_cam, f, f, res / 2, res / 2, res, res)
    hit, p, n = intersect_sphere(o, d)
    nc = normal_cam(n, world_from_cam)
    rgb = np.where(hit[..., None], shade(nc, n), 0).astype(np.float32)
    data = FrameData(rgb, np.where(hit[..., None], n, 0).astype(np.float32), p.astype(np.float32), hit.astype(np.float32))
    return ViewData(name, data, world_from_cam)


def headlight(nc, nw):
    # radiance depends on the camera-space normal only: RM++ is exact up to normal quantisation
    return np.stack([0.5 + 0.5 * nc[..., 0], 0.5 + 0.5 * nc[..., 1], np.clip(nc[..., 2], 0, 1)], -1)


def test_rm_plus_plus_reproduces_view_dependent_headlight():
    cams = orbit_world_from_cam(8, 4.0, 20.0)
    views = [sphere_view(f"v{i}", m, headlight) for i, m in enumerate(cams)]
    preds = rm_plus_plus(views[:4], views[4:])
    for t, p in zip(views[4:], preds):
        fg = t.data.coverage > 0.5
        assert np.abs(p[fg] - t.data.radiance_lin[fg]).mean() < 0.02
        assert score_view(t, p) < 0.01


def test_nearest_source_and_self_exclusion():
    cams = orbit_world_from_cam(8, 4.0, 0.0)
    views = [sphere_view(f"v{i}", m, headlight, res=8) for i, m in enumerate(cams)]
    assert nearest_source(views[2], views[:4], exclude_same=False) == 2
    assert nearest_source(views[2], views[:4], exclude_same=True) in (1, 3)
    with pytest.raises(ValueError):
        nearest_source(views[0], views[:1], exclude_same=True)


def test_lookup_copies_the_best_cosine_pixel_without_interpolation():
    cam = orbit_world_from_cam(1, 4.0, 0.0)[0]
    src = sphere_view("s", cam, lambda nc, nw: np.repeat(nc[..., 2:3], 3, -1))
    out = ReflectanceMap(src).lookup(src)
    fg = src.data.coverage > 0.5
    np.testing.assert_array_equal(out[fg], src.data.radiance_lin[fg])
    assert set(np.unique(out[fg])) <= set(np.unique(src.data.radiance_lin[fg]))


def test_rm_oracle_picks_the_one_right_source():
    cams = orbit_world_from_cam(6, 4.0, 10.0)
    truth = [sphere_view(f"v{i}", m, headlight) for i, m in enumerate(cams)]
    # sources 0, 1, 3 are corrupted (scaled colours); source 2 is the only correct one
    wrong = lambda nc, nw: 0.3 * headlight(nc, nw)[..., ::-1]  # noqa: E731
    sources = [truth[2] if i == 2 else sphere_view(f"s{i}", cams[i], wrong) for i in range(4)]
    preds, chosen, per_source = rm_oracle(sources, truth[4:], score_view)
    assert chosen == "v2" and min(per_source, key=per_source.get) == "v2" and len(per_source) == 4
    for t, p in zip(truth[4:], preds):
        assert score_view(t, p) < 0.01


def test_rm_same_view_never_copies_itself():
    cams = orbit_world_from_cam(4, 4.0, 10.0)
    views = [sphere_view(f"v{i}", m, lambda nc, nw: np.repeat(0.5 + 0.5 * nw[..., :1], 3, -1)) for i, m in enumerate(cams)]
    preds, _, _ = rm_oracle(views, views, score_view)
    for t, p in zip(views, preds):
        assert score_view(t, p) > 1e-3  # a self-copy would score exactly 0
    preds = rm_plus_plus(views, views)
    assert all(score_view(t, p) > 1e-3 for t, p in zip(views, preds))
