"""Fine per-channel fields over the image on a grid of nodes: what the water's smooth fields leave for the correction.

The water's own fields (``image_field``) are low-order on purpose, so that they cannot take the water's range
structure; a falloff clipped into a ring or a veil in a small spot is finer than they are, and what they leave the
corrected frames keep. This nuisance effect takes that rest, per channel c, with the water held:

    y_c = F_c(x) S_c + (F_c(x) B_c + G_c(x)),   log F_c(x) = sum_n f_cn w_n(x),   G_c(x) = sum_n g_cn w_n(x),

S the direct signal and B the backscatter reaching it, w_n the bilinear tent functions of the nodes of a
rows x cols grid laid corner to corner over the image (so f, g are (3, rows, cols) images of log F and G).

What pins what: as for ``image_field``, the same surface point at different image positions; it is fitted only
after the water, every other parameter held (:func:`eval.water.fields.fit_correction_grid`), so it cannot move eta or
the
backscatter, and the correction inverts it with the stack. Smoothness: the penalty (:meth:`ImageGrid.penalty`)

    lambda sum_c [ C(f_c) + C(g_c / G_SCALE) ] + ridge sum_c [ |f_c|^2 + |g_c / G_SCALE|^2 ],

C(h) the integral over the image (u, v in [0, 1]) of (d2h/du2)^2 + (d2h/dv2)^2 from the second differences of the
node images (:func:`curvature`; a plane costs nothing, and a field costs the same on any grid), lambda =
``smoothness``, and the ridge (``ridge``) keeps what the data do not pin (a node no view reaches, the constant that
trades with the albedos) at nothing.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..effect import RANK_OPTICS, Effect
from ..params import Param
from ..registry import register
from .image_field import G_SCALE

#: Nodes of the default grid (rows, cols) for a 4:3 frame.
GRID = (13, 17)


def on_nodes(nodes: torch.Tensor, pixel_uv: torch.Tensor) -> torch.Tensor:
    """(B,3,H,W) the node images ``nodes`` (3,rows,cols) interpolated bilinearly at pixel fractions ``pixel_uv``
    (B,2,H,W), node (0, 0) at the top-left corner (u = v = 0) and (rows - 1, cols - 1) at the bottom-right."""
    b, _, h, w = pixel_uv.shape
    where = (2.0 * pixel_uv - 1.0).permute(0, 2, 3, 1).reshape(1, b * h, w, 2).to(nodes.dtype)
    sampled = F.grid_sample(nodes[None], where, mode="bilinear", padding_mode="border", align_corners=True)
    return sampled.reshape(3, b, h, w).permute(1, 0, 2, 3)


def curvature(nodes: torch.Tensor) -> torch.Tensor:
    """Residuals whose sum of squares approximates the integral over the image (u, v in [0, 1]) of
    (d2f/du2)^2 + (d2f/dv2)^2 for node images ``nodes`` (3,rows,cols): the second differences along columns and
    rows over the node spacing squared, times the root of a node's area. The same field costs the same on any grid."""
    rows, cols = nodes.shape[1:]
    h_v, h_u = 1.0 / (rows - 1), 1.0 / (cols - 1)
    area = math.sqrt(h_u * h_v)
    return torch.cat([(area / h_v ** 2) * (nodes[:, 2:] - 2 * nodes[:, 1:-1] + nodes[:, :-2]).reshape(-1),
                      (area / h_u ** 2) * (nodes[:, :, 2:] - 2 * nodes[:, :, 1:-1] + nodes[:, :, :-2]).reshape(-1)])


@register
class ImageGrid(Effect):
    name = "image_grid"
    summary = "fine per-channel multiplicative and additive fields on a grid over the image (a nuisance for the " \
              "correction: what the water's smooth fields leave)"
    signature = "image position: structure fixed to the camera, finer than the water's fields (a clipped ring, a spot)"
    axis = "image_position"
    rank = RANK_OPTICS + 2
    nuisance = True
    channel_axis = {"multiplicative": 0, "additive": 0}
    params = (
        Param("multiplicative", np.zeros((3, *GRID)).tolist(), -2.0, 2.0, "", "log F at the nodes (3, rows, cols)",
              shapes=((3, -1, -1),)),
        Param("additive", np.zeros((3, *GRID)).tolist(), -0.5, 0.5, "", "G at the nodes (3, rows, cols), linear "
              "colour", shapes=((3, -1, -1),)),
        Param("smoothness", 1e-7, 0.0, 1.0, "", "weight lambda of the curvature in the fit's penalty",
              learnable=False),
        Param("ridge", 1e-6, 0.0, 1.0, "", "weight of the nodes' size in the fit's penalty", learnable=False),
    )
    neutral = {"multiplicative": np.zeros((3, *GRID)).tolist(), "additive": np.zeros((3, *GRID)).tolist()}

    def forward(self, state):
        like = state.direct
        uv = state.pixel_uv.to(like.dtype)
        factor = torch.exp(on_nodes(self.param("multiplicative", like), uv))
        return state.replace(direct=state.direct * factor,
                             backscatter=state.backscatter * factor + on_nodes(self.param("additive", like), uv))

    def penalty(self) -> torch.Tensor:
        """Residuals whose sum of squares is the penalty of the module docstring."""
        f, g = self.param("multiplicative"), self.param("additive") / G_SCALE
        root, ridge = math.sqrt(float(self.param("smoothness"))), math.sqrt(float(self.param("ridge")))
        return torch.cat([root * curvature(f), root * curvature(g),
                          ridge * f.reshape(-1), ridge * g.reshape(-1)])

    def on_grid(self, cols: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
        """(F, G) (rows, cols, 3) on a grid of the image, corner to corner."""
        u, v = np.meshgrid(np.linspace(0, 1, cols), np.linspace(0, 1, rows))
        uv = torch.from_numpy(np.stack([u, v])[None])
        with torch.no_grad():
            f = torch.exp(on_nodes(self.param("multiplicative"), uv))[0]
            g = on_nodes(self.param("additive"), uv)[0]
        return f.permute(1, 2, 0).numpy(), g.permute(1, 2, 0).numpy()
