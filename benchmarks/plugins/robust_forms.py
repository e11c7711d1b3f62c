"""Effects of forms the fitted stack does not share, for the robustness surveys of ``benchmarks/bench_water.py``.

A plugin (``watergan --plugin benchmarks/plugins/robust_forms.py ...``), not a built-in: the simulator hides these
to test that the water holds when its model is incomplete; the stack never has them.

- ``falloff_clipped``: a colour-dependent off-centre falloff that is not the vignetting polynomial, a clipped
  quadratic V_c = max(floor, 1 - s_c (d / d0)^2), d the distance from its centre (half diagonals).
- ``port_veil``: an additive veil fixed in the image (a light reflected in the port), a Gaussian spot
  G_c = a_c exp(-d^2 / (2 sigma^2)).
- ``survey_exposure``: each frame's signal scaled by its own gain exp(g_f) (auto-exposure), all channels alike.
- ``water_drift``: the water's attenuation changing along the survey, eta_c + delta_fc on the direct path.
"""

from __future__ import annotations

import numpy as np
import torch

from watergan.formation import RANK_OPTICS, RANK_SENSOR, RANK_WATER, Effect, Param, normalised_radius, register

#: Frames of the demo survey: the drifting water's ramp spans them once.
DEMO_FRAMES = 44


@register
class FalloffClipped(Effect):
    name = "falloff_clipped"
    summary = "colour-dependent off-centre falloff, a clipped quadratic V_c = max(floor, 1 - s_c (d / d0)^2)"
    signature = "image position: darkening about an off-centre point, stronger in red, flat beyond a ring"
    axis = "image_position"
    rank = RANK_OPTICS
    params = (
        Param("centre_uv", (0.5, 0.5), 0.0, 1.0, "image fraction", "falloff centre (u across, v down)"),
        Param("radius", 1.0, 0.1, 3.0, "half diagonal", "distance d0 at which V = 1 - s"),
        Param("strength", (0.3, 0.3, 0.3), 0.0, 1.0, "", "s per channel (R, G, B)"),
        Param("floor", 0.4, 0.0, 1.0, "", "least V"),
    )
    neutral = {"strength": (0.0, 0.0, 0.0)}
    simulation_params = {"centre_uv": [0.36, 0.58], "radius": 1.1, "strength": [0.6, 0.45, 0.3], "floor": 0.5}

    def forward(self, state):
        like = state.direct
        d = normalised_radius(state.pixel_uv, state.image_wh, self.param("centre_uv", like))
        s = self.param("strength", like).view(1, 3, 1, 1)
        v = torch.maximum(1.0 - s * (d / self.param("radius", like)) ** 2, self.param("floor", like))
        return state.replace(direct=state.direct * v, backscatter=state.backscatter * v)


@register
class PortVeil(Effect):
    name = "port_veil"
    summary = "an additive veil fixed in the image, a Gaussian spot G_c = a_c exp(-d^2 / (2 sigma^2))"
    signature = "image position: light added about a point of the image, the same in every frame"
    axis = "image_position"
    rank = RANK_OPTICS
    params = (
        Param("centre_uv", (0.5, 0.5), 0.0, 1.0, "image fraction", "the spot's centre"),
        Param("sigma", 0.4, 0.05, 2.0, "half diagonal", "the spot's width"),
        Param("amplitude", (0.03, 0.03, 0.03), 0.0, 0.5, "linear", "a per channel (R, G, B)"),
    )
    neutral = {"amplitude": (0.0, 0.0, 0.0)}
    simulation_params = {"centre_uv": [0.78, 0.22], "sigma": 0.45, "amplitude": [0.025, 0.045, 0.06]}

    def forward(self, state):
        like = state.direct
        d = normalised_radius(state.pixel_uv, state.image_wh, self.param("centre_uv", like))
        veil = self.param("amplitude", like).view(1, 3, 1, 1) * torch.exp(-d * d / (2 * self.param("sigma", like) ** 2))
        return state.replace(backscatter=state.backscatter + veil)


@register
class SurveyExposure(Effect):
    name = "survey_exposure"
    summary = "auto-exposure: each frame's signal scaled by its own gain exp(g_f), the same in every channel"
    signature = "frame: every pixel of a frame brighter or darker by one factor"
    axis = "frame"
    rank = RANK_SENSOR
    params = (Param("log_gain", 0.0, -1.0, 1.0, "", "log of the frame's exposure gain", per="frame"),)
    neutral = {}
    simulation_params = {"log_gain": [0.0, 0.18, -0.12, 0.08, -0.22, 0.14, -0.05]}

    def forward(self, state):
        g = torch.exp(self.per_frame("log_gain", state)).view(-1, 1, 1, 1)
        return state.replace(direct=state.direct * g, backscatter=state.backscatter * g)


@register
class WaterDrift(Effect):
    name = "water_drift"
    summary = "the attenuation changing along the survey: the direct path attenuated by exp(-delta_fc r) more"
    signature = "frame: the colour's fall with range steeper in some frames than in others"
    axis = "frame"
    rank = RANK_WATER + 2
    params = (Param("delta_eta_per_m", (0.0, 0.0, 0.0), -0.5, 0.5, "1/m", "the frame's change of eta",
                    per="frame"),)
    neutral = {}
    #: a linear ramp over the demo's frames, +-25 % of its red eta and +-30 % of its green and blue
    simulation_params = {"delta_eta_per_m": (np.linspace(-1.0, 1.0, DEMO_FRAMES)[:, None]
                                             * np.array([0.11, 0.042, 0.06])).round(4).tolist()}

    def forward(self, state):
        delta = self.per_frame("delta_eta_per_m", state).view(-1, 3, 1, 1).to(state.direct.dtype)
        return state.replace(direct=state.direct * torch.exp(-delta * state.range_m))
