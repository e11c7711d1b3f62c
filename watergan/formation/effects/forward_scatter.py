"""Forward scattering: small-angle blur of the direct signal that widens with range."""

from __future__ import annotations

import math

import torch

from ...imaging import gaussian_blur
from ..effect import RANK_BLUR, Effect
from ..params import Param
from ..registry import register

_MAX_SIGMA_PX = 32.0


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
