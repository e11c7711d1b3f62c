"""The site's water from the survey's own geometry, as a short list of named passes (docs/water.md):

1. measure:      the measurement table (:func:`eval.observations.measure_frames`);
2. fit:          the estimate (:func:`eval.water.fit_water.fit_water`);
3. bootstrap:    frames, points and board patches resampled, each replicate refitted from the estimate by a Newton
                 step (:func:`eval.bootstrap.bootstrap`);
4. alternatives: the readings of the survey that resampling cannot see (:mod:`eval.water.alternatives`);
5. fine grid:    the fine fields over the image for the corrections, fitted with the water held
                 (:func:`eval.water.fields.fit_correction_grid`);
6. intervals:    one rule over the bootstrap and the alternatives (:func:`eval.water.intervals.combine`).

Each pass is timed into ``WaterEstimate.seconds`` and announced on the progress line.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from watergan.formation import Stack
from watergan.water_record import AlternativeRecord, ParamInterval, WaterRecord

from ..bootstrap import bootstrap, inverse_hessian
from ..fit import Problem
from ..observations import Observations, SparseTracks, WaterFrame, measure_frames
from .alternatives import Context, run_alternatives
from .config import WaterConfig
from .fields import FIELD_EFFECT, field_summary, fit_correction_grid
from .fit_water import Fit, fit_water, torch_threads
from .intervals import combine
from .stack import reads_normals

#: How the intervals are made, in words (water.json's ``interval``).
INTERVAL_WORDS = ("95 %: estimate +- sqrt((1.96 x bootstrap std)^2 + change^2 [+ (1.96 x range scale sd x value)^2 for "
                  "1/m]), change the largest under the alternatives of rule quadrature; bootstrap over frames and "
                  "points; widened to cover each alternative of rule cover with the same spread around it, each of "
                  "rule bounds' accepted span, and B_inf's valley; each parameter's widenings name the alternatives")


class Passes:
    """Times the estimate's passes into ``seconds`` and announces each (``say``: a function of one line, None:
    silent): ``with passes("bootstrap", "30 replicates"): ...``."""

    def __init__(self, say: Callable[[str], None] | None = None) -> None:
        self.say, self.seconds = say, {}

    def __call__(self, name: str, detail: str = ""):
        return _Pass(self, name, detail)

    def note(self, text: str) -> None:
        if self.say is not None:
            self.say(text)


class _Pass:
    def __init__(self, passes: Passes, name: str, detail: str) -> None:
        self.passes, self.name, self.detail = passes, name, detail

    def __enter__(self):
        self.t0 = time.perf_counter()
        self.passes.note(f"water: {self.name}" + (f" ({self.detail})" if self.detail else "") + " ...")
        return self

    def __exit__(self, *exc):
        seconds = round(time.perf_counter() - self.t0, 2)
        self.passes.seconds[self.name] = round(self.passes.seconds.get(self.name, 0.0) + seconds, 2)
        if exc[0] is None:
            self.passes.note(f"water: {self.name} done in {seconds:.1f} s")
        return False


def stderr_line(text: str) -> None:
    """A progress line on standard error, and what the stage's heartbeat says it is doing."""
    from watergan.progress import say

    print(text, file=sys.stderr, flush=True)
    say(text.removeprefix("water: "))


@dataclass
class WaterEstimate:
    """The fitted stack and every parameter's estimate with its 95 % interval.

    stack:        the fitted stack (use :meth:`Stack.to_config` to save it), with the fine grid where carried.
    params:       {"effect.param": :class:`watergan.water_record.ParamInterval`}.
    fixed, held:  effects held at their values and why; {"effect.param": why} held inside fitted effects.
    tradeoffs:    [a, b, correlation] free parameter components whose bootstrap |correlation| > 0.95.
    n_points, n_observations, n_board, n_frames: sizes of the measurement table.
    rmse:         RMS residual of the views (linear colour); ``residuals``: per view (for plots).
    seconds:      wall time per pass, and ``total``.
    alternatives: the alternatives the intervals took in (:class:`watergan.water_record.AlternativeRecord`).
    iterations, converged: the main fit's L-BFGS iterations and whether its last round converged.
    fields, frames, grid, veil: the fields over the image, the gains per frame, the fine grid, the veil at the
                  views' median range (None: none).
    observations: the measurement table (not in the record: the water stage saves it beside water.json).
    """

    stack: Stack
    params: dict[str, ParamInterval]
    fixed: dict
    held: dict
    tradeoffs: list
    n_points: int
    n_observations: int
    n_board: int
    n_frames: int
    rmse: float
    seconds: dict
    alternatives: list[AlternativeRecord] = field(default_factory=list)
    iterations: int = 0
    converged: bool = True
    residuals: dict | None = None
    fields: dict | None = None
    frames: dict | None = None
    grid: dict | None = None
    veil: dict | None = None
    observations: Observations | None = None

    def to_record(self, plots: dict[str, str] | None = None) -> WaterRecord:
        """water.json's record; ``plots``: {file: what it shows} of the plots written beside it."""
        return WaterRecord(
            stack=self.stack.to_config(), params=self.params, fixed=self.fixed, held=self.held,
            tradeoffs=self.tradeoffs, n_points=self.n_points, n_observations=self.n_observations, n_board=self.n_board,
            n_frames=self.n_frames, rmse=self.rmse, seconds=self.seconds, iterations=self.iterations,
            converged=self.converged, fields=self.fields, frames=self.frames, grid=self.grid, veil=self.veil,
            alternatives=self.alternatives, interval=INTERVAL_WORDS, plots=plots)

    def to_json(self) -> dict:
        """water.json's content, no plots named."""
        return self.to_record().to_json()

    def summary(self) -> str:
        """One line: eta, B_inf and the veil at the median range with their intervals, and the level of a light
        fixed in the image taken out of the veil."""
        def with_intervals(label: str, value, low, high) -> str:
            return f"{label} " + "/".join(f"{v:.3f}[{lo:.3f},{hi:.3f}]" for v, lo, hi in zip(value, low, high,
                                                                                             strict=True))

        parts = [with_intervals(key.split(".")[1], p.value, p.low, p.high)
                 for key in ("attenuation.eta_per_m", "backscatter.b_inf")
                 if (p := self.params.get(key)) is not None and p.low is not None]
        if self.veil is not None and self.veil.get("low") is not None:
            parts.append(with_intervals(f"veil at {self.veil['range_m']:.1f} m", self.veil["value"],
                                        self.veil["low"], self.veil["high"]))
        level = self.params.get(f"{FIELD_EFFECT}.additive_level")
        if level is not None and max(level.value) > 0:
            parts.append("a light fixed in the image, " + "/".join(f"{v:.3f}" for v in level.value)
                         + ", taken out of it")
        unconverged = "" if self.converged else f", not converged in {self.iterations} iterations"
        return "water: " + "; ".join(parts) + f" (rmse {self.rmse:.4f}, {self.n_points} points{unconverged})"


def bootstrap_pass(fit: Fit, config: WaterConfig) -> tuple[list[dict], torch.Tensor | None]:
    """(the replicates as {"effect.param": value}, the inverse Hessian their Newton steps took; None without
    replicates or alternatives that need it)."""
    problem = fit.problem
    fast = Problem(fit.stack, problem.obs, config.fit, fit.names, float32=True) if config.fit.float32 else problem
    needs_inv = config.fit.bootstrap or any(getattr(a, "iterations", None) for a in config.alternatives)
    inv = inverse_hessian(fast) if fit.names and needs_inv else None
    samples = bootstrap(problem, config.fit, fast, inv)
    return [{fit.key(k): v for k, v in s.items()} for s in samples], inv


def estimate_observations(obs: Observations, config: WaterConfig | None = None, lights: list[dict] | None = None,
                          grid_obs: Observations | None = None, passes: Passes | None = None) -> WaterEstimate:
    """The passes after the measurement (see the module docstring) on the table ``obs``; ``lights``: the light rig
    survey.json declares; ``grid_obs``: the table the fine grid is fitted to (None: ``obs``)."""
    passes, config = passes or Passes(), config or WaterConfig()
    with torch_threads(config.fit.threads):
        with passes("fit"):
            fit = fit_water(obs, config, lights)
        with passes("bootstrap", f"{config.fit.bootstrap} replicates"):
            samples, inv = bootstrap_pass(fit, config)
        with torch.no_grad():
            residual = (fit.problem.y - fit.problem.albedo()[1]).numpy()
        ctx = Context(fit, obs, config, lights, samples, inv, announce=lambda line: passes.note(f"water: {line}"))
        with passes("alternatives"):
            results, prefit_s = run_alternatives(ctx)
        for p in fit.stack.parameters():
            p.requires_grad_(False)
        with passes("fine grid"):
            corrected, grid = fit_correction_grid(fit.stack, obs if grid_obs is None else grid_obs, config,
                                                  fit.range_r2)
        with passes("intervals"):
            best = fit.values()
            params, tradeoffs, veil = combine(fit.stack, best, samples, results, config.range_scale_sd,
                                              float(np.median(obs.range_m)))
    seconds = {**passes.seconds, "structures side by side": round(prefit_s, 2),
               **{f"alternative {r.alternative.key}": round(r.seconds, 2) for r in results}}
    return WaterEstimate(
        stack=corrected, params=params, fixed=fit.fixed, held=fit.held, tradeoffs=tradeoffs, n_points=obs.n_points,
        n_observations=len(obs.colour), n_board=len(obs.board_colour), n_frames=len(fit.frames),
        residuals={"residual": residual, "range_m": obs.range_m,
                   "radius": np.hypot(*(2 * obs.pixel_uv - 1).T) / np.sqrt(2)},
        rmse=float(np.sqrt((residual ** 2).mean())), seconds=seconds,
        alternatives=[r.record() for r in results], iterations=fit.iterations, converged=fit.converged,
        fields=field_summary(fit.stack, fit.range_r2, obs.colour.mean(0)), frames=fit.frame_gains, grid=grid,
        veil=veil)


def estimate_water(frames: Sequence[WaterFrame], K: np.ndarray, tracks: SparseTracks | None = None, board=None,
                   config: WaterConfig | None = None, lights: list[dict] | None = None,
                   normals: bool = False, grid_frames: Sequence[WaterFrame] | None = None,
                   say: Callable[[str], None] | None = None) -> WaterEstimate:
    """The site's water (see the module docstring).

    frames:  the survey's frames (raw linear image, range map in metres, pose; see :class:`WaterFrame`).
    K:       (3,3) pinhole intrinsics of the images, pixels (OpenCV centres).
    tracks:  optional SfM tracks (:class:`SparseTracks`, frame indices into ``frames``).
    board:   optional :class:`eval.colour.Board` (true linear colours; pixel quads per frame name): pins the gain.
    lights:  the light rig survey.json declares (per light offset_m, tilt_deg, beam_deg), modelled with the rig held.
    normals: measure each view's surface normal even when the stack reads none (the water stage does, so that the
             diagnosis's candidates that read normals can be fitted to the same table; the fit is unchanged).
    grid_frames: the same frames with the range the fine grid's table is measured on (None: the water's table).
    say:     where the passes announce themselves, one line each (None: silent).
    The measurement table is kept in ``estimate.observations``. Raises :class:`eval.observations.WaterInputError`
    when the frames cannot pin the water (too few registered frames, too little range, too few points seen at
    different ranges)."""
    t0, config = time.perf_counter(), config or WaterConfig()
    passes = Passes(say)
    with passes("measure", f"{len(frames)} frames"):
        lit = reads_normals(config, len(frames), lights)
        obs = measure_frames(frames, K, tracks, board, config.measure, normals=normals or lit)
        grid_obs = None
        if grid_frames is not None and config.correction_grid is not None:
            grid_obs = measure_frames(grid_frames, K, tracks, board, config.measure, normals=lit)
    estimate = estimate_observations(obs, config, lights, grid_obs, passes)
    estimate.observations = obs
    estimate.seconds = {"measure": passes.seconds["measure"], **estimate.seconds,
                        "total": round(time.perf_counter() - t0, 2)}
    return estimate
