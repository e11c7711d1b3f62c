"""Correction speed: frames per second correcting 640x480 images, on the CPU with 2 threads and on CUDA when present,
with peak memory.

    .venv/bin/python benchmarks/bench_restorer.py [--widths cpu|paper] [--batch 4] [--repeats 5] [--workspace WS]
        [--copies N]

Without ``--workspace``: the restorer's nets alone (depth + colour, pad/un-pad included, untrained weights: the speed
does not depend on them) on random 640x480 batches.

With ``--workspace`` (a ``watergan run`` workspace) it times both corrections as the correct stage runs them, on the
survey's frames, model load and file reading and writing included (best of ``--repeats`` passes, at most 3; every
pass's figure is kept under ``runs``), in both modes (``frames_per_s``, keyed by correction and mode):

- ``physics``: :func:`pipeline.correct_physics.correct_physics_folder`, the water stage's estimate inverted with its
  range maps (``rgb-d``) or with a flat seafloor at the navigation's altitude (``monocular``; times the site depth
  net's factor where the restorer stage trained one that won);
- ``restorer``: :func:`watergan.restore_folder.correct_folder` with the workspace's restorer, the same two ranges.

``--copies N``: on the survey's frames N times over (:func:`replicate_workspace`), as a dive of N times the survey's
length, where the start of each pass (model load, the fields' grid, the first frames in flight) counts once.

It also times the parts of one batch as one of correct's lanes runs it (:func:`watergan.restore_folder.cpu_lanes`: one
thread; :func:`watergan.restore_folder.batch_for`: one frame on a CPU), best of three: the water's inverse fields
(:class:`watergan.nets.restorer.WaterFields`: the grid's build, once, and the lookup per frame) and the restorer's nets
given them (the model's :meth:`~watergan.nets.restorer.Restorer.for_inference`
copy). Writes ``benchmarks/results/restorer.json`` (``--result``); ``--image-format`` as correct's.

Peak memory: the process's maximum resident set (``resource.getrusage``, CPU) and
``torch.cuda.max_memory_allocated`` (CUDA).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from pathlib import Path

import numpy as np
import torch

from pipeline.stages import stage_folder
from watergan.nets.restorer import WIDTH_PRESETS, Restorer, restore

ROOT = Path(__file__).resolve().parents[1]  # the repository: result files name paths relative to it


def best_s(call, times: int = 3) -> float:
    """The shortest of ``times`` runs of ``call()``, seconds."""
    best = float("inf")
    for _ in range(times):
        began = time.perf_counter()
        call()
        best = min(best, time.perf_counter() - began)
    return best


def frames_per_s(model: Restorer, device: torch.device, batch: int, repeats: int) -> float:
    """Best of ``repeats`` timed batches (after one warm-up): batch / seconds."""
    x = torch.rand(batch, 3, 480, 640, device=device)

    def run() -> None:
        restore(model, x)
        if device.type == "cuda":
            torch.cuda.synchronize()  # each run ends with the GPU's queue empty, so the next is timed alone

    with torch.no_grad():
        run()
        return batch / best_s(run, repeats)


def replicate_workspace(ws: Path, folder: Path, copies: int) -> Path:
    """A workspace ``folder/workspace`` (made afresh) whose survey is ``ws``'s frames ``copies`` times over, for
    timing the corrections on a dive's length: the frames and range maps linked as ``<copy>_<name>``, the navigation,
    the sfm stage's frame list and poses and the water's values per frame repeated (each copy of a frame keeps its
    gain), the restorer's folder linked, the survey's and dense stage's records copied. For the corrections to read
    (a stack that reads surface normals needs the dense depth maps, which are not linked)."""
    import shutil

    from eval.tracks import Tracks
    from watergan.formation import get

    new = folder / "workspace"
    if new.exists():
        shutil.rmtree(new)
    survey, ranges = stage_folder(new, "survey"), stage_folder(new, "range") / "range"
    images = survey / "images"
    for d in (images, ranges, stage_folder(new, "sfm"), stage_folder(new, "dense")):
        d.mkdir(parents=True)
    nav = json.loads((stage_folder(ws, "survey") / "survey.json").read_text())
    frames = [str(f) for f in nav["frames"]]
    for c in range(copies):
        for name in frames:
            stem = Path(name).stem
            (images / f"{c:03d}_{name}").symlink_to((stage_folder(ws, "survey") / "images" / name).resolve())
            (ranges / f"{c:03d}_{stem}.png").symlink_to((stage_folder(ws, "range") / "range" / f"{stem}.png").resolve())
    repeated = {"frames": [f"{c:03d}_{f}" for c in range(copies) for f in frames]}
    repeated.update({key: nav[key] * copies for key in ("nav_altitude_m", "nav_down_cam", "nav_depth_m")
                     if key in nav})
    (survey / "survey.json").write_text(json.dumps({**nav, **repeated}))
    for name in ("camera.json", "result.json"):
        shutil.copy(stage_folder(ws, "survey") / name, survey / name)
    shutil.copy(stage_folder(ws, "dense") / "result.json", stage_folder(new, "dense") / "result.json")
    tracks = Tracks.load(stage_folder(ws, "sfm") / "tracks.npz")
    tracks.image_names = np.array([f"{c:03d}_{n}" for c in range(copies) for n in tracks.image_names])
    tracks.registered = np.tile(tracks.registered, copies)
    tracks.world_from_cam = np.tile(tracks.world_from_cam, (copies, 1, 1))
    tracks.save(stage_folder(new, "sfm") / "tracks.npz")
    shutil.copy(stage_folder(ws, "sfm") / "result.json", stage_folder(new, "sfm") / "result.json")
    record = json.loads((stage_folder(ws, "water") / "result.json").read_text())
    for effect in record["result"]["stack"]:
        if get(effect["name"]).varies_by_frame():
            effect["params"] = {k: v * copies if isinstance(v, list) and len(v) == len(frames) else v
                                for k, v in effect["params"].items()}
    (stage_folder(new, "water") / "result.json").write_text(json.dumps(record))
    stage_folder(new, "restorer").symlink_to(stage_folder(ws, "restorer").resolve())
    return new


def correct_speed(ws: Path, repeats: int, out: Path, image_format: str = "input", copies: int = 1) -> dict:
    """Both corrections in both modes on the workspace's frames, ``copies`` times over (:func:`replicate_workspace`;
    best of the passes), and one of the restorer's batches split into its parts."""
    from pipeline.correct import physics_inputs
    from pipeline.correct_physics import correct_physics_folder
    from pipeline.workspace import Workspace
    from watergan.data import read_intrinsics
    from watergan.io import depth_or_zero, read_depth, read_image
    from watergan.nets.restorer import WaterFields, fill_range_holes
    from watergan.restore_folder import batch_for, correct_folder, cpu_lanes
    from watergan.train_restorer import load_restorer

    own = ws
    if copies > 1:
        ws = replicate_workspace(own, out / "replica", copies)
    workspace = Workspace(ws)
    images = stage_folder(ws, "survey") / "images"
    ranges = stage_folder(ws, "range") / "range"
    frames = len(list(images.glob("*.png")))
    passes = max(1, min(repeats, 3))
    fps: dict[str, dict[str, float]] = {"physics": {}, "restorer": {}}
    runs: dict[str, dict[str, list[float]]] = {"physics": {}, "restorer": {}}
    sources: dict[str, dict[str, str]] = {"physics": {}, "restorer": {}}
    range_input = load_restorer(stage_folder(ws, "restorer")).range_input
    for mode in ("rgb-d", "monocular"):
        for correction in ("physics", "restorer"):
            if correction == "restorer" and mode == "rgb-d" and not range_input:
                continue  # a monocular restorer has no RGB-D mode
            seconds = []
            for _ in range(passes):
                if correction == "physics":
                    done = correct_physics_folder(physics_inputs(workspace, images), out / correction / mode,
                                                  progress=False, mode=mode, image_format=image_format)
                    seconds.append(done.seconds)
                else:
                    done = correct_folder(stage_folder(ws, "restorer"), images, out / correction / mode, force=True,
                                          progress=False, range_dir=ranges, mode=mode, image_format=image_format)
                    seconds.append(done.seconds)
            sources[correction][mode] = done.range_source
            runs[correction][mode] = [round(frames / t, 2) for t in seconds]
            fps[correction][mode] = frames / min(seconds)
            print(f"{correction} {mode} (range from the {done.range_source}): {frames} frames, "
                  f"{fps[correction][mode]:.1f} frames/s with file I/O and model load (passes: "
                  f"{', '.join(f'{v:.1f}' for v in runs[correction][mode])})")
    lanes = cpu_lanes()
    model = load_restorer(stage_folder(ws, "restorer")).for_inference()
    batch = batch_for(torch.device("cpu"))
    paths = sorted(images.glob("*.png"))[:batch]
    x = torch.from_numpy(np.stack([read_image(p, "linear") for p in paths]).transpose(0, 3, 1, 2)).float()
    parts = {}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as one lane
    with torch.no_grad():
        range_m = water = None
        if model.range_input:
            range_m = fill_range_holes(torch.stack([torch.from_numpy(depth_or_zero(read_depth(ranges / p.name)))
                                                    for p in paths])[:, None].float())[0]
        camera = read_intrinsics(images.parent)
        intrinsics = camera.resized(*x.shape[-2:]).as_tuple() if camera is not None else None
        if model.water is not None:
            fields = WaterFields(model.water)
            began = time.perf_counter()
            fields(range_m, intrinsics)
            parts["water_grid_build_s"] = time.perf_counter() - began
            parts["water_fields_s_per_frame"] = best_s(lambda: fields(range_m, intrinsics)) / len(paths)
            water = fields(range_m, intrinsics)
        altitude = torch.full((len(paths),), 2.5) if model.altitude else None
        restore(model, x, altitude, range_m, intrinsics, water)  # warm-up
        parts["nets_s_per_frame"] = best_s(lambda: restore(model, x, altitude, range_m, intrinsics, water)) / len(paths)
    torch.set_num_threads(threads)
    return {"lanes": lanes, "batch": batch, "workspace": os.path.relpath(own, ROOT), "copies": copies,
            "frames": frames,
            "image_format": image_format, "frames_per_s": fps, "runs": runs,
            "range_source": sources, **parts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--widths", choices=sorted(WIDTH_PRESETS), default="cpu")
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--workspace", type=Path, default=None, help="also time `correct` on this workspace")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_restorer_correct"),
                        help="where --workspace's corrected frames go")
    parser.add_argument("--image-format", default="input", choices=["input", "png", "tiff", "jpeg"],
                        help="the corrected frames' format (correct's --image-format)")
    parser.add_argument("--copies", type=int, default=1,
                        help="time the corrections on the workspace's frames this many times over (a longer dive)")
    parser.add_argument("--result", type=Path, default=Path(__file__).resolve().parent / "results" / "restorer.json",
                        help="where the figures go")
    args = parser.parse_args()
    torch.set_num_threads(2)
    model = Restorer(WIDTH_PRESETS[args.widths]).eval()
    params = sum(p.numel() for p in model.parameters())
    fps = cpu_fps = frames_per_s(model, torch.device("cpu"), args.batch, args.repeats)
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"cpu (2 threads), widths {args.widths} ({params} parameters), batch {args.batch}: "
          f"{fps:.1f} frames/s at 640x480; peak RSS {peak_mib:.0f} MiB")
    if torch.cuda.is_available():
        device = torch.device("cuda")
        model = model.to(device)
        torch.cuda.reset_peak_memory_stats()
        fps = frames_per_s(model, device, args.batch, args.repeats)
        peak = torch.cuda.max_memory_allocated() / 2**20
        print(f"cuda ({torch.cuda.get_device_name()}), widths {args.widths}, batch {args.batch}: "
              f"{fps:.1f} frames/s at 640x480; peak allocated {peak:.0f} MiB")
    if args.workspace is not None:
        record = {"untrained_nets_cpu_frames_per_s": cpu_fps,
                  **correct_speed(args.workspace, args.repeats, args.out, args.image_format, args.copies)}
        print(f"one batch of {record['batch']} of the restorer on one thread: fields "
              f"{1000 * record.get('water_fields_s_per_frame', 0):.0f} ms/frame, nets "
              f"{1000 * record['nets_s_per_frame']:.0f} ms/frame ({record['lanes']} lanes side by side)")
        command = (f"benchmarks/bench_restorer.py --workspace {args.workspace} --image-format {args.image_format}"
                   f" --copies {args.copies}")
        args.result.write_text(json.dumps({"command": command, "threads": torch.get_num_threads(), **record},
                                          indent=2) + "\n")

if __name__ == "__main__":
    main()
