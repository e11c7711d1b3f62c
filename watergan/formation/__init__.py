"""The image-formation physics library shared by the simulator, WaterGAN and the diagnosis."""

from .effect import RANK_BLUR, RANK_ILLUMINATION, RANK_OPTICS, RANK_SCATTER, RANK_SENSOR, RANK_WATER, Effect
from .params import Counts, Param, ParameterError
from .registry import (
    ENTRY_POINT_GROUP,
    PluginError,
    UnknownEffectError,
    available,
    builtin_effects,
    get,
    load_plugin,
    register,
)
from .stack import Stack
from .state import FormationState, MissingInputError, normalised_radius, pixel_grid, state_from_rgbd

__all__ = [
    "Effect", "Param", "Counts", "ParameterError", "FormationState", "MissingInputError", "Stack",
    "register", "get", "available", "builtin_effects", "load_plugin", "PluginError", "UnknownEffectError",
    "ENTRY_POINT_GROUP",
    "pixel_grid", "normalised_radius", "state_from_rgbd",
    "RANK_ILLUMINATION", "RANK_WATER", "RANK_SCATTER", "RANK_BLUR", "RANK_OPTICS", "RANK_SENSOR",
]
