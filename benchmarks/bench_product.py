"""The product (issue 18): what the corrected frames achieve, the physics correction's and the restorer's, run
after run, beside raw and every baseline.

    .venv/bin/python benchmarks/bench_product.py [--out DIR] [--cases demo,demo_add,clean,generic,mono,mono_add]
                                                 [--runs 2] [--once clean,mono,generic] [--preset demo]
                                                 [extra `watergan run` options...]

Cases (each a `watergan` command line on a simulated survey; a case's workspace is reused when done):

- ``demo``: ``watergan demo`` (the default survey, ``vignetting_offcentre`` hidden, the stack without it);
- ``demo_add``: then ``watergan demo --add vignetting_offcentre`` on the same workspace (the loop's step);
- ``clean``: the demo preset with nothing hidden (``watergan simulate`` then ``watergan run``);
- ``generic``: ``clean`` with WaterGAN given the generic in-air set instead of the site-matched one;
- ``mono``: ``clean`` corrected in monocular mode (``--correct-mode monocular``: the RGB-D restorer at a flat
  seafloor's range at each frame's altitude, as for frames without range; a copy of the clean run's workspace, so only
  the correct stage and what follows it rerun);
- ``mono_add``: the same on a copy of ``demo_add``'s workspace (``watergan demo --add ... --correct-mode monocular``);
- ``mono_net``: ``clean`` with the paper's monocular restorer (``--no-restorer-range-input``: trained on the image
  and altitude alone; a copy of the clean run's workspace).

Each case runs ``--runs`` times (run r in ``OUT/<case>_r<r>``; the same code and seed: the spread is what the
budgeted training varies). Per run it records, from the eval stage's result, the board CIEDE2000 and the
consistency (variance of c/(R+G+B) across views, per channel) of raw, every baseline, the physics correction
and the restorer ("ours", with the correct stage's mode), the stage times and the correct stage's frames per
second, and checks issue 18's targets: the RGB-D restorer's board <= 1.5x the physics correction's and its
consistency below raw's and every baseline's in every channel; in monocular mode (each mono case) the board <= 2.0
and the consistency below raw's; from ``demo`` to ``demo_add`` the board and mean consistency of both corrections fall;
with the generic in-air set the restorer's board changes by <= 20 %. Per run it also records the board's mean
distance of normalised RGB and the PSNR against the in-air truth (the README's table: ``readme_table.py``). Writes
``benchmarks/results/product.json``, with the commit measured (``git describe --always --dirty``); its paths are
relative: a run's workspace to the repository's root, the water WaterGAN held to that workspace.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from pipeline.stages import stage_folder

ROOT = Path(__file__).resolve().parents[1]
BASELINES = ("raw", "histeq", "clahe", "gray_world", "jaffe", "seathru")
HIDDEN = "vignetting_offcentre"


def watergan(*args: str) -> float:
    """Run a `watergan` command (output to the console); its wall time in seconds."""
    began = time.perf_counter()
    print("$ watergan " + " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "pipeline.cli", *args], check=True, cwd=ROOT)
    return time.perf_counter() - began


def _clean_survey(out: Path, preset: str) -> Path:
    """The preset with nothing hidden, simulated once and shared by the clean, generic and mono cases."""
    survey = out / "clean_survey"
    if not (survey / "truth" / "config.json").is_file():
        watergan("simulate", "--preset", preset, "--out", str(survey), "--force")
    return survey


def _generic_rgbd(out: Path) -> Path:
    """The generic in-air set (the demo's views of scenes not drawn to resemble the site), rendered once."""
    from eval.synth.presets import PRESETS
    from eval.synth.rgbd import write_rgbd_set

    folder = out / "generic_rgbd"
    if not (folder / "camera.json").is_file():
        write_rgbd_set(folder, PRESETS["demo"].rgbd, 0)  # the demo's views; no site: generic photographs, tints
    return folder


def _copy_of(ws: Path, source: Path) -> None:
    """Start ``ws`` as a copy of the finished workspace ``source`` (only what a case changes then reruns)."""
    if not ws.exists() and (source / "run_summary.json").is_file():
        shutil.copytree(source, ws, symlinks=True)


def run_case(case: str, ws: Path, out: Path, preset: str, extra: list[str]) -> float:
    """Run one case into workspace ``ws``; returns the command's wall time."""
    common = ["--no-progress", *extra]
    if case == "demo":
        return watergan("demo", "--preset", preset, "--out", str(ws), *common)
    if case == "demo_add":
        return watergan("demo", "--preset", preset, "--out", str(ws), "--add", HIDDEN, *common)
    if case == "mono_add":  # demo_add's workspace (this run's), corrected in monocular mode
        _copy_of(ws, ws.parent / ws.name.replace("mono_add", "demo"))
        return watergan("demo", "--preset", preset, "--out", str(ws), "--add", HIDDEN, "--correct-mode", "monocular",
                        *common)
    survey = _clean_survey(out, preset)
    if case == "generic":
        common += ["--rgbd-dir", str(_generic_rgbd(out))]
    if case in ("mono", "mono_net"):  # the clean run's workspace (geometry and water reused)
        _copy_of(ws, ws.parent / ws.name.replace(case, "clean"))
        common += ["--correct-mode", "monocular"] if case == "mono" else ["--no-restorer-range-input"]
    return watergan("run", str(survey), "--workspace", str(ws), *common)


def summarise(ws: Path, seconds: float) -> dict:
    """The eval stage's figures of a finished workspace, its stage times and the correction speed."""
    from pipeline.workspace import Workspace

    w = Workspace(ws)
    ev, correct, gan = w.result("eval"), w.result("correct"), w.result("gan")
    summary = json.loads((ws / "run_summary.json").read_text())
    site_water = gan.train.get("site_water")
    if site_water and site_water.get("water_json"):
        site_water = {**site_water, "water_json": os.path.relpath(site_water["water_json"], ws)}
    return {
        "workspace": os.path.relpath(ws, ROOT), "seconds": round(seconds, 1),
        "stages": {s["stage"]: s["seconds"] for s in summary["stages"] if not s["skipped"]},
        "restorer_mode": correct.mode, "correct_fps": round(correct.fps, 2),
        "gan_site_water": site_water, "gan_steps": gan.train["steps"],
        "board_ciede2000": ev.mean_board_ciede2000,
        "board_distance": ev.mean_board_distance,
        "consistency": ev.consistency_variance,
        "psnr_db": psnr_db(w, ev.tables_json),
    }


def psnr_db(w, tables_json: str) -> dict[str, float]:
    """Per method, the eval stage's PSNR against the in-air truth in dB (empty where the survey has no truth)."""
    tables = json.loads(w.path(tables_json).read_text())["tables"]
    fidelity = next(t for t in tables if t["id"] == "fidelity")
    if fidelity["status"] != "ok":
        return {}
    row = next(r for r in fidelity["rows"] if r["label"] == "PSNR (dB)")
    return dict(zip(fidelity["columns"], row["values"], strict=True))


def targets(runs: dict[str, list[dict]]) -> dict:
    """Issue 18's targets, per run index, from the recorded figures (None where a case did not run)."""
    out: dict[str, list] = {}
    for case in ("demo_add", "clean", "demo"):
        for rec in runs.get(case, []):
            b, c = rec["board_ciede2000"], rec["consistency"]
            if rec["restorer_mode"] == "rgb-d":
                out.setdefault(f"{case}: rgb-d board <= 1.5x physics", []).append(
                    b["ours"] <= 1.5 * b["physics"])
                out.setdefault(f"{case}: rgb-d consistency below raw and every baseline, every channel", []).append(
                    all(c["ours"][k] < min(c[m][k] for m in BASELINES if m in c) for k in range(3)))
    for case in ("mono", "mono_add", "mono_net"):
        for rec in runs.get(case, []):
            b, c = rec["board_ciede2000"], rec["consistency"]
            out.setdefault(f"{case}: board <= 2.0", []).append(b["ours"] <= 2.0)
            out.setdefault(f"{case}: consistency below raw, every channel", []).append(
                all(c["ours"][k] < c["raw"][k] for k in range(3)))
    for before, after in zip(runs.get("demo", []), runs.get("demo_add", []), strict=False):
        for method in ("physics", "ours"):
            out.setdefault(f"--add lowers {method}'s board", []).append(
                after["board_ciede2000"][method] < before["board_ciede2000"][method])
            out.setdefault(f"--add lowers {method}'s mean consistency", []).append(
                sum(after["consistency"][method]) < sum(before["consistency"][method]))
    for site, generic in zip(runs.get("clean", []), runs.get("generic", []), strict=False):
        change = generic["board_ciede2000"]["ours"] / site["board_ciede2000"]["ours"] - 1
        out.setdefault("generic in-air set changes ours' board by <= 20 %", []).append(
            {"change": round(change, 3), "holds": abs(change) <= 0.2})
    return out


def print_run(case: str, r: int, rec: dict) -> None:
    b, c = rec["board_ciede2000"], rec["consistency"]
    print(f"\n{case} run {r}: {rec['seconds']:.0f} s, restorer {rec['restorer_mode']}, correct {rec['correct_fps']} "
          f"frames/s, WaterGAN {rec['gan_steps']} iterations")
    print(f"{'method':12} {'board dE':>9} {'cons R':>9} {'cons G':>9} {'cons B':>9}")
    for m in (*BASELINES, "ours", "physics", "oracle"):
        if m in c:
            print(f"{m:12} {b.get(m, float('nan')):9.3f} " + " ".join(f"{v:9.2e}" for v in c[m]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="/tmp/bench_product")
    parser.add_argument("--cases", default="demo,demo_add,clean,generic,mono,mono_add")
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--once", default="", help="cases run in the first run only (e.g. clean,mono,generic)")
    parser.add_argument("--preset", default="demo")
    parser.add_argument("--result", default=str(ROOT / "benchmarks" / "results" / "product.json"))
    args, extra = parser.parse_known_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    runs: dict[str, list[dict]] = {}
    once = {c.strip() for c in args.once.split(",") if c.strip()}
    for r in range(args.runs):
        for case in (c for c in cases if r == 0 or c not in once):
            ws = out / f"{'demo' if case == 'demo_add' else case}_r{r}"
            seconds = run_case(case, ws, out, args.preset, extra)
            rec = summarise(ws, seconds)
            if case == "demo":  # demo_add reruns in the same workspace: keep this version's eval
                shutil.copytree(stage_folder(ws, "eval"), out / f"demo_r{r}_eval_before_add", dirs_exist_ok=True)
            runs.setdefault(case, []).append(rec)
            print_run(case, r, rec)
    checks = targets(runs)
    print("\ntargets (one value per run):")
    for name, values in checks.items():
        print(f"  {name}: {values}")
    commit = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=ROOT, capture_output=True, text=True)
    result = {"preset": args.preset, "extra_options": extra, "commit": commit.stdout.strip(), "runs": runs,
              "targets": checks, "time": time.strftime("%Y-%m-%d %H:%M:%S")}
    Path(args.result).write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nwrote {args.result}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
