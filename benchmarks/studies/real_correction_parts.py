"""Which part of the physics correction moves Table II and the tile test on a real survey (issue 51).

    PYTHONPATH=. .venv/bin/python benchmarks/studies/real_correction_parts.py WS OUT [--parts gain,full]

On a ``watergan run`` workspace ``WS`` (the pool crawler's, from ``benchmarks/bench_real.py``), the water stage's
stack is inverted exactly (:func:`watergan.formation.inverse.correct_physics`, no signal floor, no gain cap) with
parts of it switched off, at the measured range only (pixels without range written 0), into ``OUT/<part>/``:

- ``gain``: the gains per frame and the camera's gain alone;
- ``gain_field``: and the fields over the image (vignetting, image field);
- ``gain_field_atten``: and the attenuation exp(eta r);
- ``full``: and the veil B_inf (1 - exp(-beta r)).

Prints Table II's consistency (variance of normalised colour across each SfM point's views, every view, x1e-4) for
raw and each part, the labelled objects' median chromaticity spread over raw's (``bench_real.object_constancy``,
the objects of ``benchmarks/data/subvo_objects.json``) with each object's, and the tile test of ``bench_real.py``
(its chromaticity distance of the bands' mean colours: the unranged pixels written 0 add nothing to a band's mean
colour, where they would count as chromaticity 0 in the per-pixel form). Writes nothing under the workspace.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

PARTS = {"gain": {"gain"}, "gain_field": {"gain", "field"}, "gain_field_atten": {"gain", "field", "atten"},
         "full": {"gain", "field", "atten", "veil"}}


def part_stack(stack: list[dict], keep: set[str]) -> list[dict]:
    """The stack's configuration with the parts not in ``keep`` switched off (see the module docstring)."""
    out = []
    for effect in copy.deepcopy(stack):
        name = effect["name"]
        if name == "backscatter" and "veil" not in keep:
            effect["params"]["b_inf"] = [0.0] * 3
        if name == "attenuation" and "atten" not in keep:
            effect["params"]["eta_per_m"] = [0.0] * 3
        if (name == "frame_gain" and "gain" not in keep) or (name in ("image_field", "vignetting")
                                                              and "field" not in keep):
            continue
        out.append(effect)
    return out


def water_inputs(ws) -> tuple[Path, object, list[dict], object, list[str]]:
    """(the survey's images folder, the water stage's result, its stack's configuration, the SfM tracks, the frame
    names in the tracks' order) of a workspace ``ws``."""
    from eval.tracks import Tracks

    water = ws.result("water")
    tracks = Tracks.load(ws.path(ws.result("sfm").tracks))
    return (ws.stage_dir("survey") / "images", water, json.loads(ws.path(water.water_json).read_text())["stack"],
            tracks, [str(n) for n in tracks.image_names])


def main() -> None:
    from bench_real import object_constancy, objects_summary, tile_test

    from eval.colour import consistency
    from pipeline.workspace import Workspace
    from watergan.formation.inverse import correct_physics
    from watergan.io import linear_to_srgb, read_image, read_millimetres, read_scene_mask

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--parts", default=",".join(PARTS))
    args = parser.parse_args()
    ws = Workspace(args.workspace)
    images, water, stack, tracks, names = water_inputs(ws)
    folders = {"raw": images}
    for part in args.parts.split(","):
        folder = args.out / part
        folder.mkdir(parents=True, exist_ok=True)
        folders[part] = folder
        config = part_stack(stack, PARTS[part])
        for k, name in enumerate(names):
            target = folder / f"{Path(name).stem}.png"
            if target.exists():
                continue
            r = read_millimetres(ws.path(ws.result("range").range_dir) / f"{Path(name).stem}.png") / 1000.0
            corrected, _ = correct_physics(read_image(images / name), np.where(r > 0, r, np.nan), config, tracks.K,
                                           frame_index=k)
            srgb = linear_to_srgb(np.clip(np.nan_to_num(corrected, nan=0.0), 0.0, 1.0))
            cv2.imwrite(str(target), np.rint(srgb[..., ::-1] * 255).astype(np.uint8))
    scores = consistency(tracks, folders, 5, 3).scores
    mask = read_scene_mask(ws.stage_dir("survey") / "scene_mask.png")
    objects = objects_summary(object_constancy(ws, folders, names))
    for part, folder in folders.items():
        tiles = tile_test(folder, names, mask)
        print(f"{part:18s} consistency x1e-4 " + " ".join(f"{v * 1e4:.2f}" for v in scores[part].variance) +
              f"   tile distance of the mean colours {tiles['tile_chromaticity_distance_of_mean']:.4f}"
              f"   objects' median spread / raw {objects['median_spread_over_raw'][part]:.3f}")
        print("    " + " ".join(f"{o}={v:.2f}" for o, v in objects["spread_over_raw_per_object"][part].items()))


if __name__ == "__main__":
    main()
