"""The one fitter of a formation stack with per-point albedos, to the measurement table (:mod:`eval.observations`).

The water estimate (:mod:`eval.water`) and the diagnosis (:mod:`eval.diagnose`) both fit with it; they differ only
in their :class:`FitConfig` (:data:`WATER_FIT` and the default).

Model of view o of point p (linear RGB, per channel c): y_oc = F_theta(J_p, state_o)_c, F the stack
(``Stack.render``) with parameters theta, J_p >= 0 the point's in-air colour (albedo, shading included), state_o
the view's geometry (a batch of 1x1 images, every tensor (N,C,1,1)). Board rows have their albedo known.

Loss: soft-L1 on the residual e, rho(e) = 2 f^2 (sqrt(1 + (e/f)^2) - 1), f = ``loss_scale``, summed over channels
and averaged over views with weights w_o (a bootstrap replicate's; 1 in the fit); plus ``board_weight`` times the
same mean over the board rows; plus the effects' penalties (``Effect.penalty``: the smoothness of ``image_field``):

    L(theta) = sum_o w_o sum_c rho(e_oc) / sum_o w_o  +  board_weight sum_b w_b sum_c rho(e_bc) / sum_b w_b
               + sum_effects |penalty|^2.

Albedo projection (variable projection): each point's albedo is its weighted least-squares value given theta, in
closed form when the stack is affine in J (J_p = sum_v w A (y - C) / sum_v w A^2, A = F(1) - F(0), C = F(0)), else
by ``secant_steps`` secant steps; clamped to [``albedo_min``, ``albedo_max``]. L is then a function of theta alone.

A stack ending in an output map (``Effect.output_map``, the camera's ``tone_curve``: y = T(F'(J)), F' the rest) is
fitted in the linear domain: each evaluation linearises the observations and the board's, x = T^-1(y) with the
curve's current parameters (gradients reach them through it), and fits x = A' J + C', A' and C' of F', which is
affine again (closed-form albedos, the board's affine terms; the affine test is that of F'). The residual is the
linear one scaled by the curve's slope at the observation, e = T'(x) (x - A' J - C'): the camera-domain residual to
first order, so ``loss_scale`` keeps its units. The plain linear residual x - A' J - C' would weigh a pixel by
1 / T'(x)^2 against the camera domain (the shadows a curve crushes heavily, the mid-tones it lifts lightly), and a
curve that squeezes every observation into a few of its segments would shrink all residuals with it: its loss has
a minimum at no camera. The albedos are then weighted by w T'^2. What a fit reports (predictions, the held-out
error) stays in the camera domain.

Minimisation: the fitted parameters start ``START_MARGIN`` of their span inside their bounds (a value on a bound has
no gradient through the sigmoid); rounds of L-BFGS (``iterations`` each, strong-Wolfe line search) until a round
lowers L by less than ``convergence_rtol`` or ``max_iterations`` are spent; then optionally a trust-region least
squares on the same residuals (``refine_evaluations``: L-BFGS stops where the loss changes little per step, which
in a flat direction can be far from the optimum); then optionally a joint polish of theta and the log albedos
(``polish_iterations``). A coarse start (``coarse_fraction``) fits a fraction of the points first, in float32, and
with ``coarse_refine_evaluations`` follows one round of its L-BFGS with the trust region on those points in float64:
the full fit then starts at the floor of the flat directions instead of crawling along them.

Bootstrap (``bootstrap`` replicates; :func:`eval.bootstrap.bootstrap`): frames drawn with replacement (the frames
that see the board apart from the others, so every replicate keeps the board), each point's views weighted
Poisson(1) and each board patch's too (the views of one point, or of one patch, share its errors). Each replicate is
refitted from the full fit: ``newton`` (one Newton step with the full fit's Hessian, halved until it lowers the
replicate's loss, then ``bootstrap_iterations`` L-BFGS iterations) or ``least_squares`` (``bootstrap_iterations``
evaluations of the trust-region least squares). The replicates' weights are drawn in order and the replicates
refitted side by side (:func:`eval.solvers.side_by_side`: the same replicates, to float rounding). The intervals'
coverage on simulated surveys: benchmarks/RESULTS/water.md.

Held-out error (:mod:`eval.heldout`, ``holdout_fraction``): those points take no part in the fit; with theta frozen
each one's albedo is fitted from half of its views and the error measured on the other half.

Degeneracy: a per-channel gain and the albedos' scale are exactly degenerate (k J = (k s)(J / s)): effects in
``fixed_effects`` keep their values (the water frees the gain when a board pins it).
"""

from __future__ import annotations

import copy
import math
from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from watergan.formation import Effect, FormationState, Stack
from watergan.formation.inverse import affine_images, affine_state

from .bootstrap import Refit
from .observations import Observations
from .solvers import lbfgs, least_squares_fit, side_by_side

#: The stack fitted by default (water and diagnosis): the simulator's visible physics, with WaterGAN's learned
#: backscatter replaced by its analytic counterpart, which has physical parameters to estimate.
DEFAULT_EFFECTS = ("attenuation", "backscatter", "vignetting", "gain")
#: Fraction of a parameter's span kept from its bounds at the start of a fit (see start_inside_bounds).
START_MARGIN = 0.01

@dataclass(frozen=True)
class FitConfig:
    """How a stack is fitted to the measurement table (defaults: the diagnosis's; the water's: :data:`WATER_FIT`)."""

    loss_scale: float = 0.02
    """Scale f of the soft-L1 loss, linear colour units: residuals above it count linearly."""
    iterations: int = 100
    """L-BFGS iterations of a round over the parameters, the albedos projected out."""
    max_iterations: int = 0
    """L-BFGS iterations of a fit at most (0: one round).
    Rounds run until one lowers the loss by less than the convergence tolerance."""
    convergence_rtol: float = 1e-3
    """A fit has converged when a round lowers its loss by less than this fraction."""
    step_rtol: float = 1e-8
    """A round of L-BFGS stops when a step changes the loss by less than this fraction of its starting value."""
    refine_evaluations: int = 0
    """Residual evaluations of a trust-region least squares after the L-BFGS rounds (0: none)."""
    polish_iterations: int = 20
    """L-BFGS iterations of a joint fit of the parameters and the log albedos after that (0: none)."""
    secant_steps: int = 4
    """Secant steps of each least-squares albedo when the stack is not affine in the albedo."""
    albedo_min: float = 1e-3
    """Least albedo of the projection."""
    albedo_max: float = 10.0
    """Largest albedo of the projection."""
    board_weight: float = 10.0
    """Weight of the board term (mean over board rows) beside the views' (mean over views)."""
    holdout_fraction: float = 0.2
    """Fraction of the points held out of the fit to measure the error."""
    fixed_effects: tuple[str, ...] = ("gain",)
    """Effects whose parameters are not fitted (gain: degenerate with the albedos' scale)."""
    bootstrap: int = 20
    """Bootstrap replicates (0: none)."""
    bootstrap_refit: Refit = Refit.least_squares
    """How each replicate is refitted from the full fit: a Newton step then L-BFGS, or trust-region least squares."""
    bootstrap_iterations: int = 40
    """L-BFGS iterations (newton) or residual evaluations (least_squares) of each replicate's refit."""
    bootstrap_points: bool = True
    """Resample the points and the board's patches too (each one's views weigh Poisson(1) times)."""
    float32: bool = False
    """Bootstrap replicates evaluate the model in float32 (parameters and loss stay float64)."""
    coarse_fraction: float = 0.0
    """Fraction of the points a first fit runs on, to convergence, before the fit on all of them (0: none).
    Each of its evaluations costs that fraction of one on all views, and it starts the full fit near its optimum."""
    coarse_refine_evaluations: int = 0
    """Residual evaluations of a trust-region least squares (as the refinement's) on the coarse fit's points,
    in float64, after one round of L-BFGS there (0: none; the coarse fit then runs its rounds to convergence): it
    follows a flat direction (red B_inf against beta) to its floor, where L-BFGS crawls, at the coarse fraction of
    the cost on all points."""
    seed: int = 0
    """Seed of the held-out split and of the bootstrap."""
    threads: int = field(default=0, metadata={"hash": False})
    """Torch threads of the water's fit (0: the run's setting, see --threads; not hashed: the estimate moves only by
    float rounding). The diagnosis's fits run on one thread."""


#: The water estimate's fit: the dense table's views and the board, albedos >= 0 (dark points pin the backscatter),
#: a coarse start on a quarter of the points, rounds to convergence, Newton-step replicates in float32.
WATER_FIT = FitConfig(loss_scale=0.01, iterations=100, max_iterations=600, step_rtol=1e-9, polish_iterations=0,
                      albedo_min=0.0, albedo_max=math.inf, holdout_fraction=0.0, fixed_effects=(), bootstrap=30,
                      bootstrap_refit=Refit.newton, bootstrap_iterations=5, float32=True, coarse_fraction=0.25,
                      coarse_refine_evaluations=20)


def soft_l1(e: torch.Tensor, scale: float) -> torch.Tensor:
    """rho(e) = 2 f^2 (sqrt(1 + (e/f)^2) - 1): e^2 for |e| << f, 2 f |e| for |e| >> f."""
    return 2.0 * scale * scale * (torch.sqrt(1.0 + (e / scale) ** 2) - 1.0)


def robust_residual(e: torch.Tensor, scale: float) -> torch.Tensor:
    """r(e) with r^2 = rho(e) (:func:`soft_l1`) and the sign of e: e sqrt(2 / (1 + sqrt(1 + (e/f)^2)))."""
    return e * torch.sqrt(2.0 / (1.0 + torch.sqrt(1.0 + (e / scale) ** 2)))


def copy_stack(stack: Stack) -> Stack:
    """An independent copy with the same parameter values."""
    return Stack.from_config(stack.to_config())


def insert_by_rank(stack: Stack, effect: Effect) -> Stack:
    """A copy of ``stack`` with ``effect`` inserted by rank (see :meth:`Stack.with_effect`)."""
    return copy_stack(stack).with_effect(effect)


def fitted_names(stack: Stack, fixed_effects: tuple[str, ...], frozen: dict[str, tuple[str, ...]]) -> list[str]:
    """Names (as in ``stack.named_parameters()``) of the raw parameters to fit: learnable ones of effects not in
    ``fixed_effects``, minus ``frozen`` {effect: params} (known settings, tied followers)."""
    return [f"effects.{i}.raw.{p.name}" for i, effect in enumerate(stack.effects) if effect.name not in fixed_effects
            for p in effect.params if p.learnable and p.name not in frozen.get(effect.name, ())]


def start_inside_bounds(stack: Stack, names: list[str], margin: float = START_MARGIN) -> None:
    """Move the starting value of each fitted raw parameter ``names`` at least ``margin`` inside its bounds (in
    place): sigmoid parameters to p = (v - lower)/(upper - lower) in [margin, 1 - margin], softplus ones to
    v - lower >= margin (on a bound d value / d raw ~ 1e-9: a fit cannot move it)."""
    by_name = dict(stack.named_parameters(remove_duplicate=False))
    limit = math.log(margin) - math.log1p(-margin)  # logit(margin) < 0; softplus(limit) ~ margin
    with torch.no_grad():
        for name in names:
            spec = stack.effects[int(name.split(".")[1])]._spec(name.rsplit(".", 1)[1])
            by_name[name].clamp_(limit, -limit) if spec.bounded_above else by_name[name].clamp_(min=limit)


def _column(a: np.ndarray, n: int, dtype) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(np.asarray(a, dtype).reshape(n, -1, 1, 1)))


def observation_state(obs: Observations, rows: np.ndarray, dtype=np.float64) -> FormationState:
    """The state of the views ``rows`` as a batch of 1x1 images; ``direct`` is a placeholder of ones. Per-point
    fields (world point and normal, water depth) are given when the table holds them."""
    n, p = len(rows), obs.point[rows]
    known_depth = obs.nav_water_depth_m is not None or obs.site_depth_m > 0
    return FormationState(
        direct=torch.ones(n, 3, 1, 1, dtype=torch.float32 if dtype == np.float32 else torch.float64),
        range_m=_column(obs.range_m[rows], n, dtype), depth_m=_column(obs.depth_m[rows], n, dtype),
        pixel_uv=_column(obs.pixel_uv[rows], n, dtype), image_wh=tuple(obs.image_wh),
        points_cam=_column(obs.points_cam[rows], n, dtype),
        normals_cam=None if obs.normals_cam is None else _column(obs.normals_cam[rows], n, dtype),
        points_world=None if obs.points_world is None else _column(obs.points_world[p], n, dtype),
        normals_world=None if obs.normals_world is None else _column(obs.normals_world[p], n, dtype),
        water_depth_m=_column(obs.water_depth_m[p], n, dtype) if known_depth and obs.points_world is not None
        else None,
        frame_index=torch.from_numpy(np.asarray(obs.frame[rows], np.int64)))


def board_state(obs: Observations, dtype=np.float64) -> FormationState:
    """The state of the board rows as a batch of 1x1 images."""
    n = len(obs.board_colour)
    return FormationState(
        direct=torch.ones(n, 3, 1, 1, dtype=torch.float32 if dtype == np.float32 else torch.float64),
        range_m=_column(obs.board_range_m, n, dtype), depth_m=_column(obs.board_depth_m, n, dtype),
        pixel_uv=_column(obs.board_pixel_uv, n, dtype), image_wh=tuple(obs.image_wh),
        points_cam=_column(obs.board_points_cam, n, dtype),
        normals_cam=None if obs.board_normals_cam is None else _column(obs.board_normals_cam, n, dtype),
        frame_index=torch.from_numpy(np.asarray(obs.board_frame, np.int64)))


def is_affine_in_albedo(stack: Stack, state: FormationState) -> bool:
    """True when F(1) - F(0.5) = F(0.5) - F(0) for these views (no sensor curve or clipping), in float64."""
    one = torch.ones(state.direct.shape[0], 3, dtype=torch.float64)
    with torch.no_grad():
        f0, f1, f2 = (render_albedo(stack, state, k * one) for k in (0.0, 0.5, 1.0))
    return bool(torch.allclose(f2 - f1, f1 - f0, atol=1e-9, rtol=1e-6))


def channels_separate(stack: Stack, state: FormationState) -> bool:
    """True when a change of one channel's albedo changes that channel's render alone for these views (no effect
    mixes the colour channels), in float64."""
    one = torch.full((state.direct.shape[0], 3), 0.5, dtype=torch.float64)
    with torch.no_grad():
        base = render_albedo(stack, state, one)
        for c in range(3):
            moved = one.clone()
            moved[:, c] = 0.6
            change = (render_albedo(stack, state, moved) - base).abs()
            if bool((change[:, [k for k in range(3) if k != c]] > 1e-12).any()):
                return False
    return True


def render_albedo(stack: Stack, state: FormationState, albedo: torch.Tensor) -> torch.Tensor:
    return stack.render(state.replace(direct=albedo.reshape(-1, 3, 1, 1).to(state.direct.dtype)))[:, :, 0, 0]


def fit_domain(curve: Effect | None, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(the observations ``y`` in the fit's domain, the slopes T' that scale its residuals) (module docstring):
    (T^-1(y), T'(T^-1(y))) for an output map ``curve``, (y, None) without one."""
    return (y, None) if curve is None else curve.linearised(y)


class Residual(torch.nn.Module):
    """The fit's residual of views of known albedo (the state's ``direct``), as a module for functional_call: t (x -
    F'(J)) with an output map (:func:`fit_domain`), y - F(J) without."""

    def __init__(self, stack: Stack) -> None:
        super().__init__()
        self.stack = stack

    def forward(self, state: FormationState, y: torch.Tensor) -> torch.Tensor:
        rest, curve = self.stack.output_map()
        x, t = fit_domain(curve, y)
        e = x - rest.render(state)[:, :, 0, 0]
        return e if t is None else t * e


class Problem:
    """The loss of a stack's fitted parameters on rows of a table (and its board rows), the albedos projected out.

    ``names``: the raw parameters fitted (:func:`fitted_names`); ``rows``: the views used (default all);
    ``board``: use the table's board rows. ``frame_weight`` (per frame index), ``point_weight`` (per point of the
    rows, in :attr:`points` order) and ``patch_weight`` (per board patch) weigh the views (None: 1)."""

    def __init__(self, stack: Stack, obs: Observations, config: FitConfig, names: list[str],
                 rows: np.ndarray | None = None, board: bool = True, float32: bool = False) -> None:
        self.stack, self.obs, self.config, self.names = stack, obs, config, names
        self.rows = np.arange(obs.n_obs) if rows is None else np.asarray(rows)
        dt = np.float32 if float32 else np.float64
        self.state = observation_state(obs, self.rows, dt)
        self.y = torch.from_numpy(obs.colour[self.rows].astype(dt))
        self.frame = torch.from_numpy(np.asarray(obs.frame[self.rows], np.int64))
        points, local = np.unique(obs.point[self.rows], return_inverse=True)
        self.points, self.local = points, torch.from_numpy(local.astype(np.int64))
        self.has_board = board and len(obs.board_colour) > 0
        if self.has_board:
            self.board_state = board_state(obs, dt)
            self.board_y = torch.from_numpy(obs.board_colour.astype(dt))
            self.board_j = torch.from_numpy(obs.board_albedo.astype(dt))
            self.board_frame = torch.from_numpy(np.asarray(obs.board_frame, np.int64))
            self.board_patch = torch.from_numpy(np.asarray(obs.board_patch, np.int64))
        self.frame_weight: torch.Tensor | None = None
        self.point_weight: torch.Tensor | None = None
        self.patch_weight: torch.Tensor | None = None
        by_name = dict(stack.named_parameters(remove_duplicate=False))  # a tied parameter under each name
        self.theta = [by_name[n] for n in names]
        self.take_gradients()
        self.rest, self.curve = stack.output_map()  # F' and T of the module docstring (F and None without a map)
        self.affine = is_affine_in_albedo(self.rest, observation_state(obs, self.rows[:1024]))
        self.doubled = affine_state(self.state) if self.affine else None
        self.board_doubled = affine_state(self.board_state) if self.has_board else None
        self.separate: bool | None = None
        """Whether the stack keeps the colour channels apart (:func:`channels_separate`); None: not asked yet."""
        self.start = torch.full((len(points), 3), 0.3, dtype=self.y.dtype)  # secant start (non-affine stacks)

    def on_copy(self) -> Problem:
        """This problem on a deep copy of its stack (its own parameters, at their values now; the table's tensors and
        the weights shared, read only): a refit on another thread leaves this one's parameters alone."""
        twin = copy.copy(self)
        twin.stack = copy.deepcopy(self.stack)
        twin.rest, twin.curve = twin.stack.output_map()
        by_name = dict(twin.stack.named_parameters(remove_duplicate=False))
        twin.theta = [by_name[n] for n in self.names]
        twin.take_gradients()
        return twin

    def take_gradients(self) -> None:
        """Make this problem's parameters the stack's only ones with gradients (another problem on the same stack
        made after this one changes them)."""
        for p in self.stack.parameters():
            p.requires_grad_(False)
        for p in self.theta:
            p.requires_grad_(True)

    # ------------------------------------------------------------------ weights, albedos, residuals
    def view_weight(self) -> torch.Tensor:
        w = torch.ones(len(self.rows), dtype=self.y.dtype)
        if self.frame_weight is not None:
            w = w * self.frame_weight.to(w.dtype)[self.frame]
        if self.point_weight is not None:
            w = w * self.point_weight.to(w.dtype)[self.local]
        return w

    def albedo(self, w: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(albedo (P_rows,3) of the points in :attr:`points` order, predicted colour (N,3), camera domain) with each
        albedo its weighted least-squares value given the parameters (see the module docstring)."""
        j, predicted, _ = self.project(w)
        if self.curve is not None:
            predicted = self.curve(self.state.replace(direct=predicted[:, :, None, None], backscatter=None)).image
            predicted = predicted[:, :, 0, 0]
        return j, predicted

    def project(self, w: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(albedos (P_rows,3), prediction (N,3), residual (N,3)), prediction and residual in the fit's domain (the
        module docstring: linear, the residual scaled by the curve's slope, with an output map)."""
        w = self.view_weight() if w is None else w
        y, slope = fit_domain(self.curve, self.y)
        wc = w[:, None] if slope is None else w[:, None] * slope * slope
        n, lo, hi = len(self.points), self.config.albedo_min, self.config.albedo_max
        if self.affine:
            a, c = affine_images(self.rest, self.state, self.doubled)
            a, c = a[:, :, 0, 0], c[:, :, 0, 0]
            num = torch.zeros(n, 3, dtype=a.dtype).index_add(0, self.local, wc * a * (y - c))
            den = torch.zeros(n, 3, dtype=a.dtype).index_add(0, self.local, wc * a * a)
            j = (num / den.clamp_min(1e-12)).clamp(lo, hi)
            predicted = a * j[self.local] + c
        else:
            zero = render_albedo(self.rest, self.state, torch.zeros_like(y))
            j = self.start
            for _ in range(self.config.secant_steps):
                a_obs = j[self.local]
                t = (render_albedo(self.rest, self.state, a_obs) - zero) / a_obs
                num = torch.zeros(n, 3, dtype=t.dtype).index_add(0, self.local, wc * t * (y - zero))
                den = torch.zeros(n, 3, dtype=t.dtype).index_add(0, self.local, wc * t * t)
                j = (num / den.clamp_min(1e-12)).clamp(max(lo, 1e-6), hi)
            predicted = render_albedo(self.rest, self.state, j[self.local])
        return j, predicted, (y - predicted) if slope is None else slope * (y - predicted)

    def penalty(self) -> torch.Tensor:
        """The effects' penalty residuals (``Effect.penalty``), float64 (empty when none has one)."""
        parts = [p for p in (effect.penalty() for effect in self.stack.effects) if p is not None]
        return torch.cat([p.reshape(-1).double() for p in parts]) if parts else torch.zeros(0, dtype=torch.float64)

    def _board_terms(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(weights (B,), residuals (B,3)) of the board rows."""
        wb = torch.ones(len(self.board_y), dtype=self.board_y.dtype)
        if self.frame_weight is not None:
            wb = wb * self.frame_weight.to(wb.dtype)[self.board_frame]
        if self.patch_weight is not None:
            wb = wb * self.patch_weight.to(wb.dtype)[self.board_patch]
        ab, cb = affine_images(self.rest, self.board_state, self.board_doubled)
        yb, slope = fit_domain(self.curve, self.board_y)
        eb = yb - (ab[:, :, 0, 0] * self.board_j + cb[:, :, 0, 0])
        return wb, eb if slope is None else slope * eb

    def loss(self) -> torch.Tensor:
        """L(theta) of the module docstring (float64)."""
        w = self.view_weight()
        e = self.project(w)[2]
        scale = self.config.loss_scale
        total = ((w[:, None] * soft_l1(e, scale)).sum() / w.sum().clamp_min(1e-12)).double()
        if self.has_board and self.config.board_weight > 0:
            wb, eb = self._board_terms()
            total = total + self.config.board_weight * ((wb[:, None] * soft_l1(eb, scale)).sum()
                                                        / wb.sum().clamp_min(1e-12)).double()
        return total + (self.penalty() ** 2).sum()

    def residuals(self) -> torch.Tensor:
        """The residual vector whose sum of squares is :meth:`loss` (for the trust-region least squares)."""
        w = self.view_weight()
        scale = self.config.loss_scale
        parts = [(torch.sqrt(w / w.sum())[:, None] * robust_residual(self.project(w)[2], scale)).reshape(-1)]
        if self.has_board and self.config.board_weight > 0:
            wb, eb = self._board_terms()
            parts.append((torch.sqrt(self.config.board_weight * wb / wb.sum())[:, None]
                          * robust_residual(eb, scale)).reshape(-1))
        return torch.cat([*(p.double() for p in parts), self.penalty()])

    # ------------------------------------------------------------------ parameters
    def flat(self) -> torch.Tensor:
        return torch.cat([p.detach().reshape(-1) for p in self.theta])

    def set_flat(self, flat: torch.Tensor) -> None:
        with torch.no_grad():
            i = 0
            for p in self.theta:
                p.copy_(flat[i:i + p.numel()].view_as(p))
                i += p.numel()

    def gradient(self) -> torch.Tensor:
        for p in self.theta:
            p.grad = None
        self.loss().backward()
        return torch.cat([p.grad.reshape(-1) for p in self.theta]).double()

    def channel_groups(self) -> tuple[list[np.ndarray], np.ndarray]:
        """(groups of flat parameter indices, each index's colour channel or -1): the entries of a parameter that
        its effect declares per channel (``Effect.channel_axis``) that differ only in their channel form a group;
        every other entry (shared by the channels, tied to another parameter, or any entry when the stack mixes the
        channels, :func:`channels_separate`) is a group of its own."""
        if self.separate is None:
            self.separate = channels_separate(self.stack, observation_state(self.obs, self.rows[:1024]))
        uses = Counter(id(p) for p in self.theta)
        channel, slots = [], []
        for name, p in zip(self.names, self.theta, strict=True):
            axis = type(self.stack.effects[int(name.split(".")[1])]).channel_axis.get(name.rsplit(".", 1)[1])
            shape = tuple(p.shape)
            if axis is None or not self.separate or uses[id(p)] > 1 or len(shape) <= axis or shape[axis] != 3:
                channel += [-1] * p.numel()
                slots += [(name, k) for k in range(p.numel())]
                continue
            index = np.indices(shape).reshape(len(shape), -1)
            channel += index[axis].tolist()
            slots += [(name, *np.delete(index, axis, 0)[:, k]) for k in range(p.numel())]
        groups: dict = {}
        for i, slot in enumerate(slots):
            groups.setdefault(slot, []).append(i)
        return [np.asarray(g) for g in groups.values()], np.asarray(channel)

    def hessian(self, step: float = 1e-3) -> torch.Tensor:
        """Central differences of the gradient in the raw parameters, symmetrised. The loss is a sum over the colour
        channels, so the entries of a group of :meth:`channel_groups` are perturbed together: the gradient's change
        in a parameter of channel c is then the column of the group's channel-c entry (the other channels' entries
        do not reach it); the columns of shared parameters come from their own rows."""
        x0 = self.flat()
        groups, channel = self.channel_groups()
        hess = torch.zeros(len(x0), len(x0), dtype=torch.float64)

        def column(fit: Problem, group: np.ndarray) -> torch.Tensor:
            d = torch.zeros_like(x0)
            d[group] = step
            fit.set_flat(x0 + d)
            gp = fit.gradient()
            fit.set_flat(x0 - d)
            return (gp - fit.gradient()) / (2 * step)

        for group, change in zip(groups, side_by_side(self, column, groups), strict=True):
            if len(group) == 1:
                hess[group[0]] = change
                continue
            for i in group:
                same = torch.from_numpy(channel == channel[i])
                hess[i, same] = change[same]
        self.set_flat(x0)
        shared, grouped = np.flatnonzero(channel < 0), np.flatnonzero(channel >= 0)
        hess[np.ix_(grouped, shared)] = hess[np.ix_(shared, grouped)].T
        return 0.5 * (hess + hess.T)

    def physical(self) -> dict[str, np.ndarray]:
        """{raw parameter name: physical value} of the fitted parameters."""
        out = {}
        for name, raw in zip(self.names, self.theta[:len(self.names)], strict=True):
            spec = self.stack.effects[int(name.split(".")[1])]._spec(name.rsplit(".", 1)[1])
            out[name] = spec.to_value(raw.detach()).numpy().copy()
        return out

    # ------------------------------------------------------------------ minimisation
    def minimise(self, iterations: int) -> float:
        """At most ``iterations`` L-BFGS iterations (see ``FitConfig.step_rtol``); returns the loss."""
        if iterations > 0 and self.theta:
            lbfgs(self.theta, self.loss, iterations, self.config.step_rtol)
        with torch.no_grad():
            return float(self.loss())

    def coarse(self, names: list[str] | None = None) -> Problem | None:
        """The problem on ``config.coarse_fraction`` of the points, drawn with the fit's seed, in float32, fitting
        ``names`` (default this problem's); its parameters are this problem's (the stack's tensors). None when the
        fraction is not in (0, 1)."""
        fraction = self.config.coarse_fraction
        if not 0 < fraction < 1:
            return None
        rng = np.random.default_rng([self.config.seed, 31])
        keep = rng.permutation(self.points)[:max(1, int(round(fraction * len(self.points))))]
        return Problem(self.stack, self.obs, replace(self.config, coarse_fraction=0.0),
                       self.names if names is None else names, self.rows[np.isin(self.obs.point[self.rows], keep)],
                       self.has_board, float32=True)

    def coarse_start(self, refine_names: list[str] | None = None) -> int:
        """A first fit on :meth:`coarse` (:meth:`converge`; with ``coarse_refine_evaluations``, one round of it and
        then :meth:`refine` in float64 over ``refine_names``, default all), whose parameters start the full fit;
        returns its L-BFGS iterations (0: none)."""
        coarse = self.coarse() if self.theta else None
        if coarse is None:
            return 0
        refine = self.config.coarse_refine_evaluations
        if refine > 0:  # one round of L-BFGS, then the trust region, which follows the flat directions
            coarse.config = replace(coarse.config, max_iterations=coarse.config.iterations)
        iterations = coarse.converge()[0]
        if refine > 0:
            Problem(self.stack, self.obs, coarse.config, coarse.names if refine_names is None else refine_names,
                    coarse.rows, coarse.has_board).refine(refine)
        return iterations

    def converge(self) -> tuple[int, bool]:
        """Rounds of :meth:`minimise` (see ``FitConfig.max_iterations``); returns (iterations, converged)."""
        config = self.config
        loss = self.minimise(config.iterations)
        done = step = config.iterations
        while done + step <= config.max_iterations:
            before, loss = loss, self.minimise(step)
            done += step
            if before - loss <= config.convergence_rtol * abs(before):
                return done, True
        return done, config.max_iterations <= config.iterations

    def refine(self, evaluations: int) -> None:
        """The trust-region least squares on :meth:`residuals` (:func:`eval.solvers.least_squares_fit`), its
        finite-difference Jacobian taken a group of :meth:`channel_groups` at a time for the per-channel rows and a
        parameter at a time for the penalty rows (which need no render)."""
        groups, channel = self.channel_groups()
        least_squares_fit(self.theta, self.residuals, evaluations, [(g, channel[g]) for g in groups],
                          lambda: self.penalty().detach())
