"""The optional adversarial cost of the fit (Maximov et al. 2019, Sec. 3.2; alpha = 0.001).

An encoder-style discriminator sees image patches: real photos vs the same patches re-synthesised
by the DAM. Patches are tone-mapped with x / (1 + x) so highlights do not dominate.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class PatchDiscriminator(nn.Module):
    """(B, 3, P, P) tone-mapped patches -> (B,) real/fake logits; P a multiple of 8."""

    def __init__(self, channels: int = 16) -> None:
        super().__init__()
        c = channels
        self.net = nn.Sequential(
            nn.Conv2d(3, c, 4, 2, 1), nn.LeakyReLU(0.2),
            nn.Conv2d(c, 2 * c, 4, 2, 1), nn.LeakyReLU(0.2),
            nn.Conv2d(2 * c, 4 * c, 4, 2, 1), nn.LeakyReLU(0.2),
            nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(4 * c, 1),
        )

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        return self.net(patches / (1 + patches)).squeeze(-1)


def discriminator_loss(d: PatchDiscriminator, real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
    """Non-saturating GAN loss of the discriminator (fake is detached)."""
    lr, lf = d(real), d(fake.detach())
    return F.binary_cross_entropy_with_logits(lr, torch.ones_like(lr)) + F.binary_cross_entropy_with_logits(lf, torch.zeros_like(lf))


def generator_loss(d: PatchDiscriminator, fake: torch.Tensor) -> torch.Tensor:
    """Non-saturating GAN loss of the generator (the DAM)."""
    lf = d(fake)
    return F.binary_cross_entropy_with_logits(lf, torch.ones_like(lf))
