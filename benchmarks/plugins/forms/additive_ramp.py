"""A veil that grows across the image along one direction, the same in every frame (light from a lamp or the
surface entering one side of the view; a hidden form for ``benchmarks/bench_forms.py``):
G_c = a_c min(1, max(0, (t - t0) / w)), t = (u - 1/2) cos(theta) + (v - 1/2) sin(theta) (u, v image fractions):
zero where t <= t0 (in view when t0 lies inside the image), a_c from t >= t0 + w. Added to the backscatter before
the sensor."""

from __future__ import annotations

import torch

from watergan.formation import RANK_OPTICS, Effect, Param, register


@register
class AdditiveRamp(Effect):
    name = "additive_ramp"
    summary = "a veil growing across the image, G_c = a_c clip((t - t0) / w, 0, 1), t along the angle theta"
    signature = "image position: light added towards one side of the image, the same in every frame"
    axis = "image_position"
    rank = RANK_OPTICS
    params = (
        Param("angle_deg", 0.0, -180.0, 180.0, "degrees", "theta: the direction the veil grows in (0: +u, 90: +v)"),
        Param("start", -0.5, -2.0, 2.0, "image fraction", "t0: where the veil starts"),
        Param("width", 1.0, 0.05, 4.0, "image fraction", "w: how far it grows to a_c"),
        Param("amplitude", (0.03, 0.03, 0.03), 0.0, 0.5, "linear", "a per channel (R, G, B)"),
    )
    neutral = {"amplitude": (0.0, 0.0, 0.0)}

    def forward(self, state):
        like = state.direct
        theta = torch.deg2rad(self.param("angle_deg", like))
        t = (state.pixel_uv[:, 0:1] - 0.5) * torch.cos(theta) + (state.pixel_uv[:, 1:2] - 0.5) * torch.sin(theta)
        shape = torch.clamp((t - self.param("start", like)) / self.param("width", like), 0.0, 1.0)
        return state.replace(backscatter=state.backscatter + self.param("amplitude", like).view(1, 3, 1, 1) * shape)
