"""The camera's tone curve: what it writes for the linear signal at its sensor, as the pipeline reads it back.

The pipeline decodes every frame with sRGB, so a camera that writes through sRGB itself is the identity here. One
that writes through its own curve (an IP camera's contrast curve, a log profile) leaves a monotone, non-linear map
between the signal and the decoded value, per channel c (one curve shared by the channels):

    y_c = D(M(E(x_c))),   x_c = max(S_c + B_c, 0),
    E(x) = (1 - m) sRGB(x) + m SLog3(x),
    M(v) = c_i + s_i (v - i / K) on segment i = min(floor(K v), K - 1),   s = K softmax(l),   c_i = sum_{j<i} s_j / K,
    D(v) = the sRGB decoding, extended past 1 along its own formula,

S and B the direct signal and the backscatter reaching the sensor (linear, 0..1 at white), sRGB the IEC 61966-2-1
encoding, SLog3 Sony's S-Log3 (code value / 1023), m the profile setting (0: sRGB, 1: S-Log3), M a monotone
piecewise-linear remap of the encoded value on K equal segments of [0, 1] (extended past 1 along its last one) with
M(0) = 0 and M(1) = 1, l the K log-slopes. Every factor is strictly increasing, so the curve is monotone for every
parameter value; with l = 0 and m = 0 it is the identity (a camera that writes sRGB). Its slope is finite
everywhere (sRGB's linear toe), so are its gradients.

What pins it: the same surface point seen at different signal levels (its views' ranges, the camera's exposures,
a gain per frame) follows one curve; M(1) = 1 leaves the albedos' scale to the albedos (a curve stretched along its
input is that scale). softmax(l) is unchanged by a constant added to every l_k: the penalty ``smoothness`` sum_k
l_k^2 (:meth:`ToneCurve.penalty`) holds that direction at 0.

In the stack the curve acts last (after the gains, the black level and the clipping curve of ``sensor_response``),
on the sum S + B: the output is no longer y = A J + C in the albedo J. It is an output map (``Effect.output_map``):
its exact inverse x = E^-1(M^-1(D^-1(y))) (:func:`tone_curve_inverse`) gives back S + B = A J + C, affine again,
which the fitter fits and the corrections invert. Below T(0) (an S-Log3 camera's black, 95 / 1023 encoded) the
inverse continues the curves' linear toes, so a dark pixel's noise maps to x < 0 instead of being clipped.
"""

from __future__ import annotations

import math

import torch

from ..effect import RANK_SENSOR, Effect
from ..params import Param
from ..registry import register

#: Segments of the remap M over the encoded value.
SEGMENTS = 8


def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    """V = 12.92 x for x <= 0.0031308, else 1.055 x^(1/2.4) - 0.055 (x >= 0, linear; not clipped at 1)."""
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


def srgb_decode(v: torch.Tensor) -> torch.Tensor:
    """x = v / 12.92 for v <= 0.04045, else ((v + 0.055) / 1.055)^2.4 (v >= 0; not clipped at 1)."""
    return torch.where(v <= 0.04045, v / 12.92, ((v.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)


def slog3_encode(x: torch.Tensor) -> torch.Tensor:
    """Sony S-Log3 as code value / 1023: (420 + 261.5 log10((x + 0.01) / 0.19)) / 1023 for x >= 0.01125, else
    (95 + x (171.2102946929 - 95) / 0.01125) / 1023 (x linear reflectance, 0.18 the middle grey)."""
    log = (420.0 + 261.5 * torch.log10((x.clamp_min(0.01125) + 0.01) / 0.19)) / 1023.0
    return torch.where(x >= 0.01125, log, (95.0 + x * (171.2102946929 - 95.0) / 0.01125) / 1023.0)


def remap(v: torch.Tensor, log_slope: torch.Tensor) -> torch.Tensor:
    """M(v) of the module docstring: monotone piecewise linear on K = len(log_slope) equal segments of [0, 1],
    M(0) = 0, M(1) = 1, slopes s = K softmax(log_slope), extended linearly past 1 (and below 0)."""
    k = log_slope.shape[-1]
    slope = k * torch.softmax(log_slope, -1)
    knots = torch.cat([slope.new_zeros(1), torch.cumsum(slope, -1) / k])
    i = torch.clamp(torch.floor(v.detach() * k), 0, k - 1).to(torch.long)
    return knots[i] + slope[i] * (v - i.to(v.dtype) / k)


def slog3_decode(v: torch.Tensor) -> torch.Tensor:
    """x of :func:`slog3_encode`: 0.19 10^((1023 v - 420) / 261.5) - 0.01 above its toe (code value 171.21), else
    (1023 v - 95) 0.01125 / (171.2102946929 - 95) (negative below code value 95)."""
    code = 1023.0 * v
    log = 0.19 * torch.pow(10.0, (code.clamp_min(171.2102946929) - 420.0) / 261.5) - 0.01
    return torch.where(code >= 171.2102946929, log, (code - 95.0) * 0.01125 / (171.2102946929 - 95.0))


def remap_inverse(u: torch.Tensor, log_slope: torch.Tensor) -> torch.Tensor:
    """v of :func:`remap` with M(v) = u: the segment i whose knots hold u (the first below 0, the last past 1), then
    v = i / K + (u - c_i) / s_i."""
    k = log_slope.shape[-1]
    slope = k * torch.softmax(log_slope, -1)
    knots = torch.cat([slope.new_zeros(1), torch.cumsum(slope, -1) / k])
    i = torch.clamp(torch.searchsorted(knots[1:-1].detach().contiguous(), u.detach().contiguous(), right=True),
                    0, k - 1)
    return i.to(u.dtype) / k + (u - knots[i]) / slope[i]


#: Newton steps of :func:`encode_inverse` for a profile between sRGB and S-Log3 (the mixture has no closed form).
NEWTON_STEPS = 60


def encode_inverse(v: torch.Tensor, log_profile: torch.Tensor) -> torch.Tensor:
    """x of E(x) = (1 - m) sRGB(x) + m SLog3(x) = v, E continued along its linear toes below 0: closed form at
    m = 0 and m = 1; between them Newton's method on E, which is increasing and concave (from any start its steps
    rise to the root after the first), run on detached values, then one step with gradients: x = x* - (E(x*) - v)
    / E'(x*), whose derivatives are the implicit function's."""
    m = float(log_profile)
    if m == 0.0:
        return srgb_decode(v)
    if m == 1.0:
        return slog3_decode(v)

    def encode(x):  # both encodings continue linearly below 0
        return (1 - log_profile) * srgb_encode(x) + log_profile * slog3_encode(x)

    with torch.enable_grad():
        x = ((1 - m) * srgb_decode(v) + m * slog3_decode(v)).detach()
        for _ in range(NEWTON_STEPS):
            x = x.detach().requires_grad_(True)
            e = encode(x)
            (slope,) = torch.autograd.grad(e.sum(), x)
            x = (x - (e.detach() - v.detach()) / slope).detach()
            if bool(((e.detach() - v.detach()).abs() < 1e-15).all()):
                break
        x = x.requires_grad_(True)
        e = encode(x)
        (slope,) = torch.autograd.grad(e.sum(), x)
    x = x.detach()
    return x - (encode(x) - v) / slope


def tone_curve_inverse(y: torch.Tensor, log_slope: torch.Tensor, log_profile: torch.Tensor) -> torch.Tensor:
    """x = E^-1(M^-1(D^-1(y))): the exact inverse of :func:`tone_curve` (where y >= T(0); below, the toes
    continued), D^-1 = :func:`srgb_encode` (linear below 0), E^-1 of :func:`encode_inverse`."""
    return encode_inverse(remap_inverse(srgb_encode(y), log_slope), log_profile)


def tone_curve(signal: torch.Tensor, log_slope: torch.Tensor, log_profile: torch.Tensor) -> torch.Tensor:
    """y = D(M(E(max(signal, 0)))) of the module docstring: ``signal`` linear (any shape), ``log_slope`` (K,),
    ``log_profile`` m in [0, 1] (0: sRGB, 1: S-Log3). Returns the decoded linear value, the signal's shape."""
    x = signal.clamp_min(0.0)
    encoded = (1.0 - log_profile) * srgb_encode(x) + log_profile * slog3_encode(x)
    return srgb_decode(remap(encoded, log_slope))


@register
class ToneCurve(Effect):
    name = "tone_curve"
    summary = "the camera's own monotone tone curve (or S-Log3) between its sensor and the sRGB the pipeline decodes"
    signature = "intensity: residual that bends with brightness the same way in every channel, across exposures"
    axis = "intensity"
    rank = RANK_SENSOR + 3  # last: after the gains, the black level and the clipping curve
    #: An S-shaped curve of an IP camera: shadows crushed, mid-tones lifted, highlights rolled off.
    simulation_params = {"log_slope": (-0.6, -0.1, 0.35, 0.45, 0.3, 0.0, -0.3, -0.5)}
    params = (
        Param("log_slope", (0.15, 0.1, 0.05, 0.0, -0.05, -0.1, -0.15, -0.2), -3.0, 3.0, "",
              "log-slope of the curve on each of 8 equal segments of the encoded value (0: that of sRGB)"),
        Param("log_profile", 0.0, 0.0, 1.0, "", "the camera's encoding: 0 sRGB, 1 Sony S-Log3", learnable=False),
        Param("smoothness", 1e-5, 0.0, 1.0, "", "penalty weight lambda of the fit", learnable=False),
    )
    neutral = {"log_slope": (0.0,) * SEGMENTS, "log_profile": 0.0}
    output_map = True

    def forward(self, state):
        like = state.direct
        out = tone_curve(state.image, self.param("log_slope", like), self.param("log_profile", like))
        # the curve acts on the sum: the result is no longer separable into direct + backscatter
        return state.replace(direct=out, backscatter=torch.zeros_like(out))

    def linearise(self, y: torch.Tensor) -> torch.Tensor:
        """S + B = T^-1(y) (:func:`tone_curve_inverse`), exact."""
        return tone_curve_inverse(y, self.param("log_slope", y), self.param("log_profile", y))

    def penalty(self) -> torch.Tensor:
        """Residuals whose sum of squares is the penalty of the module docstring."""
        return math.sqrt(float(self.param("smoothness"))) * self.param("log_slope").reshape(-1).double()
