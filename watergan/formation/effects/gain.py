"""Linear sensor gain."""

from __future__ import annotations

import torch

from ..effect import RANK_SENSOR, Effect
from ..params import Param
from ..registry import register


def apply_gain(signal: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """I_c = k_c * S_c: a linear sensor response; k is one value or one per channel (unitless)."""
    return signal * k.reshape(1, -1, 1, 1)


@register
class Gain(Effect):
    name = "gain"
    summary = "linear sensor response k (exposure, white balance), one value per channel"
    signature = "intensity: every pixel scaled by the same factor per channel"
    axis = "intensity"
    rank = RANK_SENSOR
    channel_axis = {"k": 0}
    params = (Param("k", (1.0, 1.0, 1.0), 0.01, 100.0, "", "gain per channel (R, G, B), or one value",
                    shapes=((3,), (1,))),)
    neutral = {"k": (1.0, 1.0, 1.0)}

    def forward(self, state):
        k = self.param("k", state.direct)
        return state.replace(direct=apply_gain(state.direct, k), backscatter=apply_gain(state.backscatter, k))
