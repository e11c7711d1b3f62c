"""The wall time of a survey of N frames against worker cores, from the per-stage costs in ``results/scale.json``
(docs/clusters.md, "How long a survey takes").

    python benchmarks/studies/cluster_model.py [--frames 500,10000] [--workers 2,8,64]

    T(N, W) = sfm(N) + sum over the other stages of (a_s + b_s N f_s(W))
    sfm(N)  = sfm(N0) (N / N0)^e          e from SfM's seconds at the smallest and the largest size
    a_s + b_s N                            the straight line through the stage's seconds at the two largest sizes
    f_s(W)  = 2 / W for dense, correct and eval (they run on the cluster; the costs were measured on 2 cores), else 1

Prints per size and worker count the hours and the stages that take more than ten minutes.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "results" / "scale.json"
ON_THE_CLUSTER = ("dense", "correct", "eval")
MEASURED_CORES = 2


def fit(sizes: dict) -> tuple[dict[str, tuple[float, float]], tuple[float, int, float]]:
    """({stage: (a_s seconds, b_s seconds per frame)}, (SfM's seconds at N0, N0, its exponent e))."""
    by_frames = sorted(sizes.values(), key=lambda s: s["frames"])
    small, mid, large = by_frames[0], by_frames[-2], by_frames[-1]
    lines = {}
    for stage in large["stages"]:
        if stage == "sfm":
            continue
        t1, t2 = mid["stages"][stage]["s"], large["stages"][stage]["s"]
        b = (t2 - t1) / (large["frames"] - mid["frames"])
        lines[stage] = (t1 - b * mid["frames"], b)
    s0, s1 = small["stages"]["sfm"]["s"], large["stages"]["sfm"]["s"]
    return lines, (s0, small["frames"], math.log(s1 / s0) / math.log(large["frames"] / small["frames"]))


def wall_time(lines: dict, sfm: tuple[float, int, float], frames: int, workers: int) -> dict[str, float]:
    """Seconds per stage of a survey of ``frames`` frames with ``workers`` cores for the cluster's stages."""
    s0, n0, e = sfm
    parts = {"sfm": s0 * (frames / n0) ** e}
    for stage, (a, b) in lines.items():
        share = MEASURED_CORES / workers if stage in ON_THE_CLUSTER and workers > MEASURED_CORES else 1.0
        parts[stage] = a + b * frames * share
    return parts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", default="500,10000")
    parser.add_argument("--workers", default="2,8,64")
    args = parser.parse_args()
    lines, sfm = fit(json.loads(RESULTS.read_text())["sizes"])
    print("a_s, b_s: " + ", ".join(f"{s} {a:.0f} s + {b:.3f} s/frame" for s, (a, b) in lines.items()))
    print(f"sfm: {sfm[0]:.1f} s (N / {sfm[1]})^{sfm[2]:.3f}")
    for frames in (int(f) for f in args.frames.split(",")):
        for workers in (int(w) for w in args.workers.split(",")):
            parts = wall_time(lines, sfm, frames, workers)
            big = ", ".join(f"{s} {t / 60:.0f} min" for s, t in sorted(parts.items(), key=lambda p: -p[1]) if t > 600)
            print(f"{frames:>6} frames, {workers:>2} cores: {sum(parts.values()) / 3600:5.2f} h  ({big})")


if __name__ == "__main__":
    main()
