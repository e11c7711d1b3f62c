"""The site's water from the survey's own geometry (docs/water.md lists the passes).

- :func:`estimate_water` (frames -> :class:`WaterEstimate`) and :func:`estimate_observations` (a measurement table
  -> the same): the named passes of :mod:`eval.water.estimate`.
- :func:`fit_water`: the estimate alone (:mod:`eval.water.fit_water`).
- :class:`WaterConfig` and its named sets of alternatives (:mod:`eval.water.config`); the alternatives as objects
  (:mod:`eval.water.alternatives`); the one interval rule (:mod:`eval.water.intervals`); the nuisances beside the
  stack (:mod:`eval.water.fields`); the stack (:mod:`eval.water.stack`).
"""

from .config import ALTERNATIVE_PRESETS, DEFAULT_ALTERNATIVES, WaterConfig
from .estimate import WaterEstimate, estimate_observations, estimate_water
from .fit_water import Fit, fit_water
from .stack import build_stack, held_parameters, reads_normals, tie_parameters

__all__ = ["ALTERNATIVE_PRESETS", "DEFAULT_ALTERNATIVES", "Fit", "WaterConfig", "WaterEstimate", "build_stack",
           "estimate_observations", "estimate_water", "fit_water", "held_parameters", "reads_normals",
           "tie_parameters"]
