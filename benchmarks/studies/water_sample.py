"""How many surface points the water fit needs: the estimate and its 95 % intervals against the number of points it
is fitted to, on one workspace's measurement table (issue 31: the fit on a bounded sample whose size is justified).

    PYTHONPATH=. .venv/bin/python benchmarks/studies/water_sample.py WS [--points 5000,10000,20000,40000]
        [--seeds 0] [--out benchmarks/results/water_sample.json]

Reads ``WS/04_water/observations.npz`` (the water stage's table, every frame's points with all their views, the
board's rows), ``WS/00_survey/truth/effects.json`` and the SfM stage's scale spread. For each size it draws that many
points at random (``Observations.take_points``: each point keeps all its views; the board's rows are all kept), fits
them with the default :class:`eval.water.WaterConfig` (:func:`eval.water.estimate_observations`: fit, bootstrap,
specification alternatives) and records per fitted parameter the estimate, the truth, the relative error, the 95 %
interval's width and whether it covers the truth, and the fit's seconds. The full table's row is the water stage's
own ``water.json`` (same code, same table), read rather than refitted. Writes every row to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_water import compare, truth_params  # noqa: E402

from eval.observations import Observations  # noqa: E402
from eval.water import WaterConfig, estimate_observations  # noqa: E402
from pipeline.stages import stage_folder  # noqa: E402
from watergan.water_record import read_water  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]  # the repository: result files name paths relative to it
REPORTED = ("attenuation.eta_per_m", "backscatter.b_inf", "backscatter.beta_per_m", "gain.k")


def rows_of(params: dict, truth: dict) -> dict:
    """Per reported parameter, :func:`bench_water.compare`'s row with the interval's width relative to the truth."""
    rows = compare({key: params[key] for key in REPORTED if key in params and params[key].get("fitted")}, truth)
    for row in rows.values():
        width = (np.asarray(row["high"]) - np.asarray(row["low"])) / np.abs(np.asarray(row["truth"]))
        row["rel_width"] = np.round(width, 4).tolist()
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--points", default="5000,10000,20000,40000", help="sample sizes, surface points")
    parser.add_argument("--seeds", default="0", help="seeds of the point draws")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/water_sample.json"))
    args = parser.parse_args()
    ws = args.workspace
    obs = Observations.load(stage_folder(ws, "water") / "observations.npz")
    truth = truth_params(stage_folder(ws, "survey"))
    record = json.loads((stage_folder(ws, "sfm") / "result.json").read_text())
    config = WaterConfig(range_scale_sd=float(record.get("result", record)["scale_spread"]))
    stage = read_water(stage_folder(ws, "water") / "water.json")
    rows = [{"points": obs.n_points, "views": obs.n_obs, "seed": None, "seconds": stage.seconds,
             "params": rows_of(stage.params, truth)}]
    for seed in (int(s) for s in args.seeds.split(",")):
        for n in (int(s) for s in args.points.split(",")):
            if n >= obs.n_points:
                continue
            rng = np.random.default_rng([seed, n])
            part = obs.take_points(np.sort(rng.choice(obs.n_points, n, replace=False)))
            began = time.perf_counter()
            estimate = estimate_observations(part, config, obs.lights)
            seconds = round(time.perf_counter() - began, 1)
            rows.append({"points": n, "views": part.n_obs, "seed": seed, "seconds": seconds,
                         "params": rows_of(estimate.to_json()["params"], truth)})
            eta = rows[-1]["params"]["attenuation.eta_per_m"]
            print(f"{n:>7} points {part.n_obs:>8} views {seconds:>7.1f} s  eta error {eta['rel_error']} "
                  f"width {eta['rel_width']} covered {eta['covered']}", flush=True)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps({"workspace": os.path.relpath(ws, ROOT), "command": " ".join(sys.argv),
                                            "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
