"""Analytic backscatter: veiling light that saturates with range."""

from __future__ import annotations

import torch

from ..effect import RANK_SCATTER, Effect
from ..params import Param
from ..registry import register


def backscatter_term(range_m: torch.Tensor, b_inf: torch.Tensor, beta_per_m: torch.Tensor) -> torch.Tensor:
    """B_c = B_inf,c * (1 - exp(-beta_c * r)).

    range r (B,1,H,W, metres), B_inf (3,) veiling light at infinite range (linear radiance, same
    scale as the in-air image), beta (3,) backscatter coefficient in 1/m. Returns (B,3,H,W).
    """
    return b_inf.view(1, 3, 1, 1) * -torch.expm1(-beta_per_m.view(1, 3, 1, 1) * range_m)


@register
class Backscatter(Effect):
    name = "backscatter"
    summary = "veiling light added by scattering in the water column, B_inf (1 - exp(-beta r))"
    signature = "range and intensity: dark, distant pixels tend to a constant water colour"
    axis = "range"
    rank = RANK_SCATTER
    channel_axis = {"b_inf": 0, "beta_per_m": 0}
    params = (
        Param("b_inf", (0.05, 0.18, 0.22), 0.0, 1.0, "linear radiance", "veiling light at infinite range"),
        Param("beta_per_m", (0.4, 0.3, 0.3), 0.0, 5.0, "1/m", "backscatter coefficient per channel"),
    )
    neutral = {"b_inf": (0.0, 0.0, 0.0), "beta_per_m": (0.4, 0.3, 0.3)}

    def forward(self, state):
        term = backscatter_term(state.range_m, self.param("b_inf", state.direct),
                                self.param("beta_per_m", state.direct))
        return state.replace(backscatter=state.backscatter + term)
