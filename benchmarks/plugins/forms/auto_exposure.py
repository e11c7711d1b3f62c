"""The camera's auto exposure, one gain per frame set from the frame's own pixels (a hidden form for
``benchmarks/bench_forms.py``): with Y the mean luminance 0.2126 I_R + 0.7152 I_G + 0.0722 I_B of the frame's
recorded image I = direct + backscatter, I' = (Y* / Y)^alpha I in every channel; alpha = 1 brings every frame's
mean luminance to the target Y*. The gain follows each frame's content (and so its range), so the effect cannot
act on observation columns of many frames (``needs_image``)."""

from __future__ import annotations

import torch

from watergan.formation import RANK_SENSOR, Effect, Param, register

#: Rec. 709 luminance weights of linear R, G, B.
LUMINANCE_RGB = (0.2126, 0.7152, 0.0722)


def exposure_gain(image: torch.Tensor, target: torch.Tensor | float, alpha: torch.Tensor | float) -> torch.Tensor:
    """(B,1,1,1) gains (Y* / Y)^alpha of images (B,3,H,W), Y each image's mean luminance."""
    weights = torch.tensor(LUMINANCE_RGB, dtype=image.dtype, device=image.device).view(1, 3, 1, 1)
    y = (image * weights).sum(dim=1, keepdim=True).mean(dim=(2, 3), keepdim=True).clamp_min(1e-6)
    return (target / y) ** alpha


@register
class AutoExposure(Effect):
    name = "auto_exposure"
    summary = "one gain per frame from its own mean luminance Y, I' = (Y* / Y)^alpha I"
    signature = "frame: each frame brighter or darker by a factor that follows its content"
    axis = "frame"
    rank = RANK_SENSOR + 2
    needs_image = True
    params = (
        Param("target", 0.2, 0.01, 1.0, "linear", "Y*: the mean luminance the camera exposes for"),
        Param("alpha", 1.0, 0.0, 1.0, "", "how far the gain goes towards the target (1: all the way)"),
    )
    neutral = {"alpha": 0.0}

    def forward(self, state):
        like = state.direct
        g = exposure_gain(state.direct + state.backscatter, self.param("target", like), self.param("alpha", like))
        return state.replace(direct=state.direct * g, backscatter=state.backscatter * g)
