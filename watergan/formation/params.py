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


@dataclass(frozen=True)
class Param:
    """One bounded parameter of an effect.

    ``init`` is a float (one value) or a nested tuple (per channel, per light, ...). ``shapes`` lists
    the shapes a user may give instead (-1: any length), e.g. ``((-1, 3),)`` for several lights; by
    default only the shape of ``init``.
    ``learnable=False`` marks a setting that is serialised with the effect but never optimised.
    """

    name: str
    init: float | tuple
    lower: float
    upper: float = math.inf
    units: str = ""
    doc: str = ""
    learnable: bool = True
    shapes: tuple[tuple[int, ...], ...] = ()

    def __post_init__(self) -> None:
        if not self.lower < self.upper:
            raise ParameterError(f"parameter {self.name}: lower bound {self.lower} >= upper {self.upper}")

    def check_shape(self, value: torch.Tensor, effect: str) -> None:
        """Raise a clear :class:`ParameterError` when ``value`` has a shape this parameter does not take."""
        allowed = self.shapes or (tuple(as_tensor(self.init).shape),)
        for shape in allowed:
            if len(shape) == value.ndim and all(s in (-1, n) for s, n in zip(shape, value.shape, strict=True)):
                return
        readable = " or ".join(str(tuple("N" if s == -1 else s for s in shape)) for shape in allowed)
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
