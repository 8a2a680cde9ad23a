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
    with pytest.raises(DamcapError, match="width and depth"):
        DamArchitecture(width=0)
    with pytest.raises(DamcapError, match="unknown DAM input encoding"):
        DamArchitecture(encoding="xyz")  # type: ignore[arg-type]
    with pytest.raises(DamcapError, match="radiance scale"):
        DeepAppearanceMap(DamArchitecture(), radiance_scale=math.nan)


def test_tolerances_defined_per_dtype():
    assert TOL[torch.float16] > TOL[torch.float32] > TOL[torch.float64]
