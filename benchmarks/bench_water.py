"""Site water from the survey's own geometry (issue 17): the estimate against the simulator's truth, and the
physics correction with the dense range against the oracle.

    .venv/bin/python benchmarks/bench_water.py [--out DIR] [--surveys demo0,demo1,mono0] [--bootstrap N]

For each survey (``demo0``/``demo1``: the demo preset with nothing hidden, seeds 0 and 1; ``mono0``: the demo
without the right camera, scale from the navigation altitude, dense range from SfM neighbours) it simulates the
survey, runs the pipeline's SfM and dense stages on it (reused when present), estimates the water with
:func:`eval.water.estimate_water` from the raw frames, the SfM poses, the dense range and the board (pixel
quads from the SfM poses) and prints per parameter the estimate, the truth (``truth/effects.json``), the
relative error and whether the 95 % interval covers the truth. Then it corrects every frame with
:func:`eval.water.correct_physics` (dense range, pixels without range filled with the nearest valid pixel's
range, as the evaluation does for the range-based baselines; the filled fraction is printed) and measures
board CIEDE2000 (:func:`eval.colour.board_accuracy`), consistency per channel on the SfM tracks
(:func:`eval.colour.consistency`) and PSNR against the in-air truth (:func:`eval.tables.fidelity`), beside the
oracle (:func:`eval.baselines.oracle`, the true stack and the true geometry) and the true stack with the dense
range. Writes ``benchmarks/results/water.json``.

The RGB-D training set of the preset is shrunk to one view (the water estimate does not read it).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

SURVEYS = {
    "demo0": {"seed": 0, "stereo": True},
    "demo1": {"seed": 1, "stereo": True},
    "mono0": {"seed": 0, "stereo": False},
}


def prepare(root: Path, name: str) -> Path:
    """Simulate the survey ``name`` into ``root/name/00_survey`` and run SfM and dense (each skipped when done)."""
    from eval.synth import make_config, simulate_survey
    from pipeline.dense import DenseConfig, run_dense
    from pipeline.sfm import SfmConfig, run_sfm
    from pipeline.workspace import Workspace

    spec = SURVEYS[name]
    ws = Workspace(root / name)
    survey = ws.stage_dir("survey")
    if not (survey / "truth" / "config.json").is_file():
        cfg = make_config("demo", seed=spec["seed"])
        cfg = replace(cfg, trajectory=replace(cfg.trajectory, stereo=spec["stereo"]),
                      rgbd=replace(cfg.rgbd, n_scenes=1, views_per_scene=1))
        simulate_survey(survey, cfg, force=True, progress=False)
    ws.run("sfm", SfmConfig(), run_sfm)
    ws.run("dense", DenseConfig(progress=False), run_dense)
    return ws.root


def load_inputs(ws_root: Path):
    """(frames, K, tracks, board, sfm Tracks) of a prepared workspace: raw linear frames, dense range (camera z
    from ``05_dense/depth`` as ray length; 0 = none stays NaN), SfM poses; the board's pixel quads projected
    with the true poses (what a user's board file with detected corners gives)."""
    from eval.colour import truth_board
    from eval.depth import read_depth
    from eval.tables import z_to_range
    from eval.water import SparseTracks, WaterFrame
    from pipeline.sfm import Tracks
    from watergan.data import read_image

    survey = ws_root / "00_survey"
    tracks = Tracks.load(ws_root / "04_sfm" / "tracks.npz")
    K = np.asarray(tracks.K, float)
    frames = []
    for k, name in enumerate(str(n) for n in tracks.image_names):
        path = ws_root / "05_dense" / "depth" / f"{Path(name).stem}.png"
        image = read_image(survey / "images" / name).astype(np.float32)
        if path.is_file():
            z = read_depth(path)
            r = z_to_range(np.where(z > 0, z, np.nan), K).astype(np.float32)
        else:
            r = np.full(image.shape[:2], np.nan, np.float32)
        pose = tracks.world_from_cam[k] if tracks.registered[k] else None
        frames.append(WaterFrame(name=name, image=image, range_m=r, world_from_cam=pose))
    sparse = SparseTracks(xyz=tracks.xyz, obs_point=tracks.obs_point, obs_frame=tracks.obs_image,
                          obs_xy=tracks.obs_xy)
    return frames, K, sparse, truth_board(survey), tracks


if __name__ == "__main__" and __import__("sys").argv[1:2] == ["--prepare-only"]:
    import sys

    for n in sys.argv[3].split(","):
        t = time.perf_counter()
        prepare(Path(sys.argv[2]), n)
        print(n, "prepared in", round(time.perf_counter() - t, 1), "s", flush=True)
