"""The camera's auto white balance, a gray-world gain per frame set from the frame's own pixels (a hidden form
for ``benchmarks/bench_forms.py``): with m_c the mean of channel c over the frame's recorded image
I = direct + backscatter and m = (m_R + m_G + m_B) / 3, I'_c = (m / m_c)^alpha I_c; alpha = 1 makes the frame's
mean grey, alpha < 1 corrects part of the way. The gains follow each frame's content (and so its range), so the
effect cannot act on observation columns of many frames (``needs_image``)."""

from __future__ import annotations

import torch

from watergan.formation import RANK_SENSOR, Effect, Param, register


def gray_world_gain(image: torch.Tensor, alpha: torch.Tensor | float) -> torch.Tensor:
    """(B,3,1,1) gains (m / m_c)^alpha of images (B,3,H,W): m_c each channel's mean, m their mean."""
    m = image.mean(dim=(2, 3), keepdim=True).clamp_min(1e-6)
    return (m.mean(dim=1, keepdim=True) / m) ** alpha


@register
class AutoWhiteBalance(Effect):
    name = "auto_white_balance"
    summary = "gray-world gain per frame from its own pixels, I'_c = (m / m_c)^alpha I_c"
    signature = "frame: each frame's colour pulled towards grey by gains that follow its content"
    axis = "frame"
    rank = RANK_SENSOR + 2
    needs_image = True
    params = (Param("alpha", 1.0, 0.0, 1.0, "", "how far the gains go towards the gray world (1: all the way)"),)
    neutral = {"alpha": 0.0}

    def forward(self, state):
        g = gray_world_gain(state.direct + state.backscatter, self.param("alpha", state.direct))
        return state.replace(direct=state.direct * g, backscatter=state.backscatter * g)
