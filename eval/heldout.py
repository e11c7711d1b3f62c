"""A stack fitted with points held out (the diagnosis's :func:`fit_stack`), and the held-out error of a stack fitted
elsewhere (:func:`heldout_sums`, the water's structure tests): the held-out points take no part in the fit; with the
stack frozen each one's albedo is fitted from half of its views and the error measured on the other half. The fit
itself is :mod:`eval.fit`'s."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from torch.func import functional_call

from watergan.formation import FormationState, Stack
from watergan.formation.params import to_json_value

from .bootstrap import bootstrap, normal_interval
from .fit import (
    FitConfig,
    Problem,
    Residual,
    copy_stack,
    fitted_names,
    observation_state,
    render_albedo,
    soft_l1,
    start_inside_bounds,
)
from .observations import Observations
from .solvers import lbfgs


@dataclass(frozen=True)
class Split:
    """Which views train the stack, fit held-out albedos, or test.

    train_obs / holdout_fit_obs / holdout_test_obs: (n,) view indices; holdout_points: (H,) held-out points."""

    train_obs: np.ndarray
    holdout_fit_obs: np.ndarray
    holdout_test_obs: np.ndarray
    holdout_points: np.ndarray


@dataclass(frozen=True)
class FitResult:
    """A fitted stack and how well it explains the measurements.

    stack:            the fitted stack (a new object; the input stack is not changed).
    params:           {effect: {param: {"value", "std", "units", "fitted", "boot_std", "ci95"}}}, physical values.
    albedo:           (P,3) fitted linear albedo of every point (held-out ones from their fit views).
    predicted:        (N,3) predicted linear colour of every view; residual: (N,3) observed - predicted.
    role:             (N,) 0 training view, 1 held-out fit view, 2 held-out test view.
    train_rmse:       RMSE over the training views; heldout_rmse: over the held-out test views (linear).
    heldout_sq_sum:   (H,) per held-out point, sum of squared test residuals; heldout_count: (H,) their number.
    seconds:          wall time of the fit.
    """

    stack: Stack
    params: dict
    albedo: np.ndarray
    predicted: np.ndarray
    residual: np.ndarray
    role: np.ndarray
    train_rmse: float
    heldout_rmse: float
    heldout_sq_sum: np.ndarray
    heldout_count: np.ndarray
    seconds: float

    def summary(self) -> dict:
        """JSON-ready: stack, parameters with uncertainties, errors, time."""
        return {"stack": self.stack.names, "params": self.params, "train_rmse": self.train_rmse,
                "heldout_rmse": self.heldout_rmse, "seconds": round(self.seconds, 3),
                "uncertainty": "std: 1-sigma Laplace approximation conditional on the fitted albedos (a lower "
                               "bound); ci95 (when bootstrapped): estimate +- 1.96 boot_std, bootstrap over "
                               "frames and points with the albedos refitted"}


def make_split(obs: Observations, config: FitConfig) -> Split:
    """Hold out ``holdout_fraction`` of the points; split each held-out point's views in two halves at random (the
    larger half fits the albedo)."""
    rng = np.random.default_rng([config.seed, 11])
    holdout = np.sort(rng.permutation(obs.n_points)[:int(round(config.holdout_fraction * obs.n_points))])
    is_hold = np.zeros(obs.n_points, bool)
    is_hold[holdout] = True
    obs_hold = is_hold[obs.point]
    fit_view = np.zeros(obs.n_obs, bool)
    for p in holdout:
        views = np.nonzero(obs.point == p)[0]
        fit_view[rng.permutation(views)[: (len(views) + 1) // 2]] = True
    return Split(train_obs=np.nonzero(~obs_hold)[0], holdout_fit_obs=np.nonzero(obs_hold & fit_view)[0],
                 holdout_test_obs=np.nonzero(obs_hold & ~fit_view)[0], holdout_points=holdout)


def predict(stack: Stack, obs: Observations, rows: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """(n,3) predicted linear colour of views ``rows`` given the (P,3) albedos."""
    with torch.no_grad():
        return render_albedo(stack, observation_state(obs, rows), torch.from_numpy(albedo[obs.point[rows]])).numpy()


def fit_albedos(problem: Problem, init: np.ndarray | None) -> torch.Tensor:
    """Fit the albedos of ``problem``'s points (and its parameters, when it has any; module docstring): L-BFGS
    rounds, refinement and polish. Returns the (P_rows,3) albedos in ``problem.points`` order."""
    config = problem.config
    if init is not None and np.isfinite(init[problem.points]).all():
        problem.start = torch.from_numpy(init[problem.points]).clamp(config.albedo_min, config.albedo_max)
    elif not problem.affine:
        with torch.no_grad():
            problem.start = problem.albedo()[0]
    if problem.theta:
        problem.converge()
        problem.refine(config.refine_evaluations)
    with torch.no_grad():
        start = problem.albedo()[0]
    if not config.polish_iterations:
        return start
    log_a = torch.nn.Parameter(torch.log(start.clamp_min(1e-12)))
    lbfgs([log_a, *problem.theta],
          lambda: soft_l1(Residual(problem.stack)(problem.state.replace(direct=torch.exp(log_a)[problem.local]
                                                                          .view(-1, 3, 1, 1)), problem.y),
                          config.loss_scale).sum(1).mean(), config.polish_iterations, config.step_rtol)
    return torch.exp(log_a.detach())


def laplace_std(stack: Stack, state: FormationState, y: torch.Tensor, direct: torch.Tensor, names: list[str],
                scale: float) -> dict[str, np.ndarray]:
    """Standard deviations of the physical values of the raw parameters ``names``, conditional on the albedos
    (``direct``): Cov = J H^-1 J^T, H the Hessian of sum rho(e) / (2 s^2) over the raw values (s^2 = sum rho /
    (n - k)), J = d value / d raw, e the fit's residual (module docstring). Views are treated as independent, so these
    are lower bounds."""
    if not names:
        return {}
    residual = Residual(stack)
    by_name = dict(stack.named_parameters())
    shapes = [by_name[n].shape for n in names]
    sizes = [int(np.prod(s)) for s in shapes]
    flat0 = torch.cat([by_name[n].detach().reshape(-1) for n in names])

    def unflatten(flat):
        return {n: t.view(s) for n, t, s in zip(names, torch.split(flat, sizes), shapes, strict=True)}

    def total_loss(flat):
        values = {f"stack.{n}": t for n, t in unflatten(flat).items()}
        return soft_l1(functional_call(residual, values, (state.replace(direct=direct), y)), scale).sum()

    with torch.no_grad():
        s2 = float(total_loss(flat0)) / max(y.numel() - flat0.numel(), 1)
    hess = torch.autograd.functional.hessian(total_loss, flat0) / (2.0 * s2)
    evals, evecs = torch.linalg.eigh(0.5 * (hess + hess.T))
    inv = (evecs / evals.clamp_min(evals.abs().max() * 1e-12 + 1e-300)) @ evecs.T
    specs = {n: stack.effects[int(n.split(".")[1])]._spec(n.rsplit(".", 1)[1]) for n in names}

    def to_values(flat):
        return torch.cat([specs[n].to_value(t).reshape(-1) for n, t in unflatten(flat).items()])

    jac = torch.autograd.functional.jacobian(to_values, flat0)
    std = torch.sqrt(torch.diagonal(jac @ inv @ jac.T).clamp_min(0.0))
    return {n: t.view(s).numpy() for n, t, s in zip(names, torch.split(std, sizes), shapes, strict=True)}


def describe_params(stack: Stack, std: dict[str, np.ndarray], intervals: dict | None = None) -> dict:
    """{effect: {param: {"value", "std", "units", "fitted", "boot_std", "ci95"}}}: std the Laplace std, boot_std
    and ci95 = [low, high] from the bootstrap (None for parameters not fitted, or without a bootstrap)."""
    out, intervals = {}, intervals or {}

    def json_or_none(a):
        return to_json_value(torch.from_numpy(np.asarray(a))) if a is not None else None

    for i, effect in enumerate(stack.effects):
        entry = {}
        for p in effect.params:
            key = f"effects.{i}.raw.{p.name}"
            sd, low, high = intervals.get(key, (None, None, None))
            entry[p.name] = {"value": to_json_value(effect.param(p.name)),
                             "std": to_json_value(torch.from_numpy(std[key])) if key in std else None,
                             "units": p.units, "fitted": key in std, "boot_std": json_or_none(sd),
                             "ci95": None if low is None else [json_or_none(low), json_or_none(high)]}
        out[effect.name] = entry
    return out


def point_sums(obs: Observations, split: Split, residual: np.ndarray,
               per_channel: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(sum of squared residuals, number of residual components) per held-out point of ``split``, from the (n,3)
    ``residual`` of its test views (``split.holdout_test_obs``). ``per_channel``: (H, 3) sums, one per channel, and
    each point's number of test views."""
    index = np.searchsorted(split.holdout_points, obs.point[split.holdout_test_obs])
    h = len(split.holdout_points)
    views = np.bincount(index, minlength=h)
    if per_channel:
        return np.stack([np.bincount(index, residual[:, c] ** 2, minlength=h) for c in range(3)], 1), views
    return np.bincount(index, (residual ** 2).sum(1), minlength=h), views * 3


def heldout_sums(stack: Stack, obs: Observations, split: Split, config: FitConfig,
                 per_channel: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """:func:`point_sums` (``per_channel`` alike) of a ``stack`` fitted elsewhere: each held-out point's albedo
    fitted to half its views with the stack frozen, the other half predicted (the held-out error of
    :func:`fit_stack`)."""
    stack = copy_stack(stack).to(torch.float64)
    for p in stack.parameters():
        p.requires_grad_(False)
    albedo = np.full((obs.n_points, 3), np.nan)
    held = Problem(stack, obs, config, [], split.holdout_fit_obs, board=False)
    albedo[held.points] = fit_albedos(held, None).numpy()
    test = split.holdout_test_obs
    return point_sums(obs, split, obs.colour[test] - predict(stack, obs, test, albedo), per_channel)


def fit_stack(stack: Stack, obs: Observations, split: Split, config: FitConfig | None = None,
              frozen: dict[str, tuple[str, ...]] | None = None, init_albedo: np.ndarray | None = None) -> FitResult:
    """Fit a copy of ``stack`` and the albedos to the training views (board rows not used), then measure the
    held-out error (see the module docstring). ``frozen``: {effect: parameter names} kept at their values (known
    settings); ``init_albedo``: (P,3) starting albedos (e.g. from a previous fit)."""
    began, config = time.perf_counter(), config or FitConfig()
    stack = copy_stack(stack).to(torch.float64)
    names = fitted_names(stack, config.fixed_effects, frozen or {})
    start_inside_bounds(stack, names)
    train = Problem(stack, obs, config, names, split.train_obs, board=False)
    albedo = np.full((obs.n_points, 3), np.nan)
    albedo[train.points] = fit_albedos(train, init_albedo).numpy()
    held = Problem(stack, obs, config, [], split.holdout_fit_obs, board=False)
    albedo[held.points] = fit_albedos(held, None).numpy()

    direct = torch.from_numpy(albedo[obs.point[split.train_obs]]).view(-1, 3, 1, 1)
    std = laplace_std(stack, train.state, train.y, direct, names, config.loss_scale)
    intervals = {}
    if config.bootstrap:
        train.start = torch.from_numpy(albedo[train.points]).clamp(config.albedo_min, config.albedo_max)
        samples = bootstrap(train, config)
        best = train.physical()
        for name in names:
            spec = stack.effects[int(name.split(".")[1])]._spec(name.rsplit(".", 1)[1])
            intervals[name] = normal_interval(best[name], np.array([s[name] for s in samples]), spec.lower, spec.upper)
    for p in stack.parameters():
        p.requires_grad_(False)

    predicted = predict(stack, obs, np.arange(obs.n_obs), albedo)
    residual = obs.colour - predicted
    role = np.zeros(obs.n_obs, np.int8)
    role[split.holdout_fit_obs] = 1
    role[split.holdout_test_obs] = 2
    sq_sum, count = point_sums(obs, split, residual[split.holdout_test_obs])
    return FitResult(
        stack=stack, params=describe_params(stack, std, intervals), albedo=albedo, predicted=predicted,
        residual=residual, role=role, train_rmse=float(np.sqrt(np.mean(residual[split.train_obs] ** 2))),
        heldout_rmse=float(np.sqrt(sq_sum.sum() / max(count.sum(), 1))), heldout_sq_sum=sq_sum,
        heldout_count=count, seconds=time.perf_counter() - began)
