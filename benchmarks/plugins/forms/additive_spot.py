"""Light added about a point of the image, the same in every frame (glare in the port, a lit patch of water; a
hidden form for ``benchmarks/bench_forms.py``): G_c = a_c (f + (1 - f) exp(-d^2 / (2 w^2))), d the distance from
the centre (half diagonals), f the level far from it: with f = 0 and a narrow spot the image holds its zero level,
with f > 0 no pixel is free of it. Added to the backscatter before the sensor."""

from __future__ import annotations

import torch

from watergan.formation import RANK_OPTICS, Effect, Param, normalised_radius, register


@register
class AdditiveSpot(Effect):
    name = "additive_spot"
    summary = "light added about a point, G_c = a_c (f + (1 - f) exp(-d^2 / (2 w^2)))"
    signature = "image position: light added about a point of the image, the same in every frame"
    axis = "image_position"
    rank = RANK_OPTICS
    params = (
        Param("centre_uv", (0.5, 0.5), 0.0, 1.0, "image fraction", "the spot's centre (u across, v down)"),
        Param("width", 0.4, 0.02, 4.0, "half diagonal", "the Gaussian's sigma w"),
        Param("amplitude", (0.03, 0.03, 0.03), 0.0, 0.5, "linear", "a per channel (R, G, B): the added light "
                                                                    "at the centre"),
        Param("floor", 0.0, 0.0, 1.0, "", "f: the level far from the centre, a fraction of a"),
    )
    neutral = {"amplitude": (0.0, 0.0, 0.0)}

    def forward(self, state):
        like = state.direct
        d = normalised_radius(state.pixel_uv, state.image_wh, self.param("centre_uv", like))
        f = self.param("floor", like)
        shape = f + (1.0 - f) * torch.exp(-d * d / (2 * self.param("width", like) ** 2))
        return state.replace(backscatter=state.backscatter + self.param("amplitude", like).view(1, 3, 1, 1) * shape)
