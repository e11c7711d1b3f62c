"""Smooth per-channel fields over the image: what the stack lacks on image position, carried beside the water.

A stack that lacks an effect leaves structure that a fit otherwise bends the water to explain. This nuisance
effect takes what depends on image position alone, fixed to the camera, per channel c:

    y_c = F_c(x) S_c + (F_c(x) B_c + G_c(x)),   F_c(x) = exp(sum_k f_ck m_k(x)),   G_c(x) = l_c + sum_k g_ck m_k(x),

S the direct signal and B the backscatter reaching it; m_k the monomials x^i y^j with 1 <= i + j <= d of
x = 2u - 1, y = ASPECT (2v - 1) (u, v the pixel's image fractions), without a constant: a constant F is the gain
(degenerate with the albedos' scale), a constant G a veil that the backscatter's asymptote already has, so G's
level l_c (``additive_level``) is held, not fitted (0: G vanishes at the image's centre; a fit may set it from the
fitted shape, :func:`eval.water.fields.set_light_level`). The degree d follows from the coefficients' shape (3, M),
M = (d + 1)(d + 2)/2 - 1 (5 for d = 2). F is what any falloff becomes (off-centre, colour-dependent, of another form
than the vignetting polynomial); G is an additive veil fixed in the image (a light reflected in the port).

What pins what: the same surface point seen at several image positions and ranges. Its views differ by the water's
exp(-eta dr) along range and by F and G along image position. Where the survey's range is itself a function of image
position (a level camera at one altitude over a flat floor sees r = a / cos(theta)), a field over the image is
the water's range dependence, and a per-channel field trades with a per-channel eta. So the fields are kept
uncorrelated with range: their coefficients are projected off the unit direction q (``orthogonal_to``), f -> f -
(f . q) q and the same for g, and a fit sets q to the covariance of each monomial with range over the survey's
views (q ~ sum_o (m_o - mean m)(r_o - mean r)): log F and G then have no covariance with range there. What is
linear in range over the survey belongs to the water (and to the centred vignetting); the rest of the image
structure goes to the fields. With nothing missing they stay near F = 1, G = 0.

Smoothness: a fit adds the penalty sum_ck d_k^2 lambda (f_ck^2 + (g_ck / G_SCALE)^2) (:meth:`ImageField.penalty`,
lambda = ``smoothness``, d_k the monomial's degree): higher orders cost more, a field must earn its size from the
data, and the part of F that the centred vignetting already has (its r^2) goes to the vignetting, not to F.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..effect import RANK_OPTICS, Effect
from ..params import Param
from ..registry import register

#: y scale of the basis: the image's height over its width for a 4:3 frame.
ASPECT = 0.75
#: Additive coefficients are penalised in units of this (linear colour, a typical underwater signal): a veil of 0.01
#: costs what a 10 % falloff does, the two changing such a signal alike.
G_SCALE = 0.1


def degree_of(n_terms: int) -> int:
    """The degree d whose basis has ``n_terms`` = (d + 1)(d + 2)/2 - 1 monomials."""
    d = int(round((math.sqrt(8 * (n_terms + 1) + 1) - 3) / 2))
    if (d + 1) * (d + 2) // 2 - 1 != n_terms:
        raise ValueError(f"{n_terms} coefficients are no full polynomial basis (2, 5, 9, 14, ... terms)")
    return d


def n_terms(degree: int) -> int:
    """Monomials of the basis of this degree (no constant)."""
    return (degree + 1) * (degree + 2) // 2 - 1


def monomial_degrees(degree: int) -> list[int]:
    """The total degree of each monomial of :func:`field_basis`, in its order."""
    return [d for d in range(1, degree + 1) for _ in range(d + 1)]


def field_basis(pixel_uv: torch.Tensor, degree: int) -> torch.Tensor:
    """(B,M,H,W) the monomials x^i y^j, 1 <= i + j <= degree, at pixel fractions ``pixel_uv`` (B,2,H,W), ordered by
    total degree then by the power of y."""
    x = 2.0 * pixel_uv[:, :1] - 1.0
    y = ASPECT * (2.0 * pixel_uv[:, 1:2] - 1.0)
    return torch.cat([x ** (d - j) * y ** j for d in range(1, degree + 1) for j in range(d + 1)], 1)


def apply_image_field(direct: torch.Tensor, backscatter: torch.Tensor, basis: torch.Tensor, f: torch.Tensor,
                      g: torch.Tensor, level: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(F S, F B + G) with F = exp(f . m), G = l + g . m per channel: f, g (3,M), level l (3,), basis m
    (B,M,H,W)."""
    field = torch.exp(torch.einsum("cm,bmhw->bchw", f, basis))
    additive = torch.einsum("cm,bmhw->bchw", g, basis) + level.view(1, 3, 1, 1)
    return direct * field, backscatter * field + additive


@register
class ImageField(Effect):
    name = "image_field"
    summary = "smooth per-channel multiplicative and additive fields over the image (a nuisance: what the stack lacks)"
    signature = "image position: any smooth structure fixed to the camera, multiplicative (falloff) or additive (veil)"
    axis = "image_position"
    rank = RANK_OPTICS + 1
    nuisance = True
    channel_axis = {"multiplicative": 0, "additive": 0}
    params = (
        Param("multiplicative", ((0.0,) * 5,) * 3, -2.0, 2.0, "", "log F's coefficients per channel (3, M)",
              shapes=((3, -1),)),
        Param("additive", ((0.0,) * 5,) * 3, -0.5, 0.5, "", "G's coefficients per channel (3, M), linear colour",
              shapes=((3, -1),)),
        Param("additive_level", (0.0, 0.0, 0.0), -0.5, 0.5, "linear", "G's level l per channel, held (a constant G is "
              "the backscatter's veil)", learnable=False),
        Param("smoothness", 1e-5, 0.0, 1.0, "", "penalty weight lambda of the fit", learnable=False),
        Param("orthogonal_to", (0.0,) * 5, -1.0, 1.0, "", "unit direction q of the coefficients the fields are kept "
              "off (0: none; a fit sets it to the monomials' covariance with range)", learnable=False,
              shapes=((-1,),)),
    )
    neutral = {"multiplicative": ((0.0,) * 5,) * 3, "additive": ((0.0,) * 5,) * 3, "additive_level": (0.0, 0.0, 0.0)}

    def coefficients(self, like: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(f, g) (3,M) as applied: the parameters projected off ``orthogonal_to``."""
        q = self.param("orthogonal_to", like)
        f, g = self.param("multiplicative", like), self.param("additive", like)
        return f - (f @ q)[:, None] * q, g - (g @ q)[:, None] * q

    @property
    def degree(self) -> int:
        return degree_of(self.raw["multiplicative"].shape[1])

    def forward(self, state):
        like = state.direct
        basis = field_basis(state.pixel_uv.to(like.dtype), self.degree)
        direct, back = apply_image_field(state.direct, state.backscatter, basis, *self.coefficients(like),
                                         self.param("additive_level", like))
        return state.replace(direct=direct, backscatter=back)

    def penalty(self) -> torch.Tensor:
        """Residuals whose sum of squares is the smoothness penalty of the module docstring."""
        weight = torch.tensor(monomial_degrees(self.degree), dtype=torch.float64)
        root = math.sqrt(float(self.param("smoothness")))
        return torch.cat([(root * weight * self.param("multiplicative")).reshape(-1),
                          (root * weight * self.param("additive") / G_SCALE).reshape(-1)])

    def at(self, pixel_uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(F, G) (N,3) at pixel fractions (N,2)."""
        basis = field_basis(pixel_uv.to(torch.float64).reshape(-1, 2, 1, 1), self.degree)
        with torch.no_grad():
            f, g = (torch.einsum("cm,bmhw->bc", c, basis) for c in self.coefficients())
            return torch.exp(f), g + self.param("additive_level")

    def on_grid(self, cols: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
        """(F, G) (rows, cols, 3) on a grid of the image, corner to corner."""
        u, v = np.meshgrid(np.linspace(0, 1, cols), np.linspace(0, 1, rows))
        f, g = self.at(torch.from_numpy(np.stack([u.ravel(), v.ravel()], 1)))
        return f.numpy().reshape(rows, cols, 3), g.numpy().reshape(rows, cols, 3)
