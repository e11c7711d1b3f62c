"""Learned backscatter from depth and noise (WaterGAN G-II)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..effect import RANK_SCATTER, Effect
from ..params import Param
from ..registry import register


def conv_backscatter(z: torch.Tensor, range_m: torch.Tensor, depth_scale_m: float, project: nn.Linear,
                     convs: nn.ModuleList, norm: nn.BatchNorm2d, mask_hw: tuple[int, int]) -> torch.Tensor:
    """B = LeakyReLU_0.2(BN([conv5x5_c([M(z), r / r_max]) for c in R, G, B])).

    z (B,Z) noise; M(z) = reshape(project(z)) a one-channel (h,w) mask; r / r_max the range
    normalised by ``depth_scale_m`` (the survey's maximum altitude), resized to (h,w); three
    independent 5x5 convolutions, one per output channel. Returns the (B,3,h,w) backscatter mask
    in linear radiance; the caller adds it to the image (upsampled bicubically when larger). As in
    the paper, the leaky ReLU lets the mask dip slightly below zero; the generator clamps its output.
    """
    h, w = mask_hw
    mask = project(z).view(-1, 1, h, w)
    depth = F.interpolate(range_m / depth_scale_m, size=(h, w), mode="area")
    x = torch.cat([mask, depth.expand(mask.shape[0], 1, h, w)], dim=1)
    out = torch.cat([conv(x) for conv in convs], dim=1)
    return F.leaky_relu(norm(out), 0.2)


@register
class BackscatterConv(Effect):
    name = "backscatter_conv"
    summary = "learned backscatter: noise z projected to a mask, concatenated with depth, 5x5 conv per channel"
    signature = "range and image position: a smooth veil that grows with depth, any shape the data needs"
    axis = "range"
    rank = RANK_SCATTER
    needs_image = True
    params = (
        Param("z_dim", 100.0, 1.0, 4096.0, "", "length of the noise vector z", learnable=False),
        Param("mask_height", 48.0, 4.0, 4096.0, "px", "height at which the mask is computed", learnable=False),
        Param("mask_width", 64.0, 4.0, 4096.0, "px", "width at which the mask is computed", learnable=False),
        Param("depth_scale_m", 10.0, 0.01, 1e4, "m", "range normaliser: the survey's maximum altitude",
              learnable=False),
    )

    def __init__(self, counts=None, **values) -> None:
        super().__init__(counts, **values)
        z_dim, h, w = (int(round(self.param(n).item())) for n in ("z_dim", "mask_height", "mask_width"))
        self.mask_hw = (h, w)
        self.project = nn.Linear(z_dim, h * w)
        self.convs = nn.ModuleList(nn.Conv2d(2, 1, 5, padding=2) for _ in range(3))
        self.norm = nn.BatchNorm2d(3)

    def make_neutral(self) -> None:
        """Zero convolutions give a zero mask after batch norm and leaky ReLU: the identity."""
        with torch.no_grad():
            for conv in self.convs:
                conv.weight.zero_()
                conv.bias.zero_()

    def forward(self, state):
        z = state.need("z", self.name).to(self.project.weight.dtype)
        mask = conv_backscatter(z, state.range_m.to(z.dtype), self.param("depth_scale_m").item(), self.project,
                                self.convs, self.norm, self.mask_hw)
        if mask.shape[-2:] != state.direct.shape[-2:]:
            mask = F.interpolate(mask, size=state.direct.shape[-2:], mode="bicubic", align_corners=False)
        return state.replace(backscatter=state.backscatter + mask.to(state.dtype))
