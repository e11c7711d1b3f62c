"""Why Table II stays above raw on a real survey: views of the same point compared (issue 51).

    PYTHONPATH=. .venv/bin/python benchmarks/studies/real_view_pairs.py WS [--parts OUT/gain_field_atten ...]

On a ``watergan run`` workspace ``WS`` (the pool crawler's), for raw, the correct stage's physics and restorer
frames and any further folders given (e.g. :mod:`real_correction_parts`'s), prints, x1e-4:

- pairs of views of the same SfM point (5-pixel patches, normalised colour c / (R + G + B)): their variance
  (half the squared difference) averaged over pairs at nearly the same range (within 3 %: no water between them),
  over pairs at different ranges, and over those whose range ratio exceeds the median;
- Table II's per-point variance over the points in thirds by their SfM colour's brightness;
- Table II with 5, 15 and 31-pixel patches.

Ranges are the range stage's maps at each view's pixel. Writes nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def view_ranges(ws, tracks) -> np.ndarray:
    """(M,) each observation's range (metres, NaN where the range map has none)."""
    from watergan.io import read_millimetres

    ranges = ws.result("range")
    out = np.full(len(tracks.obs_point), np.nan)
    for k, name in enumerate(tracks.image_names):
        r = read_millimetres(ws.path(ranges.range_dir) / f"{Path(str(name)).stem}.png") / 1000.0
        rows = np.flatnonzero(tracks.obs_image == k)
        xy = np.rint(tracks.obs_xy[rows]).astype(int)
        inside = (xy[:, 0] >= 0) & (xy[:, 0] < r.shape[1]) & (xy[:, 1] >= 0) & (xy[:, 1] < r.shape[0])
        values = np.full(len(rows), np.nan)
        values[inside] = r[xy[inside, 1], xy[inside, 0]]
        out[rows] = np.where(values > 0, values, np.nan)
    return out


def pair_variances(tracks, colours: np.ndarray, ranges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pair of views of one point: (variance (P,3), |log range ratio| (P,)) and whether within 3 %."""
    ok = np.isfinite(colours).all(1) & np.isfinite(ranges)
    order = np.argsort(tracks.obs_point[ok], kind="stable")
    point, c, r = tracks.obs_point[ok][order], colours[ok][order], ranges[ok][order]
    starts = np.flatnonzero(np.r_[True, point[1:] != point[:-1]])
    ends = np.r_[starts[1:], len(point)]
    variance, ratio = [], []
    for s, e in zip(starts, ends, strict=True):
        i, j = np.triu_indices(e - s, 1)
        variance.append(0.5 * (c[s + i] - c[s + j]) ** 2)
        ratio.append(np.abs(np.log(r[s + i] / r[s + j])))
    variance, ratio = np.concatenate(variance), np.concatenate(ratio)
    return variance, ratio, ratio < np.log(1.03)


def main() -> None:
    from eval.colour import consistency, observation_colours
    from eval.tables import point_variances
    from eval.tracks import Tracks
    from pipeline.workspace import Workspace

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--parts", type=Path, nargs="*", default=[])
    args = parser.parse_args()
    ws = Workspace(args.workspace)
    correct = ws.result("correct")
    tracks = Tracks.load(ws.path(ws.result("sfm").tracks))
    folders = {"raw": ws.stage_dir("survey") / "images", "physics": ws.path(correct.physics_images),
               "restorer": ws.path(correct.images), **{p.name: p for p in args.parts}}
    ranges = view_ranges(ws, tracks)
    colours = {m: observation_colours(tracks, f, 5) for m, f in folders.items()}

    def show(values: np.ndarray) -> str:
        return " / ".join(f"{v * 1e4:.2f}" for v in values)

    for method, c in colours.items():
        variance, ratio, same = pair_variances(tracks, c, ranges)
        apart = ~same & (ratio > np.median(ratio[~same]))
        print(f"{method:18s} pairs at the same range {show(variance[same].mean(0))} ({same.sum()} pairs); "
              f"at different ranges {show(variance[~same].mean(0))}; "
              f"ratio above the median {show(variance[apart].mean(0))}")
    per_point = point_variances(tracks, folders, 5, 3, colours)
    valid = np.logical_and.reduce([np.isfinite(c).all(1) for c in colours.values()])
    counts = np.bincount(tracks.obs_point[valid], minlength=len(tracks.xyz))
    brightness = tracks.rgb[counts >= 3].astype(float).sum(1)
    edges = np.percentile(brightness, [33.3, 66.7])
    for label, keep in (("darkest third", brightness <= edges[0]), ("brightest third", brightness > edges[1])):
        print(f"Table II, {label}: " + "   ".join(f"{m} {show(v[keep].mean(0))}" for m, v in per_point.items()))
    for patch_px in (5, 15, 31):
        scores = consistency(tracks, folders, patch_px, 3).scores
        print(f"Table II, {patch_px}-pixel patches: "
              + "   ".join(f"{m} {show(s.variance)}" for m, s in scores.items()))


if __name__ == "__main__":
    main()
