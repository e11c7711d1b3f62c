"""A gain per frame and channel set by the camera (a white balance or exposure that changes along the survey,
not from the frame's content; a hidden form for ``benchmarks/bench_forms.py``): I_fc = exp(g_fc) S_fc."""

from __future__ import annotations

import torch

from watergan.formation import RANK_SENSOR, Effect, Param, register


@register
class FrameColourGain(Effect):
    name = "frame_colour_gain"
    summary = "a gain per frame and channel, I_fc = exp(g_fc) S_fc"
    signature = "frame: a frame's colour scaled by its own factor per channel"
    axis = "frame"
    rank = RANK_SENSOR + 1
    params = (Param("log_gain", (0.0, 0.0, 0.0), -1.5, 1.5, "", "g_fc: log of the frame's gain per channel",
                    per="frame"),)
    neutral = {}

    def forward(self, state):
        g = torch.exp(self.per_frame("log_gain", state)).view(-1, 3, 1, 1)
        return state.replace(direct=state.direct * g, backscatter=state.backscatter * g)
