"""How the water is estimated: :class:`WaterConfig`, and the named sets of alternatives its intervals take in."""

from __future__ import annotations

from dataclasses import dataclass

from ..fit import DEFAULT_EFFECTS, WATER_FIT, FitConfig
from ..observations import DenseMeasureConfig
from .alternatives import Alternative, BoardWeight, FineFields, FreeGains, LightLevel, LossScale, Profile

#: The alternatives the intervals take in by default, in the order they run: the weighting's perturbations, the
#: light-level split, the two structures (each with its held-out test) and eta's profile under the free gains.
DEFAULT_ALTERNATIVES: tuple[Alternative, ...] = (BoardWeight(), LossScale(), LightLevel(), FreeGains(), FineFields(),
                                                 Profile())
#: Named sets of alternatives. "fast": without the fine fields over the image fitted with the water (the most
#: expensive structure: a grid of hundreds of parameters) and without eta's profile; for tests and studies whose
#: survey has nothing on image position to hide and whose question is not the width of eta's interval. "none": the
#: bootstrap alone.
ALTERNATIVE_PRESETS: dict[str, tuple[Alternative, ...]] = {
    "default": DEFAULT_ALTERNATIVES,
    "fast": (BoardWeight(), LossScale(), LightLevel(), FreeGains()),
    "none": (),
}


@dataclass(frozen=True)
class WaterConfig:
    """How the water is estimated: the effects, how the table is measured and fitted, the nuisances beside the
    stack and the alternatives its intervals take in (docs/water.md lists the passes)."""

    effects: tuple[str, ...] = DEFAULT_EFFECTS
    """Effects of the stack (any registered name), placed in scene-to-sensor order by their rank."""
    light_rig: bool = True
    """Model the lights the survey declares (the lights of survey.json) with the declared rig held.
    The stack then gets the artificial light effect with the rig's offset, tilt and beam held."""
    held_params: tuple[str, ...] = ("artificial_light.power",)
    """Parameters (effect.param) held at their starting values inside fitted effects.
    The lights' power, by default: it is exactly degenerate with the gain."""
    tied_params: tuple[tuple[str, str], ...] = (("artificial_light.eta_per_m", "attenuation.eta_per_m"),)
    """(follower, leader) pairs that share one value when both effects are in the stack (one water, one eta)."""
    initial: tuple[dict, ...] = ()
    """Optional {name, params} entries giving starting (or, for fixed effects, held) values."""
    measure: DenseMeasureConfig = DenseMeasureConfig()
    """How the measurement table is taken from the frames."""
    fit: FitConfig = WATER_FIT
    """How the stack is fitted (the gain is held without a board)."""
    field_degree: int = 2
    """Degree of the smooth fields over the image fitted beside the stack, so that what the stack lacks on image
    position bends them and not the water; 0: none. The corrections invert them with the stack."""
    frame_gain: bool = True
    """Measure a gain per frame and channel and fit it beside the stack when some frame's exceeds 10 %, so that what
    the stack lacks along the survey (auto exposure, white balance, a water that drifts) bends it and not the water;
    not when an effect of the stack already has a value per frame. The physics correction inverts it."""
    frame_gain_off_range: bool = True
    """Keep the gains per frame off the frames' mean ranges: the level of eta then comes from the frames' ranges.
    Off: the gains are free apart from their mean and always carried, and eta comes from the range differences within
    the points that frames share (a camera that sets its gains from each frame's content)."""
    field_grid: tuple[int, int] | None = None
    """Nodes (rows x cols, at least 3 x 3) of fine fields over the image fitted jointly with the water beside the
    smooth ones: they follow a falloff or a veil of any smooth shape, so that its form does not bend the water.
    None: none (one of the default alternatives fits them)."""
    correction_grid: tuple[int, int] | None = (13, 17)
    """Nodes (rows x cols, at least 3 x 3) of fine fields over the image fitted after the water with every other
    parameter held, and carried for the corrections where they exceed 5 % of the signal: what the water's smooth
    fields leave on image position. None: none."""
    field_max_range_r2: float = 0.5
    """When image position explains more than this fraction of the views' range variance (one altitude over a flat
    floor), the fields are kept uncorrelated with range."""
    alternatives: tuple[Alternative, ...] = DEFAULT_ALTERNATIVES
    """The alternatives the intervals take in, in order (a named set of them: ALTERNATIVE_PRESETS)."""
    range_scale_sd: float = 0.0
    """Relative 1-sigma uncertainty of the range maps' metric scale (the SfM stage's scale spread).
    The intervals of coefficients in 1/m widen by 1.96 x this x value, in quadrature."""

    def __post_init__(self) -> None:
        from watergan.errors import UserInputError

        for label, grid in (("field grid", self.field_grid), ("correction grid", self.correction_grid)):
            if grid is not None and min(grid) < 3:
                raise UserInputError(f"{label} {grid[0]}x{grid[1]}: the fine fields need at least 3 x 3 nodes "
                                     "(or none)")
