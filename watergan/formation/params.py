"""Bounded physical parameters and their reparameterisation.

An effect declares each parameter once as a :class:`Param`: a name with units, an initial value,
and closed bounds ``[lower, upper]``. The optimiser only ever sees an unconstrained raw tensor;
the physical value is derived from it so that it stays inside the bounds by construction:

- lower and upper finite:  value = lower + (upper - lower) * sigmoid(raw)
- only lower finite:       value = lower + softplus(raw)

Raw tensors are stored in float64 so a value set from JSON reads back unchanged; effects cast the
value to the dtype of the image they act on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..errors import UserInputError

# Distance kept from a bound when a value on the bound itself is requested (sigmoid/softplus never
# reach their limits). It is far below any physical resolution of these parameters.
_EDGE = 1e-9


class ParameterError(UserInputError):
    """A parameter value that is unknown, non-finite, of the wrong shape or out of its bounds."""


#: What a parameter may hold one row of per item (:attr:`Param.per`), and the :class:`Counts` field sizing it.
PER = ("frame", "light")


@dataclass(frozen=True)
class Counts:
    """How many rows a per-frame or per-light parameter (:attr:`Param.per`) gets when its value is not given:
    the survey's frames, and the lights survey.json declares (None: unknown)."""

    frames: int | None = None
    lights: int | None = None

    def of(self, per: str) -> int | None:
        return {"frame": self.frames, "light": self.lights}[per]


@dataclass(frozen=True)
class Param:
    """One bounded parameter of an effect.

    ``init`` is a float (one value) or a nested tuple (per channel, ...). ``shapes`` lists the shapes
    a user may give instead (-1: any length); by default only the shape of ``init``.
    ``per="frame"`` (``"light"``) makes the value one row per survey frame (per declared light), each
    row of ``init``'s shape: an effect made for a survey (:class:`Counts`) starts with ``init`` in every
    row, so a plugin never writes the survey's length; without a count a per-light value has one row
    and a per-frame value must be given. Any number of rows is accepted when given.
    ``learnable=False`` marks a setting that is serialised with the effect but never optimised.
    ``plausible``: the envelope real surveys show, where it is narrower than the bounds (a light that a
    rig can hold, a falloff centre inside the image); the diagnosis calls a fit outside it implausible.
    """

    name: str
    init: float | tuple
    lower: float
    upper: float = math.inf
    units: str = ""
    doc: str = ""
    learnable: bool = True
    shapes: tuple[tuple[int, ...], ...] = ()
    per: str = ""
    plausible: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if not self.lower < self.upper:
            raise ParameterError(f"parameter {self.name}: lower bound {self.lower} >= upper {self.upper}")
        if self.per and (self.per not in PER or self.shapes):
            raise ParameterError(f"parameter {self.name}: per must be one of {PER} (and then no shapes), got "
                                 f"per={self.per!r}, shapes={self.shapes}")

    def start_value(self, counts: Counts, effect: str) -> torch.Tensor:
        """The value an effect starts from when none is given: ``init``, one row per frame or light for a
        per-frame or per-light parameter (see the class docstring)."""
        init = as_tensor(self.init)
        if not self.per:
            return init
        rows = counts.of(self.per)
        if rows is None and self.per == "frame":
            raise ParameterError(f"{effect}.{self.name} holds one value per survey frame: make the effect for a "
                                 f"survey (Counts(frames=...)) or give the values")
        return init.expand(rows or 1, *init.shape).clone()

    def check_shape(self, value: torch.Tensor, effect: str) -> None:
        """Raise a clear :class:`ParameterError` when ``value`` has a shape this parameter does not take."""
        row = tuple(as_tensor(self.init).shape)
        allowed = ((-1, *row),) if self.per else self.shapes or (row,)
        for shape in allowed:
            if len(shape) == value.ndim and all(s in (-1, n) for s, n in zip(shape, value.shape, strict=True)):
                return
        n = f"N {self.per}s" if self.per else "N"
        readable = " or ".join(str(tuple(n if s == -1 else s for s in shape)).replace("'", "") for shape in allowed)
        raise ParameterError(f"{effect}.{self.name} has shape {tuple(value.shape)}; expected {readable}")

    @property
    def bounded_above(self) -> bool:
        return math.isfinite(self.upper)

    def check(self, value: torch.Tensor, effect: str) -> None:
        """Raise a clear :class:`ParameterError` when ``value`` is outside ``[lower, upper]``."""
        if not torch.isfinite(value).all():
            raise ParameterError(f"{effect}.{self.name} = {value.tolist()} is not finite")
        lo, hi = value.min().item(), value.max().item()
        if lo < self.lower or hi > self.upper:
            raise ParameterError(
                f"{effect}.{self.name} = {value.tolist()} is out of its bounds "
                f"[{self.lower}, {self.upper}] {self.units}".rstrip()
            )

    def to_raw(self, value: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`to_value`: the raw tensor whose physical value is ``value``."""
        v = value.to(torch.float64)
        if self.bounded_above:
            span = self.upper - self.lower
            p = ((v - self.lower) / span).clamp(_EDGE, 1 - _EDGE)
            return torch.log(p) - torch.log1p(-p)
        x = (v - self.lower).clamp_min(_EDGE)
        # inverse softplus, stable for large x: x + log(1 - exp(-x))
        return x + torch.log(-torch.expm1(-x))

    def to_value(self, raw: torch.Tensor) -> torch.Tensor:
        """Physical value from the raw tensor; inside the bounds for every finite raw."""
        if self.bounded_above:
            return self.lower + (self.upper - self.lower) * torch.sigmoid(raw)
        return self.lower + F.softplus(raw)


def as_tensor(value) -> torch.Tensor:
    """A float64 tensor from a float, nested list/tuple or tensor."""
    if isinstance(value, torch.Tensor):
        return value.detach().to(torch.float64).clone()
    return torch.as_tensor(value, dtype=torch.float64)


def to_json_value(t: torch.Tensor):
    """A JSON-ready float or nested list, rounded to 10 significant digits (float64 noise removed)."""
    t = t.detach().cpu().to(torch.float64)
    if t.ndim == 0:
        return float(f"{t.item():.10g}")
    return [to_json_value(x) for x in t]
