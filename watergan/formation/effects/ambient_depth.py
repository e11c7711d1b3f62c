"""Ambient (downwelling) light that decays with each scene point's water depth."""

from __future__ import annotations

import torch

from ..effect import RANK_ILLUMINATION, Effect
from ..params import Param
from ..registry import register


def ambient_at_depth(direct: torch.Tensor, water_depth_m: torch.Tensor, kappa_per_m: torch.Tensor,
                     reference_depth_m: torch.Tensor) -> torch.Tensor:
    """D_c = J_c exp(-K_c (d_w - d_ref)).

    d_w the scene point's depth below the surface (metres), d_ref the depth at which the in-air
    image's illumination holds, K_c (1/m) the diffuse attenuation of downwelling light per channel
    (Jerlov's Kd). Deeper points (troughs, the foot of a rock) are darker and bluer.
    """
    return direct * torch.exp(-kappa_per_m.view(1, 3, 1, 1) * (water_depth_m - reference_depth_m))


@register
class AmbientDepth(Effect):
    name = "ambient_depth"
    summary = "downwelling ambient light decaying with the scene point's water depth, per channel (Kd)"
    signature = "height: points lower on the seafloor are darker and bluer than points higher up"
    axis = "height"
    rank = RANK_ILLUMINATION + 1
    simulation_params = {"kappa_per_m": [0.46, 0.2, 0.39]}  # Jerlov 3C Kd at 650, 525, 450 nm
    params = (
        Param("kappa_per_m", (0.36, 0.07, 0.04), 0.0, 2.0, "1/m", "diffuse attenuation Kd per channel"),
        Param("reference_depth_m", 20.0, 0.0, 11000.0, "m", "depth where J's illumination holds",
              learnable=False),
    )
    neutral = {"kappa_per_m": (0.0, 0.0, 0.0)}

    def forward(self, state):
        like = state.direct
        out = ambient_at_depth(state.direct, state.need("water_depth_m", self.name),
                               self.param("kappa_per_m", like), self.param("reference_depth_m", like))
        return state.replace(direct=out)
