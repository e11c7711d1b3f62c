"""Cost of the whole pipeline against survey length: seconds and peak memory per stage at each size, and each stage's
cost per frame at the largest size over the smallest.

    .venv/bin/python benchmarks/bench_scale.py [--frames 44,176,500] [--out /tmp/bench_scale] [--gan-budget-min 4]
                                              [--restorer-budget-min 0.5] [--site-depth-steps 2000]
                                              [--stages water,sfm]

Each size is the demo survey (one hidden effect, as ``watergan demo`` ships it) flown longer over a larger site
(:func:`eval.synth.with_frames`: at least that many frames, lines and frames per line grown alike), simulated, then run
stage by stage as ``watergan run`` runs them (:func:`pipeline.run.stage_config` with these options), each stage in a
child process whose peak resident memory is read from ``os.wait4``. WaterGAN and the restorer train for a fixed time
budget and the site depth net for a fixed number of steps, so their cost does not grow with the survey; every other
stage should grow linearly. Writes ``benchmarks/results/scale.json``: per size the frames, the simulation's and each
stage's seconds and peak memory (MiB), the run's wall time and largest peak (written after every stage: ``complete`` is
false for a size still running or stopped); ``per_frame_ratio``: each stage's seconds per frame at the largest complete
size over the smallest. Each stage's entry names the commit whose code ran it. ``--stages``: rerun only those stages
on the sizes' surveys and workspaces already in ``--out`` (after a change to them), the other stages' figures kept
from scale.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "scale.json"
CHILD = """
import json, sys
from pipeline.run import run_options, stage_config
from pipeline.workspace import Workspace
stage, values = sys.argv[1], json.loads(sys.argv[2])
opts = run_options(values)
Workspace(opts.workspace).run(stage, stage_config(stage, opts), force=True)
"""


def child(args: list[str], log: Path) -> tuple[float, float]:
    """Run a child process (its output to ``log``); (seconds, its peak resident memory in MiB). A failure is an error
    naming the log."""
    began = time.perf_counter()
    with log.open("a") as out:
        process = subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(process.pid, 0)
    seconds = time.perf_counter() - began
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(args[:4])}... failed: see {log}")
    return seconds, usage.ru_maxrss / 1024


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", default="44,176,500", help="survey lengths, comma-separated")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_scale"))
    parser.add_argument("--gan-budget-min", type=float, default=4.0)
    parser.add_argument("--restorer-budget-min", type=float, default=0.5)
    parser.add_argument("--site-depth-steps", type=int, default=2000)
    parser.add_argument("--stages", default="", help="rerun only these stages on the surveys in --out")
    args = parser.parse_args()
    from pipeline.stages import STAGES

    rerun = [s for s in args.stages.split(",") if s]
    unknown = sorted(set(rerun) - set(STAGES))
    if unknown:
        raise SystemExit(f"unknown stages {unknown}: choose from {', '.join(STAGES)}")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).resolve().parent,
                            capture_output=True, text=True).stdout.strip()

    args.out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "MPLCONFIGDIR": os.environ.get("MPLCONFIGDIR", str(args.out / "mpl"))}
    os.environ.update(env)
    before = json.loads(RESULTS.read_text()) if rerun else {}
    sizes = before.get("sizes", {})
    args.history = before.get("command", "")
    for frames in (int(f) for f in args.frames.split(",")):
        survey, ws, log = args.out / f"survey{frames}", args.out / f"ws{frames}", args.out / f"log{frames}.txt"
        if rerun:
            kept = sizes[str(len(list((survey / "images").iterdir())))]  # the frames the survey was simulated with
            simulate_s, simulate_mb = kept["simulate_s"], kept["simulate_peak_mib"]
        else:
            log.unlink(missing_ok=True)
            simulate_s, simulate_mb = child([sys.executable, "-m", "pipeline.cli", "simulate", "--frames", str(frames),
                                             "--hidden", "vignetting_offcentre", "--out", str(survey), "--force"], log)
        values = {"survey_dir": str(survey), "workspace": str(ws), "progress": False,
                  "gan_budget_min": args.gan_budget_min, "restorer_budget_min": args.restorer_budget_min,
                  "restorer_site_depth_steps": args.site_depth_steps}
        count = len(list((survey / "images").iterdir()))
        print(f"{count} frames: simulated in {simulate_s:.0f} s (peak {simulate_mb:.0f} MiB)", flush=True)
        stages = kept["stages"] if rerun else {}
        for stage in rerun or STAGES:
            seconds, peak = child([sys.executable, "-c", CHILD, stage, json.dumps(values)], log)
            stages[stage] = {"s": round(seconds, 1), "peak_mib": round(peak), "commit": commit}
            print(f"  {stage:9} {seconds:8.1f} s  {seconds / count:6.2f} s/frame  peak {peak:6.0f} MiB", flush=True)
            sizes[str(count)] = {"frames": count, "simulate_s": round(simulate_s, 1),
                                 "simulate_peak_mib": round(simulate_mb), "stages": stages,
                                 "complete": set(stages) == set(STAGES),
                                 "run_s": round(sum(s["s"] for s in stages.values()), 1),
                                 "peak_mib": max(s["peak_mib"] for s in stages.values())}
            write(args, sizes)  # stage by stage: a long run that is stopped keeps what it measured
    return 0


def write(args: argparse.Namespace, sizes: dict) -> None:
    """scale.json with the sizes measured so far and, with two or more, each stage's per-frame ratio."""
    counts = sorted((c for c in sizes if sizes[c]["complete"]), key=int)
    if not counts:
        counts = sorted(sizes, key=int)
    small, large = sizes[counts[0]], sizes[counts[-1]]
    ratio = {stage: round((large["stages"][stage]["s"] / large["frames"])
                          / (small["stages"][stage]["s"] / small["frames"]), 2)
             for stage in small["stages"] if small["stages"][stage]["s"] > 0} if len(counts) > 1 else {}
    command = "benchmarks/bench_scale.py " + " ".join(sys.argv[1:])
    record = {"command": f"{args.history}, then {command}" if args.history else command, "cpus": os.cpu_count(),
              "gan_budget_min": args.gan_budget_min, "restorer_budget_min": args.restorer_budget_min,
              "site_depth_steps": args.site_depth_steps, "sizes": sizes, "per_frame_ratio": ratio}
    RESULTS.write_text(json.dumps(record, indent=2) + "\n")
    if ratio:
        print(f"per frame, {counts[-1]} frames over {counts[0]}: "
              + ", ".join(f"{stage} {value:.2f}x" for stage, value in ratio.items()), flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
