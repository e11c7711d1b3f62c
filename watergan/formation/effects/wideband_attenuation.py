"""Wideband attenuation: an effective coefficient that changes with range."""

from __future__ import annotations

import torch

from ..effect import RANK_WATER, Effect
from ..params import Param
from ..registry import register


def wideband_attenuate(direct: torch.Tensor, range_m: torch.Tensor, a: torch.Tensor, b: torch.Tensor,
                       c: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """D_c = J_c exp(-beta_c(r) r), beta_c(r) = a_c e^(b_c r) + c_c e^(d_c r).

    a, c in 1/m (>= 0), b, d in 1/m (<= 0: the effective coefficient of a broadband channel falls
    with range as the most absorbed wavelengths are used up). r metres. Acts in addition to any
    range-independent ``attenuation`` in the stack.
    """
    view = (1, 3, 1, 1)
    beta = a.view(view) * torch.exp(b.view(view) * range_m) + c.view(view) * torch.exp(d.view(view) * range_m)
    return direct * torch.exp(-beta * range_m)


@register
class WidebandAttenuation(Effect):
    name = "wideband_attenuation"
    summary = "range-dependent effective attenuation beta(r) = a e^(b r) + c e^(d r) per channel"
    signature = "range: attenuation that is stronger near the camera than a single exponential allows"
    axis = "range"
    rank = RANK_WATER + 1
    params = (
        Param("a", (0.2, 0.1, 0.1), 0.0, 5.0, "1/m", "first term's coefficient"),
        Param("b", (-0.8, -0.8, -0.8), -5.0, 0.0, "1/m", "first term's decay with range"),
        Param("c", (0.05, 0.05, 0.05), 0.0, 5.0, "1/m", "second term's coefficient"),
        Param("d", (-0.05, -0.05, -0.05), -5.0, 0.0, "1/m", "second term's decay with range"),
    )
    neutral = {"a": (0.0, 0.0, 0.0), "c": (0.0, 0.0, 0.0)}

    def forward(self, state):
        like = state.direct
        out = wideband_attenuate(state.direct, state.range_m, *(self.param(n, like) for n in "abcd"))
        return state.replace(direct=out)
