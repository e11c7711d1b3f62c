"""A gain per frame and channel: what the stack lacks along the survey, carried beside the water.

Auto-exposure and auto white balance scale each frame's signal by its own factor, and a water that changes along
the survey (its attenuation drifting) mostly does the same to a frame at its ranges. A fit without this would bend
the water to explain it. This nuisance effect takes it, per frame f and channel c:

    y_fc = exp(g'_fc) (S_c + B_c),   g' = g - Q (Q^T g) per channel,

S the direct signal and B the backscatter reaching the sensor (a gain at the sensor, like ``gain``), g the
parameters (frames, 3) and Q (frames, 2) orthonormal columns the gains are kept off (``orthogonal_to``).

What pins what: a frame flown higher sees its points farther, so its mean range makes it darker by
exp(-eta_c dr), which is what a gain per frame is too; and the same point seen in two frames differs by
g'_a - g'_b - eta (r_a - r_b), of which only the range differences that vary across the points the two frames share
(relief, view angles) pin eta apart from the gains, and only weakly. So a fit sets Q's columns to the constant and
to the frames' mean ranges (centred; :func:`eval.water.fields.decorrelate_frames`): the gains then have no mean (that is
the survey's gain ``gain.k``) and no covariance with the frames' ranges (that is the water's); they take what
changes from frame to frame apart from range: exposure, white balance, a drifting water's change at the frame's
ranges. An exposure that happens to follow altitude is taken by the water, as without this effect. A penalty
``smoothness`` sum_fc g_fc^2 (:meth:`FrameGain.penalty`) keeps the parameters' part along Q (which has no effect)
at 0. The water measures the gains first and fits them only where a frame's exceeds
``eval.water.fields.FRAME_CARRY_PCT``
(:func:`eval.water.fields.measure_frame_gains`); held at 0, they are not applied.
"""

from __future__ import annotations

import math

import torch

from ..effect import RANK_SENSOR, Effect
from ..params import Param
from ..registry import register


def apply_frame_gain(direct: torch.Tensor, backscatter: torch.Tensor,
                     g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(exp(g) S, exp(g) B) = the signal of each batch element scaled by its frame's gain; g (B,3) its log gains."""
    gain = torch.exp(g).view(-1, 3, 1, 1)
    return direct * gain, backscatter * gain


@register
class FrameGain(Effect):
    name = "frame_gain"
    summary = "a gain per frame and channel exp(g_fc) (a nuisance: exposure, white balance, water along the survey)"
    signature = "frame: every pixel of a frame brighter or darker by one factor per channel"
    axis = "frame"
    rank = RANK_SENSOR + 1
    nuisance = True
    channel_axis = {"log_gain": 1}
    params = (
        Param("log_gain", (0.0, 0.0, 0.0), -2.0, 2.0, "", "g per frame and channel (frames, 3)", per="frame"),
        Param("orthogonal_to", (0.0, 0.0), -1.0, 1.0, "", "orthonormal columns Q (frames, 2) the gains are kept off "
              "(0: none; a fit sets them to the constant and the frames' mean ranges)", per="frame", learnable=False),
        Param("smoothness", 1e-5, 0.0, 1.0, "", "penalty weight lambda of the fit", learnable=False),
    )
    neutral = {}

    def gains(self, like: torch.Tensor | None = None) -> torch.Tensor:
        """(frames, 3) g' as applied: the parameters projected off ``orthogonal_to``."""
        g, q = self.param("log_gain", like), self.param("orthogonal_to", like)
        return g - q @ (q.T @ g)

    def forward(self, state):
        g = self.gains(state.direct)
        if not g.requires_grad and not bool(g.any()):  # every gain exactly 1: held, as where the water carries none
            return state
        direct, back = apply_frame_gain(state.direct, state.backscatter, self.per_frame("log_gain", state, g))
        return state.replace(direct=direct, backscatter=back)

    def penalty(self) -> torch.Tensor:
        """Residuals whose sum of squares is the penalty of the module docstring."""
        return math.sqrt(float(self.param("smoothness"))) * self.param("log_gain").reshape(-1).double()
