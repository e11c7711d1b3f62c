"""Fitting a formation stack to the measurement table, with per-point albedos and held-out points.

Model of observation o of point p (linear RGB, per channel c):

    y_oc = F_theta(a_p, state_o)_c

F the formation stack (``Stack.render``) with parameters theta, a_p > 0 the point's in-air colour
(its "albedo", shading included), state_o the observation's geometry. The observations are laid
out as a batch of 1x1 images, every tensor (N,C,1,1), so per-observation fields such as
``frame_index`` (which is per batch element) are available to every effect.

Loss: soft-L1 on the linear colour residual e, rho(e) = 2 f^2 (sqrt(1 + (e/f)^2) - 1) with scale
f = ``loss_scale`` (quadratic below f, linear above), summed over channels, averaged over
observations.

Minimisation, by variable projection then a joint polish (L-BFGS, strong-Wolfe line search):

1. theta alone, each albedo replaced by its least-squares value given theta (:func:`ls_albedo`;
   closed form a_p = sum_v T (y - B) / sum_v T^2 with T = F(1) - F(0), B = F(0) when the stack is
   affine in the albedo, a few secant steps otherwise): ``iterations`` steps. Jointly, the albedos
   (thousands) and a parameter such as attenuation (which only the views' range differences
   constrain) make a badly conditioned problem that Adam or L-BFGS take many hundreds of steps on.
   Optionally (``refine_evaluations``) a trust-region least squares on the same reduced residuals follows
   (:func:`least_squares_fit`, scipy's ``trf`` with a finite-difference Jacobian): L-BFGS stops where the loss
   changes by less than its tolerance per step, which in a flat direction is far from the optimum. On colours
   the true stack renders exactly (small simulated surveys, seeds 1 and 3) L-BFGS stopped at red beta 0.347
   and 0.351 per m (truth 0.45; the reduced Hessian's eigenvalues span 3e-9 to 0.1), the least squares
   reached the truth to 4 digits in 7 evaluations. The bootstrap's replicates always use it (below).
2. theta and log a together on the robust loss, from there: ``polish_iterations`` steps.

Starting point: fitted parameters are moved 1% of their span inside their bounds (a value on a
bound has no gradient through the sigmoid: ``artificial_light.ambient = 0`` stayed at 0); albedos,
unless given, from secant steps at a = 0.3.

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
the albedos and treat observations as independent, so they are lower bounds (0.0002 for an eta that
was 0.07 per m off on an independent survey). Honest intervals (``FitConfig.bootstrap`` replicates):
a two-way bootstrap, frames drawn with replacement and points weighted Poisson(1), each replicate
refitted from the full fit with the albedos refitted (:func:`bootstrap_intervals`).

Coverage (tests/test_bootstrap.py: small simulated surveys, 600 points, default model, gain held): the 95 %
intervals covered 30 of 36 fitted components on seeds 1-3 when the replicates were refitted by 100 L-BFGS
iterations and colours read as 5-pixel patch means. Two causes, both measured: (1) the replicates did not move
along the flat red backscatter direction (boot_std of red beta 0.011 per m, where the converged replicates
spread 0.29), so red b_inf and beta were missed on seeds 1 and 3 (z = +2.6, -9.3; +5.5, -4.2); (2) the patch
means put green and blue eta 8-14 % high on seed 3 (z +2.6, +2.5), a bias that every replicate shares (see
:mod:`eval.diagnose_measure`). With the replicates refitted by the trust-region least squares and colours read at
one footprint on the surface: 35 of 36 on seeds 1-3 (red eta on seed 1, 2.3 % low, z -2.2, is missed) and 24 of
24 on seeds 4 and 5, held out while this was worked out.
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

from .bootstrap import normal_interval, two_way_weights
from .diagnose_measure import Measurements

#: L-BFGS stops when the loss changes by less than this fraction of its starting value.
RELATIVE_TOLERANCE = 1e-8
#: Fraction of a parameter's span kept from its bounds at the start of a fit (see start_inside_bounds).
START_MARGIN = 0.01


@dataclass(frozen=True)
class FitConfig:
    """How a stack is fitted to the measurements."""

    iterations: int = 100
    """L-BFGS iterations over the parameters with the albedos projected out (variable projection)."""
    refine_evaluations: int = 0
    """Residual evaluations of a trust-region least squares (Gauss-Newton) that finishes the variable projection
    after the L-BFGS iterations (0: none). L-BFGS alone stops short in the model's flat directions (see the module
    docstring), but off by default: on the small simulated surveys with 60 the fit reached the weakly pinned red
    backscatter's optimum (seed 2: b_inf 0.74, beta 0.008 per m; truth 0.03, 0.45) where the 40-evaluation
    replicates stop short again (31 of 36 intervals covered against 35 without it), and every candidate fit of
    the diagnosis took longer (tests/test_diagnose.py 13 min)."""
    polish_iterations: int = 20
    """L-BFGS iterations of the joint fit of parameters and albedos that follows (robust loss)."""
    secant_steps: int = 4
    """Secant steps of each least-squares albedo when the model is not affine in the albedo."""
    loss_scale: float = 0.02
    """Scale f of the soft-L1 loss, linear colour units: residuals above it count linearly."""
    holdout_fraction: float = 0.2
    """Fraction of the points held out of the fit to measure the error."""
    fixed_effects: tuple[str, ...] = ("gain",)
    """Effects whose parameters are not fitted (gain: degenerate with the albedos' scale)."""
    seed: int = 0
    """Seed of the held-out split and of the bootstrap."""
    bootstrap: int = 20
    """Replicates of the two-way bootstrap (frames drawn with replacement, points weighted Poisson(1)) that
    gives each fitted parameter of the model (not of the candidates) a 95 % interval with the albedos
    refitted; 0: the Laplace std alone."""
    bootstrap_iterations: int = 40
    """Residual evaluations of each replicate's refit, from the full fit: trust-region least squares on the
    variable projection (as ``refine_evaluations``). With 100 L-BFGS iterations instead the replicates stopped
    short in the flat directions (red B_inf and beta), and the intervals came out too narrow."""


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
                "uncertainty": "std: 1-sigma Laplace approximation conditional on the fitted albedos (a lower "
                               "bound); ci95 (when bootstrapped): estimate +- 1.96 boot_std, two-way bootstrap over "
                               "frames and points with the albedos refitted"}


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
    """A copy of ``stack`` with ``effect`` inserted by rank (see :meth:`Stack.with_effect`)."""
    return copy_stack(stack).with_effect(effect)


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


def start_inside_bounds(stack: Stack, names: list[str], margin: float = START_MARGIN) -> None:
    """Move the starting value of each fitted raw parameter ``names`` at least ``margin`` inside its
    bounds (in place): sigmoid parameters to p = (v - lower)/(upper - lower) in [margin, 1 - margin],
    softplus ones to v - lower >= margin. A value on a bound (e.g. ``artificial_light.ambient = 0``)
    has raw = logit(1e-9) ~ -21, where d value / d raw ~ 1e-9: the fit cannot move it in a few hundred steps."""
    by_name = dict(stack.named_parameters())
    limit = math.log(margin) - math.log1p(-margin)  # logit(margin) < 0; softplus(limit) ~ margin
    with torch.no_grad():
        for name in names:
            raw = by_name[name]
            spec = stack.effects[int(name.split(".")[1])]._spec(name.rsplit(".", 1)[1])
            raw.clamp_(limit, -limit) if spec.bounded_above else raw.clamp_(min=limit)


def ls_albedo(stack: Stack, state: FormationState, y: torch.Tensor, local: torch.Tensor, start: torch.Tensor,
              steps: int, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Per point and channel, the albedo a with F(a) ~ y over the point's views, by ``steps`` secant
    steps from ``start`` (n,3): with B = F(0) and each view's slope t_k = (F(a_k) - B) / a_k,
    a_{k+1} = sum_v t_k (y - B) / sum_v t_k^2 (least squares of y = a t_k + B), clamped to [1e-3, 10].
    One step is exact when the stack is affine in the albedo; otherwise the steps follow the curve's
    secant, which a single slope at a = 1 does not (a clipped F(1) gives a tiny slope and an albedo
    so large that every view is clipped and the fit has no gradient). Differentiable in the stack's
    parameters (the variable projection of :func:`fit_stack`). ``weight``: (N,) observation weights (a
    bootstrap replicate's), both sums weighted."""
    n = start.shape[0]
    w = torch.ones(len(y), 1, dtype=y.dtype) if weight is None else weight.view(-1, 1)
    zero = stack.render(state.replace(direct=torch.zeros_like(state.direct)))[:, :, 0, 0]
    albedo = start
    for _ in range(steps):
        a_obs = albedo[local]
        t = (stack.render(state.replace(direct=a_obs.view(-1, 3, 1, 1)))[:, :, 0, 0] - zero) / a_obs
        num = torch.zeros(n, 3, dtype=y.dtype).index_add(0, local, w * t * (y - zero))
        den = torch.zeros(n, 3, dtype=y.dtype).index_add(0, local, w * t * t)
        albedo = (num / den.clamp_min(1e-12)).clamp(1e-3, 10.0)
    return albedo


def robust_residual(e: torch.Tensor, scale: float) -> torch.Tensor:
    """r(e) with r^2 = rho(e) (:func:`soft_l1`) and the sign of e: e sqrt(2 / (1 + sqrt(1 + (e/f)^2)))."""
    return e * torch.sqrt(2.0 / (1.0 + torch.sqrt(1.0 + (e / scale) ** 2)))


def reduced_residuals(stack: Stack, state: FormationState, y: torch.Tensor, local: torch.Tensor, start: torch.Tensor,
                      steps: int, scale: float, weight: torch.Tensor | None = None) -> torch.Tensor:
    """(N,3) residuals of the variable projection, each point's albedo its least-squares value given the stack's
    parameters: in closed form when the stack is affine in the albedo (``steps`` 1: F(a) = T a + B, T = F(1) - F(0),
    B = F(0)), else by ``steps`` secant steps from ``start``. Scaled so that their sum of squares is the mean
    soft-L1 loss weighted by ``weight`` (N,): sqrt(w_o / sum w) r(e_oc), r :func:`robust_residual`."""
    w = torch.ones(len(y), dtype=y.dtype) if weight is None else weight
    if steps > 1:
        albedo = ls_albedo(stack, state, y, local, start, steps, w)
        pred = stack.render(state.replace(direct=albedo[local].view(-1, 3, 1, 1)))[:, :, 0, 0]
    else:
        b = stack.render(state.replace(direct=torch.zeros_like(state.direct)))[:, :, 0, 0]
        t = stack.render(state.replace(direct=torch.ones_like(state.direct)))[:, :, 0, 0] - b
        n = start.shape[0]
        num = torch.zeros(n, 3, dtype=y.dtype).index_add(0, local, w[:, None] * t * (y - b))
        den = torch.zeros(n, 3, dtype=y.dtype).index_add(0, local, w[:, None] * t * t)
        pred = t * (num / den.clamp_min(1e-12)).clamp(1e-3, 10.0)[local] + b
    return torch.sqrt(w / w.sum())[:, None] * robust_residual(pred - y, scale)


def reduced_loss(stack: Stack, state: FormationState, y: torch.Tensor, local: torch.Tensor, start: torch.Tensor,
                 steps: int, scale: float, weight: torch.Tensor | None = None) -> torch.Tensor:
    """The variable-projection loss: mean soft-L1 (weighted by ``weight``, (N,)) with each point's albedo its
    least-squares value given the stack's parameters (the sum of squares of :func:`reduced_residuals`)."""
    return (reduced_residuals(stack, state, y, local, start, steps, scale, weight) ** 2).sum()


def least_squares_fit(theta: list[torch.Tensor], residual_fn, evaluations: int) -> None:
    """Minimise the sum of squares of ``residual_fn()`` over the tensors ``theta`` (in place) by scipy's trust-region
    reflective least squares, at most ``evaluations`` residual evaluations (a 2-point finite-difference Jacobian
    costs 1 per parameter on top), Jacobian-scaled variables; the start is kept unless the fit lowers the cost.
    The 2-point Jacobian gave the same coverage as the 3-point one on tests/test_bootstrap.py's seeds 1-3 (35 of
    36, the same miss) with that test's fixture in 34 s instead of 81 s (quiet and loaded machine respectively)."""
    if evaluations <= 0 or not theta:
        return
    from scipy.optimize import least_squares

    shapes = [t.shape for t in theta]
    sizes = [t.numel() for t in theta]
    x0 = torch.cat([t.detach().reshape(-1) for t in theta]).numpy().copy()

    def assign(x: np.ndarray) -> None:
        with torch.no_grad():
            for t, part, shape in zip(theta, np.split(x, np.cumsum(sizes)[:-1]), shapes, strict=True):
                t.copy_(torch.from_numpy(part.reshape(shape)))

    def fun(x: np.ndarray) -> np.ndarray:
        assign(x)
        with torch.no_grad():
            return residual_fn().reshape(-1).numpy()

    cost0 = float((fun(x0) ** 2).sum())
    with np.errstate(all="ignore"):
        result = least_squares(fun, x0, jac="2-point", method="trf", x_scale="jac", ftol=1e-12, xtol=1e-10,
                               gtol=1e-12, max_nfev=evaluations)
    assign(result.x if np.isfinite(result.x).all() and 2.0 * result.cost <= cost0 else x0)


def is_affine_in_albedo(stack: Stack, state: FormationState, albedo: torch.Tensor) -> bool:
    """True when F(2a) - F(a) = F(a) - F(0) for these observations (no sensor curve or clipping)."""
    with torch.no_grad():
        f0, f1, f2 = (stack.render(state.replace(direct=k * albedo)) for k in (0.0, 1.0, 2.0))
    return bool(torch.allclose(f2 - f1, f1 - f0, atol=1e-9, rtol=1e-6))


def _minimise(params: list[torch.Tensor], loss_fn, iterations: int) -> None:
    """At most ``iterations`` L-BFGS iterations (strong-Wolfe line search, history 20), stopping when
    the loss changes by less than RELATIVE_TOLERANCE of its starting value."""
    if iterations <= 0:
        return
    with torch.no_grad():
        scale = abs(float(loss_fn())) + 1e-30
    lbfgs = torch.optim.LBFGS(params, lr=1.0, max_iter=iterations, history_size=20, line_search_fn="strong_wolfe",
                              tolerance_grad=1e-12, tolerance_change=RELATIVE_TOLERANCE * scale)

    def closure():
        lbfgs.zero_grad(set_to_none=True)
        loss = loss_fn()
        loss.backward()
        return loss

    lbfgs.step(closure)


def _fit_albedos(stack: Stack, meas: Measurements, obs: np.ndarray, config: FitConfig,
                 train_names: list[str], init_albedo: np.ndarray | None,
                 iterations: int) -> tuple[torch.Tensor, FormationState]:
    """Fit log albedos of the points of ``obs`` (and the raw parameters ``train_names``, which may be
    empty; see the module docstring). Returns the (P,3) albedo tensor (rows of other points are NaN)
    and the state."""
    state = observation_state(meas, obs)
    y = torch.from_numpy(meas.colour[obs])
    points, local = np.unique(meas.point[obs], return_inverse=True)
    local = torch.from_numpy(local)
    by_name = dict(stack.named_parameters())
    theta = [by_name[n] for n in train_names]
    for p in stack.parameters():
        p.requires_grad_(False)
    if init_albedo is not None and np.isfinite(init_albedo[points]).all():
        start = torch.from_numpy(init_albedo[points]).clamp(1e-3, 10.0)
    else:
        start = torch.full((len(points), 3), 0.3, dtype=torch.float64)
    steps = 1 if is_affine_in_albedo(stack, state, start[local].view(-1, 3, 1, 1)) else config.secant_steps
    with torch.no_grad():
        start = ls_albedo(stack, state, y, local, start, steps if init_albedo is None else 0)

    def render(albedo):
        return stack.render(state.replace(direct=albedo[local].view(-1, 3, 1, 1)))[:, :, 0, 0]

    if theta:  # variable projection: the parameters alone, each point's albedo its least-squares value
        for p in theta:
            p.requires_grad_(True)
        _minimise(theta, lambda: reduced_loss(stack, state, y, local, start, steps, config.loss_scale), iterations)
        least_squares_fit(theta, lambda: reduced_residuals(stack, state, y, local, start, steps, config.loss_scale),
                          config.refine_evaluations)
        with torch.no_grad():
            start = ls_albedo(stack, state, y, local, start, steps)
    log_a = torch.nn.Parameter(torch.log(start))

    def loss_fn():
        return soft_l1(render(torch.exp(log_a)) - y, config.loss_scale).sum(1).mean()

    _minimise([log_a, *theta], loss_fn, config.polish_iterations)
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


def describe_params(stack: Stack, std: dict[str, np.ndarray], intervals: dict | None = None) -> dict:
    """{effect: {param: {"value", "std", "units", "fitted", "boot_std", "ci95"}}}: std the Laplace std,
    boot_std and ci95 = [low, high] (elementwise) from :func:`bootstrap_intervals` (None for parameters not
    fitted, or without a bootstrap)."""
    out = {}
    intervals = intervals or {}

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


def bootstrap_intervals(stack: Stack, meas: Measurements, obs: np.ndarray, names: list[str], albedo: np.ndarray,
                        config: FitConfig) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """95 % intervals of the fitted raw parameters ``names`` of ``stack`` (fitted on observations ``obs``,
    albedos ``albedo``) from ``config.bootstrap`` replicates of the two-way bootstrap
    (:func:`eval.bootstrap.two_way_weights`: frames drawn with replacement, points weighted Poisson(1)).
    Each replicate refits the parameters from the full fit with ``bootstrap_iterations`` residual evaluations of
    the trust-region least squares (:func:`least_squares_fit`) on the weighted variable-projection residuals, in
    which every point's albedo is its weighted least-squares value: unlike the Laplace std the intervals are not
    conditional on the albedos, and frames and points with correlated errors count as the units they are. Returns
    {name: (sd, low, high)} of the physical values: estimate +- 1.96 sd, clipped to the bounds (stack restored)."""
    state = observation_state(meas, obs)
    y = torch.from_numpy(meas.colour[obs])
    points, local = np.unique(meas.point[obs], return_inverse=True)
    local = torch.from_numpy(local)
    start = torch.from_numpy(albedo[points]).clamp(1e-3, 10.0)
    steps = 1 if is_affine_in_albedo(stack, state, start[local].view(-1, 3, 1, 1)) else config.secant_steps
    by_name = dict(stack.named_parameters())
    theta = [by_name[n] for n in names]
    best = [t.detach().clone() for t in theta]
    specs = [stack.effects[int(n.split(".")[1])]._spec(n.rsplit(".", 1)[1]) for n in names]
    rng = np.random.default_rng([config.seed, 31])
    samples: list[list[np.ndarray]] = [[] for _ in names]
    for _ in range(config.bootstrap):
        weight = torch.from_numpy(two_way_weights(rng, meas.frame[obs], meas.point[obs]))
        with torch.no_grad():
            for t, b in zip(theta, best, strict=True):
                t.copy_(b)
        least_squares_fit(theta, lambda w=weight: reduced_residuals(stack, state, y, local, start, steps,
                                                                     config.loss_scale, w),
                          config.bootstrap_iterations)
        for k, (t, spec) in enumerate(zip(theta, specs, strict=True)):
            samples[k].append(spec.to_value(t.detach()).numpy())
    with torch.no_grad():
        for t, b in zip(theta, best, strict=True):
            t.copy_(b)
    return {n: normal_interval(spec.to_value(b).numpy(), np.array(s), spec.lower, spec.upper)
            for n, spec, b, s in zip(names, specs, best, samples, strict=True)}


def fit_stack(stack: Stack, meas: Measurements, split: Split, config: FitConfig = FitConfig(),
              frozen: dict[str, tuple[str, ...]] | None = None, init_albedo: np.ndarray | None = None) -> FitResult:
    """Fit a copy of ``stack`` and the albedos to the training observations, then measure the
    held-out error (see module docstring). ``frozen``: {effect: parameter names} kept at their
    values (known settings); ``init_albedo``: (P,3) starting albedos (e.g. from a previous fit)."""
    start = time.perf_counter()
    stack = copy_stack(stack).to(torch.float64)
    names = fitted_names(stack, config, frozen or {})
    start_inside_bounds(stack, names)
    albedo_t, state = _fit_albedos(stack, meas, split.train_obs, config, names, init_albedo, config.iterations)
    held_albedo, _ = _fit_albedos(stack, meas, split.holdout_fit_obs, config, [], None, 0)
    albedo_t[torch.from_numpy(split.holdout_points)] = held_albedo[torch.from_numpy(split.holdout_points)]
    albedo = albedo_t.numpy()

    y_train = torch.from_numpy(meas.colour[split.train_obs])
    direct = albedo_t[torch.from_numpy(meas.point[split.train_obs])].view(-1, 3, 1, 1)
    std = laplace_std(stack, state, y_train, direct, names, config.loss_scale)
    intervals = {}
    if config.bootstrap:
        intervals = bootstrap_intervals(stack, meas, split.train_obs, names, albedo, config)

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
        stack=stack, params=describe_params(stack, std, intervals), albedo=albedo, predicted=predicted,
        residual=residual, role=role, train_rmse=float(np.sqrt(np.mean(residual[split.train_obs] ** 2))),
        heldout_rmse=float(np.sqrt(sq_sum.sum() / max(count.sum(), 1))), heldout_sq_sum=sq_sum,
        heldout_count=count, seconds=time.perf_counter() - start)

