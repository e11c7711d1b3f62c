"""What the evaluation's targets ask of a correction, on a simulated survey: the oracle inversion with one of
its two inputs (the water, the range) replaced by what a real method has.

    .venv/bin/python benchmarks/studies/oracle_limits.py --workspace WS [--out DIR]

WS: a workspace of a simulated survey (``00_survey/truth``, ``01_sfm``, ``02_dense``; ``05_gan/model/stack.json``
and ``04_water`` when they ran). Every survey frame is inverted exactly, pixel by pixel, as the oracle of
:mod:`eval.baselines` does, with:

- the true stack and the true range (the oracle itself);
- the true stack and the dense stage's range (stereo/MVS, as the Jaffe-McGlamery and Sea-thru baselines get);
- the true stack and a flat-seafloor range, r = nav altitude |K^-1 (x, y, 1)| (all that a monocular
  correction knows for sure from the navigation);
- the true range and the true stack with WaterGAN's learned attenuation (eta), then also its gain and
  vignetting (the water a restorer trained on WaterGAN's pairs learns; the GAN's backscatter is a
  learned convolution with no counterpart in the true stack, so the true one is kept);
- the water stage's estimated stack (``04_water``) and the dense range: what the physics correction
  does, with the oracle's true geometry for everything but the range (rows left out when the workspace
  lacks the gan or the water stage).

For each it prints the mean colour-board distance (|n(measured) - n(true)|, n = c / (R + G + B), as
Table I), the CIEDE2000, and the colour consistency across views on the SfM points (as Table II).
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import numpy as np
import torch

from eval.baseline_runs import OracleGeometry, fill_nearest
from eval.baselines import oracle
from eval.colour import board_accuracy, consistency, truth_board
from eval.tracks import Tracks
from pipeline.stages import stage_folder
from watergan.data import read_depth, read_image, read_nav_altitudes, write_srgb8
from watergan.formation import Stack
from watergan.io import z_to_range


def with_learned(true_config: list[dict], learned: dict[str, dict], names: tuple[str, ...]) -> list[dict]:
    """The true stack configuration with the learned parameters of the effects ``names`` put in."""
    config = copy.deepcopy(true_config)
    for effect in config:
        if effect["name"] in names and effect["name"] in learned:
            effect["params"].update({k: v for k, v in learned[effect["name"]].items() if k in effect["params"]})
    return config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workspace", required=True, type=Path)
    parser.add_argument("--out", type=Path, default=Path("/tmp/oracle_limits"), help="inverted frames")
    args = parser.parse_args()
    ws = args.workspace
    survey = stage_folder(ws, "survey").resolve()
    gan_stack = stage_folder(ws, "gan") / "model" / "stack.json"
    learned = {e["name"]: e["params"] for e in json.loads(gan_stack.read_text())} if gan_stack.is_file() else {}
    water = stage_folder(ws, "water") / "result.json"
    estimated = json.loads(water.read_text())["result"]["stack"] if water.is_file() else None
    geometry = OracleGeometry(survey)
    board = truth_board(survey)
    tracks = Tracks.load(stage_folder(ws, "sfm") / "tracks.npz")
    names = sorted({str(tracks.image_names[k]) for k in tracks.obs_image} | set(board.quads))
    nav = read_nav_altitudes(survey / "survey.json", names)
    intr = geometry.intr
    K = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]])
    true_config = geometry.truth.effects["full"]

    def dense_range(name: str, shape: tuple[int, int]) -> np.ndarray:
        z = read_depth(stage_folder(ws, "dense") / "depth" / f"{Path(name).stem}.png")
        return fill_nearest(z_to_range(np.where(z > 0, z, np.nan), K)).reshape(shape)

    def plane_range(name: str, shape: tuple[int, int]) -> np.ndarray:
        return z_to_range(np.full(shape, nav[name]), K)

    variants = [("oracle: true water, true range", "oracle", (), None, None),
                ("true water, dense range", "dense_range", (), dense_range, None),
                ("true water, flat seafloor at nav altitude", "plane_range", (), plane_range, None)]
    if learned:
        variants += [("GAN's eta, true range", "gan_eta", ("attenuation",), None, None),
                     ("GAN's eta, gain, vignetting, true range", "gan_eta_gain_vignetting",
                      ("attenuation", "gain", "vignetting"), None, None)]
    if estimated:
        variants.append(("estimated water, dense range", "estimated_water_dense_range", (), dense_range, estimated))
    folders = {}
    for label, folder_name, effects, range_fn, config in variants:
        stack = Stack.from_config(config or with_learned(true_config, learned, effects))
        folders[label] = folder = args.out / folder_name
        folder.mkdir(parents=True, exist_ok=True)
        for name in names:
            state = geometry.state(name)
            if range_fn is not None:
                r = torch.from_numpy(range_fn(name, tuple(state.range_m.shape[-2:]))).float()[None, None]
                state = state.replace(range_m=r)
            write_srgb8(folder / name, oracle(read_image(survey / "images" / name), state, stack))
        result = board_accuracy(folder, board)
        print(f"{label:>42}: board mean distance {result.mean_distance:.4f}, CIEDE2000 {result.mean_ciede2000:.2f}")
    scores = consistency(tracks, {"raw": survey / "images", **folders})
    print(f"consistency on {scores.n_points} points (variance of c/(R+G+B) across views), R G B:")
    for label, score in scores.scores.items():
        print(f"{label:>42}: {' '.join(f'{v:.2e}' for v in score.variance)}")
    if learned:
        print("WaterGAN's:", json.dumps({k: learned[k] for k in ("attenuation", "gain", "vignetting") if k in learned}))


if __name__ == "__main__":
    main()
