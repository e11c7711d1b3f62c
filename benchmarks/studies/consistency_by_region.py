"""Where over the image a correction loses its colour consistency: each view's squared deviation from its point's
mean colour (the evaluation's consistency, :func:`eval.colour.consistency`, is the mean of these per point), averaged
by image region, less a reference folder's (the oracle's).

    PYTHONPATH=. .venv/bin/python benchmarks/studies/consistency_by_region.py TRACKS REFERENCE FOLDER [FOLDER ...]
        [--grid 6x8] [--width 640 --height 480]

``TRACKS``: the SfM stage's tracks.npz; ``REFERENCE``, ``FOLDER``: folders of corrected frames (SfM's names), e.g. a
``bench_water.py`` workspace's ``water_bench_NAME/oracle`` and ``.../physics``. Views are sampled as the evaluation
samples them (5x5 patch means, linear colour; points with 3 views or more in every folder). Prints per folder the mean
squared deviation per channel (x1e-5) and, per channel, the rows x cols table of its excess over the reference's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from eval.colour import observation_colours
from eval.tracks import Tracks


def squared_deviations(tracks: Tracks, colours: np.ndarray, use: np.ndarray) -> np.ndarray:
    """(M,3) each used view's squared deviation from the mean colour of its point's used views."""
    point, c = tracks.obs_point[use], colours[use]
    n = np.bincount(point, minlength=len(tracks.xyz)).astype(float)
    mean = np.stack([np.bincount(point, c[:, k], minlength=len(n)) for k in range(3)], 1) / np.maximum(n, 1)[:, None]
    return (c - mean[point]) ** 2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tracks", type=Path)
    parser.add_argument("reference", type=Path)
    parser.add_argument("folders", type=Path, nargs="+")
    parser.add_argument("--grid", default="6x8", help="regions, ROWSxCOLS")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    args = parser.parse_args()
    rows, cols = (int(v) for v in args.grid.split("x"))
    tracks = Tracks.load(args.tracks)
    folders = [args.reference, *args.folders]
    colours = [observation_colours(tracks, f, 5, True, False, None) for f in folders]
    valid = np.logical_and.reduce([np.isfinite(c).all(1) for c in colours])
    counts = np.bincount(tracks.obs_point[valid], minlength=len(tracks.xyz))
    use = valid & (counts[tracks.obs_point] >= 3)
    xy = tracks.obs_xy[use] / np.array([args.width, args.height])
    region = (np.minimum((xy[:, 1] * rows).astype(int), rows - 1),
              np.minimum((xy[:, 0] * cols).astype(int), cols - 1))
    views = np.zeros((rows, cols))
    np.add.at(views, region, 1)
    by_region = []
    np.set_printoptions(linewidth=200)
    for folder, c in zip(folders, colours, strict=True):
        dev = squared_deviations(tracks, c, use)
        print(f"{folder}: mean squared deviation x1e5", np.round(1e5 * dev.mean(0), 2))
        sums = np.zeros((rows, cols, 3))
        np.add.at(sums, region, dev)
        by_region.append(sums / np.maximum(views, 1)[..., None])
    for folder, table in zip(folders[1:], by_region[1:], strict=True):
        for k, name in enumerate("RGB"):
            print(f"{folder} {name}: excess over {args.reference} x1e5, {rows} rows x {cols} cols")
            print(np.round(1e5 * (table - by_region[0])[..., k], 1))


if __name__ == "__main__":
    main()
