"""Fitting a formation stack to the measurement table, with per-point albedos and held-out points.

Model of observation o of point p (linear RGB, per channel c):

    y_oc = F_theta(a_p, state_o)_c

F the formation stack (``Stack.render``) with parameters theta, a_p > 0 the point's in-air colour
(its "albedo", shading included), state_o the observation's geometry. The observations are laid
out as a batch of 1x1 images, every tensor (N,C,1,1), so per-observation fields such as
``frame_index`` (which is per batch element) are available to every effect.

Loss: soft-L1 on the linear colour residual e, rho(e) = 2 f^2 (sqrt(1 + (e/f)^2) - 1) with scale
f = ``loss_scale`` (quadratic below f, linear above), summed over channels, averaged over
observations; minimised jointly over theta and log a with Adam (cosine learning-rate decay).

Degeneracy: a per-channel gain k and the albedos' scale are exactly degenerate (k a = (k s)(a/s)),
so the effects named in ``FitConfig.fixed_effects`` (``gain`` by default) keep their configured
values; the albedos carry the scale.

Held-out error: a fraction of the points takes no part in the fit. With theta frozen, each held-out
point's albedo is fitted from half of its views (the "fit" views) and the error is measured on the
other half (the "test" views): RMSE over channels and test views, linear 0..1.

Uncertainty (Laplace approximation): with the albedos held at their fitted values, the covariance
of the raw parameters is H^-1, H the Hessian of the negative log-likelihood sum_o rho(e_o) / (2 s^2)
(s^2 = sum rho / (n - k), the residual variance) at the optimum; the delta method maps it to the
physical values (J = d value / d raw, Cov = J H^-1 J^T). The standard deviations are conditional on
the albedos and treat observations as independent, so they are lower bounds.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch.func import functional_call

from watergan.formation import Effect, FormationState, Stack
from watergan.formation.params import to_json_value

from .diagnose_measure import Measurements


@dataclass(frozen=True)
class FitConfig:
    """How a stack is fitted to the measurements."""

    iterations: int = 300
    """Adam iterations of the joint fit (the held-out albedo fit, albedos only, uses a third)."""
    lr: float = 0.05
    """Adam learning rate on the raw parameters and log albedos (cosine decay to 5% of it)."""
    loss_scale: float = 0.02
    """Scale f of the soft-L1 loss, linear colour units: residuals above it count linearly."""
    holdout_fraction: float = 0.2
    """Fraction of the points held out of the fit to measure the error."""
    fixed_effects: tuple[str, ...] = ("gain",)
    """Effects whose parameters are not fitted (gain: degenerate with the albedos' scale)."""
    seed: int = 0
    """Seed of the held-out split."""


@dataclass(frozen=True)
class Split:
    """Which observations train the stack, fit held-out albedos, or test.

    train_obs / holdout_fit_obs / holdout_test_obs: (n,) observation indices.
    holdout_points: (H,) indices of the held-out points.
    """

    train_obs: np.ndarray
    holdout_fit_obs: np.ndarray
    holdout_test_obs: np.ndarray
    holdout_points: np.ndarray


@dataclass(frozen=True)
class FitResult:
    """A fitted stack and how well it explains the measurements.

    stack:            the fitted stack (a new object; the input stack is not changed).
    params:           {effect: {param: {"value", "std", "units", "fitted"}}}, physical values.
    albedo:           (P,3) fitted linear albedo of every point (held-out ones from their fit views).
    predicted:        (N,3) predicted linear colour of every observation.
    residual:         (N,3) observed - predicted.
    role:             (N,) 0 training observation, 1 held-out fit view, 2 held-out test view.
    train_rmse:       RMSE over the training observations, linear.
    heldout_rmse:     RMSE over the held-out test views, linear.
    heldout_sq_sum:   (H,) per held-out point, sum of squared test residuals (for the bootstrap).
    heldout_count:    (H,) per held-out point, number of squared test residuals (views x 3).
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
                "uncertainty": "1-sigma Laplace approximation conditional on the fitted albedos (lower bound)"}


def make_split(meas: Measurements, config: FitConfig) -> Split:
    """Hold out ``holdout_fraction`` of the points; split each held-out point's views in two halves
    at random (the larger half fits the albedo)."""
    rng = np.random.default_rng([config.seed, 11])
    n_hold = int(round(config.holdout_fraction * meas.n_points))
    holdout = np.sort(rng.permutation(meas.n_points)[:n_hold])
    is_hold = np.zeros(meas.n_points, bool)
    is_hold[holdout] = True
    obs_hold = is_hold[meas.point]
    fit_view = np.zeros(meas.n_obs, bool)
    for p in holdout:
        views = np.nonzero(meas.point == p)[0]
        fit_view[rng.permutation(views)[: (len(views) + 1) // 2]] = True
    return Split(train_obs=np.nonzero(~obs_hold)[0], holdout_fit_obs=np.nonzero(obs_hold & fit_view)[0],
                 holdout_test_obs=np.nonzero(obs_hold & ~fit_view)[0], holdout_points=holdout)


def observation_state(meas: Measurements, obs: np.ndarray) -> FormationState:
    """The state of observations ``obs`` as a batch of 1x1 images (float64); ``direct`` is a
    placeholder of ones (replaced by the albedos)."""
    def col(a: np.ndarray) -> torch.Tensor:
        a = np.asarray(a, np.float64)
        return torch.from_numpy(a.reshape(len(obs), -1, 1, 1).copy())

    p = meas.point[obs]
    return FormationState(
        direct=torch.ones(len(obs), 3, 1, 1, dtype=torch.float64),
        range_m=col(meas.range_m[obs]), depth_m=col(meas.depth_m[obs]), pixel_uv=col(meas.pixel_uv[obs]),
        image_wh=tuple(meas.image_wh), points_cam=col(meas.points_cam[obs]), normals_cam=col(meas.normals_cam[obs]),
        points_world=col(meas.points_world[p]), normals_world=col(meas.normals_world[p]),
        water_depth_m=col(meas.water_depth_m[p]), frame_index=torch.from_numpy(meas.frame[obs].astype(np.int64)),
    )


def soft_l1(e: torch.Tensor, scale: float) -> torch.Tensor:
    """rho(e) = 2 f^2 (sqrt(1 + (e/f)^2) - 1): e^2 for |e| << f, 2 f |e| for |e| >> f."""
    return 2.0 * scale * scale * (torch.sqrt(1.0 + (e / scale) ** 2) - 1.0)


def copy_stack(stack: Stack) -> Stack:
    """An independent copy with the same parameter values."""
    return Stack.from_config(stack.to_config())


def insert_by_rank(stack: Stack, effect: Effect) -> Stack:
    """A new stack with ``effect`` inserted after every effect of lower or equal rank."""
    effects = list(copy_stack(stack).effects)
    at = sum(1 for e in effects if e.rank <= effect.rank)
    return Stack([*effects[:at], effect, *effects[at:]])


def fitted_names(stack: Stack, config: FitConfig, frozen: dict[str, tuple[str, ...]]) -> list[str]:
    """Names (as in ``stack.named_parameters()``) of the raw parameters to fit: learnable ones of
    effects not in ``fixed_effects``, minus ``frozen`` {effect: params} (known settings)."""
    names = []
    for i, effect in enumerate(stack.effects):
        if effect.name in config.fixed_effects:
            continue
        for p in effect.params:
            if p.learnable and p.name not in frozen.get(effect.name, ()):
                names.append(f"effects.{i}.raw.{p.name}")
    return names


def _initial_albedo(stack: Stack, state: FormationState, y: torch.Tensor, local: torch.Tensor, n: int) -> torch.Tensor:
    """Per point least squares of y = a T + B with T = F(1) - F(0), B = F(0) (exact when the
    stack is affine in the albedo, a starting point otherwise), clamped to >= 1e-3."""
    with torch.no_grad():
        zero = stack.render(state.replace(direct=torch.zeros_like(state.direct)))[:, :, 0, 0]
        t = stack.render(state)[:, :, 0, 0] - zero
        num = torch.zeros(n, 3, dtype=y.dtype).index_add_(0, local, t * (y - zero))
        den = torch.zeros(n, 3, dtype=y.dtype).index_add_(0, local, t * t)
    return (num / den.clamp_min(1e-12)).clamp(1e-3, 10.0)


def _adam(params: list[torch.Tensor], loss_fn, iterations: int, lr: float) -> None:
    opt = torch.optim.Adam(params, lr=lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda t: 0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * t / max(iterations, 1))))
    for _ in range(iterations):
        opt.zero_grad(set_to_none=True)
        loss = loss_fn()
        loss.backward()
        opt.step()
        sched.step()


def _fit_albedos(stack: Stack, meas: Measurements, obs: np.ndarray, config: FitConfig,
                 train_names: list[str], init_albedo: np.ndarray | None,
                 iterations: int) -> tuple[torch.Tensor, FormationState]:
    """Fit log albedos of the points of ``obs`` (and the raw parameters ``train_names``, which may be
    empty). Returns the (P,3) albedo tensor (rows of other points are NaN) and the state."""
    state = observation_state(meas, obs)
    y = torch.from_numpy(meas.colour[obs])
    points, local = np.unique(meas.point[obs], return_inverse=True)
    local = torch.from_numpy(local)
    if init_albedo is not None and np.isfinite(init_albedo[points]).all():
        a0 = torch.from_numpy(init_albedo[points]).clamp_min(1e-3)
    else:
        a0 = _initial_albedo(stack, state, y, local, len(points))
    log_a = torch.nn.Parameter(torch.log(a0))
    by_name = dict(stack.named_parameters())
    theta = [by_name[n] for n in train_names]
    for p in stack.parameters():
        p.requires_grad_(False)
    for p in theta:
        p.requires_grad_(True)

    def loss_fn():
        pred = stack.render(state.replace(direct=torch.exp(log_a)[local].view(-1, 3, 1, 1)))[:, :, 0, 0]
        return soft_l1(pred - y, config.loss_scale).sum(1).mean()

    _adam([log_a, *theta], loss_fn, iterations, config.lr)
    for p in stack.parameters():
        p.requires_grad_(False)
    albedo = torch.full((meas.n_points, 3), float("nan"), dtype=torch.float64)
    albedo[torch.from_numpy(points)] = torch.exp(log_a.detach())
    return albedo, state


def predict(stack: Stack, meas: Measurements, obs: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """(n,3) predicted linear colour of observations ``obs`` given the (P,3) albedos."""
    state = observation_state(meas, obs)
    with torch.no_grad():
        direct = torch.from_numpy(albedo[meas.point[obs]]).view(-1, 3, 1, 1)
        return stack.render(state.replace(direct=direct))[:, :, 0, 0].numpy()


def laplace_std(stack: Stack, state: FormationState, y: torch.Tensor, direct: torch.Tensor, names: list[str],
                scale: float) -> dict[str, np.ndarray]:
    """Standard deviations of the physical values of the raw parameters ``names`` (see module
    docstring): Cov = J H^-1 J^T, H the Hessian of sum rho(e) / (2 s^2) over raw values."""
    if not names:
        return {}
    by_name = dict(stack.named_parameters())
    shapes = [by_name[n].shape for n in names]
    sizes = [int(np.prod(s)) for s in shapes]
    flat0 = torch.cat([by_name[n].detach().reshape(-1) for n in names])

    def unflatten(flat):
        return {n: t.view(s) for n, t, s in zip(names, torch.split(flat, sizes), shapes, strict=True)}

    def total_loss(flat):
        pred = functional_call(stack, unflatten(flat), (state.replace(direct=direct),)).image[:, :, 0, 0]
        return soft_l1(pred - y, scale).sum()

    with torch.no_grad():
        dof = max(y.numel() - flat0.numel(), 1)
        s2 = float(total_loss(flat0)) / dof
    hess = torch.autograd.functional.hessian(total_loss, flat0) / (2.0 * s2)
    evals, evecs = torch.linalg.eigh(0.5 * (hess + hess.T))
    inv = (evecs / evals.clamp_min(evals.abs().max() * 1e-12 + 1e-300)) @ evecs.T
    specs = {}
    for n in names:
        idx = int(n.split(".")[1])
        effect = stack.effects[idx]
        specs[n] = effect._spec(n.rsplit(".", 1)[1])

    def to_values(flat):
        return torch.cat([specs[n].to_value(t).reshape(-1) for n, t in unflatten(flat).items()])

    jac = torch.autograd.functional.jacobian(to_values, flat0)
    std = torch.sqrt(torch.diagonal(jac @ inv @ jac.T).clamp_min(0.0))
    return {n: t.view(s).numpy() for n, t, s in zip(names, torch.split(std, sizes), shapes, strict=True)}


def describe_params(stack: Stack, std: dict[str, np.ndarray]) -> dict:
    """{effect: {param: {"value", "std", "units", "fitted"}}} (std None for parameters not fitted)."""
    out = {}
    for i, effect in enumerate(stack.effects):
        entry = {}
        for p in effect.params:
            key = f"effects.{i}.raw.{p.name}"
            entry[p.name] = {"value": to_json_value(effect.param(p.name)),
                             "std": to_json_value(torch.from_numpy(std[key])) if key in std else None,
                             "units": p.units, "fitted": key in std}
        out[effect.name] = entry
    return out


def fit_stack(stack: Stack, meas: Measurements, split: Split, config: FitConfig = FitConfig(),
              frozen: dict[str, tuple[str, ...]] | None = None, init_albedo: np.ndarray | None = None) -> FitResult:
    """Fit a copy of ``stack`` and the albedos to the training observations, then measure the
    held-out error (see module docstring). ``frozen``: {effect: parameter names} kept at their
    values (known settings); ``init_albedo``: (P,3) starting albedos (e.g. from a previous fit)."""
    start = time.perf_counter()
    stack = copy_stack(stack).to(torch.float64)
    names = fitted_names(stack, config, frozen or {})
    albedo_t, state = _fit_albedos(stack, meas, split.train_obs, config, names, init_albedo, config.iterations)
    held_albedo, _ = _fit_albedos(stack, meas, split.holdout_fit_obs, config, [], init_albedo,
                                   max(config.iterations // 3, 1))
    albedo_t[torch.from_numpy(split.holdout_points)] = held_albedo[torch.from_numpy(split.holdout_points)]
    albedo = albedo_t.numpy()

    y_train = torch.from_numpy(meas.colour[split.train_obs])
    direct = albedo_t[torch.from_numpy(meas.point[split.train_obs])].view(-1, 3, 1, 1)
    std = laplace_std(stack, state, y_train, direct, names, config.loss_scale)

    all_obs = np.arange(meas.n_obs)
    predicted = predict(stack, meas, all_obs, albedo)
    residual = meas.colour - predicted
    role = np.zeros(meas.n_obs, np.int8)
    role[split.holdout_fit_obs] = 1
    role[split.holdout_test_obs] = 2
    test = split.holdout_test_obs
    index = np.searchsorted(split.holdout_points, meas.point[test])
    sq_sum = np.bincount(index, (residual[test] ** 2).sum(1), minlength=len(split.holdout_points))
    count = np.bincount(index, minlength=len(split.holdout_points)) * 3
    return FitResult(
        stack=stack, params=describe_params(stack, std), albedo=albedo, predicted=predicted, residual=residual,
        role=role, train_rmse=float(np.sqrt(np.mean(residual[split.train_obs] ** 2))),
        heldout_rmse=float(np.sqrt(sq_sum.sum() / max(count.sum(), 1))), heldout_sq_sum=sq_sum,
        heldout_count=count, seconds=time.perf_counter() - start)

