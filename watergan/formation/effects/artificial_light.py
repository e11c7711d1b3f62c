"""Artificial lights mounted beside the camera (strobes, LED panels)."""

from __future__ import annotations

import math

import torch

from ..effect import RANK_ILLUMINATION, Effect
from ..params import Param
from ..registry import register
from ..state import dot3

#: Full width at half maximum of a Gaussian beam per unit sigma: 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


def beam_angle_deg(beam_sigma_deg: float) -> float:
    """The beam angle a strobe's data sheet gives (the full angle at which the intensity falls to half
    its on-axis value) of a Gaussian beam of sigma ``beam_sigma_deg``: 2 sqrt(2 ln 2) sigma, degrees."""
    return FWHM_PER_SIGMA * beam_sigma_deg


def check_rig(lights) -> None:
    """Raise ValueError unless ``lights`` declares a light rig as survey.json does: a list with, per light,
    ``offset_m`` (3 numbers: the position in the camera frame of ``images/``, metres) and optionally
    ``tilt_deg`` (2 numbers: the aim towards +x and +y, degrees), ``beam_deg`` (the Gaussian beam's sigma,
    degrees, > 0) and ``beam_angle_deg`` (the full angle at half intensity, degrees, > 0; given with
    ``beam_deg``, it must be FWHM_PER_SIGMA times it, within 0.01 degrees)."""

    def numbers(value, n: int) -> bool:
        return isinstance(value, list) and len(value) == n and all(
            isinstance(v, int | float) and math.isfinite(v) for v in value)

    if not isinstance(lights, list):
        raise ValueError(f"lights must be a list of lights, got {type(lights).__name__}")
    for i, light in enumerate(lights):
        if not isinstance(light, dict) or not numbers(light.get("offset_m"), 3):
            raise ValueError(f"light {i} needs offset_m: [x, y, z], its position in the camera frame in metres")
        if "tilt_deg" in light and not numbers(light["tilt_deg"], 2):
            raise ValueError(f"light {i}: tilt_deg must be [towards +x, towards +y] in degrees")
        for key in ("beam_deg", "beam_angle_deg"):
            if key in light and not (numbers([light[key]], 1) and light[key] > 0):
                raise ValueError(f"light {i}: {key} must be a positive number of degrees")
        if "beam_deg" in light and "beam_angle_deg" in light and \
                abs(light["beam_angle_deg"] - beam_angle_deg(light["beam_deg"])) > 0.01:
            raise ValueError(f"light {i}: beam_angle_deg {light['beam_angle_deg']} is not the full width at half "
                             f"intensity of a beam of sigma beam_deg {light['beam_deg']} "
                             f"({beam_angle_deg(light['beam_deg']):.2f}); give one or make them agree")


def beam_axes(tilt_deg: torch.Tensor) -> torch.Tensor:
    """(L,3) unit beam axes in the camera frame from (L,2) tilts (towards +x, towards +y), degrees."""
    tx, ty = torch.deg2rad(tilt_deg[:, 0]), torch.deg2rad(tilt_deg[:, 1])
    return torch.stack([torch.sin(tx) * torch.cos(ty), torch.sin(ty), torch.cos(tx) * torch.cos(ty)], dim=1)


def light_irradiance(points_cam: torch.Tensor, normals_cam: torch.Tensor, offset_m: torch.Tensor,
                     tilt_deg: torch.Tensor, beam_deg: torch.Tensor, power: torch.Tensor,
                     eta_per_m: torch.Tensor, ambient: torch.Tensor) -> torch.Tensor:
    """E_c(X) = ambient + sum_l P_l exp(-theta_l^2 / (2 sigma_l^2)) max(0, n . s_l / d_l) exp(-eta_c d_l) / d_l^2.

    For each light l at ``offset_m`` (camera frame, metres) with beam axis a_l (``tilt_deg``):
    s_l = L_l - X points from the scene point X to the light, d_l = |s_l| metres, theta_l the angle
    between a_l and X - L_l, sigma_l = ``beam_deg`` (Gaussian beam pattern), P_l the radiant
    intensity (irradiance at 1 m on axis at normal incidence, relative to the in-air light),
    eta_c (1/m) the attenuation on the light-to-scene path (the scene-to-camera path is the
    ``attenuation`` effect's). Returns the (B,3,H,W) irradiance factor that multiplies J.
    """
    axes = beam_axes(tilt_deg)
    total = ambient.reshape(1, 1, 1, 1).expand(points_cam.shape[0], 3, *points_cam.shape[2:])
    for l in range(offset_m.shape[0]):
        to_light = offset_m[l].view(1, 3, 1, 1) - points_cam
        s2 = dot3(to_light, to_light)
        d2 = s2.clamp_min(1e-6)
        d = torch.sqrt(d2)
        cos_incidence = (dot3(normals_cam, to_light) / d).clamp_min(0.0)
        along = -dot3(axes[l].view(1, 3, 1, 1), to_light)
        # |(X - L_l) x a_l| for the unit axis a_l: sqrt(d^2 - along^2)
        across = torch.sqrt((s2 - along * along).clamp_min(0.0) + 1e-12)
        theta = torch.atan2(across, along)
        sigma = torch.deg2rad(beam_deg[l])
        beam = torch.exp(-0.5 * (theta / sigma) ** 2)
        path = torch.exp(-eta_per_m.view(1, 3, 1, 1) * d)
        total = total + power[l] * beam * cos_incidence * path / d2
    return total


@register
class ArtificialLight(Effect):
    name = "artificial_light"
    summary = "lights offset from the camera: beam pattern, inverse square, cosine incidence, path attenuation"
    signature = "light distance: brightness falls with distance from the light and off its beam axis"
    axis = "light_distance"
    rank = RANK_ILLUMINATION
    simulation_params = {"offset_m": [[0.35, 0.0, 0.0]], "power": [6.0], "ambient": 0.3}
    rig_params = ("offset_m", "tilt_deg", "beam_deg")  # survey.json declares the light rig
    params = (
        Param("offset_m", (0.4, 0.0, 0.0), -3.0, 3.0, "m", "light position in the camera frame", per="light",
              plausible=(-1.5, 1.5)),  # a rig's arms hold lights within 1.5 m of the camera
        Param("tilt_deg", (0.0, 0.0), -60.0, 60.0, "deg", "beam axis tilt towards +x and +y", per="light"),
        Param("beam_deg", 35.0, 5.0, 90.0, "deg", "Gaussian beam width (sigma)", per="light"),
        Param("power", 4.0, 0.0, 100.0, "", "on-axis irradiance at 1 m", per="light"),
        Param("eta_per_m", (0.34, 0.24, 0.33), 0.0, 5.0, "1/m", "attenuation on the light-to-scene path"),
        Param("ambient", 0.0, 0.0, 10.0, "", "irradiance from other (natural) light"),
    )
    neutral = {"power": (0.0,), "ambient": 1.0}

    def __init__(self, counts=None, **values) -> None:
        super().__init__(counts, **values)
        counts = {n: self.raw[n].shape[0] for n in ("offset_m", "tilt_deg", "beam_deg", "power")}
        if len(set(counts.values())) != 1:
            raise ValueError(f"artificial_light: every per-light parameter needs one row per light, got {counts}")

    def forward(self, state):
        like = state.direct
        e = light_irradiance(state.need("points_cam", self.name), state.need("normals_cam", self.name),
                             *(self.param(n, like) for n in ("offset_m", "tilt_deg", "beam_deg", "power",
                                                              "eta_per_m", "ambient")))
        return state.replace(direct=state.direct * e)
