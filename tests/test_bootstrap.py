"""The two-way bootstrap (eval.bootstrap) and the diagnosis fit's intervals: do they cover the truth?

Coverage: the model attenuation, backscatter, vignetting, gain (gain held at the simulator's value, as the
diagnosis holds the configured gain) fitted from the effects' initial values to small clean simulated
surveys (eval.diagnose.small_survey_config, 600 points) of three seeds; each fitted component's 95 %
interval is checked against the value the survey was rendered with."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from eval.bootstrap import HESSIAN_FLOOR, Refit, bootstrap, inverse_hessian, normal_interval, replicate_weights
from eval.diagnose import DEFAULT_EFFECTS, small_survey_config
from eval.diagnose_measure import MeasureConfig, measure_survey
from eval.fit import FitConfig, Problem, fitted_names
from eval.heldout import fit_stack, make_split
from eval.solvers import side_by_side
from eval.synth import simulate_survey
from watergan.formation import Stack

SEEDS = (1, 2, 3)


def test_two_way_weights_are_a_frame_count_times_a_point_weight():
    """On a full frames x points table the weights are the outer product m_f q_p; a replicate keeps about
    1 - (1 - 1/10)^10 = 65 % of 10 frames, and a point's Poisson(1) weight is 0 in e^-1 = 37 % of them."""
    rng = np.random.default_rng(0)
    frame = np.repeat(np.arange(10), 20)
    point = np.tile(np.arange(20), 10)
    frames_kept, points_kept = [], []
    for _ in range(300):
        counts, point_weight, _ = replicate_weights(rng, [np.arange(10)], 20)
        w = (counts[frame] * point_weight[point]).reshape(10, 20)
        assert np.allclose(w * w.sum(), np.outer(w.sum(1), w.sum(0)))
        frames_kept.append((w > 0).any(1).mean() if w.sum() else 0.0)
        points_kept.append((w > 0).any(0).mean() if w.sum() else 0.0)
    assert 0.60 < np.mean(frames_kept) < 0.70 and 0.58 < np.mean(points_kept) < 0.68


def test_normal_interval_is_clipped_to_the_bounds():
    sd, low, high = normal_interval(np.array([0.1, 0.5]), np.array([[0.0, 0.4], [0.2, 0.6]]), 0.0, 1.0)
    assert np.allclose(sd, [np.sqrt(0.02), np.sqrt(0.02)]) and low[0] == 0.0 and 0 < low[1] < 0.5 < high[1] < 1


@pytest.fixture(scope="module")
def coverage(tmp_path_factory):
    """(bootstrap covered, Laplace covered, misses) over every fitted component of the three seeds."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    covered, laplace, misses = [], [], []
    for seed in SEEDS:
        survey = tmp_path_factory.mktemp(f"seed{seed}") / "survey"
        simulate_survey(survey, small_survey_config([], seed=seed), progress=False)
        truth = {e["name"]: e["params"] for e in json.loads((survey / "truth" / "effects.json").read_text())["visible"]}
        meas = measure_survey(survey, MeasureConfig(n_points=600, seed=seed))
        config = FitConfig(iterations=200, seed=seed)
        start = Stack.from_names(list(DEFAULT_EFFECTS))
        start["gain"].set_values(k=truth["gain"]["k"])
        fit = fit_stack(start, meas, make_split(meas, config), config)
        for effect, params in fit.params.items():
            for name, p in params.items():
                if not p["fitted"]:
                    continue
                value, sd, true = (np.ravel(x) for x in (p["value"], p["std"], truth[effect][name]))
                low, high = (np.ravel(b) for b in p["ci95"])
                inside = (low <= true) & (true <= high)
                covered += inside.tolist()
                laplace += (np.abs(value - true) <= 1.96 * sd).tolist()
                misses += [f"seed {seed} {effect}.{name}[{k}]" for k in np.flatnonzero(~inside)]
    torch.set_num_threads(previous)
    return np.mean(covered), np.mean(laplace), misses


@pytest.mark.slow
def test_bootstrap_intervals_cover_the_truth_where_the_laplace_std_does_not(coverage):
    """Measured: 34-35 of 36 components covered (94-97 %) against 10-12 of 36 (28-33 %) by estimate +- 1.96 Laplace
    std (30 of 36 and 6 of 36 with 5-pixel patch means and L-BFGS replicates, see eval.fit). The two figures of each
    are the same fits before and after a change that moved only the rounding of the gradients' sums: the 200
    L-BFGS iterations stop where such a change moves the estimates by a few of their Laplace std."""
    boot, laplace, misses = coverage
    assert boot >= 0.8 and laplace <= 0.4, (boot, laplace, misses)


@pytest.mark.slow
def test_bootstrap_intervals_cover_90_percent_of_the_parameters(coverage):
    """Measured: 35 of 36 (red eta on seed 1, 2.3 % low, is missed), and 34 of 36 after a change of the gradients'
    rounding (seed 1's blue B_inf and beta, which trade off along a valley, are missed); 24 of 24 on seeds 4 and 5,
    which were held out while the causes of the earlier 30 of 36 were found (benchmarks/RESULTS.md)."""
    boot, _, misses = coverage
    assert boot >= 0.9, misses


def test_the_newton_step_keeps_a_flat_valley_and_steps_downhill_across_a_saddle():
    """The inverse Hessian of the water's Newton replicates: a valley 1e-7 of the largest curvature (red B_inf against
    beta on a survey measured at 1.5e-7) keeps its own curvature, so a replicate moves along it as far as its data
    say; a negative eigenvalue counts by its magnitude; only what lies below the floor is lifted to it."""
    rotation = torch.linalg.qr(torch.randn(4, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0)))[0]
    curvature = torch.tensor([30.0, 30.0 * 1.5e-7, -1e-5, 30.0 * HESSIAN_FLOOR / 100], dtype=torch.float64)
    hessian = rotation @ torch.diag(curvature) @ rotation.T
    inverse = inverse_hessian(SimpleNamespace(hessian=lambda: hessian))
    along = torch.diag(rotation.T @ inverse @ rotation)
    expected = 1 / torch.tensor([30.0, 30.0 * 1.5e-7, 1e-5, 30.0 * HESSIAN_FLOOR], dtype=torch.float64)
    torch.testing.assert_close(along, expected, rtol=1e-6, atol=0)


def test_replicates_and_hessian_side_by_side_are_the_serial_ones(tmp_path):
    """On two torch threads the bootstrap's replicates and the Hessian's columns are computed on two threads side by
    side (``side_by_side``, each on its own copy of the stack): the same values as one after the other, to float
    rounding, and the problem's parameters are left where they were."""
    survey = tmp_path / "survey"
    simulate_survey(survey, small_survey_config([], seed=1), progress=False)
    meas = measure_survey(survey, MeasureConfig(n_points=300, seed=1))
    config = FitConfig(bootstrap=4, bootstrap_refit=Refit.newton, bootstrap_iterations=3, seed=1)
    stack = Stack.from_names(list(DEFAULT_EFFECTS)).to(torch.float64)
    problem = Problem(stack, meas, config, fitted_names(stack, (), {}))
    problem.minimise(20)
    x0 = problem.flat()
    previous = torch.get_num_threads()
    runs = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            hessian = problem.hessian()
            runs.append((hessian, bootstrap(problem, config, inv=torch.linalg.pinv(hessian))))
            torch.testing.assert_close(problem.flat(), x0, rtol=0, atol=0)
            assert torch.get_num_threads() == threads
        torch.set_num_threads(2)
        stacks = side_by_side(problem, lambda fit, item: id(fit.stack), list(range(4)))
    finally:
        torch.set_num_threads(previous)
    assert stacks[0] == stacks[2] == id(stack) and stacks[1] == stacks[3] != id(stack)  # shared out over two copies
    torch.testing.assert_close(runs[1][0], runs[0][0], rtol=1e-6, atol=1e-9)
    for serial, threaded in zip(runs[0][1], runs[1][1], strict=True):
        for name in serial:
            np.testing.assert_allclose(threaded[name], serial[name], rtol=1e-6)
    assert not all(np.allclose(runs[0][1][0][n], runs[0][1][1][n]) for n in runs[0][1][0])  # replicates differ
