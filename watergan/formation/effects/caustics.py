"""Caustics: the moving sunlight pattern focused by surface waves onto up-facing surfaces."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..effect import RANK_ILLUMINATION, Effect
from ..params import Param
from ..registry import register

# Three wave trains 120 degrees apart (slightly detuned) make the familiar cell-like network.
_DIRECTIONS_DEG = (0.0, 118.0, 243.0)
_SPEED_FACTORS = (1.0, 1.3, 0.7)


def caustic_pattern(points_world: torch.Tensor, frame: torch.Tensor, wavelength_m: torch.Tensor,
                    drift_m_per_frame: torch.Tensor) -> torch.Tensor:
    """P(x, y, t) = (1/3) sum_j cos(2 pi (u_j . (x, y) + v_j t drift) / lambda), in [-1, 1].

    u_j unit directions in the horizontal plane, t the frame index, lambda the pattern's
    wavelength in metres, drift how far the pattern moves per frame in metres. Returns (B,1,H,W).
    """
    t = frame.to(points_world.dtype).view(-1, 1, 1, 1)
    x, y = points_world[:, 0:1], points_world[:, 1:2]
    total = torch.zeros_like(x)
    for deg, speed in zip(_DIRECTIONS_DEG, _SPEED_FACTORS, strict=True):
        ux, uy = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        total = total + torch.cos(2 * math.pi * (ux * x + uy * y + speed * drift_m_per_frame * t) / wavelength_m)
    return total / 3.0


def apply_caustics(direct: torch.Tensor, pattern: torch.Tensor, normals_world: torch.Tensor,
                   water_depth_m: torch.Tensor, contrast: torch.Tensor, decay_per_m: torch.Tensor) -> torch.Tensor:
    """D = J (1 + kappa exp(-k d_w) max(0, n_z) P).

    kappa the contrast at the surface (0..1), k (1/m) how fast it fades with the scene point's
    water depth d_w (metres), n_z the up component of the world normal (only up-facing surfaces
    see the sun), P the pattern in [-1, 1]; the factor stays >= 0 because kappa <= 1.
    """
    up = normals_world[:, 2:3].clamp_min(0.0)
    return direct * (1.0 + contrast * torch.exp(-decay_per_m * water_depth_m) * up * pattern)


@register
class Caustics(Effect):
    name = "caustics"
    summary = "sunlight network on up-facing surfaces, contrast fading with water depth, moving per frame"
    signature = "frame: a bright-dark pattern on the seafloor that changes between frames of the same point"
    axis = "frame"
    rank = RANK_ILLUMINATION
    simulation_params = {"contrast": 0.6, "decay_per_m": 0.02}
    #: A moving periodic pattern: the fit finds the cell size and drift only from within about a quarter
    #: cycle of phase over the survey, so the grid is uniform in spatial frequency (0.5 to 10 cycles/m in
    #: steps of 0.1, cells 0.1 to 2 m) and drift (0 to 0.3 m/frame in 1 cm steps).
    start_grid = {"wavelength_m": tuple((1.0 / np.arange(0.5, 10.01, 0.1)).tolist()),
                  "drift_m_per_frame": tuple(np.arange(0.0, 0.301, 0.01).tolist())}
    params = (
        Param("contrast", 0.5, 0.0, 1.0, "", "pattern contrast at the surface"),
        Param("decay_per_m", 0.05, 0.0, 2.0, "1/m", "contrast decay with water depth"),
        Param("wavelength_m", 0.4, 0.05, 5.0, "m", "pattern cell size"),
        Param("drift_m_per_frame", 0.07, 0.0, 1.0, "m", "pattern motion between frames"),
    )
    neutral = {"contrast": 0.0}

    def forward(self, state):
        like = state.direct
        frame = state.need("frame_index", self.name)
        pattern = caustic_pattern(state.need("points_world", self.name), frame,
                                  self.param("wavelength_m", like), self.param("drift_m_per_frame", like))
        out = apply_caustics(state.direct, pattern, state.need("normals_world", self.name),
                             state.need("water_depth_m", self.name), self.param("contrast", like),
                             self.param("decay_per_m", like))
        return state.replace(direct=out)
