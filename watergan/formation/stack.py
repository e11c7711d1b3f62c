"""A formation stack: effects applied in order, built from and serialised to JSON.

The configuration is a list of ``{"name": ..., "params": {...}}``; ``params`` may be partial (the
rest take their initial values) and ``Stack.from_config(cfg).to_config()`` lists every parameter,
so a full configuration round-trips unchanged.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import nn

from .effect import Effect
from .params import Counts, ParameterError
from .registry import get
from .state import FormationState


class Stack(nn.Module):
    """Effects applied in order: ``state -> effect_1 -> ... -> effect_n``."""

    def __init__(self, effects: list[Effect]) -> None:
        super().__init__()
        names = [e.name for e in effects]
        duplicates = {n for n in names if names.count(n) > 1}
        if duplicates:
            raise ParameterError(f"a stack holds each effect once; repeated: {sorted(duplicates)}")
        self.effects = nn.ModuleList(effects)

    @classmethod
    def from_config(cls, config: list[dict] | str, counts: Counts | None = None) -> Stack:
        """From a list of ``{name, params}`` (or its JSON text); ``counts`` sizes the per-frame and per-light
        parameters not given (see :class:`~watergan.formation.params.Param`)."""
        if isinstance(config, str):
            config = json.loads(config)
        if not isinstance(config, list):
            raise ParameterError(f"a stack configuration is a list of {{name, params}}, got {type(config).__name__}")
        effects = []
        for i, item in enumerate(config):
            if isinstance(item, str):
                item = {"name": item}
            if not isinstance(item, dict) or "name" not in item:
                raise ParameterError(f"stack entry {i} must be {{'name': ..., 'params': {{...}}}}, got {item!r}")
            extra = set(item) - {"name", "params"}
            if extra:
                raise ParameterError(f"stack entry {i} ({item['name']}) has unknown keys {sorted(extra)}")
            effects.append(get(item["name"])(counts=counts, **item.get("params", {})))
        return cls(effects)

    @classmethod
    def from_names(cls, names: list[str], counts: Counts | None = None) -> Stack:
        """Each named effect at its initial parameters."""
        return cls.from_config([{"name": n} for n in names], counts)

    @staticmethod
    def rank_order(entries: list[dict | str] | tuple[dict | str, ...]) -> list[dict | str]:
        """Stack entries (``{name, params}`` or names) in scene-to-sensor order: a stable sort by
        their class ``rank``, so entries of equal rank keep the given order."""
        return sorted(entries, key=lambda e: get(e if isinstance(e, str) else e["name"]).rank)

    @classmethod
    def ordered(cls, entries: list[dict | str] | tuple[dict | str, ...], counts: Counts | None = None) -> Stack:
        """The stack of ``entries`` (``{name, params}`` or names) placed by rank (see :meth:`rank_order`)."""
        return cls.from_config(cls.rank_order(entries), counts)

    def with_effect(self, effect: Effect) -> Stack:
        """A new stack of these effects (the same modules) with ``effect`` inserted after every effect of
        lower or equal rank: in a stack ordered by rank, where :meth:`rank_order` would place it."""
        effects = list(self.effects)
        at = sum(1 for e in effects if e.rank <= effect.rank)
        return type(self)([*effects[:at], effect, *effects[at:]])

    @classmethod
    def load(cls, path: str | Path) -> Stack:
        return cls.from_config(json.loads(Path(path).read_text()))

    def to_config(self) -> list[dict]:
        return [e.to_config() for e in self.effects]

    def to_json(self) -> str:
        return json.dumps(self.to_config(), indent=2)

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.effects]

    def __getitem__(self, name: str) -> Effect:
        for e in self.effects:
            if e.name == name:
                return e
        raise KeyError(f"stack has no effect '{name}'; it has {self.names}")

    def output_map(self) -> tuple[Stack, Effect | None]:
        """(the stack before its output map, the map) when the last effect is an invertible output map
        (:attr:`Effect.output_map`: y = T(F'(J)), F' the rest), the rest sharing these effects' modules and
        parameters; (this stack, None) otherwise (an output map elsewhere is an ordinary effect, not affine in J).
        :meth:`ordered` puts an output map last."""
        if len(self.effects) and self.effects[-1].output_map:
            return type(self)(list(self.effects)[:-1]), self.effects[-1]
        return self, None

    def forward(self, state: FormationState) -> FormationState:
        for effect in self.effects:
            state = effect(state)
        return state

    def render(self, state: FormationState) -> torch.Tensor:
        """The recorded image (direct + backscatter) after every effect."""
        return self(state).image
