"""The two-way bootstrap of a survey fit: frames drawn with replacement, and each surface point's views
weighted Poisson(1) times.

Frames alone are not independent units (the views of one point share its texture and registration
errors), nor are points alone (the views of one frame share its exposure, pose and range errors); a
replicate draws both, and an observation's weight is the product of its frame's count and its point's
weight. :mod:`eval.water` resamples its frames and points the same way (with the board's frames drawn
apart); :mod:`eval.diagnose_fit` uses these helpers for its parameter intervals.
"""

from __future__ import annotations

import numpy as np


def two_way_weights(rng: np.random.Generator, frame: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(N,) weights of one replicate for N observations of frames ``frame`` and points ``point`` (integer
    labels): w_o = m_f(o) q_p(o), m the number of times each frame present is drawn when as many frames are
    drawn with replacement, q ~ Poisson(1) per point."""
    frames, frame_index = np.unique(frame, return_inverse=True)
    points, point_index = np.unique(point, return_inverse=True)
    frame_count = np.bincount(rng.integers(0, len(frames), len(frames)), minlength=len(frames))
    point_weight = rng.poisson(1.0, len(points))
    return (frame_count[frame_index] * point_weight[point_index]).astype(np.float64)


def normal_interval(estimate: np.ndarray, samples: np.ndarray, lower: float, upper: float,
                    z: float = 1.96) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(sd, low, high): the replicates' standard deviation (over axis 0 of ``samples``) and the interval
    estimate +- z sd, clipped to [lower, upper]."""
    sd = np.std(samples, axis=0, ddof=1)
    return sd, np.clip(estimate - z * sd, lower, upper), np.clip(estimate + z * sd, lower, upper)
