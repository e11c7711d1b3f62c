"""The diagnosis on the demo preset with one hidden effect at a time (and none).

Prints per case: the verdict, the best candidate's held-out error change (95% bootstrap interval),
the true hidden effect's rank among the candidates, points / observations, seconds per fit (mean
over the base fit and the candidate refits) and the wall time of the whole diagnosis.

Surveys are simulated into ``--cache`` (reused when present). Torch runs on one thread.

Run: .venv/bin/python benchmarks/bench_diagnose.py [--hidden a,b,...] [--points N] [--cache DIR]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from eval.diagnose import DiagnoseConfig, run_diagnose
from eval.diagnose_measure import MeasureConfig
from eval.synth import make_config, simulate_survey

CASES = ("vignetting_offcentre", "artificial_light", "sensor_response", "caustics", "none")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hidden", default=",".join(CASES), help="hidden effects to try, one per case ('none')")
    parser.add_argument("--points", type=int, default=3000, help="3D points sampled per survey")
    parser.add_argument("--cache", default="/tmp/watergan-bench-diagnose", help="folder of simulated surveys")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for case in [c.strip() for c in args.hidden.split(",") if c.strip()]:
        survey = Path(args.cache) / case
        if not (survey / "truth" / "config.json").is_file():
            simulate_survey(survey, make_config("demo", hidden=[] if case == "none" else [case], seed=0),
                            force=True, progress=False)
        for old in (survey / "diagnose").glob("*"):
            old.unlink()
        start = time.perf_counter()
        result = run_diagnose(survey, DiagnoseConfig(measure=MeasureConfig(n_points=args.points)), progress=False)
        wall = time.perf_counter() - start
        fit = json.loads((survey / "diagnose" / "fit.json").read_text())
        fits = [fit["seconds"], *(r["seconds"] for r in result.ranking)]
        names = [r["name"] for r in result.ranking]
        top = result.ranking[0]
        rows.append({
            "hidden": case, "verdict": result.verdict.splitlines()[0], "best_change": top["change"],
            "best_ci95": top["ci95"], "hidden_rank": names.index(case) + 1 if case in names else None,
            "points": result.n_points, "obs": result.n_obs, "s_per_fit": sum(fits) / len(fits), "wall_s": wall,
            "base_heldout_rmse": result.heldout_rmse, "unexplained": result.unexplained_axes,
        })
        r = rows[-1]
        print(f"[{case}] {r['verdict']}\n    top change {r['best_change'] * 100:+.1f}% "
              f"[{r['best_ci95'][0] * 100:+.1f}%, {r['best_ci95'][1] * 100:+.1f}%], hidden effect ranked "
              f"{r['hidden_rank']}, {r['points']} points / {r['obs']} obs, {r['s_per_fit']:.1f} s per fit, "
              f"{r['wall_s']:.0f} s in all; unexplained axes: {r['unexplained'] or 'none'}", flush=True)
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
