"""The survey frame and its metric scale, from every source SfM can use: a stereo rig, a board of known size,
navigation altitudes (their equations, the order of preference and the choice: :mod:`pipeline.sfm`), and what
vehicles log: a position track, or a camera at a known height over a floor.

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
held-out check fits the first half of the frames (in the frames' order, time for a survey's names) and reads the
second half's scale on its own.

A dead-reckoned track (wheel odometry, a DVL's integrated velocity, a log that advances one step per frame across a
gap in the recording) errs by a walk: its error accumulates, so the similarity's residuals r_i follow each other
(the Durbin-Watson statistic DW = sum |r_i+1 - r_i|^2 / sum |r_i|^2 is near 2 for white errors and near 0 for a
walk), and one bad step shifts every later position and bends the similarity's scale. Where DW < ``DEAD_RECKONED_DW``
the scale is read from the steps, whose errors are independent: s = median |P_i+1 - P_i| / |C_i+1 - C_i| over the
steps that go straight (the track turns by less than ``STRAIGHT_DEG`` on either side: in a turn a camera away from
the logged point sweeps an arc the point does not) and move (at least ``MOVE_FRACTION`` of the median step), spread
= their MAD / median; the similarity still gives the orientation, the mirror and the residual.

Height (``camera_height_m``: crawlers, ROVs on skids, a diver's frame): the floor is the plane through the most
sparse points with every camera on one side (RANSAC), h_i the cameras' distances to it, s = camera_height_m /
median(h_i), spread = MAD(h) / median(h); the held-out check reads each half's heights on their own.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eval.tracks import Tracks
from watergan.errors import UserInputError
from watergan.io import DataError, read_grey8, read_json

#: Robust refits of the track's similarity, and the residual (in robust standard deviations) that drops a frame.
TRIM_ROUNDS, TRIM_MAD = 3, 3.0
#: The frames the first fit starts from: those whose median distance ratio to the others is within this fraction of
#: the median over all pairs (a glitch's ratios are all off).
START_TOLERANCE = 0.25
#: The Durbin-Watson statistic of the positions fit's residuals (consecutive frames) below which the track is read as
#: dead-reckoned, its errors accumulating from step to step (white errors give about 2), and its scale taken from its
#: steps.
DEAD_RECKONED_DW = 1.0
#: A step counts as straight when the track turns by less than this (degrees) from the step before and to the step
#: after it, and as a move when it is at least this fraction of the track's median step.
STRAIGHT_DEG, MOVE_FRACTION = 10.0, 0.5
#: Straight moving steps the steps' scale needs (fewer: the positions fit's).
MIN_STEPS = 8


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
    estimator: str
    """"positions" (the similarity's scale) or "steps" (the median ratio of the straight steps: a dead-reckoned
    track, :func:`step_scale`)."""
    durbin_watson: float
    """The Durbin-Watson statistic of the positions fit's residuals over consecutive kept frames."""


def _in_plane(centres: np.ndarray, dims: int) -> np.ndarray:
    """The centres (N,3) in the frame of their first ``dims`` principal directions (dims 3: unchanged)."""
    if dims == 3:
        return centres
    _, _, vt = np.linalg.svd(centres - centres.mean(0), full_matrices=False)
    return (centres - centres.mean(0)) @ vt[:dims].T


def step_scale(src: np.ndarray, positions: np.ndarray) -> tuple[float, float, int]:
    """(median, MAD / median, count) of |P_i+1 - P_i| / |C_i+1 - C_i| over the straight moving steps between
    consecutive frames (``STRAIGHT_DEG``, ``MOVE_FRACTION``; ``src``: the centres as the fit takes them); count 0 and
    NaNs when there are fewer than ``MIN_STEPS``."""
    d_pos, d_src = np.diff(positions, axis=0), np.diff(src, axis=0)
    length = np.linalg.norm(d_pos, axis=1)
    unit = d_pos / np.maximum(length, 1e-12)[:, None]
    turn = np.degrees(np.arccos(np.clip((unit[1:] * unit[:-1]).sum(1), -1.0, 1.0)))
    turn = np.maximum(np.r_[0.0, turn], np.r_[turn, 0.0])
    moved = np.linalg.norm(d_src, axis=1) > 0
    ok = (turn < STRAIGHT_DEG) & (length >= MOVE_FRACTION * np.median(length)) & moved
    if ok.sum() < MIN_STEPS:
        return float("nan"), float("nan"), 0
    ratios = length[ok] / np.linalg.norm(d_src[ok], axis=1)
    median = float(np.median(ratios))
    return median, float(np.median(np.abs(ratios - median)) / median), int(ok.sum())


def fit_track(centres: np.ndarray, positions: np.ndarray, estimator: str | None = None) -> TrackFit:
    """The robust similarity of the module docstring between camera centres (N,3) and positions (N,2|3), in time
    order; its scale from the positions or, for a dead-reckoned track, from the steps (``estimator``: None chooses
    by the residuals' Durbin-Watson statistic, ``DEAD_RECKONED_DW``)."""
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
    offsets = src[keep] @ (s * R).T + t - positions[keep]
    residual = np.linalg.norm(offsets, axis=1)
    durbin_watson = float(np.sum(np.diff(offsets, axis=0) ** 2) / max(np.sum(offsets**2), 1e-300))
    i, j = np.triu_indices(int(keep.sum()), 1)
    d_pos = np.linalg.norm(positions[keep][i] - positions[keep][j], axis=1)
    d_sfm = np.linalg.norm(src[keep][i] - src[keep][j], axis=1)
    far = (d_pos >= 0.1 * d_pos.max()) & (d_sfm > 0)
    ratios = d_pos[far] / d_sfm[far]
    spread = float(np.median(np.abs(ratios - np.median(ratios))) / np.median(ratios)) if far.any() else float("nan")
    chosen = estimator or ("steps" if durbin_watson < DEAD_RECKONED_DW else "positions")
    if chosen == "steps":
        step, step_spread, count = step_scale(src, positions)
        if count:
            s, spread = step, step_spread
        else:
            chosen = "positions"
    return TrackFit(scale=float(s), spread=spread, residual_m=float(np.sqrt(np.mean(residual**2))),
                    kept=int(keep.sum()), used=len(src), mirrored=bool(np.linalg.det(R) < 0), estimator=chosen,
                    durbin_watson=durbin_watson)


def track_halves(centres: np.ndarray, positions: np.ndarray, estimator: str | None = None) -> dict:
    """The held-out check: the track's scale fitted on the first half of the frames (time order) and on the second
    alone, by ``estimator`` (the whole track's: :func:`fit_track`); ``heldout_pct`` = 100 |s_first / s_second - 1|."""
    half = len(positions) // 2
    first, second = (fit_track(centres[part], positions[part], estimator)
                     for part in (slice(0, half), slice(half, None)))
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


def camera_heights(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(N,) the cameras' (``centres``, N,3) distances to the floor of the sparse ``points`` (:func:`floor_plane`),
    model units."""
    n, d = floor_plane(points, centres)
    return centres @ n - d


def height_scale(points: np.ndarray, centres: np.ndarray, camera_height_m: float) -> tuple[float, float, dict]:
    """(s, spread, detail) from a camera at a known height over a floor (see the module docstring); detail: its
    halves (:func:`height_halves`)."""
    heights = camera_heights(points, centres)
    median = float(np.median(heights))
    detail = {"halves": height_halves(heights, camera_height_m)} if len(heights) >= 10 else {}
    return camera_height_m / median, float(np.median(np.abs(heights - median)) / median), detail


def height_halves(heights: np.ndarray, camera_height_m: float = 1.0) -> dict:
    """The held-out check of a camera riding at a constant height: the scale camera_height_m / median(h) of the first
    half of the frames (time order) and of the second, from the cameras' heights ``heights`` over the floor (model
    units); ``heldout_pct`` = 100 |s_first / s_second - 1|. The model's own scale drift between the halves, whatever
    gave the model its scale."""
    half = len(heights) // 2
    first, second = (camera_height_m / float(np.median(h)) for h in (heights[:half], heights[half:]))
    return {"first": round(first, 6), "second": round(second, 6),
            "heldout_pct": round(100 * abs(first / second - 1), 2)}


def survey_frame(points: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (rows: new axes in old coordinates) and origin o of the survey frame: z = the
    normal of the points' least-squares plane (towards the cameras), x = main direction of the
    camera centres within that plane, origin = the points' median."""
    origin = np.median(points, axis=0)
    _, _, vt = np.linalg.svd(points - points.mean(0), full_matrices=False)
    normal = vt[2]
    if np.median((centres - origin) @ normal) < 0:
        normal = -normal
    flat = centres - centres.mean(0)
    flat -= np.outer(flat @ normal, normal)
    _, _, vc = np.linalg.svd(flat, full_matrices=False) if len(flat) > 1 else (None, None, np.eye(3))
    x_axis = vc[0] - (vc[0] @ normal) * normal
    if np.linalg.norm(x_axis) < 1e-9:
        x_axis = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    x_axis /= np.linalg.norm(x_axis)
    return np.stack([x_axis, np.cross(normal, x_axis), normal]), origin


def _robust_ratio(samples: np.ndarray, what: str, minimum: int = 10) -> tuple[float, float]:
    """(median, median absolute deviation / median) of the finite positive ``samples``; an error naming another
    source when fewer than ``minimum`` are left."""
    samples = samples[np.isfinite(samples) & (samples > 0)]
    if samples.size < minimum:
        raise UserInputError(f"only {samples.size} usable samples for the {what} scale (need {minimum}): "
                             f"use another scale source (--scale)")
    med = float(np.median(samples))
    return med, float(np.median(np.abs(samples - med)) / med)


def stereo_scale(tracks: Tracks, images_dir: Path, right_dir: Path, baseline_m: float,
                 max_images: int = 12, max_obs: int = 400, patch: int = 7, min_ncc: float = 0.95
                 ) -> tuple[float, float]:
    """Scale from a rectified stereo rig: for each sparse observation (x, y) of a left image, the
    patch around it is searched along row y of the right image (NCC, parabolic sub-pixel peak);
    z_stereo = fx b / d. Returns (median of z_stereo / z_sfm, relative spread)."""
    import cv2

    fx = float(tracks.K[0, 0])
    z_sfm_all = tracks.depths()
    half = patch // 2
    ratios = []
    registered = np.flatnonzero(tracks.registered)
    for k in registered[np.linspace(0, len(registered) - 1, min(max_images, len(registered))).astype(int)]:
        name = str(tracks.image_names[k])
        right_path = right_dir / name
        try:
            left, right = read_grey8(images_dir / name), read_grey8(right_path)
        except DataError:
            continue
        obs = np.flatnonzero(tracks.obs_image == k)
        obs = obs[np.linspace(0, len(obs) - 1, min(max_obs, len(obs))).astype(int)] if len(obs) else obs
        h, w = left.shape
        d_max = w // 3
        for m in obs:
            x, y = np.rint(tracks.obs_xy[m]).astype(int)
            if not (half + d_max <= x < w - half and half <= y < h - half):
                continue
            template = left[y - half:y + half + 1, x - half:x + half + 1]
            if template.std() < 2:
                continue
            strip = right[y - half:y + half + 1, x - half - d_max:x + half + 1]
            score = cv2.matchTemplate(strip, template, cv2.TM_CCOEFF_NORMED)[0]
            j = int(np.argmax(score))
            if score[j] < min_ncc or j in (0, len(score) - 1):
                continue
            a, b, c = score[j - 1], score[j], score[j + 1]
            offset = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else 0.0
            disparity = d_max - (j + offset)  # strip column j is right-image x = x - d_max + j
            if disparity > 1.0:
                ratios.append(fx * baseline_m / disparity / z_sfm_all[m])
    return _robust_ratio(np.array(ratios), "stereo")


def altitude_scale(points: np.ndarray, centres: np.ndarray, nav_altitude_m: np.ndarray) -> tuple[float, float]:
    """s = median(nav altitude) / median(camera height above the points' median height) with the
    heights measured along the survey frame's z (``points``/``centres`` already rotated, unscaled)."""
    heights = centres[:, 2] - np.median(points[:, 2])
    if np.median(heights) <= 0:
        raise UserInputError("the cameras are not above the sparse points: cannot use the altitude scale")
    s = float(np.median(nav_altitude_m) / np.median(heights))
    per_image = nav_altitude_m / heights
    spread = float(np.median(np.abs(per_image - s)) / s)
    return s, spread


def triangulate_dlt(projections: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """A 3D point from its pixel positions (V,2) in V >= 2 views with 3x4 projections (V,3,4): the
    null vector of the stacked rows x P_3 - P_1, y P_3 - P_2 (linear DLT, rows normalised)."""
    rows = np.concatenate([xy[:, :1] * projections[:, 2] - projections[:, 0],
                           xy[:, 1:] * projections[:, 2] - projections[:, 1]])
    rows /= np.linalg.norm(rows, axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(rows)
    return vt[-1, :3] / vt[-1, 3]


def read_board_corners(path: Path, width_m: float = 0.0, height_m: float = 0.0
                       ) -> tuple[dict[str, np.ndarray], float, float]:
    """Board file -> (image name -> (Q,4,2) pixel quads, NaN when not visible; true width; true height)."""
    data = read_json(path, "board file")
    try:
        images = {}
        for name, corners in data["images"].items():
            if corners is None:
                continue
            quads = [q if q is not None else [[np.nan, np.nan]] * 4 for q in corners] \
                if np.ndim(corners[0]) == 2 or corners[0] is None else [corners]
            images[name] = np.array(quads, float).reshape(-1, 4, 2)
    except (ValueError, KeyError, TypeError, IndexError, AttributeError) as exc:
        raise UserInputError(f"board file {path} must have 'images' (file name -> 4 pixel corners, or 4 per "
                             f"patch): {exc}") from exc
    side = data.get("patch_side_m", 0.0)
    width_m = width_m or data.get("width_m", side)
    height_m = height_m or data.get("height_m", side) or width_m
    if not all(isinstance(v, int | float) and v > 0 for v in (width_m, height_m)):
        raise UserInputError(f"give the board's true size (width_m/height_m or patch_side_m in {path}, "
                             f"or --board-width-m/--board-height-m)")
    if len({q.shape[0] for q in images.values()}) > 1:
        raise UserInputError(f"board file {path}: every image must list the same number of quads")
    return images, float(width_m), float(height_m)


def board_scale(tracks: Tracks, quads: dict[str, np.ndarray], width_m: float, height_m: float
                ) -> tuple[float, float]:
    """Scale from a board of known size: corners triangulated from >= 2 registered views (DLT),
    s = median(true edge length / triangulated edge length). Returns (s, relative spread)."""
    index = {str(n): k for k, n in enumerate(tracks.image_names)}
    views = [(index[n], q) for n, q in quads.items() if n in index and tracks.registered[index[n]]]
    if not views:
        raise UserInputError("no registered image has board corners: check the board file's image names")
    projections = []
    for k, _ in views:
        cam_from_world = np.linalg.inv(tracks.world_from_cam[k])
        projections.append(tracks.K @ cam_from_world[:3])
    projections = np.array(projections)
    corners = np.stack([q for _, q in views])  # (V,Q,4,2)
    xyz = np.full(corners.shape[1:3] + (3,), np.nan)
    for qi in range(corners.shape[1]):
        for ci in range(4):
            seen = np.isfinite(corners[:, qi, ci]).all(1)
            if seen.sum() >= 2:
                xyz[qi, ci] = triangulate_dlt(projections[seen], corners[seen, qi, ci])
    true = np.array([width_m, height_m, width_m, height_m])
    measured = np.linalg.norm(xyz - np.roll(xyz, -1, axis=1), axis=2)  # edges 0-1, 1-2, 2-3, 3-0
    return _robust_ratio((true / measured).ravel(), "board", minimum=3)


def track_scale(tracks: Tracks, survey: dict, survey_path: Path) -> tuple[float, float, dict]:
    """(s, spread, detail) of the position track (:func:`fit_track`, :func:`track_halves`)."""
    frames = survey.get("frames") or sorted(str(n) for n in tracks.image_names)
    positions = dict(zip(frames, survey["nav_position_m"], strict=False))
    index = [k for k in np.flatnonzero(tracks.registered) if str(tracks.image_names[k]) in positions]
    if len({len(positions[str(tracks.image_names[k])]) for k in index}) > 1:
        raise UserInputError(f"{survey_path}: nav_position_m mixes 2-D and 3-D positions")
    centres = tracks.world_from_cam[index, :3, 3]
    xy = np.array([positions[str(tracks.image_names[k])] for k in index], float)
    fit = fit_track(centres, xy)
    detail = {"residual_m": round(fit.residual_m, 4), "used": fit.used, "kept": fit.kept, "mirrored": fit.mirrored,
              "estimator": fit.estimator, "durbin_watson": round(fit.durbin_watson, 3)}
    if len(index) >= 10:
        detail["halves"] = track_halves(centres, xy, fit.estimator)
    return fit.scale, fit.spread, detail
