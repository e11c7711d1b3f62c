"""Monocular depth against the planes, per survey: does a depth net beat a flat seafloor where the scene has relief?

    .venv/bin/python benchmarks/bench_depth.py NAME=WORKSPACE [NAME=WORKSPACE ...] [--steps 600] [--json F]

Each WORKSPACE is a finished ``watergan run`` (its survey, dense depth and, for the first row, the restorer's
depth maps). For each it measures, against the dense stage's stereo/MVS depth (:func:`eval.depth.
compare_depth_folders`: over all pixels and over relief pixels, more than 5 cm from the frame's best plane):

- ``restorer``: the restorer's depth net (relative depth, trained on WaterGAN's pairs), aligned by a scale per
  frame, beside the flat seafloor under the same alignment: every frame (the net never saw the survey's);
- ``site_net``: the site depth net (:mod:`watergan.nets.site_depth`: a factor on the flat seafloor's depth)
  trained on the survey's own frames with dense depth as the restorer stage trains it
  (:func:`pipeline.site_depth.fit_site_depth`, ``--steps`` steps, into the scratch folder), measured metric on the
  held-out frames (every 4th, never trained on) beside the flat seafloor at the navigation's altitude and attitude as
  it is: what monocular correction would take.

``relief_rmse_ratio`` of a survey is the site net's RMSE on relief pixels over the flat seafloor's (held-out frames,
both metric); ``restorer_relief_rmse_ratio`` the restorer's net's over the flat seafloor's on the same frames, both
aligned by a scale per frame. ``monocular_correction``: the restorer's monocular correction with the flat seafloor
and with the site net, consistency and board beside its RGB-D correction's (:func:`monocular_correction`). Writes
``benchmarks/results/depth.json``
(or ``--json``). One torch job at a time: the training time is reported.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from dataclasses import asdict
from pathlib import Path

import torch

from eval.colour import ColourEvalConfig
from eval.depth import DepthCompareConfig, Navigation, compare_depth_folders
from pipeline.evaluate import run_colour_eval
from pipeline.site_depth import fit_site_depth
from pipeline.workspace import Workspace
from watergan.restore_folder import correct_folder
from watergan.train_site_depth import SiteDepthConfig

ROOT = Path(__file__).resolve().parents[1]  # the repository: result files name paths relative to it


def _summary(result) -> dict:
    return {"relief_rmse_ratio": result.relief_rmse_ratio, "all_rmse_ratio": result.all_rmse_ratio,
            "ratio_to": result.ratio_to, "relief_fraction": result.relief_fraction, "frames": len(result.per_image),
            "sources": {name: asdict(m) for name, m in result.sources.items()}}


def bench_survey(ws: Workspace, out: Path, steps: int) -> dict:
    survey = ws.stage_dir("survey")
    dense = ws.path(ws.require("dense", "the depth benchmark").depth_dir)
    nav = Navigation.from_survey(survey / "survey.json")
    if nav is None or not nav.altitude_m:
        raise SystemExit(f"{ws.root}: the survey has no camera.json or no nav_altitude_m")
    record: dict = {"workspace": os.path.relpath(ws.root, ROOT)}  # relative to the repository's root
    correct = ws.result("correct")
    if correct is not None and correct.depth:
        pred = ws.path(correct.depth)
        record["restorer"] = _summary(compare_depth_folders(pred, dense, out / "restorer",
                                                            DepthCompareConfig(pred_dir=str(pred)), nav))

    site = fit_site_depth(ws, SiteDepthConfig(steps=steps), out / "site_net")
    if "relief_rmse_ratio" not in site:
        raise SystemExit(f"{ws.root}: no site depth net: {site['why']}")
    held = json.loads((out / "site_net" / site["metrics"]).read_text())
    record["site_net"] = {**{k: site[k] for k in ("use", "why", "steps", "seconds", "loss", "held_out_frames")},
                          "train_frames": len(site["train"]), "sources": held["sources"],
                          "relief_rmse_ratio": held["relief_rmse_ratio"], "all_rmse_ratio": held["all_rmse_ratio"],
                          "relief_fraction": held["relief_fraction"]}
    if "restorer" in record:  # the restorer's net on the same held-out frames
        pred = out / "restorer_held" / "pred"
        pred.mkdir(parents=True, exist_ok=True)
        for name in site["held_out"]:
            source = ws.path(correct.depth) / f"{Path(name).stem}.npy"
            if source.is_file():
                shutil.copyfile(source, pred / source.name)
        record["restorer_relief_rmse_ratio"] = compare_depth_folders(
            pred, dense, out / "restorer_held", DepthCompareConfig(pred_dir=str(pred)), nav).relief_rmse_ratio
    record["relief_rmse_ratio"] = held["relief_rmse_ratio"]
    if correct is not None and correct.images:
        record["monocular_correction"] = monocular_correction(ws, out, correct)
    return record


def monocular_correction(ws: Workspace, out: Path, correct) -> dict:
    """The restorer's monocular correction with the flat seafloor and with the site net (forced on, whatever its
    record says: a copy of the restorer's folder), beside its RGB-D correction and raw, on the same SfM points and
    board: consistency per channel and board CIEDE2000, and their ratios to the RGB-D correction's."""
    model = ws.folder("restorer")
    site_model = out / "site_model"
    site_model.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(model / "restorer.pt", site_model / "restorer.pt")
    shutil.copyfile(out / "site_net" / "site_depth.pt", site_model / "site_depth.pt")
    record = json.loads((out / "site_net" / "site_depth.json").read_text())
    (site_model / "site_depth.json").write_text(json.dumps({**record, "use": True}))
    images = ws.folder("survey") / "images"
    began = {}
    for name, folder in (("floor", model), ("site", site_model)):
        began[name] = time.perf_counter()
        result = correct_folder(folder, images, out / f"mono_{name}", force=True, progress=False, mode="monocular")
        began[name] = result.corrected / (time.perf_counter() - began[name])
    folders = (f"raw={images}", f"rgbd={ws.path(correct.images)}", f"floor={out / 'mono_floor' / 'images'}",
               f"site={out / 'mono_site' / 'images'}")
    colour = run_colour_eval(ws, ColourEvalConfig(folders=folders, truth_dir=str(ws.folder("survey"))),
                             out / "colour")
    scores = {n: list(v.variance) for n, v in colour.consistency.scores.items()}
    board = {n: b.mean_ciede2000 for n, b in colour.board.items()}
    return {"consistency": scores, "board_ciede2000": board, "frames_per_s": began,
            "consistency_over_rgbd": {n: [a / b for a, b in zip(scores[n], scores["rgbd"], strict=True)]
                                      for n in ("floor", "site")},
            "board_over_rgbd": {n: board[n] / board["rgbd"] for n in ("floor", "site")} if board else {},
            "note": "over all frames: the site net trained on 3 of every 4 of them"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("surveys", nargs="+", help="NAME=WORKSPACE")
    parser.add_argument("--steps", type=int, default=SiteDepthConfig.steps, help="site depth net training steps")
    parser.add_argument("--out", default="/tmp/bench_depth", help="scratch folder for the comparisons")
    parser.add_argument("--json", default=str(Path(__file__).resolve().parent / "results" / "depth.json"))
    args = parser.parse_args()
    torch.set_num_threads(2)
    results = {}
    for item in args.surveys:
        name, _, path = item.partition("=")
        began = time.perf_counter()
        results[name] = bench_survey(Workspace(path), Path(args.out) / name, args.steps)
        r = results[name]
        site = r["site_net"]["sources"]
        print(f"{name}: site net (held-out, metric) relief RMSE {site['depth net']['relief']['rmse_m']:.4f} m vs "
              f"flat seafloor {site['flat seafloor']['relief']['rmse_m']:.4f} m: {r['relief_rmse_ratio']:.2f}x "
              f"(all pixels {r['site_net']['all_rmse_ratio']:.2f}x); restorer's net (aligned) "
              f"{r.get('restorer_relief_rmse_ratio', float('nan')):.2f}x; {time.perf_counter() - began:.0f} s",
              flush=True)
        mono = r.get("monocular_correction")
        if mono:
            for n in ("floor", "site"):
                c = ", ".join(f"{v:.2f}" for v in mono["consistency_over_rgbd"][n])
                print(f"  monocular correction, {n}: consistency R/G/B {c}x the RGB-D correction's, board "
                      f"{mono['board_over_rgbd'].get(n, float('nan')):.2f}x; {mono['frames_per_s'][n]:.1f} frames/s")
    Path(args.json).write_text(json.dumps({"command": " ".join(["benchmarks/bench_depth.py", *sys.argv[1:]]),
                                           "threads": torch.get_num_threads(), "surveys": results}, indent=1) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
