"""Centred lens vignetting with a polynomial falloff (WaterGAN G-III)."""

from __future__ import annotations

import torch

from ..effect import RANK_OPTICS, Effect
from ..params import Param
from ..registry import register
from ..state import normalised_radius


def vignetting_coefficients(a_margin: torch.Tensor, b: torch.Tensor, c: torch.Tensor):
    """(a, b, c) of V = 1 + a r^2 + b r^4 + c r^6 with the paper's constraint held by construction.

    With c > 0 and a = b^2 / (3c) + a_margin, a_margin > 0, the discriminant 4b^2 - 12ac =
    -12 c a_margin < 0, so dV/d(r^2) = a + 2b r^2 + 3c r^4 > 0: V rises monotonically from 1.
    """
    return b * b / (3.0 * c) + a_margin, b, c


def vignetting_falloff(r: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """The falloff polynomial a r^2 + b r^4 + c r^6 (unitless; r is the normalised radius)."""
    r2 = r * r
    return r2 * (a + r2 * (b + r2 * c))


def vignette(signal: torch.Tensor, r: torch.Tensor, a: torch.Tensor, b: torch.Tensor,
             c: torch.Tensor) -> torch.Tensor:
    """G3 = G2 / V with V = 1 + a r^2 + b r^4 + c r^6.

    signal G2 (B,3,H,W), r (B,1,H,W) distance from the image centre divided by the half diagonal
    (0 at the centre, 1 at a corner); a, b, c unitless. Edges darken by the factor 1/V.
    """
    return signal / (1.0 + vignetting_falloff(r, a, b, c))


VIGNETTING_PARAMS = (
    Param("a_margin", 0.3, 0.0, 10.0, "", "a - b^2/(3c): how far a is above the constraint's limit"),
    Param("b", 0.0, -10.0, 10.0, "", "r^4 coefficient"),
    Param("c", 0.05, 0.0, 10.0, "", "r^6 coefficient (> 0)"),
)


@register
class Vignetting(Effect):
    name = "vignetting"
    summary = "centred lens falloff, output / (1 + a r^2 + b r^4 + c r^6), 4b^2 - 12ac < 0 (paper G-III)"
    signature = "image position: a radially symmetric darkening about the image centre"
    axis = "image_position"
    rank = RANK_OPTICS
    params = VIGNETTING_PARAMS
    neutral = {"a_margin": 0.0, "b": 0.0, "c": 0.0}

    def coefficients(self, like=None):
        return vignetting_coefficients(self.param("a_margin", like), self.param("b", like), self.param("c", like))

    def forward(self, state):
        r = normalised_radius(state.pixel_uv, state.image_wh)
        a, b, c = self.coefficients(state.direct)
        return state.replace(direct=vignette(state.direct, r, a, b, c),
                             backscatter=vignette(state.backscatter, r, a, b, c))
