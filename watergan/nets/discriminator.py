"""The WaterGAN discriminator: DCGAN's, for 48x64 RGB images.

    D(x) = linear(flatten(h4)),  h1 = LReLU(conv1(2x - 1)),  h_k = LReLU(BN(conv_k(h_{k-1}))), k = 2..4

conv_k: 5x5, stride 2, padding 2, channels width * (1, 2, 4, 8) (the paper: 64, 128, 256, 512);
leaky ReLU slope 0.2; batch norm on all but the first convolution; one logit per image. The input
x is a linear image in 0..1, mapped to -1..1 first.
"""

from __future__ import annotations

import torch
from torch import nn


class Discriminator(nn.Module):
    """DCGAN discriminator; ``width`` is the channel count of the first convolution."""

    def __init__(self, width: int = 64, image_hw: tuple[int, int] = (48, 64)) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        channels_in, h, w = 3, *image_hw
        for k in range(4):
            channels_out = width * 2**k
            layers.append(nn.Conv2d(channels_in, channels_out, 5, stride=2, padding=2))
            if k > 0:
                layers.append(nn.BatchNorm2d(channels_out))
            layers.append(nn.LeakyReLU(0.2))
            channels_in, h, w = channels_out, (h + 1) // 2, (w + 1) // 2
        self.features = nn.Sequential(*layers)
        self.logit = nn.Linear(channels_in * h * w, 1)
        for module in self.modules():  # DCGAN initialisation: N(0, 0.02) weights, BN scale N(1, 0.02)
            if isinstance(module, nn.Conv2d | nn.Linear):
                nn.init.normal_(module.weight, 0.0, 0.02)
                nn.init.zeros_(module.bias)
            elif isinstance(module, nn.BatchNorm2d):
                nn.init.normal_(module.weight, 1.0, 0.02)
                nn.init.zeros_(module.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B,3,H,W) linear images in 0..1 -> (B,) logits (real > 0)."""
        return self.logit(self.features(2.0 * x - 1.0).flatten(1)).squeeze(1)
