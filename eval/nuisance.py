"""Smooth nuisance fields over the image, fitted beside the physical stack (:mod:`eval.fit`).

A stack that lacks an effect leaves structure in the residuals that the fit otherwise bends the water to explain.
Two per-channel fields fixed to the camera take what depends on image position alone:

    y = F_c(x) (A_c J + C_c) + G_c(x),   F_c(x) = exp(sum_k f_ck m_k(x)),   G_c(x) = sum_k g_ck m_k(x),

m_k the monomials x^i y^j with 1 <= i + j <= ``degree`` of x = 2u - 1, y = 0.75 (2v - 1) (u, v the pixel's image
fractions; 0.75 keeps a 4:3 frame's aspect), without a constant: a constant F is the gain (degenerate with the
albedos' scale), a constant G is a veil that the backscatter's asymptote already has. F is what any falloff
becomes (off-centre, colour-dependent, of another form than the stack's polynomial); G is an additive veil fixed in
the image (a light reflected in the port).

What pins what: the same surface point seen at several image positions and ranges. Its views differ by the
water's exp(-eta dr) along range and by F and G along image position; a low-order basis over the image cannot
follow range within a frame, and across frames the same image position sees many ranges, so the fields cannot take
over the water's range dependence. With nothing missing the fields stay near 0 (F = 1, G = 0).
"""

from __future__ import annotations

import numpy as np
import torch

#: y scale of the basis: the image's height over its width for a 4:3 frame.
ASPECT = 0.75


def monomials(pixel_uv: np.ndarray, degree: int) -> np.ndarray:
    """(N,M) the basis m_k at pixel fractions ``pixel_uv`` (N,2): x^i y^j, 1 <= i + j <= degree, x = 2u - 1,
    y = ASPECT (2v - 1), ordered by total degree then by the power of y."""
    x = 2.0 * np.asarray(pixel_uv, np.float64)[:, 0] - 1.0
    y = ASPECT * (2.0 * np.asarray(pixel_uv, np.float64)[:, 1] - 1.0)
    cols = [x ** (d - j) * y ** j for d in range(1, degree + 1) for j in range(d + 1)]
    return np.stack(cols, 1) if cols else np.zeros((len(x), 0))


class Fields:
    """The coefficients of F (``multiplicative``, (3,M)) and G (``additive``, (3,M)), starting at 0 (F = 1, G = 0)."""

    def __init__(self, degree: int, dtype: torch.dtype = torch.float64) -> None:
        self.degree = degree
        m = len(monomials(np.zeros((1, 2)), degree)[0])
        self.multiplicative = torch.zeros(3, m, dtype=dtype, requires_grad=True)
        self.additive = torch.zeros(3, m, dtype=dtype, requires_grad=True)

    @property
    def tensors(self) -> list[torch.Tensor]:
        return [self.multiplicative, self.additive]

    def apply(self, a: torch.Tensor, c: torch.Tensor, basis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(F A, F C + G) of views whose basis is ``basis`` (N,M): the affine model y = A J + C with the fields."""
        f = torch.exp(basis @ self.multiplicative.to(basis.dtype).T)
        return a * f, c * f + basis @ self.additive.to(basis.dtype).T

    def at(self, pixel_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F (N,3), G (N,3)) at pixel fractions ``pixel_uv`` (N,2)."""
        basis = torch.from_numpy(monomials(pixel_uv, self.degree))
        with torch.no_grad():
            return (torch.exp(basis @ self.multiplicative.detach().double().T).numpy(),
                    (basis @ self.additive.detach().double().T).numpy())

    def summary(self, grid: int = 33) -> dict:
        """JSON-ready: the coefficients and, over a grid of the image, each channel's range of F and of G."""
        u, v = np.meshgrid(np.linspace(0, 1, grid), np.linspace(0, 1, grid))
        f, g = self.at(np.stack([u.ravel(), v.ravel()], 1))
        return {"degree": self.degree,
                "multiplicative": np.round(self.multiplicative.detach().double().numpy(), 6).tolist(),
                "additive": np.round(self.additive.detach().double().numpy(), 6).tolist(),
                "F_min": np.round(f.min(0), 4).tolist(), "F_max": np.round(f.max(0), 4).tolist(),
                "G_min": np.round(g.min(0), 5).tolist(), "G_max": np.round(g.max(0), 5).tolist()}
