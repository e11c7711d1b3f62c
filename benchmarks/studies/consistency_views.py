"""How much range diversity the raw colour consistency sees: SfM tracks against every view of a point.

The evaluation's consistency (eval.colour) is measured on SfM tracks, which link views of similar scale and
angle; a simulated survey's truth knows every view that sees a point. For a simulated survey and its SfM
tracks this prints:

- tracks: the per-track spread of range (max - min over the track's views, metres; range from the SfM
  poses and points), median and 90th percentile;
- all views: ``--points`` random pixels of every third frame, unprojected with the true depth and pose,
  projected into every frame and kept where the true depth there agrees (within 1 cm + 1 %, so not
  occluded); the same 5x5 patch means of the linear raw images, c / (R + G + B), variance across views
  (points with >= 3 views) averaged over points, and the per-point range spread.

Run: PYTHONPATH=. .venv/bin/python benchmarks/studies/consistency_views.py --survey S --tracks W/01_sfm/tracks.npz
"""

from __future__ import annotations

import argparse

import numpy as np

from eval.colour import normalise, patch_means, read_rgb
from eval.synth import load_truth
from eval.synth.camera import project, unproject
from eval.tracks import Tracks


def track_range_spread(tracks: Tracks, min_views: int = 3) -> np.ndarray:
    """Per track with >= ``min_views`` observations: max - min camera-to-point distance, metres."""
    centres = tracks.world_from_cam[tracks.obs_image, :3, 3]
    ranges = np.linalg.norm(tracks.xyz[tracks.obs_point] - centres, axis=1)
    low = np.full(len(tracks.xyz), np.inf)
    high = np.zeros(len(tracks.xyz))
    np.minimum.at(low, tracks.obs_point, ranges)
    np.maximum.at(high, tracks.obs_point, ranges)
    keep = np.bincount(tracks.obs_point, minlength=len(tracks.xyz)) >= min_views
    return (high - low)[keep]


def all_view_consistency(survey: str, points_per_frame: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(3,) mean per-point variance of c / (R + G + B) over every view that sees the point, and the per-point
    range spread (metres), from the survey's truth."""
    truth = load_truth(survey)
    intr = truth.intrinsics
    n = len(truth.frames)
    images = [read_rgb(truth.root / "images" / name) for name in truth.frames]
    depths = [truth.depth_m(k) for k in range(n)]
    rng = np.random.default_rng(seed)
    points = []
    for k in range(0, n, 3):
        uv = np.stack([rng.uniform(10, intr.width - 10, points_per_frame),
                       rng.uniform(10, intr.height - 10, points_per_frame)], 1)
        z = depths[k][np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
        points.append(unproject(uv, z, truth.world_from_cam[k], intr))
    points = np.concatenate(points)
    colours = np.full((len(points), n, 3), np.nan)
    ranges = np.full((len(points), n), np.nan)
    for k in range(n):
        uv, z = project(points, truth.world_from_cam[k], intr)
        inside = np.isfinite(uv).all(1) & (uv[:, 0] > 3) & (uv[:, 0] < intr.width - 4) \
            & (uv[:, 1] > 3) & (uv[:, 1] < intr.height - 4)
        ij = np.rint(uv[inside]).astype(int)
        seen = np.zeros(len(points), bool)
        seen[inside] = np.abs(depths[k][ij[:, 1], ij[:, 0]] - z[inside]) < 0.01 + 0.01 * z[inside]
        colours[seen, k] = normalise(patch_means(images[k], uv[seen], 5)[0])
        ranges[seen, k] = np.linalg.norm(points[seen] - truth.world_from_cam[k][:3, 3], axis=1)
    keep = np.isfinite(colours[..., 0]).sum(1) >= 3
    variance = np.nanvar(colours[keep], axis=1).mean(0)
    return variance, np.nanmax(ranges[keep], 1) - np.nanmin(ranges[keep], 1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--survey", required=True, help="a simulated survey folder (with truth/)")
    parser.add_argument("--tracks", required=True, help="the SfM stage's tracks.npz for that survey")
    parser.add_argument("--points", type=int, default=200, help="random pixels per sampled frame")
    args = parser.parse_args(argv)
    spread = track_range_spread(Tracks.load(args.tracks))
    print(f"SfM tracks ({len(spread)} with >= 3 views): range spread median {np.median(spread):.2f} m, "
          f"p90 {np.percentile(spread, 90):.2f} m")
    variance, view_spread = all_view_consistency(args.survey, args.points)
    print(f"all views ({len(view_spread)} points): range spread median {np.median(view_spread):.2f} m; raw "
          f"consistency R {variance[0]:.2e} G {variance[1]:.2e} B {variance[2]:.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
