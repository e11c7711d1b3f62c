"""A declared light rig (survey.json's ``lights``) as known settings of the effects that model it.

An effect lists in ``rig_params`` the parameters a rig declaration fixes (``artificial_light``: each light's
``offset_m``, ``tilt_deg``, ``beam_deg``). Every fit that knows the survey's lights (the diagnosis, the water
stage) sets them from the declaration and holds them: they are measured on the vehicle, and a fit that moved
them would trade them against the water (a light moved away reads as attenuation).
"""

from __future__ import annotations

from .stack import Stack


def declared_rig(effect, lights: list[dict] | None) -> tuple[str, ...]:
    """The ``rig_params`` of an effect (class or instance) that every declared light gives."""
    return tuple(k for k in effect.rig_params if lights and all(k in light for light in lights))


def rig_settings(cls, lights: list[dict] | None) -> dict:
    """Initial values of an effect from the declared light rig (empty without lights or ``rig_params``): the
    declared rig parameters, one row per light (the effect's other per-light parameters get one row per light
    from the survey's :class:`~watergan.formation.Counts`)."""
    if not lights or not cls.rig_params:
        return {}
    return {key: [light[key] for light in lights] for key in declared_rig(cls, lights)}


def held_rig(stack: Stack, lights: list[dict] | None) -> dict[str, tuple[str, ...]]:
    """{effect name: parameter names} of the stack that the declared rig fixes (known settings, not fitted)."""
    if not lights:
        return {}
    return {e.name: declared_rig(e, lights) for e in stack.effects if e.rig_params}
