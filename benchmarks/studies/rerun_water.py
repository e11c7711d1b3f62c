"""Rerun a finished workspace's water, physics correction and evaluation with the code on PYTHONPATH, into a new
workspace that copies the old one's survey, SfM and dense stages (the old workspace is not touched; WaterGAN and
the restorer are not retrained, so only the physics correction is evaluated, beside raw and the oracle).

    PYTHONPATH=. .venv/bin/python benchmarks/studies/rerun_water.py OLD_WS NEW_WS [--field-degree N]

Prints the water stage's summary and seconds, and the evaluation's board CIEDE2000 and consistency per method;
writes them to NEW_WS/metrics.json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from dataclasses import replace
from pathlib import Path

from pipeline.stages import stage_folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--field-degree", type=int, help="the fields' degree (default: WaterConfig's)")
    args = parser.parse_args()
    if args.new.exists():
        raise SystemExit(f"{args.new} exists: give a new folder")
    args.new.mkdir(parents=True)
    for stage in ("survey", "sfm", "dense"):
        shutil.copytree(stage_folder(args.old, stage), stage_folder(args.new, stage))
    for f in args.old.iterdir():
        if f.is_file():
            shutil.copy(f, args.new / f.name)

    from pipeline.correct import CorrectStage
    from pipeline.evaluate import EvaluateConfig
    from pipeline.range import RangeConfig
    from pipeline.water import WaterStage
    from pipeline.workspace import Workspace

    ws = Workspace(args.new)
    config = WaterStage(progress=False)
    if args.field_degree is not None:
        config = replace(config, field_degree=args.field_degree)
    ws.run("range", RangeConfig(progress=False))
    began = time.perf_counter()
    water = ws.run("water", config)
    print(f"water stage {time.perf_counter() - began:.1f} s: {water.summary}", flush=True)
    ws.run("correct", CorrectStage(progress=False))
    result = ws.run("eval", EvaluateConfig(methods=("raw", "oracle"), progress=False))
    metrics = {"board": result.mean_board_ciede2000, "consistency": result.consistency_variance}
    print(json.dumps(metrics))
    (args.new / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")


if __name__ == "__main__":
    main()
