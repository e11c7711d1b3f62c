"""The stack the water fits: the configured effects, the nuisances beside them, a declared light rig, tied and
held parameters (see docs/water.md)."""

from __future__ import annotations

import numpy as np
import torch

from watergan.formation import Counts, Stack, get
from watergan.formation.effects.image_field import n_terms
from watergan.formation.inverse import needs_normals
from watergan.formation.rig import held_rig, rig_settings

from ..fit import fitted_names
from ..observations import Observations
from .config import WaterConfig
from .fields import FIELD_EFFECT, FRAME_EFFECT, GRID_EFFECT

#: The effect that models a declared light rig when the configured stack has none.
RIG_EFFECT = "artificial_light"


def rig_lights(config: WaterConfig, lights: list[dict] | None) -> list[dict]:
    """The declared lights the fit models (none when ``config.light_rig`` is off)."""
    return list(lights or []) if config.light_rig else []


def build_stack(config: WaterConfig, n_frames: int | None = None, lights: list[dict] | None = None) -> Stack:
    """The stack to fit: ``config.effects`` by rank, starting values from ``config.initial``; parameters held per
    frame (``Param(per="frame")``, e.g. a plugin's auto-exposure) get ``n_frames`` rows. With declared ``lights``
    (survey.json's, see ``WaterConfig.light_rig``) the stack models the rig: ``RIG_EFFECT`` is added unless an
    effect with ``rig_params`` is listed, each such effect takes the declared rig values
    (:func:`watergan.formation.rig.rig_settings`) and one row per light of its other per-light parameters.
    ``config.tied_params`` are then tied (:func:`tie_parameters`)."""
    lights = rig_lights(config, lights)
    given = {e["name"]: dict(e.get("params", {})) for e in config.initial}
    names = list(dict.fromkeys(list(config.effects) + list(given)))
    if config.field_degree > 0:
        names += [FIELD_EFFECT] if FIELD_EFFECT not in names else []
        zeros = np.zeros((3, n_terms(config.field_degree))).tolist()
        given[FIELD_EFFECT] = {"multiplicative": zeros, "additive": zeros, "orthogonal_to": zeros[0],
                               **given.get(FIELD_EFFECT, {})}
    if config.field_grid is not None:
        names += [GRID_EFFECT] if GRID_EFFECT not in names else []
        zeros = np.zeros((3, *config.field_grid)).tolist()
        given[GRID_EFFECT] = {"multiplicative": zeros, "additive": zeros, **given.get(GRID_EFFECT, {})}
    if config.frame_gain and n_frames and not any(get(n).varies_by_frame() for n in names):
        names.append(FRAME_EFFECT)
    if lights and not any(get(n).rig_params for n in names):
        names.append(RIG_EFFECT)
    entries = [{"name": n, "params": {**given.get(n, {}), **rig_settings(get(n), lights)}} for n in names]
    stack = Stack.ordered(entries, counts=Counts(frames=n_frames, lights=len(lights) or None)).to(torch.float64)
    tie_parameters(stack, config.tied_params)
    return stack


def reads_normals(config: WaterConfig, n_frames: int, lights: list[dict] | None = None) -> bool:
    """Whether the stack :func:`build_stack` makes reads each view's surface normal (a declared light rig, an effect
    added that reads them): its tables then measure them."""
    return needs_normals(build_stack(config, n_frames, lights))


def tie_parameters(stack: Stack, tied: tuple[tuple[str, str], ...]) -> list[str]:
    """Make each follower parameter ("effect.param") the same tensor as its leader where both effects are in the
    stack (in place; the follower takes the leader's value): fitting the leader moves both. Returns the tied
    followers. Raises ValueError when the two differ in bounds or shape (one raw value cannot serve both)."""
    done = []
    for follower, leader in tied:
        (f_name, f_param), (l_name, l_param) = follower.split(".", 1), leader.split(".", 1)
        if f_name not in stack.names or l_name not in stack.names:
            continue
        f_effect, l_effect = stack[f_name], stack[l_name]
        f_spec, l_spec = f_effect._spec(f_param), l_effect._spec(l_param)
        if (f_spec.lower, f_spec.upper) != (l_spec.lower, l_spec.upper) or \
                f_effect.raw[f_param].shape != l_effect.raw[l_param].shape:
            raise ValueError(f"cannot tie {follower} to {leader}: their bounds or shapes differ")
        f_effect.raw[f_param] = l_effect.raw[l_param]
        done.append(follower)
    return done


def held_parameters(stack: Stack, config: WaterConfig, lights: list[dict] | None) -> dict[str, str]:
    """{"effect.param": why} of the parameters held inside fitted effects: the declared rig
    (:func:`watergan.formation.rig.held_rig`), ``config.held_params`` and the tied followers."""
    held = {}
    for name, params in held_rig(stack, rig_lights(config, lights)).items():
        held.update({f"{name}.{p}": "declared in survey.json's lights (a known setting, not fitted)" for p in params})
    for key in config.held_params:
        if key.split(".", 1)[0] in stack.names:
            held.setdefault(key, "held at its starting value (see WaterConfig.held_params)")
    for follower, leader in config.tied_params:
        if follower.split(".", 1)[0] in stack.names and leader.split(".", 1)[0] in stack.names:
            held[follower] = f"tied to {leader} (one water)"
    return held


def water_names(stack: Stack, obs: Observations, config: WaterConfig,
                lights: list[dict] | None) -> tuple[list[str], dict[str, str], dict[str, str]]:
    """(the raw parameters of ``stack`` the water's fit moves, {effect: why} of the effects it holds (``gain``
    without a board), {"effect.param": why} of the parameters it holds inside fitted effects
    (:func:`held_parameters`))."""
    fixed = {name: "held at its configured value" for name in config.fit.fixed_effects}
    if len(obs.board_colour) == 0 and "gain" in stack.names:
        fixed["gain"] = "no board: degenerate with the albedo scale (and B_inf's level), held at its value"
    held = held_parameters(stack, config, lights)
    by_effect: dict[str, tuple[str, ...]] = {}
    for key in held:
        name, param = key.split(".", 1)
        by_effect[name] = (*by_effect.get(name, ()), param)
    return fitted_names(stack, tuple(fixed), by_effect), fixed, held
