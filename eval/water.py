"""The site's water from the survey's own geometry.

``estimate_water(frames, K, ...)`` measures the survey's table (:func:`eval.observations.measure_frames`: dense
correspondences, optional SfM tracks and board) and fits a formation stack to it (default
:data:`eval.fit.DEFAULT_EFFECTS`; any registered effect may be added) with the one fitter (:mod:`eval.fit`,
configured by :data:`eval.fit.WATER_FIT`); ``watergan.formation.inverse.correct_physics`` inverts the fitted stack
pixel by pixel with each pixel's range. Both are functions of arrays: the pipeline's ``water`` stage reads the
workspace and calls them.

Model. Every built-in effect of the default stack is affine in the in-air colour J, so a view o (a surface point p
seen in frame f at pixel x_o with range r_o) records per channel c

    y_oc = A_c(x_o, r_o; theta) J_pc + C_c(x_o, r_o; theta)
    (default stack: A = k_c exp(-eta_c r) / V(x),  C = k_c B_inf,c (1 - exp(-beta_c r)) / V(x)),

with A = render(J = 1) - render(J = 0) and C = render(J = 0) of the stack (so added effects need no special code).
Per point the albedo J_p is projected out in closed form (clamped at 0); theta is fitted on a soft-L1 loss of the
views plus ``board_weight`` times that of the board rows (known J).

What pins what (and what does not):

- attenuation eta_c: the same point seen at several ranges; the ratio of its views falls as exp(-eta_c dr).
  Frames flown at different altitudes see a point at one image position at different ranges, which separates eta
  from the vignetting; channel differences of eta are pinned even without that (the centred vignetting and the
  range are the same for the three channels).
- backscatter B_inf,c: the offset of each view (C above) that no albedo explains: points seen at several ranges
  give C(r2) - (A2/A1) C(r1), for beta near eta B_inf (1 - exp(-eta dr)). Dark pixels (J clamped at 0) record C
  alone. The board pins C at its ranges outright (known J, the black patch).
- backscatter beta_c: only through the curvature of C over the survey's range span; the family J_p + d,
  B(r) - d exp(-eta r) is close to the model's, so beta is weakly pinned, the more weakly the closer beta is to eta.
- vignetting (a, b, c): the same point at different image positions; ``vignetting_offcentre`` (added) also its
  centre and per-channel strength (only the product of the two vignettings, and the strength ratios between
  channels, are pinned).
- gain k_c: exactly degenerate with the albedos' scale per channel (k J = (k s)(J / s)), and B_inf carries the
  same factor. With a board, its known J pins k (and B_inf's absolute level); without one ``gain`` keeps its
  configured value (1) and is reported as fixed.
- the fields over the image (``image_field``, degree ``field_degree``; :func:`decorrelate_fields`): what the stack
  lacks on image position, multiplicative F and additive G per channel, pinned by the same point at different image
  positions; where image position explains most of the range (one altitude over a flat floor) they are kept
  uncorrelated with range, which is then the water's. An effect on image position added to the stack is fitted
  before them (:func:`stack_first`): the fields take only what its form leaves. G's level is not pinned (a constant
  light is B_inf's level over the survey's ranges): the fit holds G at 0 at the image's centre, and where the fields
  are additive alone (a light fixed in the image) :func:`set_light_level` moves the light's least level over the
  views out of the veil.
- the gains per frame (``frame_gain``, ``frame_gain=True``; :func:`decorrelate_frames`): what the stack lacks from
  frame to frame (exposure, white balance, a drifting water), per frame and channel, pinned by the same points seen
  in several frames; kept off the constant (the survey's gain) and off the frames' mean ranges (the water's), so
  eta's level comes from the frames' ranges as without them.
- a camera that sets its gains from each frame's content makes them follow the frames' mean ranges, which the gains
  are kept off: ``structure_alternatives`` (by default the gains free of the ranges, ``frame_gain_off_range=False``)
  refits the water from its start under another structure (:func:`structure_fits`), and each parameter's change
  counts in its interval as a specification alternative's; fitted with and without it on four fifths of the
  points, the other fifth's views say whether the survey prefers it (predicted better over the whole 95 % interval
  of the paired change).
- a falloff or a veil whose shape the smooth fields do not share (a clipped ring, a spot) leaves its rest to eta
  and the veil: the second structure alternative fits fine fields over the image (``image_grid``, ``field_grid``
  nodes, a curvature penalty) jointly with the water, so that only what the same point at different ranges and
  image positions says pins eta; what a survey at one altitude over a flat floor cannot separate (image position
  then explains range) stays with the smooth fields' decorrelation.

Uncertainty: the fitter's bootstrap (:func:`eval.bootstrap.bootstrap`: frames, points and board patches resampled,
each replicate refitted from the full fit by a Newton step and a few L-BFGS iterations). Resampling cannot see a
bias that every subset shares, so the fit is repeated under ``spec_alternatives`` (by default the board weighted 10x
less; refitted from the full fit by the same Newton step and ``SPEC_ITERATIONS`` L-BFGS iterations) and each
parameter's largest change is added in quadrature (each alternative's own change is kept beside it,
``specification_by``): interval = estimate +- sqrt((1.96 sd_boot)^2 + change^2 [+ (1.96
range_scale_sd value)^2 for coefficients in 1/m]), clipped to the bounds. A structure alternative is another model
of the survey rather than a perturbation of this one, so the interval also covers each one's estimate with the
same sampling spread around it (:func:`eval.intervals.cover_the_structures`: the union of their 95 % intervals,
the veil's alike). Where the survey prefers gains per frame free of the ranges, eta's loss is nearly flat (a gain
per frame takes its effect on each frame's mean range) and the resampling spread far narrower than where eta may
go: its interval also covers what the held-out views accept along eta under them (:mod:`eval.eta_profile`,
:func:`eval.intervals.cover_the_profiles`). A component on a bound
(:func:`eval.intervals.on_bound`) gets its parameter's whole range: the data pushed it out of the model and do not
pin it. Pairs of parameter components whose bootstrap correlation exceeds 0.95 are reported as trade-offs
(:func:`eval.intervals.describe_intervals`). Where B_inf and beta trade (a short range span), what the survey pins
is the veil over its ranges: ``veil`` gives B_inf (1 - exp(-beta r)) at the views' median range with its interval,
bootstrap and specification change alike (:func:`eval.intervals.veil_at_median_range`), and B_inf's interval covers
the valley along which the veil's and beta's intervals leave it (:func:`eval.intervals.cover_the_valley`).

A declared light rig (``lights``: survey.json's strobes, per light offset_m, tilt_deg, beam_deg): the stack gets
``artificial_light`` (:func:`build_stack`), so each view's in-air colour is lit by

    E_c(X) = ambient + sum_l P_l exp(-theta_l^2 / (2 sigma_l^2)) max(0, n . s_l / d_l) exp(-eta_c d_l) / d_l^2

(X the point and n its surface normal in the view's camera frame, s_l = L_l - X, d_l = |s_l|), and
A = k_c E_c(X) exp(-eta_c r) / V(x). There the rig (offset, tilt, beam) is declared and held; the light path's eta
is tied to ``attenuation.eta_per_m`` (one water); the power P_l is exactly degenerate with the gain and held (the
gain and B_inf's level are then in units of it); ambient is the brightness that does not fall with the distance
from the lights. Normals come from each frame's range map smoothed by ``measure.normal_smooth_px``.

Known limits: the vignetting polynomial's b and c trade with each other (the falloff as a function is pinned, not
its coefficients). The fit starts on ``fit.coarse_fraction`` of the points (:meth:`eval.fit.Problem.coarse_start`):
a round of L-BFGS, then a trust-region least squares there, which follows the flat directions (red B_inf against
beta, the two vignettings) to their floor where L-BFGS crawls along them; then it runs on all the points.
Measured accuracy and coverage: benchmarks/RESULTS/water.md ("Site water").

Bad input: fewer than ``min_frames`` frames with a pose and range, range on too small a part of the frames, or too
few points seen at different ranges raise :class:`WaterInputError`, saying what to give.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from watergan.errors import UserInputError
from watergan.formation import Counts, Stack, get
from watergan.formation.effects.image_field import n_terms
from watergan.formation.inverse import needs_normals
from watergan.formation.rig import held_rig, rig_settings
from watergan.water_record import WaterRecord, alternative_key

from .bootstrap import bootstrap, inverse_hessian, newton_refit, paired_rmse_change
from .eta_profile import eta_profile
from .fields import (
    FIELD_EFFECT,
    FRAME_CARRY_PCT,
    FRAME_EFFECT,
    GRID_EFFECT,
    decorrelate_fields,
    decorrelate_frames,
    field_summary,
    fit_correction_grid,
    frame_summary,
    measure_frame_gains,
    set_light_level,
    stack_first,
    trust_region_names,
)
from .fit import (
    DEFAULT_EFFECTS,
    WATER_FIT,
    FitConfig,
    Problem,
    fitted_names,
    heldout_sums,
    make_split,
    start_inside_bounds,
)
from .intervals import (
    cover_the_profiles,
    cover_the_structures,
    cover_the_valley,
    describe_intervals,
    veil_at_median_range,
)
from .observations import DenseMeasureConfig, Observations, SparseTracks, WaterFrame, measure_frames


@dataclass(frozen=True)
class WaterConfig:
    """How the water is estimated: the effects, how the table is measured (``measure``) and fitted (``fit``).
    The water stage's own settings (the board file, the range maps, ``--add``): ``pipeline.water.WaterStage``."""

    effects: tuple[str, ...] = DEFAULT_EFFECTS
    """Effects of the stack (any registered name), placed in scene-to-sensor order by their rank."""
    light_rig: bool = True
    """Model the lights the survey declares (survey.json's ``lights``) with the declared rig held.
    The stack gets ``artificial_light`` (unless an effect with ``rig_params`` is already listed) with the rig's
    offset, tilt and beam held."""
    held_params: tuple[str, ...] = ("artificial_light.power",)
    """Parameters ("effect.param") held at their starting values inside fitted effects.
    The lights' power, by default: it is exactly degenerate with the gain."""
    tied_params: tuple[tuple[str, str], ...] = (("artificial_light.eta_per_m", "attenuation.eta_per_m"),)
    """(follower, leader) pairs that share one value when both effects are in the stack (one water, one eta)."""
    initial: tuple[dict, ...] = ()
    """Optional {name, params} entries giving starting (or, for fixed effects, held) values."""
    measure: DenseMeasureConfig = DenseMeasureConfig()
    """How the measurement table is taken from the frames."""
    fit: FitConfig = WATER_FIT
    """How the stack is fitted (``fit.fixed_effects``: held effects; ``gain`` is added without a board)."""
    field_degree: int = 2
    """Degree of the smooth fields over the image (``image_field``) fitted beside the stack, so that what the stack
    lacks on image position bends them and not the water; 0: none. The corrections invert them with the stack."""
    frame_gain: bool = True
    """Measure a gain per frame and channel (``frame_gain``) and fit it beside the stack when a frame's exceeds
    ``FRAME_CARRY_PCT`` (:func:`measure_frame_gains`), so that what the stack lacks along the survey (auto-exposure,
    white balance, a water that drifts) bends it and not the water; not when an effect of the stack already has a
    value per frame. The physics correction inverts it with the stack."""
    frame_gain_off_range: bool = True
    """Keep the gains per frame off the frames' mean ranges (:func:`decorrelate_frames`): eta's level then comes
    from the frames' ranges. False: the gains are free apart from their mean and carried whatever their size, and eta
    comes from the range differences within the points that frames share (a camera that sets its gains from each
    frame's content)."""
    field_grid: tuple[int, int] | None = None
    """Nodes (rows x cols, at least 3 x 3) of fine fields over the image (``image_grid``) fitted jointly with the
    water beside the smooth ones: they follow a falloff or a veil of any smooth shape, so that its form does not
    bend the water (eta is then pinned by the same point at different ranges and image positions alone). None: none
    (the structure alternative of ``structure_alternatives`` sets them)."""
    correction_grid: tuple[int, int] | None = (13, 17)
    """Nodes (rows x cols, at least 3 x 3) of the fine fields over the image (``image_grid``) fitted after the water
    with every other parameter held, and carried for the corrections where they exceed ``eval.fields.FIELD_FLAT_PCT``
    (:func:`fit_correction_grid`): what the water's smooth fields leave on image position. None: none."""
    field_max_range_r2: float = 0.5
    """When image position explains more than this fraction of the views' range variance (one altitude over a flat
    floor), the fields are kept uncorrelated with range (:func:`decorrelate_fields`)."""
    spec_alternatives: tuple[dict, ...] | None = None
    """Changes of the fit's configuration (e.g. ``{"board_weight": 1.0}``) under which the fit is repeated.
    Each parameter's largest change widens its interval (in quadrature with the bootstrap). None: board weight / 10
    with a board, else loss scale x 3."""
    structure_alternatives: tuple[dict, ...] = ({"frame_gain_off_range": False}, {"field_grid": (13, 17)})
    """Changes of the model's structure (fields of this configuration) under which the water is fitted again
    from its start, without bootstrap: each parameter's change counts in its interval as a specification
    alternative's does, and a held-out test says whether the survey prefers it (:func:`structure_fits`). By default
    the gains per frame free of the frames' ranges (a camera that sets them from each frame's content) and fine
    fields over the image fitted with the water (a falloff or a veil of a shape the smooth fields do not share).
    Empty: none."""
    eta_profile: bool = True
    """Where the survey prefers the gains per frame free of the frames' ranges, widen eta's interval to what its
    held-out views accept along eta under them (:mod:`eval.eta_profile`; up to five fits more). False: not asked."""
    range_scale_sd: float = 0.0
    """Relative 1-sigma uncertainty of the range maps' metric scale (e.g. the SfM stage's ``scale_spread``).
    The intervals of coefficients in 1/m widen by 1.96 x this x value, in quadrature."""


# ------------------------------------------------------------------------------------ the stack

#: The effect that models a declared light rig when the configured stack has none.
RIG_EFFECT = "artificial_light"
#: The share of the points a structure alternative's held-out test leaves out, and its bootstrap's resamples.
STRUCTURE_HOLDOUT, STRUCTURE_TEST_RESAMPLES = 0.2, 500
#: L-BFGS iterations of each specification alternative's refit after its Newton step from the full fit.
SPEC_ITERATIONS = 30


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



@dataclass
class WaterEstimate:
    """The fitted stack and every parameter's estimate with its 95 % interval.

    stack:        the fitted stack (use :meth:`Stack.to_config` to save it).
    params:       {"effect.param": {"value", "low", "high", "std", "p2_5", "p97_5", "units", "fitted",
                  "pinned_by", "on_bound"}}; fixed parameters have value only.
    fixed:        effects held at their values (e.g. gain without a board) and why.
    held:         {"effect.param": why} parameters held (a declared light rig, the lights' power) or tied to
                  another (the light path's eta to the attenuation's) inside fitted effects.
    tradeoffs:    [(a, b, correlation)] free parameter components whose bootstrap |correlation| > 0.95.
    n_points, n_observations, n_board, n_frames: sizes of the measurement table.
    rmse:         RMS residual of the views (linear colour); ``residuals``: per view (for plots).
    seconds:      wall time (measuring, fitting, bootstrap).
    """

    stack: Stack
    params: dict
    fixed: dict
    held: dict
    tradeoffs: list
    n_points: int
    n_observations: int
    n_board: int
    n_frames: int
    rmse: float
    seconds: dict
    alternatives: list = field(default_factory=list)
    iterations: int = 0
    """L-BFGS iterations of the main fit."""
    converged: bool = True
    """Whether the main fit converged (see ``FitConfig.convergence_rtol``) within ``fit.max_iterations``."""
    residuals: dict | None = None
    """Per view: residual (N,3) (observed - fitted, linear), range_m (N,), radius (N,) (distance from the
    image centre, 1 at the corners); not in :meth:`to_json`."""
    fields: dict | None = None
    """The fields over the image fitted beside the stack (:func:`field_summary`); None: none fitted."""
    frames: dict | None = None
    """The gains per frame measured, and fitted beside the stack when carried (:func:`frame_summary`); None: none."""
    structure: list = field(default_factory=list)
    """Each structure alternative's held-out test and whether the survey prefers it (:func:`structure_fits`)."""
    grid: dict | None = None
    """The fine fields over the image fitted after the water for the corrections, and whether ``stack`` carries
    them (:func:`fit_correction_grid`); None: none fitted."""
    veil: dict | None = None
    """The backscatter at the views' median range with its interval (:func:`eval.intervals.veil_at_median_range`)."""
    observations: Observations | None = None
    """The measurement table the estimate was fitted to (:func:`estimate_water` sets it; not in :meth:`to_json`:
    the water stage saves it beside water.json for the diagnosis)."""

    def to_record(self, plots: dict[str, str] | None = None) -> WaterRecord:
        """water.json's record (:class:`watergan.water_record.WaterRecord`); ``plots``: {file: what it shows} of
        the plots written beside it (None: none named)."""
        return WaterRecord(
            stack=self.stack.to_config(), params=self.params, fixed=self.fixed, held=self.held,
            tradeoffs=self.tradeoffs, n_points=self.n_points, n_observations=self.n_observations, n_board=self.n_board,
            n_frames=self.n_frames, rmse=self.rmse, seconds=self.seconds, iterations=self.iterations,
            converged=self.converged, fields=self.fields, frames=self.frames, grid=self.grid, veil=self.veil,
            structure=self.structure or None,
            interval="95 %: estimate +- sqrt((1.96 x bootstrap std)^2 + specification^2 [+ (1.96 x range scale sd x "
                     "value)^2 for 1/m]); bootstrap over frames and points; specification: largest change of the "
                     "estimate under the specification alternatives " + json.dumps(self.alternatives) + "; widened "
                     "to cover each structure alternative's estimate +- the same spread (structures), and eta's to "
                     "what the held-out views accept under the free gains (profile)",
            plots=plots)

    def to_json(self) -> dict:
        """water.json's content, no plots named (:meth:`to_record`)."""
        return self.to_record().to_json()

    def summary(self) -> str:
        """One line: eta, B_inf and the veil at the median range (what a short range span pins) with their
        intervals, and the level of a light fixed in the image taken out of the veil (:func:`set_light_level`)."""
        parts = []

        def with_intervals(label: str, p: dict) -> str:
            return f"{label} " + "/".join(
                f"{v:.3f}[{lo:.3f},{hi:.3f}]" for v, lo, hi in zip(p["value"], p["low"], p["high"], strict=True))

        for key in ("attenuation.eta_per_m", "backscatter.b_inf"):
            if key in self.params and self.params[key].get("low") is not None:
                parts.append(with_intervals(key.split(".")[1], self.params[key]))
        if self.veil is not None and self.veil.get("low") is not None:
            parts.append(with_intervals(f"veil at {self.veil['range_m']:.1f} m", self.veil))
        level = self.params.get(f"{FIELD_EFFECT}.additive_level", {}).get("value")
        if level is not None and max(level) > 0:
            parts.append("a light fixed in the image, " + "/".join(f"{v:.3f}" for v in level) + ", taken out of it")
        unconverged = "" if self.converged else f", not converged in {self.iterations} iterations"
        return "water: " + "; ".join(parts) + f" (rmse {self.rmse:.4f}, {self.n_points} points{unconverged})"



def _key(stack: Stack, raw_name: str) -> str:
    """"effect.param" of a raw parameter name "effects.I.raw.PARAM"."""
    return f"{stack.effects[int(raw_name.split('.')[1])].name}.{raw_name.rsplit('.', 1)[1]}"


#: The attenuation's key in the fits' {"effect.param": value}.
ETA = "attenuation.eta_per_m"
#: The configuration fields that only matter where the stack carries gains per frame.
FRAME_SETTINGS = frozenset({"frame_gain_off_range"})


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


def structure_fits(obs: Observations, config: WaterConfig, lights: list[dict] | None,
                   changes: Sequence[dict]) -> tuple[list[dict], list[dict]]:
    """(fits, tests): {"effect.param": value} of the water fitted under each of the ``changes`` of ``config`` (from
    its start, no bootstrap, no alternatives of its own, no fine grid), and each change's held-out test: the water
    fitted with and without it on the points less ``STRUCTURE_HOLDOUT`` of them, the held-out points' views predicted
    (:func:`eval.fit.heldout_sums`), d = RMSE_change / RMSE_without - 1 with its bootstrap 95 % interval
    (:func:`eval.bootstrap.paired_rmse_change`); ``preferred`` where the whole interval is below 0 (the survey
    predicts the views it was not fitted to better with that structure); ``eta_per_m``: that fit's attenuation.
    Where the survey prefers gains per frame free of the frames' ranges, ``eta_profile``: eta's held-out profile
    under them (:func:`eval.eta_profile.eta_profile`: "low" / "high", eta at its bounds; "open_low" / "open_high",
    per channel, where the survey accepted the profile's last step; eta_0 and each step's held-out changes)."""
    if not changes:
        return [], []
    alone = replace(config, structure_alternatives=(), spec_alternatives=(), correction_grid=None,
                    fit=replace(config.fit, bootstrap=0))
    split = make_split(obs, replace(config.fit, holdout_fraction=STRUCTURE_HOLDOUT))
    train = obs.take_points(np.setdiff1d(np.arange(obs.n_points), split.holdout_points))
    base_sq, count = heldout_sums(fit_observations(train, alone, lights).stack, obs, split, config.fit)
    fits, tests = [], []
    for change in changes:
        changed = replace(alone, **change)
        trained = fit_observations(train, changed, lights).stack
        cand_sq, _ = heldout_sums(trained, obs, split, config.fit)
        d, ci, _ = paired_rmse_change(base_sq, cand_sq, count, STRUCTURE_TEST_RESAMPLES, config.fit.seed)
        params = fit_observations(obs, changed, lights).params
        fits.append({key: np.asarray(p["value"], float) for key, p in params.items() if p.get("fitted")})
        tests.append({"alternative": dict(change), "eta_per_m": np.round(fits[-1].get(ETA, []), 6).tolist(),
                      "heldout_change_pct": round(100 * d, 2),
                      "ci95_pct": [round(100 * ci[0], 2), round(100 * ci[1], 2)], "preferred": bool(ci[1] < 0)})
        if config.eta_profile and tests[-1]["preferred"] and change.get("frame_gain_off_range") is False \
                and ETA in fits[-1]:
            tests[-1]["eta_profile"] = eta_profile(trained, train, obs, split, changed.fit, water_names(
                trained, train, changed, lights)[0], STRUCTURE_TEST_RESAMPLES)
    return fits, tests


def fit_observations(obs: Observations, config: WaterConfig = WaterConfig(),
                     lights: list[dict] | None = None, grid_obs: Observations | None = None) -> WaterEstimate:
    """Fit the stack to a measurement table, bootstrap it and repeat it under the specification alternatives (see
    the module docstring). ``lights``: the light rig survey.json declares (see :func:`build_stack`); ``grid_obs``:
    the table the fine grid is fitted to (:func:`fit_correction_grid`; None: ``obs``)."""
    for label, grid in (("field_grid", config.field_grid), ("correction_grid", config.correction_grid)):
        if grid is not None and min(grid) < 3:
            raise UserInputError(f"{label} {grid[0]}x{grid[1]}: the fine fields need at least 3 x 3 nodes (or none)")
    t0 = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(config.fit.threads or threads)
    try:
        frames = np.unique(np.concatenate([obs.frame, obs.board_frame]))
        stack = build_stack(config, obs.n_frames or int(frames.max()) + 1, lights)
        names, fixed, held = water_names(stack, obs, config, lights)
        gain_names = [n for n in names if stack.effects[int(n.split(".")[1])].name == FRAME_EFFECT]
        names = [n for n in names if n not in gain_names]
        range_r2 = decorrelate_fields(stack, obs, config.field_max_range_r2)
        decorrelate_frames(stack, obs, config.frame_gain_off_range)
        start_inside_bounds(stack, names + gain_names)
        problem = Problem(stack, obs, config.fit, names)
        x_start = problem.flat()
        iterations = stack_first(stack, obs, config.fit, names)
        problem.take_gradients()
        iterations += problem.coarse_start(trust_region_names(stack, names)) if not iterations else 0
        frame_gains = None
        if gain_names:
            frame_gains = measure_frame_gains(problem, gain_names, frames)
            # the water again from its start, beside the gains the frames want
            if frame_gains["carried"] or not config.frame_gain_off_range:
                problem.set_flat(x_start)
                names += gain_names
                first = stack_first(stack, obs, config.fit, names)
                problem = Problem(stack, obs, config.fit, names)
                iterations += first or problem.coarse_start(trust_region_names(stack, names))
            else:
                fixed[FRAME_EFFECT] = (f"the frames' gains are small (up to {max(frame_gains['largest_pct']):.1f} %, "
                                       f"under {FRAME_CARRY_PCT:.0f} %): held at 1")
        done, converged = problem.converge()
        iterations += done
        if gain_names and gain_names[0] in names:
            frame_gains = frame_summary(stack, frames, carried=True)
        problem.refine(config.fit.refine_evaluations)
        x_best, best = problem.flat(), problem.physical()
        t_fit = time.perf_counter() - t0

        fast = Problem(stack, obs, config.fit, names, float32=True) if config.fit.float32 else problem
        refits = config.fit.bootstrap or config.spec_alternatives != ()  # Newton steps from the full fit
        inv = inverse_hessian(fast) if names and refits else None
        samples = bootstrap(problem, config.fit, fast, inv)
        t_boot = time.perf_counter() - t0 - t_fit
        alternatives = config.spec_alternatives
        if alternatives is None:
            alternatives = ({"board_weight": config.fit.board_weight / 10},) if problem.has_board else \
                ({"loss_scale": config.fit.loss_scale * 3},)
        spec_fits = []
        for change in alternatives:  # each refitted from the full fit as a bootstrap replicate is, in float64
            problem.config = replace(config.fit, **change)
            newton_refit(problem, x_best, inv, SPEC_ITERATIONS)
            spec_fits.append({_key(stack, k): v for k, v in problem.physical().items()})
        problem.config = config.fit
        problem.set_flat(x_best)
        with torch.no_grad():
            residual = (problem.y - problem.albedo()[1]).numpy()
        rmse = float(np.sqrt((residual ** 2).mean()))
        for p in stack.parameters():
            p.requires_grad_(False)
        mean_signal = obs.colour.mean(0)
        named = {_key(stack, k): v for k, v in best.items()}
        named_samples = [{_key(stack, k): v for k, v in s.items()} for s in samples]
        range_m = float(np.median(obs.range_m))
        fields = field_summary(stack, range_r2, mean_signal)
        form = fields["form"] if fields and "backscatter.b_inf" in named else ""
        factor = set_light_level(stack, obs, form, range_m)
        centred = None
        if factor is not None:  # the split applied to every fit; the fit without it is an alternative
            centred = dict(named)
            for fit in (named, *named_samples, *spec_fits):
                fit["backscatter.b_inf"] = fit["backscatter.b_inf"] * factor
            spec_fits.append(centred)
            alternatives = (*alternatives, {"image_field.additive_level": 0.0})
            fields = field_summary(stack, range_r2, mean_signal)
        changes = [c for c in config.structure_alternatives if gain_names or not set(c) <= FRAME_SETTINGS]
        fits, structure = structure_fits(obs, config, lights, changes)
        spec_fits += fits
        alternatives = (*alternatives, *changes)
        t_spec = time.perf_counter() - t0 - t_fit - t_boot
        corrected, grid = fit_correction_grid(stack, obs if grid_obs is None else grid_obs, config, range_r2)
        spec = {key: np.max([np.abs(fit[key] - value) for fit in spec_fits
                             if np.shape(fit.get(key)) == np.shape(value)], 0, initial=0.0)
                for key, value in named.items()}
        params, tradeoffs = describe_intervals(stack, named, named_samples, fixed, spec, config.range_scale_sd)
        cover_the_structures(stack, params, fits, config.range_scale_sd)
        cover_the_profiles(params, ETA, [test["eta_profile"] for test in structure if "eta_profile" in test])
        for key, value in named.items():  # each alternative's own change, for the report's words on trust
            if "specification" in params[key]:
                params[key]["specification_by"] = {
                    alternative_key(change): np.round(np.abs(fit[key] - value), 6).tolist()
                    for change, fit in zip(alternatives, spec_fits, strict=True)
                    if np.shape(fit.get(key)) == np.shape(value)}
        veil = veil_at_median_range(stack, named_samples, range_m, tuple(spec_fits), centred, tuple(fits))
        cover_the_valley(params, veil)
        return WaterEstimate(stack=corrected, params=params, fixed=fixed, held=held, tradeoffs=tradeoffs,
                             n_points=obs.n_points,
                             n_observations=len(obs.colour), n_board=len(obs.board_colour), n_frames=len(frames),
                             residuals={"residual": residual, "range_m": obs.range_m,
                                        "radius": np.hypot(*(2 * obs.pixel_uv - 1).T) / np.sqrt(2)},
                             rmse=rmse, seconds={"fit": round(t_fit, 2), "bootstrap": round(t_boot, 2),
                                                 "specification": round(t_spec, 2),
                                                 **({"grid": grid["seconds"]} if grid else {})},
                             alternatives=[dict(a) for a in alternatives], iterations=iterations,
                             converged=converged, fields=fields,
                             frames=frame_gains, grid=grid, structure=structure,
                             veil=veil)
    finally:
        torch.set_num_threads(threads)


def estimate_water(frames: Sequence[WaterFrame], K: np.ndarray, tracks: SparseTracks | None = None, board=None,
                   config: WaterConfig = WaterConfig(), lights: list[dict] | None = None,
                   normals: bool = False, grid_frames: Sequence[WaterFrame] | None = None) -> WaterEstimate:
    """The site's water (see the module docstring).

    frames:  the survey's frames (raw linear image, range map in metres, pose; see :class:`WaterFrame`).
    K:       (3,3) pinhole intrinsics of the images, pixels (OpenCV centres).
    tracks:  optional SfM tracks (:class:`SparseTracks`, frame indices into ``frames``).
    board:   optional :class:`eval.colour.Board` (true linear colours; pixel quads per frame name): pins the gain.
    lights:  the light rig survey.json declares (``lights``: per light offset_m, tilt_deg, beam_deg): modelled by
             ``artificial_light`` with the rig held (:func:`build_stack`, ``WaterConfig.light_rig``).
    normals: measure each view's surface normal even when the stack reads none (the water stage does, so that
             the diagnosis's candidates that read normals can be fitted to the same table; the fit is unchanged).
    grid_frames: the same frames with the range the fine grid's table is measured on (the water stage's: the fused
             mesh's where the dense range has none, so that the grid has views at the image's edges); None: the
             water's table. Measured only when the configuration has a grid; its time counts in ``measure``.
    The measurement table is kept in ``estimate.observations``.
    Raises :class:`WaterInputError` when the frames cannot pin the water (too few registered frames, too
    little range, too few points seen at different ranges)."""
    t0 = time.perf_counter()
    lit = reads_normals(config, len(frames), lights)
    obs = measure_frames(frames, K, tracks, board, config.measure, normals=normals or lit)
    grid_obs = None
    if grid_frames is not None and config.correction_grid is not None:
        grid_obs = measure_frames(grid_frames, K, tracks, board, config.measure, normals=lit)
    t_measure = time.perf_counter() - t0
    estimate = fit_observations(obs, config, lights, grid_obs)
    estimate.observations = obs
    estimate.seconds = {"measure": round(t_measure, 2), **estimate.seconds,
                        "total": round(time.perf_counter() - t0, 2)}
    return estimate
