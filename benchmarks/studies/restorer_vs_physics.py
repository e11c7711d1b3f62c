"""A trained restorer against the physics correction on one workspace, and the floor its training pairs allow.

    .venv/bin/python benchmarks/studies/restorer_vs_physics.py --workspace WS [--model DIR] [--out DIR]

1. Corrects the survey's frames with the restorer in ``--model`` (default: the workspace's ``06_restorer``;
   an RGB-D restorer takes the range stage's maps) into ``--out`` and prints frames per second, then
   the board CIEDE2000 and the consistency per channel (:func:`eval.colour.board_accuracy`,
   :func:`eval.colour.consistency`, as the eval stage measures them) of raw, the restorer and the physics
   correction (``07_correct/physics/images``). Needs a simulated survey (the board's truth).
2. Inverts the site water exactly (:func:`watergan.formation.inverse.correct_physics` with the gan stage's
   ``stack.json``) on the first 20 of the gan stage's training pairs (``05_gan/generated``: underwater, range,
   in-air) and prints
   the RMSE (stored sRGB) against the in-air images: what a restorer trained on those 8-bit pairs could reach.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from eval.colour import board_accuracy, consistency, truth_board
from eval.tracks import Tracks
from pipeline.stages import STAGES, stage_folder
from watergan.formation.inverse import correct_physics
from watergan.io import linear_to_srgb, read_depth, read_image
from watergan.restore_folder import correct_folder


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workspace", required=True)
    parser.add_argument("--model", default=None, help=f"restorer folder (default: WS/{STAGES['restorer'].folder})")
    parser.add_argument("--out", default="/tmp/restorer_vs_physics")
    args = parser.parse_args()
    ws, out = Path(args.workspace), Path(args.out)
    model = Path(args.model) if args.model else stage_folder(ws, "restorer")

    r = correct_folder(model, stage_folder(ws, "survey") / "images", out, force=True, progress=False,
                       range_dir=stage_folder(ws, "range") / "range")
    print(f"corrected {r.corrected} frames in {r.seconds:.1f} s = {r.corrected / r.seconds:.1f} frames/s "
          f"({r.mode} mode)")
    board = truth_board(stage_folder(ws, "survey"))
    folders = {"raw": stage_folder(ws, "survey") / "images", "restorer": out / "images",
               "physics": stage_folder(ws, "correct") / "physics" / "images"}
    cons = consistency(Tracks.load(stage_folder(ws, "sfm") / "tracks.npz"), folders)
    for name, path in folders.items():
        print(f"{name:9} board CIEDE2000 {board_accuracy(path, board).mean_ciede2000:6.3f}  consistency "
              + " ".join(f"{v:.2e}" for v in cons.scores[name].variance))

    pairs = stage_folder(ws, "gan") / "generated"
    stack = json.loads((stage_folder(ws, "gan") / "model" / "stack.json").read_text())
    errors = []
    for item in json.loads((pairs / "manifest.json").read_text())["items"][:20]:
        inverted, valid = correct_physics(read_image(pairs / item["underwater"]), read_depth(pairs / item["range"]),
                                          stack)
        diff = linear_to_srgb(np.clip(inverted, 0, 1)) - linear_to_srgb(read_image(pairs / item["inair"]))
        errors.append((diff[valid] ** 2).mean(0))
    print("exact inverse of the site water on the training pairs, RMSE (stored sRGB) R G B:",
          np.sqrt(np.mean(errors, 0)).round(4).tolist())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
