"""Vignetting about a free centre, with an optional strength per channel."""

from __future__ import annotations

import torch

from ..effect import RANK_OPTICS, Effect
from ..params import Param
from ..registry import register
from ..state import normalised_radius
from .vignetting import VIGNETTING_PARAMS, vignetting_coefficients, vignetting_falloff


def vignette_offcentre(signal: torch.Tensor, r: torch.Tensor, a, b, c, strength: torch.Tensor) -> torch.Tensor:
    """S_c / V_c with V_c = 1 + s_c (a r^2 + b r^4 + c r^6).

    r (B,1,H,W) is the distance from the free centre (pixels / half diagonal); s (3,) scales the
    falloff per channel (s = 0: no vignetting in that channel). Same constraint on a, b, c as the
    centred model, so each V_c rises monotonically with r.
    """
    return signal / (1.0 + strength.view(1, 3, 1, 1) * vignetting_falloff(r, a, b, c))


@register
class VignettingOffcentre(Effect):
    name = "vignetting_offcentre"
    summary = "lens or housing falloff about an off-centre point, optional per-channel strength"
    signature = "image position: darkening that is radially symmetric about a point other than the centre"
    axis = "image_position"
    rank = RANK_OPTICS
    simulation_params = {"centre_uv": [0.61, 0.44], "a_margin": 0.5, "c": 0.1, "strength": [1.0, 0.9, 0.8]}
    params = (
        Param("centre_uv", (0.5, 0.5), 0.0, 1.0, "image fraction", "falloff centre (u across, v down)",
              plausible=(0.02, 0.98)),  # inside the image
        *VIGNETTING_PARAMS,
        Param("strength", (1.0, 1.0, 1.0), 0.0, 3.0, "", "falloff scale per channel (R, G, B)"),
    )
    neutral = {"centre_uv": (0.5, 0.5), "a_margin": 0.0, "b": 0.0, "c": 0.0, "strength": (0.0, 0.0, 0.0)}

    def forward(self, state):
        like = state.direct
        r = normalised_radius(state.pixel_uv, state.image_wh, self.param("centre_uv", like))
        a, b, c = vignetting_coefficients(self.param("a_margin", like), self.param("b", like),
                                          self.param("c", like))
        s = self.param("strength", like)
        return state.replace(direct=vignette_offcentre(state.direct, r, a, b, c, s),
                             backscatter=vignette_offcentre(state.backscatter, r, a, b, c, s))
