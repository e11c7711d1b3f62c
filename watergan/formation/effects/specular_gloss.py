"""A glossy surface: light reflected off a glaze (tiles, wet rock, plastic) that grows as the surface is seen
more obliquely, on top of its Lambertian colour."""

from __future__ import annotations

import torch

from ..effect import RANK_ILLUMINATION, Effect
from ..params import Param
from ..registry import register
from ..state import FormationState, dot3, vector_length


def incidence_cosine(points_cam: torch.Tensor, normals_cam: torch.Tensor) -> torch.Tensor:
    """cos theta = |n . X| / |X| (B,1,H,W): the cosine of the angle between the unit surface normal n and the ray
    from the scene point X (camera frame, metres) back to the camera; 1 seen head-on, 0 at grazing. The normal's
    sign does not matter (a surface is seen from the side it faces)."""
    return (dot3(normals_cam, points_cam).abs() / vector_length(points_cam, 1).clamp_min(1e-9)).clamp(0.0, 1.0)


def state_incidence_cosine(state: FormationState, effect: str) -> torch.Tensor:
    """:func:`incidence_cosine` of a state's camera-frame points and normals (``effect`` names who needs them)."""
    return incidence_cosine(state.need("points_cam", effect), state.need("normals_cam", effect))


def add_gloss(direct: torch.Tensor, cos_theta: torch.Tensor, gloss: torch.Tensor,
              exponent: torch.Tensor) -> torch.Tensor:
    """D_c = J_c + a_c (1 - cos theta)^p.

    J (B,3,H,W) the surface's Lambertian radiance (linear, 0..1 for white), cos theta (B,1,H,W) the incidence
    cosine of the view ray (:func:`incidence_cosine`), a (3,) the reflected light's radiance at grazing (linear, per
    channel), p the lobe's exponent (unitless). This is the angle-dependent part of a reflection weighted by
    Schlick's Fresnel term, k F(theta) with F = F0 + (1 - F0)(1 - cos theta)^5 (p = 5, a = k (1 - F0)); the
    constant part k F0 is the same in every view and belongs to the albedo. A smaller p is a broader lobe (a rough
    glaze, or light from above reflected towards an oblique camera). Added at the surface, the term is attenuated
    along the path like the surface's own light."""
    lobe = (1.0 - cos_theta).clamp_min(1e-12) ** exponent  # above 0: finite gradients in p
    return direct + gloss.view(1, 3, 1, 1) * lobe


@register
class SpecularGloss(Effect):
    name = "specular_gloss"
    summary = "light reflected off a glossy surface, a_c (1 - cos theta)^p (theta the view's incidence angle)"
    signature = "incidence angle: views seen obliquely brighter than the same surface seen head-on"
    axis = "incidence_angle"
    rank = RANK_ILLUMINATION + 2  # light leaving the surface, before the water
    channel_axis = {"gloss": 0}
    simulation_params = {"gloss": (0.15, 0.15, 0.15), "exponent": 1.0}
    params = (
        Param("gloss", (0.02, 0.02, 0.02), 0.0, 0.5, "linear radiance", "reflected radiance at grazing per channel"),
        Param("exponent", 2.0, 0.5, 8.0, "", "lobe exponent p (5: Schlick's Fresnel term)"),
    )
    neutral = {"gloss": (0.0, 0.0, 0.0)}

    def forward(self, state):
        like = state.direct
        out = add_gloss(state.direct, state_incidence_cosine(state, self.name), self.param("gloss", like),
                        self.param("exponent", like))
        return state.replace(direct=out)
