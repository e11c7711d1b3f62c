"""Cost of `watergan run` against survey size: seconds per stage, correction frames per second and
peak memory, on the demo survey and on one 4x larger (twice the lines, twice the frames per line,
over a site twice as long and wide).

    .venv/bin/python benchmarks/bench_run.py [--out /tmp/bench_run] [--sizes 1,4] [--gan-budget-min 4]
                                            [--restorer-budget-min 2.5]

Each size is simulated (one hidden effect, as the demo), then run in a child process whose peak
resident memory is read from ``getrusage(RUSAGE_CHILDREN)``. WaterGAN and the restorer train for a
fixed time budget, so their cost does not grow with the survey; every other stage should grow
about linearly. Writes ``bench_run.json`` in ``--out`` and prints a table with the ratio per stage.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path


def survey_config(scale: int):
    """The demo preset with ``scale`` (1 or 4) times the frames: lines and frames per line doubled
    for 4, over a site twice as long and wide."""
    from eval.synth import make_config

    config = make_config("demo", hidden=["vignetting_offcentre"])
    if scale == 1:
        return config
    if scale != 4:
        raise SystemExit("--sizes takes 1 and 4")
    trajectory = replace(config.trajectory, n_lines=2 * config.trajectory.n_lines,
                         frames_per_line=2 * config.trajectory.frames_per_line)
    scene = replace(config.scene, size_x_m=2 * config.scene.size_x_m, size_y_m=2 * config.scene.size_y_m)
    return replace(config, trajectory=trajectory, scene=scene)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="/tmp/bench_run")
    parser.add_argument("--sizes", default="1,4", help="survey sizes relative to the demo (1 and/or 4)")
    parser.add_argument("--gan-budget-min", type=float, default=4.0)
    parser.add_argument("--restorer-budget-min", type=float, default=2.5)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("MPLCONFIGDIR", str(out / "mpl"))
    from eval.synth import simulate_survey

    rows = {}
    for scale in (int(s) for s in args.sizes.split(",")):
        ws = out / f"x{scale}"
        config = survey_config(scale)
        began = time.perf_counter()
        summary = simulate_survey(ws / "00_survey", config, force=True, progress=False)
        simulate_s = time.perf_counter() - began
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        began = time.perf_counter()
        subprocess.run([sys.executable, "-m", "pipeline.cli", "run", str(ws / "00_survey"), "--workspace", str(ws),
                        "--gan-budget-min", str(args.gan_budget_min), "--restorer-budget-min",
                        str(args.restorer_budget_min), "--no-progress", "--force", "all"],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall_s = time.perf_counter() - began
        peak_mb = max(before, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024
        run = json.loads((ws / "run_summary.json").read_text())
        correct = json.loads((ws / "06_correct" / "result.json").read_text())["result"]
        rows[scale] = {"frames": summary.frames, "width": summary.width, "height": summary.height,
                       "simulate_s": round(simulate_s, 1), "run_s": round(wall_s, 1),
                       "stage_s": {s["stage"]: s["seconds"] for s in run["stages"]},
                       "correct_fps": round(correct["fps"], 2), "peak_rss_mb": round(peak_mb)}
        print(f"x{scale}: {summary.frames} frames, run {wall_s:.0f} s, peak RSS {peak_mb:.0f} MB "
              f"(the largest child so far), correction {correct['fps']:.1f} frames/s", flush=True)

    (out / "bench_run.json").write_text(json.dumps(rows, indent=2) + "\n")
    scales = sorted(rows)
    print(f"\n{'stage':10}" + "".join(f"{f'x{s} (s)':>12}" for s in scales) + ("   ratio" if len(scales) > 1 else ""))
    for stage in rows[scales[0]]["stage_s"]:
        values = [rows[s]["stage_s"][stage] for s in scales]
        ratio = f"   {values[-1] / values[0]:5.2f}" if len(scales) > 1 and values[0] > 0 else ""
        print(f"{stage:10}" + "".join(f"{v:12.1f}" for v in values) + ratio)
    print(f"{'total':10}" + "".join(f"{rows[s]['run_s']:12.1f}" for s in scales))
    print(f"written: {out / 'bench_run.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
