"""A multiplicative falloff about any point of the image with a polynomial profile (a hidden form for
``benchmarks/bench_forms.py``): V_c = 1 - s_c (d / d_max)^n, d the distance from the centre (half diagonals),
d_max the distance from the centre to the image's farthest corner, so the darkening is s_c there and 0 at the
centre. Applied to the direct signal and the backscatter alike (a lens or port effect)."""

from __future__ import annotations

import math

import torch

from watergan.formation import RANK_OPTICS, Effect, Param, normalised_radius, register


@register
class FalloffPolynomial(Effect):
    name = "falloff_polynomial"
    summary = "falloff about any point, V_c = 1 - s_c (d / d_max)^n, d_max the farthest corner's distance"
    signature = "image position: darkening growing as a power of the distance from a point, per channel"
    axis = "image_position"
    rank = RANK_OPTICS
    params = (
        Param("centre_uv", (0.5, 0.5), 0.0, 1.0, "image fraction", "the undarkened point (u across, v down)"),
        Param("strength", (0.3, 0.3, 0.3), 0.0, 0.95, "", "s per channel (R, G, B): darkening at d_max"),
        Param("power", 2.0, 0.5, 8.0, "", "n"),
    )
    neutral = {"strength": (0.0, 0.0, 0.0)}

    def forward(self, state):
        like = state.direct
        centre = self.param("centre_uv", like)
        w, h = state.image_wh
        far = torch.sqrt((torch.maximum(centre[0], 1 - centre[0]) * w) ** 2
                         + (torch.maximum(centre[1], 1 - centre[1]) * h) ** 2) / (0.5 * math.hypot(w, h))
        d = normalised_radius(state.pixel_uv, state.image_wh, centre)
        v = 1.0 - self.param("strength", like).view(1, 3, 1, 1) * (d / far) ** self.param("power", like)
        return state.replace(direct=state.direct * v, backscatter=state.backscatter * v)
