"""Safe elementwise math: closed-form values, finite gradients at the singular points, NaN kept."""

from __future__ import annotations

import math

import pytest
import torch

from damcap.common.numerics import EPS, dot, reflect, safe_div, safe_normalize, safe_pow


def test_safe_div_closed_form_and_the_sign_of_the_floor():
    num = torch.tensor([6.0, 1.0, 1.0, 1.0, -3.0])
    den = torch.tensor([3.0, 0.0, -1e-12, 1e-12, -2.0])
    out = safe_div(num, den, eps=0.25)
    # |den| below eps becomes eps with den's sign; 0 counts as positive
    assert out.tolist() == pytest.approx([2.0, 4.0, -4.0, 4.0, 1.5], rel=1e-7)
    assert safe_div(torch.tensor(1.0), torch.tensor(0.0)).item() == pytest.approx(1.0 / EPS, rel=1e-6)


def test_safe_div_broadcasts_and_has_finite_gradients_at_zero():
    num = torch.ones(4, 1, 3)
    den = torch.zeros(1, 5, 3, requires_grad=True)
    out = safe_div(num, den, eps=0.5)
    assert out.shape == (4, 5, 3) and torch.allclose(out, torch.full_like(out, 2.0))
    out.sum().backward()
    assert torch.isfinite(den.grad).all()


def test_safe_div_does_not_hide_nan():
    out = safe_div(torch.tensor([float("nan"), 1.0]), torch.tensor([1.0, float("nan")]))
    assert torch.isnan(out).all()


def test_safe_pow_value_and_gradient_at_zero():
    x = torch.tensor([0.0, 4.0, -1.0], dtype=torch.float64, requires_grad=True)
    y = safe_pow(x, 0.5, eps=1e-6)
    assert y.tolist() == pytest.approx([1e-3, 2.0, 1e-3], rel=1e-9)
    y.sum().backward()
    # d sqrt(x)/dx = 0.5 / sqrt(x) at x = 4; the clamped entries get no gradient, and none is inf
    assert x.grad.tolist() == pytest.approx([0.0, 0.25, 0.0], abs=1e-12)
    assert torch.isnan(safe_pow(torch.tensor(float("nan")), 2.0))


def test_safe_normalize_unit_length_zero_vector_and_batch_shapes():
    v = torch.tensor([[3.0, 0.0, 4.0], [0.0, 0.0, 0.0], [0.0, -2.0, 0.0]], requires_grad=True)
    u = safe_normalize(v)
    assert torch.allclose(u.detach(), torch.tensor([[0.6, 0.0, 0.8], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), atol=1e-7)
    u.sum().backward()
    assert torch.isfinite(v.grad).all()
    # any leading shape, and along another axis
    b = torch.randn(2, 3, 5, 3, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(safe_normalize(b).norm(dim=-1), torch.ones(2, 3, 5), atol=1e-6)
    assert torch.allclose(safe_normalize(b, dim=1).norm(dim=1), torch.ones(2, 5, 3), atol=1e-6)
    assert torch.isnan(safe_normalize(torch.tensor([float("nan"), 1.0, 0.0]))).all()


def test_safe_normalize_gradcheck():
    v = torch.randn(6, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1), requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: safe_normalize(x, eps=1e-12), (v,))


def test_dot_einsum_path_equals_the_sum_and_broadcasts():
    g = torch.Generator().manual_seed(2)
    a, b = torch.randn(7, 3, generator=g), torch.randn(7, 3, generator=g)
    assert torch.allclose(dot(a, b), (a * b).sum(-1, keepdim=True), atol=1e-6)
    assert dot(a, b, keepdim=False).shape == (7,)
    # broadcasting (shapes differ) and another axis take the plain path
    assert torch.allclose(dot(a, b[:1]), (a * b[:1]).sum(-1, keepdim=True), atol=1e-6)
    assert torch.allclose(dot(a, b, dim=0, keepdim=False), (a * b).sum(0), atol=1e-6)
    assert dot(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([4.0, -5.0, 6.0])).item() == pytest.approx(12.0)


def test_reflect_closed_form_unit_length_and_gradcheck():
    s = 1 / math.sqrt(2)
    r = reflect(torch.tensor([s, 0.0, s]), torch.tensor([0.0, 0.0, 1.0]))
    assert r.tolist() == pytest.approx([-s, 0.0, s], abs=1e-7)
    # head-on view reflects onto itself; reflecting twice is the identity
    n = torch.tensor([0.0, 1.0, 0.0])
    assert reflect(n, n).tolist() == pytest.approx([0.0, 1.0, 0.0])
    g = torch.Generator().manual_seed(3)
    v = safe_normalize(torch.randn(10, 3, dtype=torch.float64, generator=g))
    nn_ = safe_normalize(torch.randn(10, 3, dtype=torch.float64, generator=g))
    assert torch.allclose(reflect(reflect(v, nn_), nn_), v, atol=1e-12)
    assert torch.allclose(reflect(v, nn_).norm(dim=-1), torch.ones(10, dtype=torch.float64), atol=1e-12)
    assert torch.autograd.gradcheck(reflect, (v.clone().requires_grad_(), nn_.clone().requires_grad_()))
