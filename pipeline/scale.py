"""Metric scale from what vehicles log: a position track, or a camera at a known height over a floor.

Track (``nav_position_m`` per frame: [x, y] in a horizontal plane, or [x, y, z], metres; from navigation.csv's
``x_m``/``y_m``/``z_m`` or easting/northing): a robust similarity between the SfM camera centres C_i and the
positions P_i,

    P_i ~ s R C_i + t,

R a rotation or a mirror image of one (a log's horizontal axes are not always right-handed seen from above: the
data's x and z with y up are not; the scale does not depend on it, and the fit says which), by Umeyama's least
squares, started on the frames whose distance ratios to the others agree with the median ratio
(``START_TOLERANCE``) and refitted ``TRIM_ROUNDS`` times without the frames whose residual exceeds ``TRIM_MAD``
robust standard deviations (a position glitch, a frame SfM placed wrongly). With 2-D positions the
centres are first taken in the plane of their two principal directions (a vehicle at a constant height; a straight
track leaves one of them noise, which the similarity ignores). The spread is the median absolute deviation over the
median of the per-pair ratios |P_i - P_j| / |C_i - C_j| (pairs at least a tenth of the track's extent apart); the
held-out check fits the first half of the frames (in time order) and reads the second half's scale on its own.

Height (``camera_height_m``: crawlers, ROVs on skids, a diver's frame): the floor is the plane through the most
sparse points with every camera on one side (RANSAC), h_i the cameras' distances to it, s = camera_height_m /
median(h_i), spread = MAD(h) / median(h).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from watergan.errors import UserInputError

#: Robust refits of the track's similarity, and the residual (in robust standard deviations) that drops a frame.
TRIM_ROUNDS, TRIM_MAD = 3, 3.0
#: The frames the first fit starts from: those whose median distance ratio to the others is within this fraction of
#: the median over all pairs (a glitch's ratios are all off).
START_TOLERANCE = 0.25


def similarity_align(src: np.ndarray, dst: np.ndarray, reflection: bool = False
                     ) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama's least-squares similarity dst ~ s R src + t for point sets (N,D), N >= D, any dimension D.
    With centred sets X, Y and the SVD U D V^T of Y^T X / N: R = U S V^T (S fixes a reflection unless
    ``reflection``: then R may mirror), s = trace(D S) / var(X), t = mean(dst) - s R mean(src). Returns (s, R, t)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    x, y = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(y.T @ x / len(src))
    sign = np.eye(src.shape[1])
    if not reflection and np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[-1, -1] = -1
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / (x**2).sum(1).mean())
    return scale, rotation, mu_d - scale * rotation @ mu_s


@dataclass
class TrackFit:
    scale: float
    """s: metres per SfM unit."""
    spread: float
    """MAD / median of the per-pair distance ratios."""
    residual_m: float
    """RMS distance between the kept frames' positions and their similarity-mapped centres, metres."""
    kept: int
    """Frames the robust fit kept."""
    used: int
    """Registered frames with a position."""
    mirrored: bool
    """Whether the positions' axes are a mirror image of the reconstruction's (a log's x, y seen from below)."""


def _in_plane(centres: np.ndarray, dims: int) -> np.ndarray:
    """The centres (N,3) in the frame of their first ``dims`` principal directions (dims 3: unchanged)."""
    if dims == 3:
        return centres
    _, _, vt = np.linalg.svd(centres - centres.mean(0), full_matrices=False)
    return (centres - centres.mean(0)) @ vt[:dims].T


def fit_track(centres: np.ndarray, positions: np.ndarray) -> TrackFit:
    """The robust similarity of the module docstring between camera centres (N,3) and positions (N,2|3)."""
    positions = np.asarray(positions, float)
    if len(positions) < 5:
        raise UserInputError(f"only {len(positions)} registered frames have a position: the track scale needs 5")
    src = _in_plane(np.asarray(centres, float), positions.shape[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = (np.linalg.norm(positions[:, None] - positions[None], axis=2)
                  / np.linalg.norm(src[:, None] - src[None], axis=2))
    np.fill_diagonal(ratios, np.nan)
    per_frame = np.nanmedian(np.where(np.isfinite(ratios), ratios, np.nan), axis=1)
    keep = np.abs(per_frame / np.nanmedian(ratios) - 1) < START_TOLERANCE
    if keep.sum() < max(3, len(src) // 2):
        keep = np.ones(len(src), bool)
    for _ in range(TRIM_ROUNDS):
        s, R, t = similarity_align(src[keep], positions[keep], reflection=True)
        residual = np.linalg.norm(src @ (s * R).T + t - positions, axis=1)
        sigma = 1.4826 * np.median(np.abs(residual[keep] - np.median(residual[keep])))
        new = residual <= np.median(residual[keep]) + TRIM_MAD * max(sigma, 1e-9)
        if new.sum() < max(3, len(src) // 2) or (new == keep).all():
            break
        keep = new
    s, R, t = similarity_align(src[keep], positions[keep], reflection=True)
    residual = np.linalg.norm(src[keep] @ (s * R).T + t - positions[keep], axis=1)
    i, j = np.triu_indices(int(keep.sum()), 1)
    d_pos = np.linalg.norm(positions[keep][i] - positions[keep][j], axis=1)
    d_sfm = np.linalg.norm(src[keep][i] - src[keep][j], axis=1)
    far = (d_pos >= 0.1 * d_pos.max()) & (d_sfm > 0)
    ratios = d_pos[far] / d_sfm[far]
    spread = float(np.median(np.abs(ratios - np.median(ratios))) / np.median(ratios)) if far.any() else float("nan")
    return TrackFit(scale=float(s), spread=spread, residual_m=float(np.sqrt(np.mean(residual**2))),
                    kept=int(keep.sum()), used=len(src), mirrored=bool(np.linalg.det(R) < 0))


def track_halves(centres: np.ndarray, positions: np.ndarray) -> dict:
    """The held-out check: the similarity fitted on the first half of the frames (time order) and on the second
    alone; ``heldout_pct`` = 100 |s_first / s_second - 1|."""
    half = len(positions) // 2
    first, second = fit_track(centres[:half], positions[:half]), fit_track(centres[half:], positions[half:])
    return {"first": round(first.scale, 6), "second": round(second.scale, 6),
            "heldout_pct": round(100 * abs(first.scale / second.scale - 1), 2)}


def floor_plane(points: np.ndarray, centres: np.ndarray, iterations: int = 500, seed: int = 0
                ) -> tuple[np.ndarray, float]:
    """(n, d) of the plane n . x = d through the most sparse points (inliers within 1 % of the points' extent) with
    at least 95 % of the cameras on one side, n towards the cameras (RANSAC)."""
    rng = np.random.default_rng(seed)
    points = np.asarray(points, float)
    tolerance = 0.01 * float(np.linalg.norm(np.percentile(points, 95, 0) - np.percentile(points, 5, 0)))
    best, best_count = None, 0
    for _ in range(iterations):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        d = float(n @ a)
        side = centres @ n - d
        if np.median(side) < 0:
            n, d, side = -n, -d, -side
        if (side > 0).mean() < 0.95:
            continue
        count = int((np.abs(points @ n - d) < tolerance).sum())
        if count > best_count:
            best, best_count = (n, d), count
    if best is None:
        raise UserInputError("no plane of the sparse points has the cameras on one side: the camera height scale "
                             "needs a floor in view")
    n, d = best
    inliers = points[np.abs(points @ n - d) < tolerance]
    centre = inliers.mean(0)
    _, _, vt = np.linalg.svd(inliers - centre, full_matrices=False)
    refined = vt[2] if vt[2] @ n > 0 else -vt[2]
    return refined, float(refined @ centre)


def height_scale(points: np.ndarray, centres: np.ndarray, camera_height_m: float) -> tuple[float, float]:
    """(s, spread) from a camera at a known height over a floor (see the module docstring)."""
    n, d = floor_plane(points, centres)
    heights = centres @ n - d
    median = float(np.median(heights))
    return camera_height_m / median, float(np.median(np.abs(heights - median)) / median)
