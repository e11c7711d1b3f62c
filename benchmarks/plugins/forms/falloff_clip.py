"""A multiplicative falloff about any point of the image with a clipped quadratic profile (a hidden form for
``benchmarks/bench_forms.py``): V_c = 1 - s_c min(1, (d / w)^2), d the distance from the centre (half diagonals):
darkening s_c on and beyond the ring d = w, flat there. Applied to the direct signal and the backscatter alike."""

from __future__ import annotations

import torch

from watergan.formation import RANK_OPTICS, Effect, Param, normalised_radius, register


@register
class FalloffClip(Effect):
    name = "falloff_clip"
    summary = "falloff about any point, V_c = 1 - s_c min(1, (d / w)^2): flat beyond the ring d = w"
    signature = "image position: darkening about a point that stops growing at a ring, per channel"
    axis = "image_position"
    rank = RANK_OPTICS
    params = (
        Param("centre_uv", (0.5, 0.5), 0.0, 1.0, "image fraction", "the undarkened point (u across, v down)"),
        Param("strength", (0.3, 0.3, 0.3), 0.0, 0.95, "", "s per channel (R, G, B): darkening beyond the ring"),
        Param("width", 1.0, 0.05, 4.0, "half diagonal", "the ring's radius w"),
    )
    neutral = {"strength": (0.0, 0.0, 0.0)}

    def forward(self, state):
        like = state.direct
        d = normalised_radius(state.pixel_uv, state.image_wh, self.param("centre_uv", like))
        profile = torch.clamp((d / self.param("width", like)) ** 2, max=1.0)
        v = 1.0 - self.param("strength", like).view(1, 3, 1, 1) * profile
        return state.replace(direct=state.direct * v, backscatter=state.backscatter * v)
