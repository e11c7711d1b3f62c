"""Speed of the survey simulator on this machine.

Prints, per preset: seconds per rendered frame (ray casting, normals, albedo, shading), seconds per
applied full formation stack on one frame, and the wall time of ``simulate_survey`` (with the hidden
off-centre vignetting, as ``watergan demo`` simulates it) written to a temporary folder; the load average
before each run (other processes on the machine slow it). Writes ``benchmarks/results/simulate.json``.

Run: .venv/bin/python benchmarks/bench_simulate.py [--presets demo,reef,auv] [--repeats N]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from eval.synth import PRESETS, make_config, simulate_survey
from eval.synth.camera import intrinsics_for
from eval.synth.imaging import build_stacks, linear_image
from eval.synth.render import frame_state, make_raycaster, render_view
from eval.synth.scene import build_scene
from eval.synth.trajectory import lawnmower
from watergan.device import single_torch_thread

HIDDEN = ["vignetting_offcentre"]


def bench_preset(name: str, repeats: int) -> dict:
    cfg = make_config(name, hidden=HIDDEN, seed=0)
    intr = intrinsics_for(cfg.camera)
    scene = build_scene(cfg.scene, cfg.seed)
    caster = make_raycaster(scene)
    poses = lawnmower(cfg.trajectory, intr, cfg.seed).world_from_cam
    render_view(caster, scene, intr, poses[0], cfg.render)  # warm-up (texture caches, thread pools)

    start = time.perf_counter()
    views = [render_view(caster, scene, intr, poses[k % len(poses)], cfg.render) for k in range(repeats)]
    per_frame = (time.perf_counter() - start) / repeats

    _, _, full = build_stacks(cfg.formation.visible, cfg.formation.hidden)
    state = frame_state(views[0], 0, cfg.render.site_depth_m)
    with single_torch_thread():  # as simulate_survey runs it
        linear_image(full, state)
        start = time.perf_counter()
        for _ in range(repeats):
            linear_image(full, state)
        per_stack = (time.perf_counter() - start) / repeats

    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        result = simulate_survey(Path(tmp) / name, cfg, progress=False)
        total = time.perf_counter() - start
    print(f"{name}: render {intr.width}x{intr.height} frame {per_frame:.3f} s/frame (mean of {repeats}); "
          f"full stack {per_stack:.4f} s ({' -> '.join(full.names)})")
    print(f"{name}: simulate {total:.1f} s ({result.frames} frames, stereo={result.stereo}, {result.n_rgbd} RGB-D "
          f"views; 1-min load average before: {load:.2f})")
    return {"render_s_per_frame": round(per_frame, 4), "stack_s_per_frame": round(per_stack, 5),
            "simulate_s": round(total, 2), "frames": result.frames, "width": result.width, "height": result.height,
            "stereo": result.stereo, "rgbd_views": result.n_rgbd, "hidden": HIDDEN, "load_average_before": load}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", default="demo,reef,auv", help=f"comma-separated, of {', '.join(PRESETS)}")
    parser.add_argument("--repeats", type=int, default=10, help="frames rendered / stacks applied for the means")
    parser.add_argument("--json", type=Path, default=Path(__file__).parent / "results" / "simulate.json")
    args = parser.parse_args(argv)
    results = {name: bench_preset(name, args.repeats) for name in args.presets.split(",")}
    command = "benchmarks/bench_simulate.py " + " ".join(argv if argv is not None else sys.argv[1:])
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"command": command, "cpus": os.cpu_count(), "presets": results}, indent=2) + "\n")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
