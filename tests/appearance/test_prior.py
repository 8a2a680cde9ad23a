"""The fit's prior (appearance/prior.py): samples, their weights, and what the prior does to a fit."""

from __future__ import annotations

import numpy as np
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, encode_inputs
from damcap.appearance.fit import FitOptions, fit_dam
from damcap.appearance.pixels import PixelSamples
from damcap.appearance.prior import hemisphere_view_dirs, nearest_distance, prior_samples, unconstrained_weight


def _samples(n: int = 4000, seed: int = 0) -> PixelSamples:
    """Pixels of one view from +z: normals on the upper half of a sphere, view direction +z,
    radiance 1 + n_x (a gradient the DAM can represent)."""
    g = torch.Generator().manual_seed(seed)
    nrm = torch.randn(n, 3, generator=g)
    nrm[:, 2] = nrm[:, 2].abs() + 0.3
    nrm = nrm / nrm.norm(dim=1, keepdim=True)
    view = torch.tensor([[0.0, 0.0, 1.0]]).expand(n, 3).clone()
    rad = (1 + nrm[:, :1]).expand(n, 3).clone()
    return PixelSamples(view_dir_world=view, normal_world=nrm, radiance_lin=rad, weight=torch.ones(n),
                        frame_index=torch.arange(n) % 5)


def test_hemisphere_directions_are_unit_and_face_their_normal():
    n = torch.nn.functional.normalize(torch.randn(5000, 3, generator=torch.Generator().manual_seed(1)), dim=1)
    v = hemisphere_view_dirs(n, torch.Generator().manual_seed(2))
    assert torch.allclose(v.norm(dim=1), torch.ones(5000), atol=1e-5)
    cos = (v * n).sum(1)
    assert bool((cos >= 0).all())
    assert abs(float(cos.mean()) - 0.5) < 0.02  # uniform on a hemisphere: E[cos] = 1/2


def test_nearest_distance_and_weight_against_brute_force():
    g = torch.Generator().manual_seed(0)
    x, ref = torch.randn(300, 6, generator=g), torch.randn(200, 6, generator=g)
    brute = torch.stack([(ref - xi).norm(dim=1).min() for xi in x])
    assert torch.allclose(nearest_distance(x, ref, chunk=7), brute, atol=1e-5)
    w = unconstrained_weight(torch.tensor([0.0, 0.1, 10.0]), 0.1)
    assert float(w[0]) == 0.0 and abs(float(w[1]) - (1 - np.exp(-1))) < 1e-6 and float(w[2]) == 1.0


def test_prior_samples_weigh_unseen_directions_more():
    s = _samples()
    prior = DeepAppearanceMap(DamArchitecture(width=8, depth=2), 2.0, generator=torch.Generator().manual_seed(0))
    p = prior_samples(prior, s, "nr", radiance_scale=2.0, count=3000, sigma=0.25, seed=0)
    assert p.inputs.shape == (3000, 6) and p.target.shape == (3000, 3) and p.weight.shape == (3000,)
    # the targets are the prior's radiance in the fit's unit
    view, normal = p.inputs[:, 3:], p.inputs[:, :3]  # nr: (n, r); r of a unit v about n gives back v
    v = 2 * (view * normal).sum(1, keepdim=True) * normal - view
    assert torch.allclose(p.target, prior(v, normal) / 2.0, atol=1e-4)
    # samples seen from +z (like the training pixels) weigh less than those seen from below the horizon of z
    seen_like = v[:, 2] > 0.95
    unseen = v[:, 2] < 0.0
    assert float(p.weight[seen_like].mean()) < 0.5 * float(p.weight[unseen].mean())
    # same seed, same samples
    q = prior_samples(prior, s, "nr", 2.0, 3000, 0.25, seed=0)
    assert torch.equal(p.inputs, q.inputs) and torch.equal(p.weight, q.weight)


def test_the_prior_decides_where_the_data_say_nothing():
    """Training pixels seen only from +z; a prior that answers 0.25 everywhere. Far from the
    training directions the fit follows the prior with it and not without it."""
    s = _samples()
    # the joint network: a separable one carries the data's f(N) + g(R) into the far directions and
    # follows the prior less there (measured: 0.58 against 1.09 without the prior)
    opts = FitOptions(steps=300, width=16, depth=2, holdout_views=0, checkpoint_every=0, seed=0, separable=False)
    const = DeepAppearanceMap(DamArchitecture(width=8, depth=2), 1.0)
    with torch.no_grad():
        const.weights_flat.zero_()
    p = prior_samples(const, s, "nr", radiance_scale=1.0, count=4000, sigma=0.25, seed=0)
    p.target[:] = 0.25  # the prior's answer
    with_prior = fit_dam(s, opts, prior=p).model
    without = fit_dam(s, opts).model
    g = torch.Generator().manual_seed(5)
    n = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=1)
    v = hemisphere_view_dirs(n, g)
    far = (v[:, 2] < -0.5)
    x_far = encode_inputs(v[far], n[far], "nr")
    scale = with_prior.radiance_scale
    err_with = (with_prior.forward_normalised(x_far) * scale - 0.25 * 1.0).abs().mean()
    err_without = (without.forward_normalised(x_far) * without.radiance_scale - 0.25).abs().mean()
    assert float(err_with) < 0.5 * float(err_without), (float(err_with), float(err_without))
    # where the data speak, both fit them
    x_seen = encode_inputs(s.view_dir_world[:500], s.normal_world[:500], "nr")
    for m in (with_prior, without):
        fit_err = (m.forward_normalised(x_seen) * m.radiance_scale - s.radiance_lin[:500]).abs().mean()
        assert float(fit_err) < 0.1
