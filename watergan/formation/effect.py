"""The base class of every image-formation effect.

An effect is a small ``torch.nn.Module``: a pure, differentiable function carries the equation
(module-level, docstring with units), the class declares its bounded parameters once, and
``forward(state) -> state`` reads the inputs it needs from the state and returns a new state.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import nn

from .params import Counts, Param, ParameterError, as_tensor, to_json_value
from .state import FormationState

# Where an effect sits in the chain from scene to sensor; the simulator orders hidden effects by it.
RANK_ILLUMINATION = 10   # light reaching the scene (artificial light, caustics, ambient)
RANK_WATER = 20          # attenuation along the scene-to-camera path
RANK_SCATTER = 30        # light added by the water (backscatter, marine snow)
RANK_BLUR = 40           # forward scatter
RANK_OPTICS = 50         # lens (vignetting)
RANK_SENSOR = 60         # sensor gain and response


class Effect(nn.Module):
    """Base class. Subclasses set the class attributes and implement :meth:`forward`.

    name:        registered name (snake case), used in JSON stacks and on the command line.
    summary:     one line: what the effect does physically.
    signature:   one line: the residual it explains (by image position, range, intensity,
                 light distance, height, spatial frequency, frame, incidence angle).
    axis:        the residual axis of that signature, one of AXES (the diagnosis bins along it).
    params:      the bounded parameters.
    neutral:     parameter values that make the effect the identity (tests rely on it).
    rank:        position in the scene-to-sensor chain (see RANK_*).
    needs_image: True when the effect acts on neighbourhoods of whole images (blur, learned masks),
                 so it cannot act on per-point observation columns.
    start_grid:  starting values the diagnosis tries before fitting the effect, {param: values} (the
                 best combination wins), for effects whose fit has many local minima; empty: the fit
                 starts from the initial values.
    simulation_params: the values the simulator gives the effect when it hides it in a survey,
                 {param: value} (partial; the rest take their initial values): strong enough to be
                 found by the diagnosis on the demo survey, within what real surveys show.
    rig_params:  parameters that a declared rig fixes (survey.json's lights): known settings, set
                 from the declaration and held, not fitted, by the diagnosis.
    nuisance:    True for an effect that stands in for what the stack lacks rather than for one physical
                 effect (``image_field``, ``frame_gain``): the diagnosis never offers it as a candidate and the
                 simulator never hides it.
    channel_axis: {param: axis} of parameters whose entries along that axis (of length 3: R, G, B) each act on
                 their own colour channel only; a fit differentiates the three together (the loss is a sum over
                 channels, so they do not interact).
    same_colour_as: {param: "effect.param"} of a parameter per channel that cannot be told from another effect's where
                 their fitted values share one colour (a black level of the veil's colour is a share of the veil):
                 the diagnosis then refuses the candidate.
    output_map:  True for an invertible map of the recorded image, y = T(x) with x the image before it (a camera's
                 tone curve), acting pixel by pixel and channel by channel: it implements :meth:`linearise`, T^-1,
                 exactly, and is taken so as the stack's last effect (:meth:`Stack.output_map`). The fitter and the
                 corrections then work on T^-1(y), where the rest of the stack is affine in the in-air colour again.
    """

    AXES: ClassVar[tuple[str, ...]] = (
        "image_position", "range", "intensity", "light_distance", "height", "spatial_frequency", "frame",
        "incidence_angle",
    )

    name: ClassVar[str] = ""
    summary: ClassVar[str] = ""
    signature: ClassVar[str] = ""
    axis: ClassVar[str] = ""
    params: ClassVar[tuple[Param, ...]] = ()
    neutral: ClassVar[dict[str, object]] = {}
    rank: ClassVar[int] = RANK_WATER
    needs_image: ClassVar[bool] = False
    start_grid: ClassVar[dict[str, tuple[float, ...]]] = {}
    simulation_params: ClassVar[dict[str, object]] = {}
    rig_params: ClassVar[tuple[str, ...]] = ()
    nuisance: ClassVar[bool] = False
    channel_axis: ClassVar[dict[str, int]] = {}
    same_colour_as: ClassVar[dict[str, str]] = {}
    output_map: ClassVar[bool] = False

    def __init__(self, counts: Counts | None = None, **values) -> None:
        """Physical ``values`` by parameter name (the rest start from their ``init``); ``counts``: the survey's
        frames and lights, which size the per-frame and per-light parameters not given (:attr:`Param.per`)."""
        super().__init__()
        unknown = set(values) - {p.name for p in self.params}
        if unknown:
            known = ", ".join(p.name for p in self.params) or "none"
            raise ParameterError(f"effect '{self.name}' has no parameter {sorted(unknown)}; it has: {known}")
        self.raw = nn.ParameterDict()
        for p in self.params:
            value = as_tensor(values[p.name]) if p.name in values else p.start_value(counts or Counts(), self.name)
            p.check_shape(value, self.name)
            p.check(value, self.name)
            self.raw[p.name] = nn.Parameter(p.to_raw(value), requires_grad=p.learnable)

    def param(self, name: str, like: torch.Tensor | None = None) -> torch.Tensor:
        """The physical value of a parameter, cast to ``like``'s dtype and device when given."""
        spec = self._spec(name)
        value = spec.to_value(self.raw[name])
        return value.to(dtype=like.dtype, device=like.device) if like is not None else value

    def _spec(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise ParameterError(f"effect '{self.name}' has no parameter '{name}'")

    @classmethod
    def varies_by_frame(cls) -> bool:
        """Whether the effect holds a value per survey frame (a :class:`Param` with ``per="frame"``): it has no
        value for an image of no known frame."""
        return any(p.per == "frame" for p in cls.params)

    def per_frame(self, name: str, state: FormationState, value: torch.Tensor | None = None) -> torch.Tensor:
        """The row of per-frame parameter ``name`` (or of ``value``, one row per frame derived from it) for each
        element of the state's batch (its ``frame_index``), cast to the state's dtype: shape (B, *row)."""
        value = self.param(name, state.direct) if value is None else value
        frame = state.need("frame_index", self.name).to(torch.long)
        if len(frame) and int(frame.max()) >= value.shape[0]:
            raise ParameterError(f"{self.name}.{name} holds {value.shape[0]} frames' values; the data has frame "
                                 f"{int(frame.max())} (make the effect for this survey: Counts(frames=...))")
        return value[frame.to(value.device)]

    def values(self) -> dict[str, torch.Tensor]:
        """Every parameter's physical value (float64, detached)."""
        return {p.name: self.param(p.name).detach() for p in self.params}

    def set_values(self, **values) -> None:
        """Set physical values (checked against the bounds) without changing shapes."""
        for name, value in values.items():
            spec = self._spec(name)
            t = as_tensor(value)
            spec.check_shape(t, self.name)
            spec.check(t, self.name)
            with torch.no_grad():
                self.raw[name] = nn.Parameter(spec.to_raw(t).to(self.raw[name].device),
                                              requires_grad=spec.learnable)

    def make_neutral(self) -> None:
        """Set the effect to the identity (its ``neutral`` values; learned layers override this)."""
        self.set_values(**self.neutral)

    def linearise(self, y: torch.Tensor) -> torch.Tensor:
        """x = T^-1(y) of an output map (:attr:`output_map`), elementwise, differentiable in y and the parameters."""
        raise NotImplementedError(f"effect '{self.name}' is not an output map")

    def linearised(self, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(x, t): x = T^-1(y) (:meth:`linearise`) and t = T'(x) = 1 / (dx/dy), elementwise (by autograd), both
        differentiable in the parameters where gradients are enabled (detached where they are not)."""
        grad = torch.is_grad_enabled()
        with torch.enable_grad():
            y = y.detach().requires_grad_(True)
            x = self.linearise(y)
            (dx,) = torch.autograd.grad(x.sum(), y, create_graph=grad)
        return (x, 1.0 / dx) if grad else (x.detach(), 1.0 / dx.detach())

    def penalty(self) -> torch.Tensor | None:
        """Residuals whose sum of squares a fit adds to its loss (a prior on the parameters); None: no penalty."""
        return None

    def to_config(self) -> dict:
        """``{"name": ..., "params": {...}}`` with JSON-ready physical values."""
        return {"name": self.name, "params": {k: to_json_value(v) for k, v in self.values().items()}}

    def forward(self, state: FormationState) -> FormationState:  # pragma: no cover - abstract
        raise NotImplementedError

    @classmethod
    def describe(cls) -> str:
        """Human-readable block for ``watergan effects``."""
        lines = [f"{cls.name}: {cls.summary}", f"    explains: {cls.signature}"]
        for p in cls.params:
            hi = "inf" if not p.bounded_above else f"{p.upper:g}"
            fixed = "" if p.learnable else " (fixed setting)"
            per = f" per {p.per}" if p.per else ""
            bounds = f"[{p.lower:g}, {hi}] {p.units}{fixed}"
            lines.append(f"    - {p.name} = {_shown(p.init)}{per} in {bounds}  {p.doc}".rstrip())
        return "\n".join(lines)

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={to_json_value(v)}" for k, v in self.values().items())


def _shown(init) -> str:
    """A parameter's starting value for :meth:`Effect.describe`: as given, or its shape when it has many entries."""
    value = as_tensor(init)
    if value.numel() <= 15:
        return str(init)
    same = bool((value == value.flatten()[0]).all())
    return (f"{value.flatten()[0].item():g} at every entry of " if same else "an array of ") + \
        "x".join(map(str, value.shape))
