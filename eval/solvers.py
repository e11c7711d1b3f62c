"""The numerical engines the fitter (:class:`eval.fit.Problem`) runs on: L-BFGS, the trust-region least squares with
its grouped finite-difference Jacobian, and work shared over threads on copies of a problem.

Trust region: scipy's reflective least squares, Jacobian-scaled variables, steps solved exactly (an SVD of the
Jacobian) up to ``EXACT_SOLVER_MAX`` parameters and by LSMR beyond; the start is kept unless the fit lowers the cost.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

#: At most this many threads refit bootstrap replicates, or take the Hessian's columns, side by side
#: (:func:`side_by_side`).
SIDE_BY_SIDE_THREADS = 4


#: Curvature pairs L-BFGS keeps. A fit of the water's few dozen parameters ends its rounds within them; one of fine
#: fields over the image (about 1,300 node values) needs a longer memory to follow their coupling.
LBFGS_HISTORY = 100


def lbfgs(params: list[torch.Tensor], loss_fn, iterations: int, rtol: float) -> None:
    """At most ``iterations`` L-BFGS iterations (strong-Wolfe line search, ``LBFGS_HISTORY`` pairs), stopping when a
    step changes the loss by less than ``rtol`` of its starting value."""
    with torch.no_grad():
        scale = abs(float(loss_fn())) + 1e-30
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iterations, history_size=LBFGS_HISTORY,
                            line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=rtol * scale)

    def closure():
        opt.zero_grad(set_to_none=True)
        loss = loss_fn()
        loss.backward()
        return loss

    opt.step(closure)


#: Parameters up to which the trust region solves its steps exactly (an SVD of the Jacobian); beyond (gains per frame
#: of a long survey: hundreds of columns over a hundred thousand rows), by LSMR's iterations, which need no SVD.
EXACT_SOLVER_MAX = 64


def least_squares_fit(theta: list[torch.Tensor], residual_fn, evaluations: int,
                      groups: list[tuple[np.ndarray, np.ndarray]] | None = None, penalty_fn=None) -> None:
    """Minimise the sum of squares of ``residual_fn()`` over the tensors ``theta`` (in place) by scipy's trust-region
    reflective least squares, at most ``evaluations`` residual evaluations, Jacobian-scaled variables, steps solved
    exactly up to ``EXACT_SOLVER_MAX`` parameters and by LSMR beyond; the start is kept unless the fit lowers the
    cost. The Jacobian is scipy's forward differences (step sqrt(eps) max(1, |x|)),
    one residual evaluation per parameter on top, or, with ``groups`` (flat parameter indices and each one's colour
    channel, -1: none; the residuals channel-last, entry k of channel k mod 3, then ``penalty_fn()``'s rows), one
    per group (:func:`grouped_jacobian`)."""
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

    last: list = [None, None]

    def fun(x: np.ndarray) -> np.ndarray:
        assign(x)
        with torch.no_grad():
            f = residual_fn().reshape(-1).numpy()
        last[:] = x.copy(), f
        return f

    def penalty(x: np.ndarray) -> np.ndarray:
        assign(x)
        with torch.no_grad():
            return penalty_fn().reshape(-1).numpy()

    def jac(x: np.ndarray) -> np.ndarray:
        f0 = last[1] if last[0] is not None and np.array_equal(last[0], x) else fun(x)
        return grouped_jacobian(fun, x, f0, groups, None if penalty_fn is None else penalty)

    cost0 = float((fun(x0) ** 2).sum())
    with np.errstate(all="ignore"):
        result = least_squares(fun, x0, jac="2-point" if groups is None else jac, method="trf", x_scale="jac",
                               ftol=1e-12, xtol=1e-10, gtol=1e-12, max_nfev=evaluations,
                               tr_solver="exact" if len(x0) <= EXACT_SOLVER_MAX else "lsmr")
    assign(result.x if np.isfinite(result.x).all() and 2.0 * result.cost <= cost0 else x0)


def grouped_jacobian(fun, x: np.ndarray, f0: np.ndarray, groups: list[tuple[np.ndarray, np.ndarray]],
                     penalty=None) -> np.ndarray:
    """Forward differences of ``fun`` at ``x`` (``f0`` = fun(x)) with scipy's steps, h_i = sqrt(eps) max(1, |x_i|)
    signed like x_i, a group's entries moved together: where the residuals of channel c depend on the channel-c
    entries (and the shared ones) alone, the column of a channel-c entry is the change of the channel-c residuals
    (zero elsewhere), as moving it alone would give. An entry of channel -1 must be a group of its own. ``penalty``:
    a function of x giving fun's last rows (which need not keep the channels apart), differenced an entry at a time
    (None: no such rows)."""
    h = np.sqrt(np.finfo(float).eps) * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
    h = (x + h) - x
    jacobian = np.zeros((len(f0), len(x)))
    head = len(f0) - (0 if penalty is None else len(penalty(x)))
    for index, channel in groups:
        moved = x.copy()
        moved[index] += h[index]
        change = fun(moved)[:head] - f0[:head]
        for i, c in zip(index, channel, strict=True):
            if c < 0:
                jacobian[:head, i] = change / h[i]
            else:  # channel c's residuals are every third entry from c
                jacobian[c:head:3, i] = change[c::3] / h[i]
    if head < len(f0):
        for i in range(len(x)):
            moved = x.copy()
            moved[i] += h[i]
            jacobian[head:, i] = (penalty(moved) - f0[head:]) / h[i]
    return jacobian


def in_threads(work, jobs: dict, limit: int = SIDE_BY_SIDE_THREADS) -> dict:
    """{key: work(job)} of ``jobs``, up to ``limit`` of them at once (and no more than torch's threads), each on an
    equal share of torch's threads (the threads a pool starts take the count set before it: one each on two cores, a
    render of some 10^5 views uses a second torch thread poorly)."""
    threads = torch.get_num_threads()
    workers = min(threads, limit, len(jobs))
    if workers <= 1:
        return {key: work(job) for key, job in jobs.items()}
    torch.set_num_threads(threads // workers)
    try:
        with ThreadPoolExecutor(workers) as pool:
            return dict(zip(jobs, pool.map(work, jobs.values()), strict=True))
    finally:
        torch.set_num_threads(threads)


def side_by_side(problem, work, items: list) -> list:
    """[work(fit, item) for item in items], the items shared out over up to ``SIDE_BY_SIDE_THREADS`` threads (as
    many as torch's), each with its own copy of ``problem`` (:meth:`eval.fit.Problem.on_copy`, ``problem`` itself
    the first) and an equal share of torch's threads (:func:`in_threads`). ``work`` sets the parameters it needs; the
    copies are discarded."""
    workers = min(torch.get_num_threads(), SIDE_BY_SIDE_THREADS, len(items))
    if workers <= 1:
        return [work(problem, item) for item in items]
    fits = [problem] + [problem.on_copy() for _ in range(workers - 1)]
    parts = in_threads(lambda job: [work(job[0], item) for item in job[1]],
                       {w: (fits[w], items[w::workers]) for w in range(workers)})
    return [parts[i % workers][i // workers] for i in range(len(items))]
