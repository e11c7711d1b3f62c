"""The sensor's black level: an offset per channel that the camera adds (or leaves after subtracting its own)."""

from __future__ import annotations

from ..effect import RANK_SENSOR, Effect
from ..params import Param
from ..registry import register


def add_black_level(backscatter, offset):
    """B'_c = B_c + b_c: the offset b (3,) (linear radiance, 0..1 at white; negative where the camera subtracts more
    than its dark signal) added to the additive part of the signal, so that I_c = S_c + B_c + b_c. It sits after the
    gains (it is not scaled by the exposure) and before the tone curve; it is not vignetted, which is what sets it
    apart from a backscatter that has saturated with range."""
    return backscatter + offset.view(1, 3, 1, 1)


@register
class BlackLevel(Effect):
    name = "black_level"
    summary = "a black-level offset b per channel at the sensor, I = S + B + b (after the gains, before the curve)"
    signature = "intensity: dark views brighter (or darker) than the model by one amount per channel, at any range"
    axis = "intensity"
    rank = RANK_SENSOR + 2  # after the gains, before the tone curve
    channel_axis = {"offset": 0}
    # only the vignetting, which scales the veil and not the offset, tells an offset of the veil's colour from it
    same_colour_as = {"offset": "backscatter.b_inf"}
    simulation_params = {"offset": (0.012, 0.01, 0.008)}
    params = (Param("offset", (0.005, 0.005, 0.005), -0.05, 0.05, "linear radiance",
                    "black level per channel (R, G, B)"),)
    neutral = {"offset": (0.0, 0.0, 0.0)}

    def forward(self, state):
        return state.replace(backscatter=add_black_level(state.backscatter, self.param("offset", state.direct)))
