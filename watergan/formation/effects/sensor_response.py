"""Non-linear sensor response: a gamma curve and clipping."""

from __future__ import annotations

import torch

from ..effect import RANK_SENSOR, Effect
from ..params import Param
from ..registry import register


def sensor_curve(signal: torch.Tensor, gamma: torch.Tensor, saturation: torch.Tensor) -> torch.Tensor:
    """I = s * (min(max(S, 0), s) / s)^(1/gamma).

    S is the linear signal, s the clipping level (same units), gamma the curve exponent (1: linear).
    Everything above s reads s; the curve maps 0 to 0 and s to s.
    """
    x = torch.minimum(signal.clamp_min(1e-6), saturation) / saturation
    return saturation * x ** (1.0 / gamma)


@register
class SensorResponse(Effect):
    name = "sensor_response"
    summary = "non-linear sensor curve I = s (S/s)^(1/gamma), clipped at the saturation level s"
    signature = "intensity: residual that bends with predicted brightness and flattens at the top"
    axis = "intensity"
    rank = RANK_SENSOR + 1  # after the linear gain
    simulation_params = {"gamma": 1.4, "saturation": 0.8}
    params = (
        Param("gamma", 1.2, 0.2, 5.0, "", "curve exponent (1: linear)"),
        Param("saturation", 1.0, 0.05, 10.0, "linear radiance", "clipping level"),
    )
    neutral = {"gamma": 1.0, "saturation": 10.0}

    def forward(self, state):
        like = state.direct
        out = sensor_curve(state.image, self.param("gamma", like), self.param("saturation", like))
        # the curve acts on the sum: the result is no longer separable into direct + backscatter
        return state.replace(direct=out, backscatter=torch.zeros_like(out))
