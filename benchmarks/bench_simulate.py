"""Speed of the survey simulator on this machine.

Prints: seconds per rendered 640x480 frame (ray casting, normals, albedo, shading), seconds per
applied full formation stack on one 640x480 frame, and the wall time of ``simulate_survey`` for the
demo preset (with the hidden off-centre vignetting) written to a temporary folder.

Run: .venv/bin/python benchmarks/bench_simulate.py [--repeats N]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from eval.synth import make_config, simulate_survey
from eval.synth.camera import intrinsics_for
from eval.synth.imaging import build_stacks, linear_image, single_torch_thread
from eval.synth.render import frame_state, make_raycaster, render_view
from eval.synth.scene import build_scene
from eval.synth.trajectory import lawnmower


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10, help="frames rendered / stacks applied for the means")
    args = parser.parse_args()
    cfg = make_config("demo", hidden=["vignetting_offcentre"], seed=0)
    intr = intrinsics_for(cfg.camera)
    scene = build_scene(cfg.scene, cfg.seed)
    caster = make_raycaster(scene)
    poses = lawnmower(cfg.trajectory, intr, cfg.seed).world_from_cam
    render_view(caster, scene, intr, poses[0], cfg.render)  # warm-up (texture caches, thread pools)

    start = time.perf_counter()
    views = [render_view(caster, scene, intr, poses[k % len(poses)], cfg.render) for k in range(args.repeats)]
    per_frame = (time.perf_counter() - start) / args.repeats

    _, _, full = build_stacks(cfg.formation.visible, cfg.formation.hidden)
    state = frame_state(views[0], 0, cfg.render.site_depth_m)
    with single_torch_thread():  # as simulate_survey runs it
        linear_image(full, state)
        start = time.perf_counter()
        for _ in range(args.repeats):
            linear_image(full, state)
        per_stack = (time.perf_counter() - start) / args.repeats

    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        result = simulate_survey(Path(tmp) / "demo", cfg, progress=False)
        total = time.perf_counter() - start

    print(f"render 640x480 frame:        {per_frame:.3f} s/frame (mean of {args.repeats})")
    print(f"full stack on 640x480 frame: {per_stack:.4f} s ({' -> '.join(full.names)})")
    print(f"simulate demo preset:        {total:.1f} s ({result.frames} frames, stereo={result.stereo}, "
          f"{result.n_rgbd} RGB-D views)")


if __name__ == "__main__":
    main()
