"""Incremental mapping alone on an SfM stage's matched database, with the stage's mapper options and one change at a
time: seconds, images registered and the cameras' error against the simulator's truth.

    PYTHONPATH=. .venv/bin/python benchmarks/studies/sfm_mapping.py WS/01_sfm/database.db SURVEY
        [--variants colmap,stage,growth14,growth20,redundant] [--out /tmp/sfm_mapping]

Each variant runs ``pycolmap.incremental_mapping`` on the database (features and matches as the stage left them) with
:func:`pipeline.sfm._incremental_options` (the stage's options) and the variant's changes: ``colmap`` puts back
COLMAP's defaults for the global bundle adjustment (growth 1.1, redundant points kept); ``growth14``/``growth20``:
that with the global adjustment at 40 % / 100 % growth; ``redundant``: that with the redundant points left out;
``stage``: the stage's own options. The registered cameras' centres are compared with ``SURVEY/truth`` after a
similarity (:func:`pipeline.scale.similarity_align`): RMS and largest error as a share of the true centres' extent.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

from eval.synth import load_truth
from pipeline.colmap import colmap_errors_only
from pipeline.scale import similarity_align
from pipeline.sfm import SfmConfig, _incremental_options

COLMAP = {"ba_global_frames_ratio": 1.1, "ba_global_points_ratio": 1.1,
          "mapper.ba_global_ignore_redundant_points3D": False}
VARIANTS = {
    "colmap": COLMAP,
    "growth14": {**COLMAP, "ba_global_frames_ratio": 1.4, "ba_global_points_ratio": 1.4},
    "growth20": {**COLMAP, "ba_global_frames_ratio": 2.0, "ba_global_points_ratio": 2.0},
    "redundant": {**COLMAP, "mapper.ba_global_ignore_redundant_points3D": True},
    "stage": {},
}


def options_for(variant: str, cam: dict):
    """The stage's incremental options with the variant's changes ("a.b": nested option b of a)."""
    options = _incremental_options(cam, SfmConfig())
    for key, value in VARIANTS[variant].items():
        *parents, name = key.split(".")
        target = options
        for parent in parents:
            target = getattr(target, parent)
        setattr(target, name, value)
    return options


def main() -> None:
    import pycolmap

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("database", type=Path)
    parser.add_argument("survey", type=Path)
    parser.add_argument("--variants", default="colmap,stage")
    parser.add_argument("--out", type=Path, default=Path("/tmp/sfm_mapping"))
    args = parser.parse_args()
    truth = load_truth(args.survey)
    index = {name: k for k, name in enumerate(truth.frames)}
    cam = json.loads((args.survey / "camera.json").read_text())
    for variant in args.variants.split(","):
        out = args.out / variant
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        began = time.perf_counter()
        with colmap_errors_only():
            models = pycolmap.incremental_mapping(args.database, args.survey / "images", out, options_for(variant, cam))
        seconds = time.perf_counter() - began
        rec = max(models.values(), key=lambda r: r.num_reg_images())
        images = list(rec.images.values())
        est = np.array([image.projection_center() for image in images])
        true = truth.world_from_cam[[index[image.name] for image in images], :3, 3]
        s, R, t = similarity_align(est, true)
        error = np.linalg.norm(s * est @ R.T + t - true, axis=1)
        extent = float(np.linalg.norm(true.max(0) - true.min(0)))
        print(f"{variant:10} {seconds:7.1f} s  registered {rec.num_reg_images()}  centres RMS "
              f"{100 * np.sqrt(np.mean(error**2)) / extent:.3f} % max {100 * error.max() / extent:.3f} % of the extent",
              flush=True)


if __name__ == "__main__":
    main()
