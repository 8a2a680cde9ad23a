"""The output layer solved in closed form: the features and layout it works on, one step against an
independent least-squares solve, and recovery of a known output layer."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, dam_forward, encode_inputs
from damcap.appearance.pixels import PixelSamples
from damcap.appearance.readout import irls_step, l1_cost, last_hidden, output_layer, solve_output_layer, with_output_layer

ARCHS = [DamArchitecture(), DamArchitecture(bias=True), DamArchitecture(width=8, separable=True), DamArchitecture(width=6, depth=2, activation="softplus")]


def _samples(n: int, seed: int, radiance: torch.Tensor | None = None) -> PixelSamples:
    g = torch.Generator().manual_seed(seed)
    v = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    rad = torch.rand(n, 3, generator=g) if radiance is None else radiance
    return PixelSamples(v, nrm, rad, torch.rand(n, generator=g) + 0.5, torch.zeros(n, dtype=torch.int64))


@pytest.mark.parametrize("arch", ARCHS)
def test_the_dam_is_softplus_of_its_output_layer_on_the_last_hidden_features(arch):
    flat = DeepAppearanceMap(arch, 1.0, generator=torch.Generator().manual_seed(0)).get_flat_weights().double()
    if arch.bias:
        flat = flat + 0.1  # non-zero biases
    s = _samples(50, 1)
    x = encode_inputs(s.view_dir_world, s.normal_world, arch.encoding).double()
    h, w = last_hidden(flat, arch, x), output_layer(flat, arch)
    assert h.shape == (50, arch.width + arch.bias) and w.shape == (3, arch.width + arch.bias)
    torch.testing.assert_close(torch.nn.functional.softplus(h @ w.T), dam_forward(flat, x, arch))


@pytest.mark.parametrize("arch", ARCHS)
def test_with_output_layer_replaces_the_output_layer_alone(arch):
    flat = torch.arange(arch.num_weights, dtype=torch.float32)
    assert torch.equal(with_output_layer(flat, arch, output_layer(flat, arch)), flat)
    new = with_output_layer(flat, arch, torch.full((3, arch.width + arch.bias), -1.0))
    n_out = 3 * arch.width + (3 if arch.bias else 0)
    assert torch.equal(new[:-n_out], flat[:-n_out]) and bool((new[-n_out:] == -1).all())
    assert torch.equal(output_layer(new, arch), torch.full((3, arch.width + arch.bias), -1.0))
    assert flat[-1] == arch.num_weights - 1  # the input is not modified


def test_one_step_is_the_damped_weighted_gauss_newton_solution():
    """Reference: numpy's least squares on rows scaled by sqrt(IRLS weight), per channel, with the
    Levenberg rows sqrt(damping x mean diagonal) I appended."""
    g = torch.Generator().manual_seed(3)
    h = torch.randn(200, 5, generator=g, dtype=torch.float64)
    w = torch.randn(3, 5, generator=g, dtype=torch.float64)
    y = torch.rand(200, 3, generator=g, dtype=torch.float64) * 2
    wt = torch.rand(200, generator=g, dtype=torch.float64) + 0.1
    got = irls_step(h, w, y, wt, damping=0.01, floor=1e-3)
    for c in range(3):
        z = (h @ w[c]).numpy()
        r = y[:, c].numpy() - np.logaddexp(0, z)
        a = wt.numpy() / np.maximum(np.abs(r), 1e-3)
        j = (1 / (1 + np.exp(-z)))[:, None] * h.numpy()
        lam = 0.01 * np.mean(np.diag(j.T @ (a[:, None] * j)))
        rows = np.vstack([np.sqrt(a)[:, None] * j, np.sqrt(lam) * np.eye(5)])
        rhs = np.concatenate([np.sqrt(a) * r, np.zeros(5)])
        delta = np.linalg.lstsq(rows, rhs, rcond=None)[0]
        np.testing.assert_allclose(got[c].numpy(), w[c].numpy() + delta, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("arch", [DamArchitecture(), DamArchitecture(bias=True)])
def test_the_solve_recovers_a_known_output_layer_and_keeps_the_hidden_layers(arch):
    truth = DeepAppearanceMap(arch, 2.0, generator=torch.Generator().manual_seed(5))
    s = _samples(3000, 6)
    x = encode_inputs(s.view_dir_world, s.normal_world, arch.encoding)
    radiance = 2.0 * dam_forward(truth.get_flat_weights(), x, arch).detach()  # in units of the scale 2
    s = _samples(3000, 6, radiance)
    w_true = output_layer(truth.get_flat_weights(), arch)
    start = DeepAppearanceMap(arch, 2.0, with_output_layer(truth.get_flat_weights(), arch,
                                                            w_true + 0.3 * torch.randn(w_true.shape, generator=torch.Generator().manual_seed(7))))
    res = solve_output_layer(start, s, iterations=30, max_samples=3000)
    assert res.l1_after < 1e-3 * res.l1_before and 1 <= res.iterations <= 30
    torch.testing.assert_close(output_layer(res.model.get_flat_weights(), arch), w_true, atol=2e-3, rtol=0)
    n_out = w_true.numel()
    assert torch.equal(res.model.get_flat_weights()[:-n_out], start.get_flat_weights()[:-n_out])
    assert res.model.radiance_scale == 2.0


def test_the_solve_never_raises_the_cost_and_zero_iterations_keep_the_model():
    model = DeepAppearanceMap(DamArchitecture(), 1.0, generator=torch.Generator().manual_seed(8))
    s = _samples(2000, 9)  # radiance no DAM of these hidden layers reproduces exactly
    previous = None
    for k in (1, 2, 5):
        res = solve_output_layer(model, s, k, max_samples=1000)
        assert res.l1_after <= res.l1_before and res.iterations <= k
        assert previous is None or res.l1_after <= previous  # more iterations: never a higher cost
        previous = res.l1_after
    again = solve_output_layer(model, s, 5, max_samples=1000)  # the subset is seeded
    assert torch.equal(again.model.get_flat_weights(), res.model.get_flat_weights())
    kept = solve_output_layer(model, s, 0, max_samples=1000)
    assert kept.model is model and kept.iterations == 0
    # the reported cost is the cost of the returned layer on the solve's samples
    x = encode_inputs(s.view_dir_world, s.normal_world, "nr").double()
    flat = res.model.get_flat_weights().double()
    full = l1_cost(last_hidden(flat, model.arch, x), output_layer(flat, model.arch), s.radiance_lin.double(), s.weight.double())
    assert abs(full - res.l1_after) < 0.05 * res.l1_after  # a 1000-sample subset of 2000: close to the full cost
