"""The adversarial cost's discriminator and losses: shapes, tone mapping, closed-form losses at logit 0."""

from __future__ import annotations

import math

import pytest
import torch

from damcap.appearance.adversarial import PatchDiscriminator, discriminator_loss, generator_loss


def _zero_logit(d: PatchDiscriminator) -> PatchDiscriminator:
    last = d.net[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
    return d


@pytest.mark.parametrize("p", [8, 16, 40])
def test_logits_per_patch(p):
    torch.manual_seed(0)
    d = PatchDiscriminator(channels=4)
    out = d(torch.rand(5, 3, p, p))
    assert out.shape == (5,) and torch.isfinite(out).all()


def test_patches_are_tone_mapped_before_the_network():
    torch.manual_seed(1)
    d = PatchDiscriminator(channels=4)
    x = torch.rand(3, 3, 16, 16) * 50
    with torch.no_grad():
        assert torch.allclose(d(x), d.net(x / (1 + x)).squeeze(-1), atol=1e-6)
        # a highlight a million times brighter saturates instead of dominating
        assert torch.allclose(d(torch.full((1, 3, 16, 16), 1e6)), d.net(torch.ones(1, 3, 16, 16)).squeeze(-1), atol=1e-5)


def test_losses_at_logit_zero_are_ln2():
    d = _zero_logit(PatchDiscriminator(channels=4))
    real, fake = torch.rand(4, 3, 16, 16), torch.rand(4, 3, 16, 16)
    assert discriminator_loss(d, real, fake).item() == pytest.approx(2 * math.log(2), rel=1e-6)
    assert generator_loss(d, fake).item() == pytest.approx(math.log(2), rel=1e-6)


def test_the_discriminator_loss_does_not_reach_the_generator():
    torch.manual_seed(2)
    d = PatchDiscriminator(channels=4)
    real = torch.rand(2, 3, 16, 16)
    fake = torch.rand(2, 3, 16, 16, requires_grad=True)
    discriminator_loss(d, real, fake).backward()
    assert fake.grad is None and d.net[0].weight.grad is not None
    generator_loss(d, fake).backward()
    assert fake.grad is not None and fake.grad.abs().sum() > 0


def test_a_confident_discriminator_has_a_small_loss():
    """Logits +20 on real, -20 on fake: loss 2 log(1 + e^-20) ~ 4e-9; the generator's is ~20."""
    d = _zero_logit(PatchDiscriminator(channels=4))
    with torch.no_grad():
        d.net[-1].bias.fill_(20.0)
    real = torch.rand(2, 3, 8, 8)
    assert generator_loss(d, real).item() == pytest.approx(math.log1p(math.exp(-20)), rel=1e-3)
    with torch.no_grad():
        d.net[-1].bias.fill_(-20.0)
    assert generator_loss(d, real).item() == pytest.approx(20.0, rel=1e-6)
    assert discriminator_loss(d, real, real).item() == pytest.approx(20.0 + math.log1p(math.exp(-20)), rel=1e-6)
