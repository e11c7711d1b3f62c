"""The diagnosis with one hidden effect at a time (and none): is the hidden effect found?

Per case it prints the verdict and one table row: the hidden effect's rank among the candidates
(or why it is not a candidate), the held-out RMSE of the model before and after adding it, the
relative change, the best candidate, points / observations and the wall time. A case passes the
bar of tests/test_diagnose.py when the hidden effect ranks first and cuts the held-out error by at
least 50 %.

Surveys: ``--survey small`` (eval.diagnose.small_survey_config, what the tests use) or ``demo``
(the demo preset, 44 frames of 640x480). ``--geometry sfm`` puts each survey in a workspace, runs
pipeline.sfm on it and measures on the reconstruction (small surveys then have 320x240 frames, as in
the end-to-end test: SIFT finds too few features at 160x120). Surveys are simulated into ``--cache``
(reused when present). Torch runs on one thread.

Run: .venv/bin/python benchmarks/bench_diagnose.py [--survey small|demo] [--hidden a,b,...|all]
     [--geometry truth|sfm] [--points N] [--iterations N] [--cache DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
import zlib  # noqa: F401  load before pycolmap
from pathlib import Path

import torch

from eval.diagnose import DiagnoseConfig, small_survey_config
from eval.diagnose_measure import MeasureConfig
from eval.fit import FitConfig
from eval.synth import HIDDEN_DEFAULTS, make_config, simulate_survey
from pipeline.diagnose import run_diagnose
from pipeline.stages import stage_folder

ALL = (*HIDDEN_DEFAULTS, "none")


def survey_dir(cache: Path, survey: str, case: str, geometry: str) -> Path:
    """Simulate (once) and return the target to diagnose: a survey folder, or a workspace with SfM."""
    hidden = [] if case == "none" else case.split("+")
    root = cache / f"{survey}-{case}"
    target = stage_folder(root, "survey") if geometry == "sfm" else root
    if not (target / "truth" / "config.json").is_file():
        config = small_survey_config(hidden, width_px=320 if geometry == "sfm" else 160) if survey == "small" \
            else make_config("demo", hidden=hidden, seed=0)
        simulate_survey(target, config, force=True, progress=False)
    if geometry == "sfm":
        from pipeline.sfm import SfmConfig
        from pipeline.workspace import Workspace

        Workspace(root).run("sfm", SfmConfig())
        return root
    return target


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--survey", choices=("small", "demo"), default="small")
    parser.add_argument("--hidden", default="all", help="cases, comma-separated: effect names, a+b for two, 'none'")
    parser.add_argument("--geometry", choices=("truth", "sfm"), default="truth")
    parser.add_argument("--points", type=int, default=0, help="3D points (default: 600 small, as the tests; 3000 demo)")
    parser.add_argument("--iterations", type=int, default=0, help="L-BFGS iterations per fit (default: 60 small, "
                                                                  "as the tests; 100 demo)")
    parser.add_argument("--cache", default="/tmp/watergan-bench-diagnose", help="folder of simulated surveys")
    args = parser.parse_args()
    torch.set_num_threads(1)
    small = args.survey == "small"
    config = DiagnoseConfig(geometry=args.geometry,
                            measure=MeasureConfig(n_points=args.points or (600 if small else 3000)),
                            fit=FitConfig(iterations=args.iterations or (60 if small else 100)),
                            bootstrap=500 if small else 2000, plots=False)
    cases = ALL if args.hidden == "all" else tuple(c.strip() for c in args.hidden.split(",") if c.strip())
    rows = []
    for case in cases:
        target = survey_dir(Path(args.cache), args.survey, case, args.geometry)
        for stale in (target / "diagnose", stage_folder(target, "diagnose")):
            shutil.rmtree(stale, ignore_errors=True)
        (target / "model_ledger.jsonl").unlink(missing_ok=True)
        start = time.perf_counter()
        result = run_diagnose(target, config, progress=False)
        wall = time.perf_counter() - start
        names = [r["name"] for r in result.ranking]
        hidden = case.split("+")[0]
        mine = result.ranking[names.index(hidden)] if hidden in names else None
        rows.append({"hidden": case, "rank": names.index(hidden) + 1 if mine else None,
                     "not_candidate": result.skipped.get(hidden, ""), "before": result.heldout_rmse,
                     "after": mine["heldout_rmse"] if mine else None, "change": mine["change"] if mine else None,
                     "best": result.best, "points": result.n_points, "obs": result.n_obs, "wall_s": round(wall, 1),
                     "verdict": result.verdict.splitlines()[0]})
        r = rows[-1]
        found = (f"rank {r['rank']}, {r['before']:.5f} -> {r['after']:.5f} ({r['change'] * 100:+.0f}%)" if mine
                 else f"not a candidate ({r['not_candidate']})" if r["not_candidate"] else "no hidden effect")
        print(f"[{case}] {found}; best {r['best']}; {r['points']} points / {r['obs']} obs, {wall:.0f} s\n"
              f"    {r['verdict']}", flush=True)
    print("\n| hidden | rank | held-out before -> after | change | verdict |\n|---|---|---|---|---|")
    for r in rows:
        cells = (f"{r['rank']}", f"{r['before']:.4f} -> {r['after']:.4f}", f"{r['change'] * 100:+.0f}%") \
            if r["rank"] else ("-", f"{r['before']:.4f}", "-")
        print(f"| {r['hidden']} | {' | '.join(cells)} | {r['best'] or 'none'} |")
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
