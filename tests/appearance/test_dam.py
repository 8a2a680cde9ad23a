"""The DAM: size, flat weights, encodings, outputs at the extremes, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, dam_forward, encode_inputs
from damcap.common.errors import DamcapError
from damcap.common.numerics import safe_normalize
from tests.conftest import TOL


def test_paper_size_is_3360_weights():
    assert DamArchitecture(encoding="vn").num_weights == 3360
    assert DamArchitecture(encoding="nr").num_weights == 3360
    assert DamArchitecture(encoding="vnr").num_weights == 3360 + 3 * 32
    assert DamArchitecture(width=8, depth=2, bias=True, encoding="vn").num_weights == 6 * 8 + 8 + 8 * 8 + 8 + 8 * 3 + 3


def test_flat_weights_round_trip_and_batched_forward():
    arch = DamArchitecture()
    a = DeepAppearanceMap(arch, generator=torch.Generator().manual_seed(0))
    b = DeepAppearanceMap(arch, generator=torch.Generator().manual_seed(1))
    x = torch.randn(50, 6)
    b.set_flat_weights(a.get_flat_weights())
    torch.testing.assert_close(a.forward_normalised(x), b.forward_normalised(x))
    batch = torch.stack([a.get_flat_weights(), 2 * a.get_flat_weights()])
    out = dam_forward(batch, x.expand(2, 50, 6), arch)
    assert out.shape == (2, 50, 3)
    torch.testing.assert_close(out[0], a.forward_normalised(x))
    with pytest.raises(DamcapError, match="expected"):
        a.set_flat_weights(torch.zeros(10))


def test_nr_encoding_is_the_mirror_direction():
    v = safe_normalize(torch.tensor([[1.0, 0.0, 1.0]]))
    n = torch.tensor([[0.0, 0.0, 1.0]])
    x = encode_inputs(v, n, "nr")
    torch.testing.assert_close(x[0, 3:], torch.tensor([-v[0, 0], 0.0, v[0, 2]]))
    # (N, R) carries the same information as (V, N): V = 2 (N.R) N - R
    r = x[:, 3:]
    torch.testing.assert_close(2 * (n * r).sum(-1, keepdim=True) * n - r, v)


@pytest.mark.parametrize("encoding", ["vn", "nr", "vnr"])
def test_output_non_negative_and_finite_at_extremes(encoding):
    model = DeepAppearanceMap(DamArchitecture(encoding=encoding), radiance_scale=1e6)
    n = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, -1.0]]).repeat(3, 1)
    # grazing (n.v = 0), slightly negative (interpolation), exactly along axes, and half precision
    v = torch.cat([torch.tensor([[0.0, 1, 0], [1.0, 0, 0], [0, 1.0, -0.01], [0, 0, -1.0]]),
                   torch.tensor([[1.0, 0, 0]]).repeat(4, 1), torch.tensor([[0.0, 0.0, 1.0]]).repeat(4, 1)])
    out = model(v.half(), n.half())
    assert out.dtype == torch.float32 and torch.isfinite(out).all() and (out >= 0).all()
    big = model.forward_normalised(torch.full((1, model.arch.layer_shapes[0][1]), 1e30))
    assert torch.isfinite(big).all()


def test_gradcheck_float64():
    arch = DamArchitecture(width=4, depth=2, encoding="vn", activation="tanh")
    w = torch.randn(arch.num_weights, dtype=torch.float64, requires_grad=True)
    x = torch.randn(5, 6, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda w: dam_forward(w, x, arch).double(), (w,), eps=1e-6, atol=1e-4)


def test_bad_architecture_is_a_clear_error():
    with pytest.raises(DamcapError, match=r"DAM width must be an integer in \[1, 4096\], got 0"):
        DamArchitecture(width=0)
    with pytest.raises(DamcapError, match="unknown DAM input encoding"):
        DamArchitecture(encoding="xyz")  # type: ignore[arg-type]
    with pytest.raises(DamcapError, match="radiance scale"):
        DeepAppearanceMap(DamArchitecture(), radiance_scale=math.nan)


def test_tolerances_defined_per_dtype():
    assert TOL[torch.float16] > TOL[torch.float32] > TOL[torch.float64]


def _separable(width: int = 8, depth: int = 3, **kw) -> DamArchitecture:
    return DamArchitecture(width=width, depth=depth, separable=True, **kw)


def test_separable_size_counts_only_the_branch_weights():
    # first layer: each unit sees 3 inputs; hidden: two (w/2 x w/2) blocks; output: all w units
    for w, d in ((8, 2), (44, 4), (32, 3)):
        assert _separable(w, d).num_weights == 3 * w + (d - 1) * w * w // 2 + 3 * w
    assert _separable(8, 2, bias=True).num_weights == 3 * 8 + 8 + 8 * 8 // 2 + 8 + 3 * 8 + 3
    assert _separable(44, 4).num_weights <= DamArchitecture().num_weights


@pytest.mark.parametrize("bias", [False, True])
def test_separable_dam_is_a_sum_of_a_normal_term_and_a_mirror_term(bias):
    """softplus^-1 of the output is f(N) + g(R): its mixed difference over (N, R) pairs is 0."""
    arch = _separable(bias=bias, activation="tanh")
    w = torch.randn(arch.num_weights, dtype=torch.float64)
    n1, n2, r1, r2 = torch.randn(4, 20, 3, dtype=torch.float64)
    pre = lambda n, r: torch.log(torch.expm1(dam_forward(w, torch.cat([n, r], -1), arch)))  # noqa: E731
    mixed = pre(n1, r1) - pre(n1, r2) - pre(n2, r1) + pre(n2, r2)
    assert mixed.abs().max() < 1e-9
    assert (pre(n1, r1) - pre(n2, r1)).abs().max() > 1e-3  # both terms are live
    assert (pre(n1, r1) - pre(n1, r2)).abs().max() > 1e-3


def test_separable_dam_batched_gradients_and_init():
    arch = _separable()
    w = torch.randn(arch.num_weights, dtype=torch.float64, requires_grad=True)
    x = torch.randn(5, 6, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda w: dam_forward(w, x, arch).double(), (w,), eps=1e-6, atol=1e-4)
    batch = torch.stack([w.detach(), -w.detach()])
    torch.testing.assert_close(dam_forward(batch, x.expand(2, 5, 6), arch)[1], dam_forward(-w.detach(), x, arch))
    # He-uniform over each unit's own inputs: 3 for the first layer, width/2 for the hidden ones
    init = DeepAppearanceMap(_separable(64, 2), generator=torch.Generator().manual_seed(0)).get_flat_weights()
    first, hidden = init[:64 * 3], init[64 * 3:64 * 3 + 64 * 32]
    assert math.sqrt(6 / 3) * 0.95 < first.abs().max() <= math.sqrt(6 / 3)
    assert math.sqrt(6 / 32) * 0.95 < hidden.abs().max() <= math.sqrt(6 / 32)


def test_separable_needs_nr_and_an_even_width():
    with pytest.raises(DamcapError, match="separable DAM needs the encoding 'nr' and an even width"):
        _separable(encoding="vn")
    with pytest.raises(DamcapError, match="even width, got encoding 'nr', width 7"):
        _separable(width=7)


@pytest.mark.parametrize("arch", [DamArchitecture(encoding="vn"), DamArchitecture(), DamArchitecture(encoding="vnr", bias=True),
                                  DamArchitecture(width=8, separable=True)], ids=["vn", "nr", "vnr-bias", "separable"])
def test_rotated_world_weights_read_the_rotated_world(arch):
    """f'(V, N) = f(R V, R N) for every encoding, one DAM or a batch."""
    from damcap.appearance.dam import rotated_world_weights, init_weights

    g = torch.Generator().manual_seed(0)
    w = torch.stack([init_weights(arch, g) for _ in range(2)])
    axis_angle = torch.tensor([[0.3, -0.5, 0.8], [-0.9, 0.1, 2.2]])  # rotations exp([a]x)
    skew = torch.zeros(2, 3, 3)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -axis_angle[:, 2], axis_angle[:, 1], -axis_angle[:, 0]
    rot = torch.linalg.matrix_exp(skew - skew.transpose(1, 2))
    v, n = safe_normalize(torch.randn(2, 64, 3, generator=g)), safe_normalize(torch.randn(2, 64, 3, generator=g))
    turned = dam_forward(rotated_world_weights(w, arch, rot), encode_inputs(v, n, arch.encoding), arch)
    direct = dam_forward(w, encode_inputs(v @ rot.transpose(1, 2), n @ rot.transpose(1, 2), arch.encoding), arch)
    assert torch.allclose(turned, direct, rtol=1e-4, atol=1e-6)
    one = rotated_world_weights(w[0], arch, rot[0])
    assert torch.allclose(dam_forward(one, encode_inputs(v[0], n[0], arch.encoding), arch), direct[0], rtol=1e-4, atol=1e-6)
