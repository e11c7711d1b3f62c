"""How far eta may move before the views the fit did not see say no: its held-out profile.

Where the gains per frame are free of the frames' ranges (``WaterConfig.frame_gain_off_range=False``), a gain per
frame takes eta's effect on each frame's mean range, and only the range differences within the points that frames
share pin eta. The loss is then nearly flat along eta: the fit stops wherever L-BFGS stalls, and the bootstrap,
which resamples points around that stop, sees a spread far narrower than the distance eta may travel. The profile
asks the survey directly:

1. the fit on the training points is polished (:func:`settle`: a round of L-BFGS, the trust-region refinement,
   which follows a flat direction to its floor where L-BFGS crawls, then rounds until the loss falls by less than
   ``PROFILE_FIT``'s ``convergence_rtol`` per round), giving eta_0;
2. eta is held at f eta_0 for each factor f of ``PROFILE_STEPS`` (nearest first, below and above), everything else
   refitted on the training points from the previous step, settled the same way;
3. each channel's held-out views (the points the training left out, their albedos fitted to half their views, the
   other half predicted: :func:`eval.heldout.heldout_sums`) give the paired change d = RMSE_f / RMSE_0 - 1 and its
   bootstrap 95 % interval [lo, hi] (:func:`eval.bootstrap.paired_rmse_change`). The channels' fits are independent
   (each has its own albedos, gains, fields and water), so one fit per factor serves the three;
4. a channel whose lo > 0 rejects f: near eta_0 the change grows as a (f - 1)^2 and the interval's half-width as
   b |f - 1|, so lo reaches 0 at |f_b - 1| = |f - 1| (d - lo) / d, the channel's bound on that side (no nearer
   eta_0 than the step before). A channel that accepts f moves on to the next step; one that accepts the last step
   is bounded there and ``open`` on that side (the survey accepts at least that far).

The bounds [f_low eta_0, f_high eta_0] then widen eta's interval (:func:`eval.water.intervals.combine`, rule
"bounds").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch

from watergan.formation import Stack

from ..bootstrap import paired_rmse_change
from ..fit import FitConfig, Problem
from ..heldout import Split, heldout_sums
from ..observations import Observations

#: Factors on eta_0 of the profile's steps below and above it, nearest first.
PROFILE_STEPS = ((0.8, 0.6), (1.25, 1.6))
#: The polish and each step's fit: after the refinement, L-BFGS rounds until the loss falls by less than this per
#: round, at most this many iterations (the water fit's own rounds stop where the flat direction still moves eta).
PROFILE_FIT = {"convergence_rtol": 1e-5, "max_iterations": 3000}
#: The attenuation's effect and parameter.
ATTENUATION, ETA = "attenuation", "eta_per_m"


def channel_changes(base_sq: np.ndarray, cand_sq: np.ndarray, count: np.ndarray, resamples: int,
                    seed: int) -> np.ndarray:
    """(3, 3) per channel: the held-out paired change d and its bootstrap 95 % interval (lo, hi), from the (H, 3)
    per-point sums of squared residuals of the two fits and each point's number of test views ``count``."""
    return np.array([[d, *ci] for d, ci, _ in (paired_rmse_change(base_sq[:, c], cand_sq[:, c], count, resamples,
                                                                   seed) for c in range(3))])


def bound(factor: float, d: float, lo: float, previous: float) -> float:
    """The factor at which a rejected step's lower bound of the change reaches 0 (see the module docstring, 4.),
    no nearer 1 than the ``previous`` step's."""
    reached = 1.0 + (factor - 1.0) * (d - lo) / d
    return max(reached, previous) if factor > 1 else min(reached, previous)


def set_eta(stack: Stack, eta_per_m: np.ndarray) -> None:
    """Set the attenuation's eta in place (the same tensor: a parameter tied to it follows)."""
    effect = stack[ATTENUATION]
    raw = effect.raw[ETA]
    with torch.no_grad():
        raw.copy_(effect._spec(ETA).to_raw(torch.as_tensor(eta_per_m, dtype=raw.dtype)))


def eta_profile(stack: Stack, train: Observations, obs: Observations, split: Split, fit: FitConfig,
                names: list[str], resamples: int, say: Callable[[str], None] | None = None) -> dict:
    """The held-out profile of eta (see the module docstring) of ``stack`` fitted on ``train`` (the points of
    ``obs`` less ``split``'s held-out ones) with the raw parameters ``names``; ``stack`` is left polished (in place).
    ``say(line)`` before the polish and before each step, for the progress line (None: silent).
    Returns (JSON-ready) {"eta_per_m": eta_0, "low" / "high": eta at the bounds, "open_low" / "open_high": per
    channel, where the last step was accepted, "steps": [{"factor", "change_pct": per channel d, lo, hi}]}."""
    say = say or (lambda line: None)
    config = replace(fit, **PROFILE_FIT)
    fits = 1 + sum(map(len, PROFILE_STEPS))
    say(f"eta's profile: the polish (step 1 of at most {fits})")
    settle(Problem(stack, train, config, names))
    polished = [p.detach().clone() for p in stack.parameters()]
    eta0 = stack[ATTENUATION].param(ETA).detach().numpy().copy()
    raw = f"effects.{stack.names.index(ATTENUATION)}.raw.{ETA}"
    held_names = [n for n in names if n != raw]
    base_sq, count = heldout_sums(stack, obs, split, fit, per_channel=True)
    out = {"eta_per_m": np.round(eta0, 6).tolist(), "steps": []}
    for side, steps in zip(("low", "high"), PROFILE_STEPS, strict=True):
        factors, accepted, previous = np.ones(3), np.ones(3, bool), 1.0
        restore(stack, polished)
        for factor in steps:
            if not accepted.any():
                break
            say(f"eta's profile: eta held at {factor:g}x the polished "
                f"{' / '.join(f'{v:.3f}' for v in eta0)} per m, the rest refitted "
                f"(step {len(out['steps']) + 2} of at most {fits})")
            set_eta(stack, eta0 * factor)
            settle(Problem(stack, train, config, held_names))
            change = channel_changes(base_sq, heldout_sums(stack, obs, split, fit, per_channel=True)[0], count,
                                     resamples, fit.seed)
            out["steps"].append({"factor": factor, "change_pct": np.round(100 * change, 3).tolist()})
            for c in np.flatnonzero(accepted):
                d, lo, _ = change[c]
                rejected = lo > 0
                factors[c] = bound(factor, d, lo, previous) if rejected else factor
                accepted[c] = not rejected
            previous = factor
        out[side], out[f"open_{side}"] = np.round(eta0 * factors, 6).tolist(), accepted.tolist()
    restore(stack, polished)
    return out


def settle(problem: Problem) -> None:
    """``problem`` fitted from where its stack is: a round of L-BFGS, the trust-region refinement
    (``coarse_refine_evaluations`` residual evaluations: the water fit's coarse start's), then rounds to convergence."""
    problem.minimise(problem.config.iterations)
    problem.refine(problem.config.coarse_refine_evaluations)
    problem.converge()


def restore(stack: Stack, values: list[torch.Tensor]) -> None:
    """Put ``values`` (one per ``stack.parameters()``) back into the stack's parameters, in place."""
    with torch.no_grad():
        for p, v in zip(stack.parameters(), values, strict=True):
            p.copy_(v)
