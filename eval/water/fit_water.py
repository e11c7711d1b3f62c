"""The water's estimate alone: :func:`fit_water` fits the stack and its nuisances to a measurement table (a coarse
start, the gains per frame, rounds to convergence, a refinement). No bootstrap, no alternatives: the passes of
:func:`eval.water.estimate.estimate_observations` add those."""

from __future__ import annotations

import contextlib
import copy
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from watergan.formation import Stack

from ..fit import Problem, start_inside_bounds
from ..observations import Observations
from .config import WaterConfig
from .fields import (
    FRAME_CARRY_PCT,
    FRAME_EFFECT,
    decorrelate_fields,
    decorrelate_frames,
    frame_summary,
    measure_frame_gains,
    stack_first,
    trust_region_names,
)
from .stack import build_stack, water_names


@dataclass
class Fit:
    """The fitted water: the stack at the optimum of ``problem`` (the fit of ``names``, raw parameter names).

    fixed, held:  {effect: why} held effects, {"effect.param": why} held parameters inside fitted ones.
    frames:       the frame labels with views or board rows; ``frame_gains``: the gains per frame measured or
                  fitted (None: the stack has none).
    range_r2:     the share of the views' range variance that image position explains.
    iterations, converged, seconds: the L-BFGS iterations, whether the last round converged, its wall time.
    """

    stack: Stack
    problem: Problem
    names: list[str]
    config: WaterConfig
    fixed: dict
    held: dict
    frames: np.ndarray
    frame_gains: dict | None
    range_r2: float
    iterations: int
    converged: bool
    seconds: float

    def key(self, raw_name: str) -> str:
        """"effect.param" of a raw parameter name "effects.I.raw.PARAM"."""
        return f"{self.stack.effects[int(raw_name.split('.')[1])].name}.{raw_name.rsplit('.', 1)[1]}"

    def values(self) -> dict[str, np.ndarray]:
        """{"effect.param": physical value} of the fitted parameters, where the stack is now."""
        return {self.key(k): v for k, v in self.problem.physical().items()}


@contextlib.contextmanager
def torch_threads(threads: int):
    """Torch's threads set to ``threads`` inside (0: left as they are), restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads or before)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def cold_start(stack: Stack, obs: Observations, config: WaterConfig, names: list[str], gain_names: list[str],
               frames: np.ndarray, fixed: dict, float32: bool = False) -> tuple[Problem, list[str], int, dict | None]:
    """The fit's start from the configured values: the stack first where an effect on image position was added,
    a coarse start on part of the points, the gains per frame measured and carried where some frame's exceeds
    ``FRAME_CARRY_PCT`` (or always, kept free of the ranges), then the start again beside them; the problems evaluate
    the model in ``float32`` or float64. Returns (the problem to converge, the names it fits, iterations, the gains per
    frame measured)."""
    start_inside_bounds(stack, names + gain_names)
    problem = Problem(stack, obs, config.fit, names, float32=float32)
    x_start = problem.flat()
    iterations = stack_first(stack, obs, config.fit, names, float32)
    problem.take_gradients()
    iterations += problem.coarse_start(trust_region_names(stack, names)) if not iterations else 0
    measured = None
    if gain_names:
        measured = measure_frame_gains(problem, gain_names, frames)
        if measured["carried"] or not config.frame_gain_off_range:  # the start again, beside the gains
            problem.set_flat(x_start)
            names = names + gain_names
            first = stack_first(stack, obs, config.fit, names, float32)
            problem = Problem(stack, obs, config.fit, names, float32=float32)
            iterations += first or problem.coarse_start(trust_region_names(stack, names))
        else:
            fixed[FRAME_EFFECT] = (f"the frames' gains are small (up to {max(measured['largest_pct']):.1f} %, "
                                   f"under {FRAME_CARRY_PCT:.0f} %): held at 1")
    return problem, names, iterations, measured


def fit_water(obs: Observations, config: WaterConfig | None = None, lights: list[dict] | None = None,
              float32: bool = False) -> Fit:
    """The stack of ``config`` (with the declared ``lights``) fitted to the table ``obs`` from its configured values
    (:func:`cold_start`), then rounds of L-BFGS to convergence and the trust-region refinement. ``float32``: the
    model evaluated in float32, as the coarse start's and the bootstrap's are, for an alternative's fit, whose
    held-out test and values move by far more than float32's rounding; the estimate's own fit is float64."""
    t0, config = time.perf_counter(), config or WaterConfig()
    with torch_threads(config.fit.threads):
        frames = np.unique(np.concatenate([obs.frame, obs.board_frame]))
        stack = build_stack(config, obs.n_frames or int(frames.max()) + 1, lights)
        names, fixed, held = water_names(stack, obs, config, lights)
        gain_names = [n for n in names if stack.effects[int(n.split(".")[1])].name == FRAME_EFFECT]
        names = [n for n in names if n not in gain_names]
        range_r2 = decorrelate_fields(stack, obs, config.field_max_range_r2)
        decorrelate_frames(stack, obs, config.frame_gain_off_range)
        problem, names, iterations, measured = cold_start(stack, obs, config, names, gain_names, frames, fixed,
                                                          float32)
        done, converged = problem.converge()
        if gain_names and gain_names[0] in names:
            measured = frame_summary(stack, frames, carried=True)
        problem.refine(config.fit.refine_evaluations)
    return Fit(stack=stack, problem=problem, names=names, config=config, fixed=fixed, held=held, frames=frames,
               frame_gains=measured, range_r2=range_r2, iterations=iterations + done, converged=converged,
               seconds=round(time.perf_counter() - t0, 2))


def fit_from(fit: Fit, obs: Observations) -> Fit:
    """``fit``'s structure refitted to the table ``obs`` (the same frames, a subset of the points, as a held-out
    test's training points) from ``fit``'s values: rounds of L-BFGS to convergence and the refinement, on a copy of
    its stack (tied parameters kept tied). Its start is the optimum of a table that holds ``obs``, so it needs few
    rounds; the structure's flat directions keep that start (what a structure of its own needs a cold start for)."""
    t0 = time.perf_counter()
    with torch_threads(fit.config.fit.threads):
        stack = copy.deepcopy(fit.stack)
        problem = Problem(stack, obs, fit.config.fit, fit.names)
        done, converged = problem.converge()
        problem.refine(fit.config.fit.refine_evaluations)
    return replace(fit, stack=stack, problem=problem, iterations=done, converged=converged,
                   seconds=round(time.perf_counter() - t0, 2))
