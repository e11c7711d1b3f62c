"""A multiplicative falloff about any point of the image with a Gaussian profile (a hidden form for
``benchmarks/bench_forms.py``): V_c = 1 - s_c (1 - exp(-d^2 / (2 w^2))), d the distance from the centre (half
diagonals): darkening tending to s_c far from the centre. Applied to the direct signal and the backscatter alike."""

from __future__ import annotations

import torch

from watergan.formation import RANK_OPTICS, Effect, Param, normalised_radius, register


@register
class FalloffGaussian(Effect):
    name = "falloff_gaussian"
    summary = "falloff about any point, V_c = 1 - s_c (1 - exp(-d^2 / (2 w^2)))"
    signature = "image position: darkening about a point that levels off smoothly, per channel"
    axis = "image_position"
    rank = RANK_OPTICS
    params = (
        Param("centre_uv", (0.5, 0.5), 0.0, 1.0, "image fraction", "the undarkened point (u across, v down)"),
        Param("strength", (0.3, 0.3, 0.3), 0.0, 0.95, "", "s per channel (R, G, B): darkening far away"),
        Param("width", 0.6, 0.05, 4.0, "half diagonal", "the Gaussian's sigma w"),
    )
    neutral = {"strength": (0.0, 0.0, 0.0)}

    def forward(self, state):
        like = state.direct
        d = normalised_radius(state.pixel_uv, state.image_wh, self.param("centre_uv", like))
        profile = 1.0 - torch.exp(-d * d / (2 * self.param("width", like) ** 2))
        v = 1.0 - self.param("strength", like).view(1, 3, 1, 1) * profile
        return state.replace(direct=state.direct * v, backscatter=state.backscatter * v)
