"""Backscatter whose coefficient differs from the direct signal's (beta_B != beta_D)."""

from __future__ import annotations

import torch

from ..effect import RANK_SCATTER, Effect
from ..params import Param
from ..registry import register


def decoupled_backscatter(range_m: torch.Tensor, b_inf: torch.Tensor, ratio: torch.Tensor,
                          beta_d_per_m: torch.Tensor) -> torch.Tensor:
    """B_c = B_inf,c (1 - exp(-rho_c beta_D,c r)): veiling light whose coefficient beta_B = rho beta_D.

    beta_D (1/m) is the direct signal's attenuation coefficient, as fitted by ``attenuation``; rho
    (unitless) their ratio (the revised formation model measures rho far from 1); B_inf linear
    radiance; r metres. Returns (B,3,H,W).
    """
    beta_b = ratio.view(1, 3, 1, 1) * beta_d_per_m.view(-1, 3, 1, 1)
    return b_inf.view(1, 3, 1, 1) * -torch.expm1(-beta_b * range_m)


@register
class BackscatterCoefficient(Effect):
    name = "backscatter_coefficient"
    summary = "a veiling-light term whose coefficient is rho times the direct attenuation (beta_B != beta_D)"
    signature = "range: veiling light that saturates at a different rate from the direct decay"
    axis = "range"
    rank = RANK_SCATTER + 1  # after `attenuation` has recorded beta_D
    params = (
        Param("b_inf", (0.03, 0.05, 0.05), 0.0, 1.0, "linear radiance", "veiling light at infinite range"),
        Param("ratio", (3.0, 3.0, 3.0), 0.05, 20.0, "", "rho = beta_B / beta_D per channel"),
    )
    neutral = {"b_inf": (0.0, 0.0, 0.0), "ratio": (3.0, 3.0, 3.0)}

    def forward(self, state):
        beta_d = state.need("beta_d_per_m", self.name).to(state.dtype)
        term = decoupled_backscatter(state.range_m, self.param("b_inf", state.direct),
                                     self.param("ratio", state.direct), beta_d)
        return state.replace(backscatter=state.backscatter + term)
