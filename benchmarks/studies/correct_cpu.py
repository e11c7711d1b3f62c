"""The correct stage's processor time per frame (issue 31: what bounds each correction on two cores).

    PYTHONPATH=. .venv/bin/python benchmarks/studies/correct_cpu.py WS [--rounds 2] [--mode rgb-d]

``WS``: a ``watergan run`` workspace with range maps and an RGB-D restorer, e.g. the dive that
``bench_restorer.py --copies N`` builds (``OUT/replica/workspace``). On a quiet machine, ``--rounds`` rounds of: the
physics correction, the restorer with batches of 4 and the restorer with the stage's default batch
(:func:`watergan.restore_folder.batch_for`), each printed as frames per second and the process's CPU time per frame over
every thread (``resource.getrusage``), with the ceiling that CPU time allows on the machine's cores. Outputs go to a
temporary folder.
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

from pipeline.stages import stage_folder


def cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    import watergan.restore_folder as pc
    from pipeline.correct import physics_inputs
    from pipeline.correct_physics import correct_physics_folder
    from pipeline.workspace import Workspace

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--mode", default="rgb-d", choices=["rgb-d", "monocular"])
    args = parser.parse_args()
    ws = args.workspace
    images, ranges = stage_folder(ws, "survey") / "images", stage_folder(ws, "range") / "range"
    frames = len(list(images.iterdir()))
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as tmp:
        inputs = physics_inputs(Workspace(ws), images)
        runs = {"physics": lambda: correct_physics_folder(inputs, Path(tmp) / "physics", progress=False,
                                                          mode=args.mode)}
        for batch in (4, 0):
            runs[f"restorer, batch {batch or 'default'}"] = (
                lambda b=batch: pc.correct_folder(stage_folder(ws, "restorer"), images, Path(tmp) / "restorer",
                                                  force=True, progress=False, range_dir=ranges, mode=args.mode,
                                                  batch_size=b))
        for _ in range(args.rounds):
            for name, run in runs.items():
                cpu0, began = cpu_s(), time.perf_counter()
                run()
                cpu, wall = cpu_s() - cpu0, time.perf_counter() - began
                print(f"{name}: {frames / wall:.1f} frames/s, CPU {1000 * cpu / frames:.1f} ms a frame, ceiling on "
                      f"{cores} cores {cores * frames / cpu:.1f} frames/s", flush=True)


if __name__ == "__main__":
    main()
