"""The water estimate on one workspace's SfM and dense results, without the stage machinery: the fit alone, so that
two versions of the code (or two settings) can be compared on the same geometry.

    PYTHONPATH=. .venv/bin/python benchmarks/studies/water_on_workspace.py WS [--sfm 01_sfm] [--dense 02_dense]
        [--field-degree N] [--max-points N] [--sample-seed S] [--out water.json] [--table table.npz]

Reads ``WS/00_survey`` (images, the simulator's board truth, survey.json's lights), the SfM stage's tracks.npz and
result.json (its scale spread) and the dense stage's depth maps and fused mesh (the fine grid's table, as the water
stage's); estimates the water with the default
:class:`eval.water.WaterConfig` (``--field-degree``: the fields over the image, ``image_field``, of that degree; 0
none; ``--max-points``/``--sample-seed``: the measurement's bound on the points and the seed of their draw) and the
truth's board, measuring normals as the water stage does; prints the one-line summary (and, on a simulated survey,
each parameter's relative error and coverage against the truth, :func:`bench_water.compare`) and writes
``water.json``'s content to ``--out`` (and the measurement table to ``--table``). Older workspaces (folders 04_sfm,
05_dense) are read with ``--sfm`` / ``--dense``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_water import compare, truth_params  # noqa: E402

from eval.colour import truth_board
from eval.observations import DenseMeasureConfig
from eval.tracks import Tracks
from eval.water import WaterConfig, estimate_water
from pipeline.range import water_frames
from pipeline.stages import STAGES, stage_folder  # noqa: E402
from pipeline.water import fine_grid_frames, survey_lights


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--sfm", default=STAGES["sfm"].folder, help="the SfM stage's folder")
    parser.add_argument("--dense", default=STAGES["dense"].folder, help="the dense stage's folder")
    parser.add_argument("--range", default=STAGES["range"].folder, help="the range stage's folder")
    parser.add_argument("--field-degree", type=int, default=WaterConfig().field_degree,
                        help="the fields' degree (0: none)")
    parser.add_argument("--max-points", type=int, default=DenseMeasureConfig().max_points,
                        help="points lifted over the survey at most")
    parser.add_argument("--sample-seed", type=int, default=DenseMeasureConfig().seed, help="seed of the points' draw")
    parser.add_argument("--out", type=Path, default=Path("water.json"), help="where to write the estimate")
    parser.add_argument("--table", type=Path, help="where to write the measurement table (npz)")
    args = parser.parse_args()
    ws = args.workspace
    record = json.loads((ws / args.sfm / "result.json").read_text())
    sfm = record.get("result", record)
    survey = stage_folder(ws, "survey")
    tracks = Tracks.load(ws / args.sfm / "tracks.npz")
    frames = water_frames(tracks, survey / "images", ws / args.dense / "depth")
    config = replace(WaterConfig(), range_scale_sd=float(sfm["scale_spread"]), field_degree=args.field_degree)
    config = replace(config, measure=replace(config.measure, max_points=args.max_points, seed=args.sample_seed))
    K, lights = np.asarray(tracks.K, float), survey_lights(survey)
    grid_frames = fine_grid_frames(frames, K, ws / args.range / "range", config, lights)
    estimate = estimate_water(frames, K, board=truth_board(survey), config=config, lights=lights, normals=True,
                              grid_frames=grid_frames)
    print(estimate.summary())
    if (survey / "truth" / "effects.json").is_file():
        for key, row in compare(estimate.params, truth_params(survey)).items():
            print(f"  {key}: relative error {row['rel_error']}, covered {row.get('covered')}")
    args.out.write_text(json.dumps(estimate.to_json(), default=str) + "\n")
    if args.table:
        estimate.observations.save(args.table)


if __name__ == "__main__":
    main()
