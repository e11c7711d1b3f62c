"""Forward scattering: small-angle blur of the direct signal that widens with range."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..effect import RANK_BLUR, Effect
from ..params import Param
from ..registry import register

_MAX_SIGMA_PX = 32.0


def gaussian_blur(image: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur with reflected borders; sigma in pixels."""
    radius = max(1, int(math.ceil(3.0 * sigma_px)))
    x = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device)
    k = torch.exp(-0.5 * (x / sigma_px) ** 2)
    k = k / k.sum()
    c = image.shape[1]
    pad_h, pad_w = min(radius, image.shape[-2] - 1), min(radius, image.shape[-1] - 1)
    out = F.pad(image, (pad_w, pad_w, 0, 0), mode="reflect")
    out = F.conv2d(out, k[radius - pad_w: radius + pad_w + 1].view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    out = F.pad(out, (0, 0, pad_h, pad_h), mode="reflect")
    return F.conv2d(out, k[radius - pad_h: radius + pad_h + 1].view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)


def forward_scatter_blur(direct: torch.Tensor, range_m: torch.Tensor, mix: torch.Tensor,
                         sigma_frac_per_m: torch.Tensor, width_px: int) -> torch.Tensor:
    """D' = (1 - m) D + m (G_sigma(r) * D), sigma(r) = k r W pixels.

    m is the scattered fraction (0..1), k (``sigma_frac_per_m``) the blur width as a fraction of the
    image width W per metre of range. The spatially varying blur is the linear interpolation in
    sigma between blurs at fixed widths 0, 1, 2, 4, ... 32 px (differentiable in k and m).
    """
    sigma = (sigma_frac_per_m * width_px * range_m).clamp(0.0, _MAX_SIGMA_PX)
    levels = [0.0] + [2.0 ** i for i in range(int(math.log2(_MAX_SIGMA_PX)) + 1)]
    top = float(sigma.max().detach())
    used = [s for i, s in enumerate(levels) if i == 0 or levels[i - 1] <= top]
    spread = torch.zeros_like(direct)
    for i, s in enumerate(used):
        left = used[i - 1] if i > 0 else s - 1.0
        right = used[i + 1] if i + 1 < len(used) else s + 1.0
        hat = torch.minimum((sigma - left) / (s - left), (right - sigma) / (right - s)).clamp(0.0, 1.0)
        spread = spread + hat * (direct if s == 0.0 else gaussian_blur(direct, s))
    return (1.0 - mix) * direct + mix * spread


@register
class ForwardScatter(Effect):
    name = "forward_scatter"
    summary = "blur of the direct signal whose width grows with range, mixed with the unblurred signal"
    signature = "spatial frequency: fine texture loses contrast with range, edges soften"
    axis = "spatial_frequency"
    rank = RANK_BLUR
    simulation_params = {"mix": 0.4, "sigma_frac_per_m": 0.004}
    needs_image = True
    params = (
        Param("mix", 0.3, 0.0, 1.0, "", "fraction of the direct signal that is forward scattered"),
        Param("sigma_frac_per_m", 0.003, 0.0, 0.02, "1/m", "blur sigma per metre, as a fraction of image width"),
    )
    neutral = {"mix": 0.0, "sigma_frac_per_m": 0.003}

    def forward(self, state):
        like = state.direct
        out = forward_scatter_blur(state.direct, state.range_m, self.param("mix", like),
                                   self.param("sigma_frac_per_m", like), state.direct.shape[-1])
        return state.replace(direct=out)
