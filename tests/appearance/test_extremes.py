"""Numerical stability at the extremes, property-based (hypothesis): grazing and axis-aligned
geometry, radiance over 12 decades, half precision, black and clipped frames."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, encode_inputs
from damcap.appearance.fit import FitOptions, fit_dam, training_l1
from damcap.appearance.views import radiance_scale_of
from damcap.appearance.metrics import dssim
from damcap.appearance.pixels import PixelSamples

FAST = settings(max_examples=25, deadline=None)
unit = st.floats(-1.0, 1.0, allow_nan=False, width=32)
vec = st.tuples(unit, unit, unit)
scale = st.sampled_from([1e-30, 1e-6, 1.0, 1e6, 1e30])


@FAST
@given(v=vec, n=vec, sv=scale, sn=scale, encoding=st.sampled_from(["vn", "nr", "vnr"]), half=st.booleans())
def test_dam_output_is_finite_and_non_negative_for_any_direction(v, n, sv, sn, encoding, half):
    """Any view and normal (unnormalised, zero, grazing, back-facing, along the axes), at any
    length and in half precision: radiance stays finite and >= 0; encoded inputs stay bounded."""
    model = DeepAppearanceMap(DamArchitecture(encoding=encoding), radiance_scale=1e6, generator=torch.Generator().manual_seed(0))
    vt, nt = torch.tensor([v]) * sv, torch.tensor([n]) * sn
    if half:
        vt, nt = vt.clamp(-6e4, 6e4).half(), nt.clamp(-6e4, 6e4).half()
    x = encode_inputs(vt, nt, encoding)
    assert torch.isfinite(x).all() and x.abs().max() <= 3.0 + 1e-5
    out = model(vt, nt)
    assert out.dtype == torch.float32 and torch.isfinite(out).all() and (out >= 0).all()


@FAST
@given(theta=st.floats(0.0, math.pi / 2 + 0.05), axis=st.sampled_from([0, 1, 2]), sign=st.sampled_from([-1.0, 1.0]))
def test_half_precision_inputs_match_float32_near_grazing(theta, axis, sign):
    """Axis-aligned normals and views from head-on to slightly below the horizon: float16 inputs
    give the float32 result up to half-precision rounding of the inputs."""
    n = torch.zeros(1, 3)
    n[0, axis] = sign
    t = torch.zeros(1, 3)
    t[0, (axis + 1) % 3] = 1.0
    v = math.cos(theta) * n + math.sin(theta) * t
    model = DeepAppearanceMap(DamArchitecture(), generator=torch.Generator().manual_seed(1))
    full, half = model(v, n), model(v.half(), n.half())
    torch.testing.assert_close(half, full, rtol=5e-3, atol=5e-3)


@settings(max_examples=6, deadline=None)
@given(decades=st.integers(0, 12), seed=st.integers(0, 1000))
def test_fit_is_stable_for_radiance_over_twelve_decades(decades, seed):
    """One capture's radiance from 1e-6 up to 1e-6 * 10**decades (<= 1e6): the fit's cost and
    weights stay finite and it learns (its cost falls below that of its start)."""
    g = torch.Generator().manual_seed(seed)
    n = torch.nn.functional.normalize(torch.randn(2048, 3, generator=g), dim=-1)
    v = torch.nn.functional.normalize(n + 0.5 * torch.randn(2048, 3, generator=g), dim=-1)
    base = (n[:, 1:2].clamp_min(0) + 0.05).repeat(1, 3)  # a smooth appearance, known up to scale
    exponent = torch.rand(2048, 1, generator=g) * decades - 6.0  # log10 radiance in [-6, -6 + decades]
    rad = base * 10.0 ** exponent.clamp(max=6.0)
    samples = PixelSamples(v, n, rad.float(), torch.ones(2048), torch.zeros(2048, dtype=torch.int64))
    res = fit_dam(samples, FitOptions(steps=60, holdout_views=0, checkpoint_every=0, seed=seed))
    w = res.model.get_flat_weights()
    assert torch.isfinite(w).all() and math.isfinite(res.model.radiance_scale) and res.model.radiance_scale > 0
    start = DeepAppearanceMap(res.model.arch, radiance_scale_of(rad), generator=torch.Generator().manual_seed(seed))
    assert training_l1(res.model, samples) < training_l1(start, samples)


@FAST
@given(kind=st.sampled_from(["black", "clipped", "tiny", "huge", "random"]), seed=st.integers(0, 100))
def test_dssim_is_finite_and_bounded_for_black_clipped_and_extreme_frames(kind, seed):
    rng = np.random.default_rng(seed)
    cov = np.zeros((24, 24), np.float32)
    cov[4:20, 4:20] = 1.0
    ref = {"black": np.zeros((24, 24, 3)), "clipped": np.full((24, 24, 3), 65504.0), "tiny": rng.random((24, 24, 3)) * 1e-6,
           "huge": rng.random((24, 24, 3)) * 1e6, "random": rng.random((24, 24, 3))}[kind].astype(np.float32)
    for pred in (np.zeros_like(ref), ref, rng.random(ref.shape).astype(np.float32) * 1e6):
        d = dssim(ref, pred, cov)
        assert d is not None and math.isfinite(d) and 0.0 <= d <= 1.0
    assert dssim(ref, ref, cov) == pytest.approx(0.0, abs=1e-4)  # float32 SSIM of identical images: ~6e-6


@FAST
@given(s=st.sampled_from([1e-6, 1e-3, 1.0, 1e3, 1e6]), seed=st.integers(0, 100))
def test_view_directions_do_not_depend_on_the_scene_scale(s, seed):
    """Tiny and huge scenes: scaling every position and camera centre by s leaves V unchanged."""
    from damcap.appearance.pixels import view_dir_world

    rng = np.random.default_rng(seed)
    p = rng.normal(size=(64, 3))
    c = rng.normal(size=3) * 4 + 6
    np.testing.assert_allclose(view_dir_world(p * s, c * s), view_dir_world(p, c), atol=2e-6)


def test_duplicate_cameras_are_harmless_for_the_baselines(small_capture):
    """Two frames from the same camera: RM++ picks the duplicate (distance 0) and reproduces it."""
    import dataclasses

    from damcap.appearance.baselines import rm_plus_plus
    from damcap.appearance.views import load_views
    from damcap.common.capture_folder import read_capture

    views = load_views(read_capture(small_capture), "train")
    twin = dataclasses.replace(views[0], name=views[0].name + "-twin")
    pred = rm_plus_plus([views[1], twin, views[2]], [views[0]])[0]
    assert np.isfinite(pred).all()
    assert dssim(views[0].data.radiance_lin, pred, views[0].data.coverage) < 1e-3
