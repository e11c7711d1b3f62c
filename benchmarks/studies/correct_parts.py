"""Where the correct stage's time goes on two cores (issue 31: the restorer at 30 frames/s).

    PYTHONPATH=. .venv/bin/python benchmarks/studies/correct_parts.py WS [--passes 3]

On a ``watergan run`` workspace ``WS`` with range maps and an RGB-D restorer, on a quiet machine:

- frames per second of :func:`watergan.restore_folder.correct_folder` (the restorer, RGB-D) and
  :func:`pipeline.correct_physics.correct_physics_folder` (the physics correction, RGB-D) with one lane (torch on one
  thread) and with two (torch on two threads: :func:`watergan.restore_folder.cpu_lanes`), ``--passes`` passes each;
- the restorer with two lanes writing no files (its ``_write`` replaced by nothing): what reading the frames and range
  maps, the water's fields and the nets alone allow;
- the physics correction's steps on one thread, milliseconds a frame, over 12 frames after one that builds the
  fields' table (reading the frame and its range map, the inverse, clipping, sRGB encoding, quantising, PNG encoding,
  writing, the mask).

Prints the figures; writes nothing under the workspace (outputs go to a temporary folder).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pipeline.stages import stage_folder


def lanes(ws: Path, passes: int, out: Path) -> None:
    import watergan.restore_folder as pc
    from pipeline.correct import physics_inputs
    from pipeline.correct_physics import correct_physics_folder
    from pipeline.workspace import Workspace

    workspace = Workspace(ws)
    images, ranges = stage_folder(ws, "survey") / "images", stage_folder(ws, "range") / "range"
    frames = len(list(images.glob("*.png")))

    def restorer() -> float:
        return pc.correct_folder(stage_folder(ws, "restorer"), images, out / "restorer", force=True, progress=False,
                                 range_dir=ranges, mode="rgb-d").seconds

    def physics() -> float:
        return correct_physics_folder(physics_inputs(workspace, images), out / "physics", progress=False).seconds

    threads = torch.get_num_threads()
    for n in (1, 2):
        torch.set_num_threads(n)
        for name, run in (("restorer", restorer), ("physics", physics)):
            print(f"{name}, {n} lane(s): frames/s {[round(frames / run(), 1) for _ in range(passes)]}")
    torch.set_num_threads(2)
    write = pc._write
    pc._write = lambda *args, **kwargs: None
    try:
        print(f"restorer, 2 lanes, no files written: frames/s {[round(frames / restorer(), 1) for _ in range(passes)]}")
    finally:
        pc._write = write
        torch.set_num_threads(threads)


def physics_steps(ws: Path, out: Path, frames: int = 12) -> None:
    from eval.tracks import Tracks
    from pipeline.correct_physics import invert_with_fields
    from pipeline.workspace import Workspace
    from watergan.formation import get
    from watergan.io import atomic_write_bytes, encode_png, linear_to_srgb, quantise, read_depth, read_image, write_png
    from watergan.nets.restorer import WaterFields

    workspace = Workspace(ws)
    water = workspace.result("water")
    K = np.asarray(Tracks.load(workspace.path(workspace.result("sfm").tracks)).K, float)
    fields = WaterFields([e for e in water.stack if not get(e["name"]).varies_by_frame()])
    names = sorted(p.name for p in (stage_folder(ws, "survey") / "images").glob("*.png"))[:frames + 1]
    seconds: dict[str, float] = {}

    def lap(step: str, began: float) -> float:
        """Add the time since ``began`` to ``step``; returns now."""
        now = time.perf_counter()
        seconds[step] = seconds.get(step, 0.0) + now - began
        return now

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for k, name in enumerate(names):
            if k == 1:
                seconds.clear()  # the first frame builds the fields' table
            t = time.perf_counter()
            image = read_image(stage_folder(ws, "survey") / "images" / name, dtype=np.float32)
            t = lap("read frame", t)
            range_m = read_depth(stage_folder(ws, "range") / "range" / name)
            t = lap("read range map", t)
            corrected, valid = invert_with_fields(image, range_m, fields, K)
            t = lap("inverse", t)
            rgb = np.clip(np.nan_to_num(corrected, copy=False), 0.0, 1.0, out=corrected)
            t = lap("clip", t)
            srgb = linear_to_srgb(rgb)
            t = lap("sRGB encode", t)
            levels = quantise(srgb, 8)
            t = lap("quantise", t)
            data = encode_png(levels)
            t = lap("PNG encode", t)
            atomic_write_bytes(out / name, data)
            t = lap("write", t)
            write_png(out / f"mask_{name}", np.where(valid, 255, 0).astype(np.uint8))
            lap("mask", t)
    finally:
        torch.set_num_threads(threads)
    for step, s in seconds.items():
        print(f"physics on one thread, {step}: {1000 * s / frames:.1f} ms a frame")
    print(f"physics on one thread, total: {1000 * sum(seconds.values()) / frames:.1f} ms a frame")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--passes", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        lanes(args.workspace, args.passes, Path(tmp))
        physics_steps(args.workspace, Path(tmp))


if __name__ == "__main__":
    main()
