"""A multiplicative falloff about any point of the image with a cosine-power profile (a hidden form for
``benchmarks/bench_forms.py``): V_c = 1 - s_c (1 - cos^n(pi/2 min(1, d / w))), d the distance from the centre
(half diagonals): darkening s_c on and beyond d = w. Applied to the direct signal and the backscatter alike."""

from __future__ import annotations

import math

import torch

from watergan.formation import RANK_OPTICS, Effect, Param, normalised_radius, register


@register
class FalloffCosine(Effect):
    name = "falloff_cosine"
    summary = "falloff about any point, V_c = 1 - s_c (1 - cos^n(pi/2 min(1, d / w)))"
    signature = "image position: darkening about a point with a cosine-power shoulder, per channel"
    axis = "image_position"
    rank = RANK_OPTICS
    params = (
        Param("centre_uv", (0.5, 0.5), 0.0, 1.0, "image fraction", "the undarkened point (u across, v down)"),
        Param("strength", (0.3, 0.3, 0.3), 0.0, 0.95, "", "s per channel (R, G, B): darkening beyond d = w"),
        Param("width", 1.2, 0.05, 4.0, "half diagonal", "w, where the cosine reaches zero"),
        Param("power", 4.0, 0.5, 8.0, "", "n"),
    )
    neutral = {"strength": (0.0, 0.0, 0.0)}

    def forward(self, state):
        like = state.direct
        d = normalised_radius(state.pixel_uv, state.image_wh, self.param("centre_uv", like))
        angle = 0.5 * math.pi * torch.clamp(d / self.param("width", like), max=1.0)
        profile = 1.0 - torch.cos(angle).clamp_min(0.0) ** self.param("power", like)  # cos(pi/2) < 0 in float32
        v = 1.0 - self.param("strength", like).view(1, 3, 1, 1) * profile
        return state.replace(direct=state.direct * v, backscatter=state.backscatter * v)
