"""The output layer solved in closed form: the features and layout it works on, one step against an
independent least-squares solve, and recovery of a known output layer. The first and output layers
solved together: the Jacobian against autograd's, one step against an independent least-squares
solve (with and without the prior), recovery of known first and output layers, and the prior's pull."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, dam_forward, encode_inputs
from damcap.appearance.pixels import PixelSamples
from damcap.appearance.readout import (first_layer_entries, first_layer_size, irls_step, joint_jacobian, joint_step, l1_cost, last_hidden,
                                      output_layer, solve_first_and_output_layers, solve_output_layer, with_first_layer, with_output_layer)

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


# --------------------------------------------------------------------------------------------
# the first and output layers together
# --------------------------------------------------------------------------------------------

def _pre_softplus(flat: torch.Tensor, arch: DamArchitecture, x: torch.Tensor) -> torch.Tensor:
    """The DAM's output before its softplus, by dam_forward (softplus inverted where it is stable)."""
    y = dam_forward(flat, x, arch)
    return torch.log(torch.expm1(y))


@pytest.mark.parametrize("arch", ARCHS + [DamArchitecture(width=6, depth=3, activation="shifted_softplus", bias=True)])
def test_the_joint_jacobian_is_autograds(arch):
    """dz/d(first layer's stored weights, then biases) against torch.func.jacrev of dam_forward's
    output through the flat weights (so the flat layout, separable blocks included, is checked too),
    and the output layer's derivative h."""
    g = torch.Generator().manual_seed(11)
    flat = DeepAppearanceMap(arch, 1.0, generator=g).get_flat_weights().double() + (0.05 if arch.bias else 0.0)
    s = _samples(7, 12)
    x = encode_inputs(s.view_dir_world, s.normal_world, arch.encoding).double()
    z, jac, h = joint_jacobian(flat, arch, x)
    q = first_layer_size(arch)
    assert jac.shape == (7, 3, q) and q == arch.layer_weight_counts[0] + (arch.width if arch.bias else 0)
    torch.testing.assert_close(z, _pre_softplus(flat, arch, x))
    ref = torch.func.jacrev(lambda w: _pre_softplus(w, arch, x))(flat)  # (7, 3, P)
    torch.testing.assert_close(jac, ref[..., :q])
    torch.testing.assert_close(h, last_hidden(flat, arch, x))


@pytest.mark.parametrize("arch", ARCHS)
def test_with_first_layer_replaces_the_first_layer_alone(arch):
    flat = torch.arange(arch.num_weights, dtype=torch.float32)
    q = first_layer_size(arch)
    assert torch.equal(with_first_layer(flat, arch, flat[:q]), flat)
    new = with_first_layer(flat, arch, torch.full((q,), -1.0))
    assert bool((new[:q] == -1).all()) and torch.equal(new[q:], flat[q:])
    rows, cols = first_layer_entries(arch)
    w0 = torch.zeros(arch.layer_shapes[0])
    w0[rows, cols] = 1.0
    assert int(w0.sum()) == arch.layer_weight_counts[0] == len(set(zip(rows.tolist(), cols.tolist())))  # each stored entry once


def test_one_joint_step_is_the_damped_weighted_gauss_newton_solution():
    """Reference: numpy's least squares on the full Jacobian [sigmoid(z) jac_first, sigmoid(z) h in
    channel c's block], rows scaled by sqrt(IRLS weight), with the prior's rows sqrt(6 mu sum w) I
    (against sqrt(6 mu sum w) (theta_0 - theta)) and then the Levenberg rows appended."""
    g = torch.Generator().manual_seed(13)
    n, q, f = 60, 4, 3
    jac = torch.randn(n, 3, q, generator=g, dtype=torch.float64)
    h = torch.randn(n, f, generator=g, dtype=torch.float64)
    z = torch.randn(n, 3, generator=g, dtype=torch.float64)
    y = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2
    wt = torch.rand(n, generator=g, dtype=torch.float64) + 0.1
    offset = torch.randn(q + 3 * f, generator=g, dtype=torch.float64)
    for prior in (0.0, 0.02):
        got = joint_step(jac, h, z, y, wt, damping=0.01, prior=prior, offset=offset, floor=1e-3).numpy()
        zz = z.numpy()
        s = 1 / (1 + np.exp(-zz))
        r = y.numpy() - np.logaddexp(0, zz)
        a = wt.numpy()[:, None] / np.maximum(np.abs(r), 1e-3)
        rows = np.zeros((n, 3, q + 3 * f))
        rows[..., :q] = s[..., None] * jac.numpy()
        for c in range(3):
            rows[:, c, q + c * f:q + (c + 1) * f] = s[:, c, None] * h.numpy()
        j = rows.reshape(3 * n, -1)
        aa, rr = a.reshape(-1), r.reshape(-1)
        mu = 6 * prior * wt.numpy().sum()
        normal = j.T @ (aa[:, None] * j) + mu * np.eye(q + 3 * f)
        lam = 0.01 * np.mean(np.diag(normal))
        stack = np.vstack([np.sqrt(aa)[:, None] * j, np.sqrt(mu) * np.eye(q + 3 * f), np.sqrt(lam) * np.eye(q + 3 * f)])
        rhs = np.concatenate([np.sqrt(aa) * rr, -np.sqrt(mu) * offset.numpy(), np.zeros(q + 3 * f)])
        np.testing.assert_allclose(got, np.linalg.lstsq(stack, rhs, rcond=None)[0], rtol=1e-7, atol=1e-10)


@pytest.mark.parametrize("arch", [DamArchitecture(width=8, depth=2), DamArchitecture(width=8, depth=2, bias=True),
                                  DamArchitecture(width=8, depth=2, separable=True)])
def test_the_joint_solve_recovers_known_first_and_output_layers_and_keeps_the_middle(arch):
    """Radiance from a DAM; the start has its first and output layers disturbed: the solve brings
    the cost to near zero and changes nothing else."""
    truth = DeepAppearanceMap(arch, 2.0, generator=torch.Generator().manual_seed(15))
    s = _samples(3000, 16)
    x = encode_inputs(s.view_dir_world, s.normal_world, arch.encoding)
    s = _samples(3000, 16, 2.0 * dam_forward(truth.get_flat_weights(), x, arch).detach())
    q, flat = first_layer_size(arch), truth.get_flat_weights()
    g = torch.Generator().manual_seed(17)
    w_out = output_layer(flat, arch)
    start_flat = with_output_layer(with_first_layer(flat, arch, flat[:q] + 0.15 * torch.randn(q, generator=g)), arch,
                                   w_out + 0.15 * torch.randn(w_out.shape, generator=g))
    start = DeepAppearanceMap(arch, 2.0, start_flat)
    res = solve_first_and_output_layers(start, s, iterations=40, max_samples=3000, dtype=torch.float64)
    assert res.l1_after < 0.02 * res.l1_before and 1 <= res.iterations <= 40
    n_out = w_out.numel()
    assert torch.equal(res.model.get_flat_weights()[q:-n_out], start_flat[q:-n_out])  # the middle layers as given
    assert res.model.radiance_scale == 2.0


def test_the_joint_solve_never_raises_the_cost_and_the_prior_holds_it_near_the_start():
    model = DeepAppearanceMap(DamArchitecture(width=16, depth=3), 1.0, generator=torch.Generator().manual_seed(18))
    s = _samples(2000, 19)  # radiance no DAM reproduces exactly
    start = model.get_flat_weights()
    distances = []
    for prior in (0.0, 1e-3, 1e-1, 1e3):
        res = solve_first_and_output_layers(model, s, 5, max_samples=1000, prior=prior)
        assert res.l1_after <= res.l1_before and res.iterations <= 5
        distances.append(float((res.model.get_flat_weights() - start).norm()))
    assert distances[0] > distances[1] > distances[2] > distances[3]  # a stronger prior, a nearer solution
    assert distances[3] < 1e-3 * distances[0]
    again = solve_first_and_output_layers(model, s, 5, max_samples=1000)  # the subset is seeded
    assert torch.equal(again.model.get_flat_weights(), solve_first_and_output_layers(model, s, 5, max_samples=1000).model.get_flat_weights())
    kept = solve_first_and_output_layers(model, s, 0, max_samples=1000)
    assert kept.model is model and kept.iterations == 0


@pytest.mark.parametrize("case", ["one sample", "zero weights", "black target"])
def test_the_joint_solve_at_the_extremes_returns_a_finite_dam_never_worse(case):
    """288 unknowns from one pixel (the damping keeps the solve finite), pixels that do not count
    (nothing to lower: the model is kept), and an all-black capture."""
    model = DeepAppearanceMap(DamArchitecture(), 1.0, generator=torch.Generator().manual_seed(21))
    s = _samples(1 if case == "one sample" else 500, 22, torch.zeros(500, 3) if case == "black target" else None)
    if case == "zero weights":
        s = PixelSamples(s.view_dir_world, s.normal_world, s.radiance_lin, torch.zeros(500), s.frame_index)
    res = solve_first_and_output_layers(model, s, 5, max_samples=2048, prior=1e-4)
    assert torch.isfinite(res.model.get_flat_weights()).all()
    assert res.l1_after <= res.l1_before or (case == "zero weights" and res.model is model)
    if case == "zero weights":
        assert res.model is model and res.iterations == 0
    if case == "black target":
        assert res.l1_after < 0.5 * res.l1_before


@pytest.mark.parametrize("solve", [solve_output_layer, solve_first_and_output_layers])
def test_the_solves_refuse_a_dam_with_surface_factors(solve):
    model = DeepAppearanceMap(DamArchitecture(width=4, depth=1), 1.0).with_spatial(object())  # any spatial factor
    with pytest.raises(ValueError, match="plain DAM"):
        solve(model, _samples(10, 20), 1, 10)
