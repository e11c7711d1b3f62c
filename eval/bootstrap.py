"""The bootstrap of a survey fit: frames drawn with replacement, and each surface point's views (and each board
patch's) weighted Poisson(1) times.

Frames alone are not independent units (the views of one point share its texture and registration errors), nor are
points alone (the views of one frame share its exposure, pose and range errors); a replicate draws both, and a
view's weight is the product of its frame's count and its point's weight. :func:`bootstrap` draws its replicates
with :func:`replicate_weights` and refits each from the full fit (``Refit``: a Newton step with the full fit's
inverse Hessian, :func:`inverse_hessian`, then L-BFGS, or the trust-region least squares), side by side
(:func:`eval.solvers.side_by_side`). :func:`paired_rmse_change` compares two models' held-out errors on the same
points (the diagnosis's candidate test).
"""

from __future__ import annotations

from enum import StrEnum
from typing import TYPE_CHECKING

import numpy as np
import torch

from .solvers import side_by_side

if TYPE_CHECKING:
    from .fit import FitConfig, Problem

#: Least eigenvalue of the Hessian a Newton step inverts, as a fraction of the largest (:func:`inverse_hessian`).
HESSIAN_FLOOR = 1e-8


class Refit(StrEnum):
    """How a bootstrap replicate is refitted from the full fit."""

    newton = "newton"
    least_squares = "least_squares"


def replicate_weights(rng: np.random.Generator, frame_groups: list[np.ndarray], n_points: int,
                      n_patches: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One replicate: (frame counts indexed by frame label, (n_points,) point weights, (n_patches,) patch weights).
    Each group of frame labels (e.g. the frames that see the board, and the others) is drawn with replacement as
    many times as it has frames, so every replicate keeps every group; points and patches weigh Poisson(1)."""
    size = max((int(g.max()) + 1 for g in frame_groups if len(g)), default=0)
    counts = np.zeros(size)
    for group in frame_groups:
        if len(group):
            np.add.at(counts, rng.choice(group, len(group), replace=True), 1.0)
    points = rng.poisson(1.0, n_points).astype(np.float64)
    patches = rng.poisson(1.0, n_patches).astype(np.float64) if n_patches else np.zeros(0)
    return counts, points, patches


def normal_interval(estimate: np.ndarray, samples: np.ndarray, lower: float, upper: float,
                    z: float = 1.96) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(sd, low, high): the replicates' standard deviation (over axis 0 of ``samples``) and the interval
    estimate +- z sd, clipped to [lower, upper]."""
    sd = np.std(samples, axis=0, ddof=1)
    return sd, np.clip(estimate - z * sd, lower, upper), np.clip(estimate + z * sd, lower, upper)


def paired_rmse_change(base_sq_sum: np.ndarray, cand_sq_sum: np.ndarray, count: np.ndarray, n: int,
                       seed: int) -> tuple[float, tuple[float, float], float]:
    """Relative change d = RMSE_cand / RMSE_base - 1 over held-out points (per point: the sums of squared test
    residuals of each model and their number), its bootstrap 95 % interval and p = the fraction of ``n`` resamples
    (points drawn with replacement, the same draw for both models) with d >= 0."""
    rng = np.random.default_rng([seed, 13])
    h = len(count)
    idx = rng.integers(0, h, (n, h))
    total = count[idx].sum(1)
    d = np.sqrt(cand_sq_sum[idx].sum(1) / total) / np.sqrt(base_sq_sum[idx].sum(1) / total) - 1.0
    change = np.sqrt(cand_sq_sum.sum() / count.sum()) / np.sqrt(base_sq_sum.sum() / count.sum()) - 1.0
    return float(change), (float(np.quantile(d, 0.025)), float(np.quantile(d, 0.975))), float(np.mean(d >= 0))


def inverse_hessian(problem: Problem) -> torch.Tensor:
    """H^-1 of ``problem``'s loss at its parameters, each eigenvalue taken by its magnitude (a negative one is the
    finite differences' noise along a flat direction, or a saddle: the step goes downhill either way) and at least
    ``HESSIAN_FLOOR`` of the largest. The floor must stay below the flattest valley the data pin: a Newton step is
    damped along any direction whose eigenvalue it lifts, and the bootstrap's replicates then do not spread along it
    (see benchmarks/RESULTS/water.md, "The bootstrap along the valley")."""
    evals, evecs = torch.linalg.eigh(problem.hessian())
    return (evecs / evals.abs().clamp_min(evals.abs().max() * HESSIAN_FLOOR + 1e-300)) @ evecs.T


def newton_refit(problem: Problem, x0: torch.Tensor, inv: torch.Tensor, iterations: int) -> None:
    """Refit ``problem`` (its weights or configuration changed) from the full fit's ``x0``: one Newton step with the
    full fit's inverse Hessian ``inv``, halved until it lowers the loss (kept at ``x0`` after six halvings), then
    ``iterations`` L-BFGS iterations."""
    problem.set_flat(x0)
    step = -(inv @ problem.gradient())
    with torch.no_grad():
        before = float(problem.loss())
        for _ in range(6):
            problem.set_flat(x0 + step)
            if float(problem.loss()) < before:
                break
            step = step / 2
        else:
            problem.set_flat(x0)
    problem.minimise(iterations)


def bootstrap(problem: Problem, config: FitConfig, replicas: Problem | None = None,
              inv: torch.Tensor | None = None) -> list[dict[str, np.ndarray]]:
    """``config.bootstrap`` replicates of the fit of ``problem`` (at its optimum; see the module docstring), each
    {raw name: physical value}. ``replicas``: the problem the replicates are evaluated on (e.g. the same stack in
    float32; default ``problem``); ``inv``: its inverse Hessian when already computed (``newton``). The parameters
    are restored afterwards."""
    fast = replicas or problem
    if not config.bootstrap or not problem.names:
        return []
    rng = np.random.default_rng([config.seed, 29])
    frames = np.unique(problem.frame.numpy())
    board_frames = np.unique(problem.board_frame.numpy()) if problem.has_board else np.zeros(0, np.int64)
    groups = [board_frames, np.setdiff1d(frames, board_frames)]
    n_patches = int(problem.board_patch.max()) + 1 if problem.has_board else 0
    x0 = fast.flat()
    if config.bootstrap_refit == Refit.newton and inv is None:
        inv = inverse_hessian(fast)
    weights = [replicate_weights(rng, groups, len(fast.points) if config.bootstrap_points else 0,
                                 n_patches if config.bootstrap_points else 0) for _ in range(config.bootstrap)]

    def refit(fit: Problem, replicate: tuple) -> dict[str, np.ndarray]:
        counts, points, patches = replicate
        fit.frame_weight = torch.from_numpy(counts)
        if config.bootstrap_points:
            fit.point_weight = torch.from_numpy(points)
            fit.patch_weight = torch.from_numpy(patches) if n_patches else None
        if config.bootstrap_refit == Refit.newton:
            newton_refit(fit, x0, inv, config.bootstrap_iterations)
        else:
            fit.set_flat(x0)
            fit.refine(config.bootstrap_iterations)
        return fit.physical()

    try:
        return side_by_side(fast, refit, weights)
    finally:
        fast.frame_weight = fast.point_weight = fast.patch_weight = None
        fast.set_flat(x0)
