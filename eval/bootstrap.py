"""The bootstrap of a survey fit: frames drawn with replacement, and each surface point's views (and each board
patch's) weighted Poisson(1) times.

Frames alone are not independent units (the views of one point share its texture and registration errors), nor are
points alone (the views of one frame share its exposure, pose and range errors); a replicate draws both, and a
view's weight is the product of its frame's count and its point's weight. :func:`eval.fit.bootstrap` draws its
replicates with :func:`replicate_weights`. :func:`paired_rmse_change` compares two models' held-out errors on the
same points (the diagnosis's candidate test).
"""

from __future__ import annotations

import numpy as np


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
