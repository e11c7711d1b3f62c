"""Attenuation of the direct signal along the scene-to-camera path (WaterGAN G-I)."""

from __future__ import annotations

import torch

from ..effect import RANK_WATER, Effect
from ..params import Param
from ..registry import register


def attenuate(direct: torch.Tensor, range_m: torch.Tensor, eta_per_m: torch.Tensor) -> torch.Tensor:
    """D_c = J_c * exp(-eta_c * r).

    direct J (B,3,H,W, linear radiance), range r (B,1,H,W, metres), eta (3,) per-channel
    attenuation coefficient in 1/m. Returns the attenuated direct signal D (same units as J).
    """
    return direct * torch.exp(-eta_per_m.view(1, 3, 1, 1) * range_m)


@register
class Attenuation(Effect):
    name = "attenuation"
    summary = "direct signal decays exponentially with range, per channel (paper G-I)"
    signature = "range: colour shifts and darkens with distance, red fastest in ocean water"
    axis = "range"
    rank = RANK_WATER
    channel_axis = {"eta_per_m": 0}
    params = (
        Param("eta_per_m", (0.34, 0.24, 0.33), 0.0, 5.0, "1/m",
              "attenuation coefficient per channel (R, G, B); > 0 in water"),
    )
    neutral = {"eta_per_m": (0.0, 0.0, 0.0)}

    def forward(self, state):
        eta = self.param("eta_per_m", state.direct)
        return state.replace(direct=attenuate(state.direct, state.range_m, eta),
                             beta_d_per_m=eta.view(1, 3, 1, 1))
