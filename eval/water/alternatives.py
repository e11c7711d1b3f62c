"""The alternatives the water's intervals take in: other readings of the survey that resampling cannot see.

An alternative is a small frozen dataclass with a ``key``, the ``words`` the report prints, what kind of survey
would pin it (``pinned_by``), the ``rules`` by which its values widen an interval (:func:`eval.water.intervals.combine`:
"quadrature", "cover", "bounds"), ``applies(ctx)`` and ``refit(ctx) -> AlternativeFit | None``. They run in the order
of ``WaterConfig.alternatives`` on one :class:`Context`, which holds the estimate, the bootstrap's replicates and
inverse Hessian, and (made once, on first use) the held-out split and the estimate's structure fitted to the
training points. Adding one is a class here and a test. The built-ins:

- :class:`BoardWeight`, :class:`LossScale`: the weighting perturbed (the board weighted 10x less; without a board
  the robust loss 3x wider), refitted from the estimate by a Newton step and a few L-BFGS iterations.
- :class:`LightLevel`: where the fields over the image are additive alone (a light fixed in the image), the veil is
  split between the water and the light (:func:`eval.water.fields.set_light_level`); the fit before the split is
  the alternative, and the split applies to the replicates and the alternatives made before it.
- :class:`FreeGains`, :class:`FineFields`: another structure (the gains per frame free of the frames' ranges; fine
  fields over the image fitted with the water) fitted to convergence on the training points from the configured
  start, as the estimate was (from the estimate, a fit along a flat direction stays where the estimate is and says
  nothing of where the other model lands); that one fit gives its held-out test against the estimate's structure
  fitted on the same points from the estimate (whose optimum is that structure's basin), and its values. The fits
  run side by side (:meth:`Context.prefit`). A structure holds the estimate's, so a fit of it that stops above the
  estimate's structure's training loss has stopped in another basin: it is fitted again from that fit.
- :class:`Profile`: where the survey prefers the free gains, eta as far as the held-out views accept it under them
  (:func:`eval.water.profile.eta_profile`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from watergan.water_record import AlternativeRecord

from ..bootstrap import newton_refit, paired_rmse_change
from ..fit import copy_stack
from ..heldout import heldout_sums, make_split
from ..solvers import in_threads
from .fields import FRAME_EFFECT, split_light

if TYPE_CHECKING:
    import torch

    from ..observations import Observations
    from .config import WaterConfig
    from .fit_water import Fit

#: The attenuation's key in the fits' {"effect.param": value}.
ETA = "attenuation.eta_per_m"
#: The share of the points the held-out tests leave out, and their bootstrap's resamples.
HOLDOUT_FRACTION, TEST_RESAMPLES = 0.2, 500
#: The survey prefers a structure when it predicts its held-out views better with it by more than this share of the
#: held-out RMSE over the whole 95 % interval. Two fits that stop where a round lowers the loss by less than 1e-3 of
#: it differ by up to about 0.05 % in RMSE for their stops alone: a difference inside twice that is no preference.
PREFERRED_CHANGE = 0.001
#: A structure holds the estimate's (its own terms at zero give the estimate's model), so its fit to the training
#: points must reach the estimate's structure's loss there; a fit from the configured start that stops above it by
#: more than this share of it has stopped in another basin, and the structure is fitted again from the estimate's
#: structure's training fit (:meth:`Context.prefit`).
NESTED_LOSS_TOLERANCE = 1e-3
#: An alternative's record keeps the values of the parameters of at most this many components.
RECORD_COMPONENTS = 9


@dataclass
class AlternativeFit:
    """What an alternative found: its ``values`` ({"effect.param": value} of the fitted parameters), its held-out
    test (``change``: d = RMSE_alternative / RMSE_estimate - 1 on the held-out points, ``ci``: its 95 % interval),
    a profile's span, its wall time (a structure's: its own fits' too, made side by side with the others');
    ``fit``: its own fit where a later alternative reads it."""

    alternative: Alternative
    values: dict[str, np.ndarray]
    change: float | None = None
    ci: tuple[float, float] | None = None
    profile: dict | None = None
    seconds: float = 0.0
    fit: Fit | None = None

    @property
    def preferred(self) -> bool:
        """The survey predicts its held-out views better with it (the whole interval of the change below
        -``PREFERRED_CHANGE``)."""
        return self.ci is not None and self.ci[1] < -PREFERRED_CHANGE

    @property
    def rejected(self) -> bool:
        """The survey predicts its held-out views worse with it (the whole interval of the change above
        ``PREFERRED_CHANGE``)."""
        return self.ci is not None and self.ci[0] > PREFERRED_CHANGE

    def record(self) -> AlternativeRecord:
        a = self.alternative
        return AlternativeRecord(
            key=a.key, words=a.words, pinned_by=a.pinned_by, seconds=round(self.seconds, 2), profile=self.profile,
            values={k: np.round(v, 6).tolist() for k, v in self.values.items() if np.size(v) <= RECORD_COMPONENTS},
            heldout_change_pct=None if self.change is None else round(100 * self.change, 2),
            ci95_pct=None if self.ci is None else [round(100 * self.ci[0], 2), round(100 * self.ci[1], 2)],
            preferred=None if self.ci is None else self.preferred,
            rejected=None if self.ci is None else self.rejected)


@dataclass
class Context:
    """What the alternatives share (see the module docstring). ``fit``: the estimate; ``samples``: the bootstrap's
    replicates ({"effect.param": value}); ``inv``: the inverse Hessian of the Newton steps (None: no replicates);
    ``results``: the alternatives' fits so far, by key; ``announce(line)``: where a pass says what it is doing, for
    the progress line (None: silent)."""

    fit: Fit
    obs: Observations
    config: WaterConfig
    lights: list[dict] | None
    samples: list[dict]
    inv: torch.Tensor | None
    results: dict[str, AlternativeFit] = field(default_factory=dict)
    trained: dict[str, Fit] = field(default_factory=dict)
    tests: dict[str, AlternativeFit] = field(default_factory=dict)
    announce: Callable[[str], None] | None = None

    def __post_init__(self) -> None:
        self.x_best = self.fit.problem.flat()

    @cached_property
    def split(self):
        return make_split(self.obs, replace(self.config.fit, holdout_fraction=HOLDOUT_FRACTION))

    @cached_property
    def train(self) -> Observations:
        return self.obs.take_points(np.setdiff1d(np.arange(self.obs.n_points), self.split.holdout_points))

    def say(self, line: str) -> None:
        if self.announce is not None:
            self.announce(line)

    def prefit(self, structures: list[Structure]) -> None:
        """The estimate's structure and each of ``structures`` fitted to the training points (into ``trained``, ""
        for the estimate's), side by side (threads sharing torch's: a fit of some 10^5 views uses a second torch
        thread poorly): each structure from the configured start, in float32 (:meth:`_cold`), the costliest first
        (:attr:`Structure.cost`), then the estimate's from its own values (:func:`eval.water.fit_water.fit_from`),
        so that the threads finish together; announced before a structure is fitted again."""
        from .fit_water import fit_from

        jobs = {a.key: self._cold(self.train, a.changed(self.config))
                for a in sorted(structures, key=lambda a: -a.cost) if a.key not in self.trained}
        if "" not in self.trained:
            jobs[""] = lambda: fit_from(self.fit, self.train)
        self.trained.update(in_threads(lambda job: job(), jobs))
        base = training_loss(self.trained[""])
        for a in structures:
            cold = self.trained[a.key]
            cold_loss = training_loss(cold)
            if cold_loss > base * (1 + NESTED_LOSS_TOLERANCE):
                self.say(f"{a.key}: its fit stopped {cold_loss / base - 1:.1%} above the estimate's structure's "
                         f"training loss, fitted again from that fit")
                warm = self._warm(a)
                best = cold if cold_loss <= training_loss(warm) else warm
                self.trained[a.key] = replace(best, seconds=round(cold.seconds + warm.seconds, 2))

    def _cold(self, obs: Observations, config: WaterConfig):
        from .fit_water import fit_water

        return lambda: fit_water(obs, config, self.lights, float32=True)

    def _warm(self, structure: Structure) -> Fit:
        """``structure`` fitted to the training points from the estimate's structure's training fit (its own terms
        at their configured values)."""
        from .fit_water import fit_water

        config = replace(structure.changed(self.config), initial=tuple(self.trained[""].stack.to_config()))
        return fit_water(self.train, config, self.lights, float32=True)

    @cached_property
    def base_sums(self) -> tuple[np.ndarray, np.ndarray]:
        """The held-out sums of the estimate's structure fitted to the training points."""
        if "" not in self.trained:
            self.prefit([])
        return heldout_sums(self.trained[""].stack, self.obs, self.split, self.config.fit)

    def heldout_change(self, fit: Fit) -> tuple[float, tuple[float, float]]:
        """(d, 95 % interval) of ``fit``'s held-out error against the estimate's structure's, on the same points."""
        base_sq, count = self.base_sums
        cand_sq, _ = heldout_sums(fit.stack, self.obs, self.split, self.config.fit)
        d, ci, _ = paired_rmse_change(base_sq, cand_sq, count, TEST_RESAMPLES, self.config.fit.seed)
        return d, ci


def training_loss(fit: Fit) -> float:
    """The loss ``fit`` reached on the table it was fitted to."""
    import torch

    with torch.no_grad():
        return float(fit.problem.loss())


@dataclass(frozen=True)
class Alternative:
    """The base of the alternatives (see the module docstring)."""

    key: ClassVar[str] = ""
    words: ClassVar[str] = ""
    pinned_by: ClassVar[str] = ""
    rules: ClassVar[tuple[str, ...]] = ("quadrature",)

    def applies(self, ctx: Context) -> bool:
        return True

    def refit(self, ctx: Context) -> AlternativeFit | None:
        raise NotImplementedError


@dataclass(frozen=True)
class Reweight(Alternative):
    """The estimate refitted with the fit's setting ``setting`` multiplied by ``factor`` (where the survey has a
    board, or has none: ``needs_board``): a Newton step from the estimate with its inverse Hessian, then
    ``iterations`` L-BFGS iterations; the estimate is restored after."""

    setting: ClassVar[str] = ""
    needs_board: ClassVar[bool] = True
    factor: float = 1.0
    iterations: int = 30

    def applies(self, ctx: Context) -> bool:
        return ctx.inv is not None and ctx.fit.problem.has_board == self.needs_board

    def refit(self, ctx: Context) -> AlternativeFit:
        problem = ctx.fit.problem
        problem.config = replace(ctx.config.fit, **{self.setting: getattr(ctx.config.fit, self.setting) * self.factor})
        try:
            newton_refit(problem, ctx.x_best, ctx.inv, self.iterations)
            return AlternativeFit(self, ctx.fit.values())
        finally:
            problem.config = ctx.config.fit
            problem.set_flat(ctx.x_best)


@dataclass(frozen=True)
class BoardWeight(Reweight):
    key: ClassVar[str] = "board_weight"
    words: ClassVar[str] = "the board weighted 10x less"
    setting: ClassVar[str] = "board_weight"
    factor: float = 0.1


@dataclass(frozen=True)
class LossScale(Reweight):
    key: ClassVar[str] = "loss_scale"
    words: ClassVar[str] = "a robust loss 3x wider"
    setting: ClassVar[str] = "loss_scale"
    needs_board: ClassVar[bool] = False
    factor: float = 3.0


@dataclass(frozen=True)
class LightLevel(Alternative):
    key: ClassVar[str] = "light_level"
    words: ClassVar[str] = "the light fixed in the image left in the veil"

    def refit(self, ctx: Context) -> AlternativeFit | None:
        before = ctx.fit.values()
        if "backscatter.b_inf" not in before:
            return None
        factor = split_light(ctx.fit.stack, ctx.obs, ctx.fit.range_r2)
        if factor is None:
            return None
        for values in (*ctx.samples, *(r.values for r in ctx.results.values())):  # made from the unsplit estimate
            if "backscatter.b_inf" in values:
                values["backscatter.b_inf"] = values["backscatter.b_inf"] * factor
        return AlternativeFit(self, before)


@dataclass(frozen=True)
class Structure(Alternative):
    """Another structure of the model (``changed(config)``), fitted on the training points from the configured start
    (:meth:`Context.prefit`): that fit gives its held-out test against the estimate's structure and its values,
    whatever the test says (under a missing effect the estimate's structure is wrong too, and the held-out views'
    preference between two wrong models does not say which lands nearer the water: measured in
    benchmarks/RESULTS/water.md). The values (with the fit's own light split) widen the intervals both ways: in
    quadrature, and covered with the bootstrap's spread around them."""

    rules: ClassVar[tuple[str, ...]] = ("quadrature", "cover")
    #: Its fit's cost beside the other structures' (the order they start in, :meth:`Context.prefit`).
    cost: ClassVar[float] = 1.0

    def changed(self, config: WaterConfig) -> WaterConfig:
        raise NotImplementedError

    def test(self, ctx: Context) -> AlternativeFit:
        """Its held-out test alone (no values yet), made once per context (``ctx.tests``)."""
        if self.key not in ctx.tests:
            if self.key not in ctx.trained:
                ctx.prefit([self])
            trained = ctx.trained[self.key]
            change, ci = ctx.heldout_change(trained)
            ctx.tests[self.key] = AlternativeFit(self, {}, change=change, ci=ci, seconds=trained.seconds,
                                                 fit=trained)
        return ctx.tests[self.key]

    def refit(self, ctx: Context) -> AlternativeFit:
        result = self.test(ctx)
        source = result.fit
        result.values = source.values()
        factor = split_light(copy_stack(source.stack), ctx.obs, source.range_r2) \
            if "backscatter.b_inf" in result.values else None
        if factor is not None:
            result.values["backscatter.b_inf"] = result.values["backscatter.b_inf"] * factor
        return result


@dataclass(frozen=True)
class FreeGains(Structure):
    key: ClassVar[str] = "free_gains"
    words: ClassVar[str] = ("the gains per frame free to follow the frames' ranges (a camera's auto exposure or white "
                            "balance)")
    pinned_by: ClassVar[str] = "a survey with more range within each frame (relief, a tilted view)"

    def applies(self, ctx: Context) -> bool:
        return FRAME_EFFECT in ctx.fit.stack.names and ctx.config.frame_gain_off_range

    def changed(self, config: WaterConfig) -> WaterConfig:
        return replace(config, frame_gain_off_range=False)


@dataclass(frozen=True)
class FineFields(Structure):
    key: ClassVar[str] = "fine_fields"
    words: ClassVar[str] = "fine fields over the image fitted with the water (a falloff or a veil of any smooth shape)"
    pinned_by: ClassVar[str] = ("a survey that sees the same points at more ranges from one image position (frames at "
                                "several altitudes)")
    cost: ClassVar[float] = 2.0  # some 1,300 node values over the image: the longest fit
    nodes: tuple[int, int] = (13, 17)

    def applies(self, ctx: Context) -> bool:
        return ctx.config.field_grid is None

    def changed(self, config: WaterConfig) -> WaterConfig:
        return replace(config, field_grid=self.nodes)


@dataclass(frozen=True)
class Profile(Alternative):
    """Where the survey prefers the structure ``under`` (the free gains), eta's held-out profile under it: the
    interval covers what its held-out views accept."""

    key: ClassVar[str] = "eta_profile"
    words: ClassVar[str] = "eta as far as the held-out views accept it with the gains per frame free"
    pinned_by: ClassVar[str] = "a survey with more range within each frame (relief, a tilted view)"
    rules: ClassVar[tuple[str, ...]] = ("bounds",)
    under: str = FreeGains.key

    def applies(self, ctx: Context) -> bool:
        result = ctx.results.get(self.under)
        return result is not None and result.preferred and ETA in result.values

    def refit(self, ctx: Context) -> AlternativeFit:
        from .profile import eta_profile

        trained = ctx.results[self.under].fit
        profile = eta_profile(trained.stack, ctx.train, ctx.obs, ctx.split, trained.config.fit, trained.names,
                              TEST_RESAMPLES, say=ctx.say)
        return AlternativeFit(self, {}, profile={"param": ETA, **profile})


def run_alternatives(ctx: Context) -> tuple[list[AlternativeFit], float]:
    """Each of ``ctx.config.alternatives`` that applies, in order, refitted (announced before each:
    :attr:`Context.announce`), the structures' fits on the training points first, side by side
    (:meth:`Context.prefit`). Returns (their fits, the ones that found something, also in ``ctx.results``; the seconds
    of the structures' fits side by side)."""
    todo = list(ctx.config.alternatives)
    structures = [a for a in todo if isinstance(a, Structure) and a.applies(ctx)]
    began = time.perf_counter()
    if structures:
        ctx.say("the estimate's structure and " + ", ".join(a.key for a in structures)
                + " fitted side by side on four fifths of the points")
        ctx.prefit(structures)
    prefit_s = time.perf_counter() - began
    for i, alternative in enumerate(todo):
        if not alternative.applies(ctx):
            continue
        ctx.say(f"alternative {i + 1}/{len(todo)}: {alternative.words}")
        began = time.perf_counter()
        result = alternative.refit(ctx)
        if result is not None:  # a structure's own fits, made side by side before, are in its seconds already
            result.seconds += time.perf_counter() - began
            ctx.results[alternative.key] = result
    return list(ctx.results.values()), prefit_s
