"""The CUDA paths on a GPU machine: ``correct --device cuda`` against the CPU, ``train-restorer --device cuda``, and the
dense stage's patch-match stereo (pycolmap built with CUDA).

    python3 benchmarks/bench_gpu.py --workspace WS [--copies N] [--pairs DIR] [--small SURVEY --small-sfm SFM_DIR]

- ``--workspace``: a finished ``watergan run`` workspace (without ``--copies``, a folder holding its ``06_restorer``,
  ``00_survey/images`` with ``camera.json`` and ``survey.json``, and ``03_range/range`` is enough): its frames
  corrected on CUDA and on the CPU
  (best of 2 passes, file I/O and model load included), and the CUDA colours against the CPU's (levels of 8 bits);
  then in monocular mode on CUDA.
- ``--copies N`` (``correct_rate``): the workspace's frames N times over (:func:`bench_restorer.replicate_workspace`),
  corrected by the restorer on CUDA as ``watergan correct`` runs it (model load and file I/O included, best of 2
  passes): the readers and lanes of :func:`watergan.restore_folder.correct_chunk` swept, then the defaults in both
  modes with PNG and JPEG output; the same frames on the machine's CPU cores; the physics correction (a CPU path) on the
  workspace's own frames, best of 3 passes; the codecs alone on the same frames (OpenCV on the CPU's threads,
  torchvision's nvJPEG on the GPU) and the restorer's nets alone on CUDA.
- ``--pairs``: a ``generate`` folder: an RGB-D restorer trained on it on CUDA for 20 + 20 iterations (time, peak
  memory, held-out RMSE).
- ``--small`` / ``--small-sfm``: a simulated survey and its sfm output (``tracks.npz``, ``sparse/``): patch-match depth
  maps through :func:`pipeline.dense.run_patch_match_folder` (the fusion after it is left out: it needs open3d), each
  against the simulator's true depth.

Writes ``benchmarks/results/gpu.json`` (or ``--json``), keeping the sections this run did not measure.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from bench_restorer import replicate_workspace  # this folder: the script's own

from pipeline.stages import stage_folder


def correct_check(ws: Path, out: Path) -> dict:
    """Frames per second on CUDA and on the CPU, and how far the CUDA colours are from the CPU's."""
    import cv2

    from watergan.restore_folder import correct_folder

    record = {}
    for device in ("cuda", "cpu"):
        best = float("inf")
        for _ in range(2):
            began = time.perf_counter()
            result = correct_folder(stage_folder(ws, "restorer"), stage_folder(ws, "survey") / "images", out / device,
                                    force=True, progress=False, range_dir=stage_folder(ws, "range") / "range",
                                    device=device)
            best = min(best, time.perf_counter() - began)
        record[device] = {"mode": result.mode, "frames": result.corrected, "best_s": best,
                          "frames_per_s": result.corrected / best, "torch_threads": torch.get_num_threads()}
    worst, differing, pixels = 0, 0, 0
    for path in sorted((out / "cpu" / "images").glob("*.png")):
        cpu = cv2.imread(str(path)).astype(int)
        cuda = cv2.imread(str(out / "cuda" / "images" / path.name)).astype(int)
        d = np.abs(cpu - cuda).max(axis=2)
        worst, differing, pixels = max(worst, int(d.max())), differing + int((d > 0).sum()), pixels + d.size
    record["cuda_vs_cpu"] = {"max_levels": worst, "share_differing": differing / pixels}
    mono = correct_folder(stage_folder(ws, "restorer"), stage_folder(ws, "survey") / "images", out / "mono", force=True,
                          progress=False, device="cuda", mode="monocular")
    record["cuda_monocular"] = {"mode": mono.mode, "frames": mono.corrected, "seconds": mono.seconds}
    return record


def rate_check(ws: Path, out: Path, copies: int) -> dict:
    """Frames per second of ``correct`` on CUDA over the workspace's frames repeated ``copies`` times (see the module
    docstring), and the parts that bound it."""
    import os

    import watergan.restore_folder as correct
    from pipeline.correct import physics_inputs
    from pipeline.correct_physics import correct_physics_folder
    from pipeline.workspace import Workspace
    from watergan.data import read_intrinsics
    from watergan.io import read_image
    from watergan.nets.restorer import WaterFields, restore
    from watergan.train_restorer import load_restorer

    replica = replicate_workspace(ws, out / "frames", copies)
    images, ranges = stage_folder(replica, "survey") / "images", stage_folder(replica, "range") / "range"
    frames = len(list(images.iterdir()))

    def timed(passes: int = 2, **kwargs) -> float:
        best = float("inf")
        for _ in range(passes):
            began = time.perf_counter()
            done = correct.correct_folder(stage_folder(ws, "restorer"), images, out / "out", force=True, progress=False,
                                          range_dir=ranges, **kwargs)
            best = min(best, time.perf_counter() - began)
            assert done.corrected == frames and not done.failed, (done.corrected, done.failed)
        return round(frames / best, 1)

    record: dict = {"frames": frames, "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                    "default_readers": correct.io_threads(torch.device("cuda")),
                    "default_lanes": correct.cuda_lanes(), "sweep": {}}
    own = correct.io_threads, correct.cuda_lanes
    try:
        for readers, lanes in ((2, 4), (4, 8), (8, 8), (8, 16), (16, 8)):
            correct.io_threads, correct.cuda_lanes = (lambda dev, r=readers: r), (lambda n=lanes: n)
            record["sweep"][f"readers {readers}, lanes {lanes}"] = fps = timed(device="cuda", mode="rgb-d")
            print(f"restorer rgb-d png, readers {readers}, lanes {lanes}: {fps} frames/s", flush=True)
    finally:
        correct.io_threads, correct.cuda_lanes = own
    record["frames_per_s"] = {}
    for mode in ("rgb-d", "monocular"):
        for image_format in ("png", "jpeg"):
            key = f"restorer cuda {mode} {image_format}"
            record["frames_per_s"][key] = fps = timed(device="cuda", mode=mode, image_format=image_format)
            print(f"{key}: {fps} frames/s", flush=True)
    record["frames_per_s"]["restorer cpu rgb-d png"] = fps = timed(passes=1, device="cpu", mode="rgb-d")
    print(f"restorer cpu ({torch.get_num_threads()} threads) rgb-d png: {fps} frames/s", flush=True)
    workspace, own_frames = Workspace(ws), len(list((stage_folder(ws, "survey") / "images").glob("*.png")))
    for mode in ("rgb-d", "monocular"):
        inputs = physics_inputs(workspace, stage_folder(ws, "survey") / "images")
        best = min(correct_physics_folder(inputs, out / "physics", progress=False, mode=mode).seconds
                   for _ in range(3))
        record["frames_per_s"][f"physics cpu {mode} png ({own_frames} frames)"] = fps = round(own_frames / best, 1)
        print(f"physics {mode} on {own_frames} frames ({correct.cpu_lanes()} lanes): {fps} frames/s", flush=True)
    record["parts"] = part_rates(ws, images, ranges, out / "parts", correct.cuda_lanes())
    print(json.dumps(record["parts"], indent=1), flush=True)
    record["codecs"] = codec_rates(sorted(images.iterdir()), correct.cuda_lanes())
    print(json.dumps(record["codecs"], indent=1), flush=True)
    record["frames_per_s"]["restorer cuda rgb-d png, image files only"] = fps = images_only(timed)
    print(f"restorer cuda rgb-d png writing no depth files: {fps} frames/s", flush=True)
    model = load_restorer(stage_folder(ws, "restorer")).for_inference().cuda()
    x = torch.from_numpy(np.stack([read_image(p, "linear", np.float32) for p in sorted(images.iterdir())[:16]])
                         ).permute(0, 3, 1, 2).cuda()
    r = torch.full((16, 1, *x.shape[-2:]), 2.5, device="cuda") if model.range_input else None
    altitude = torch.full((16,), 2.5, device="cuda") if model.altitude else None
    fields = WaterFields(model.water) if model.water is not None else None
    intrinsics = read_intrinsics(images.parent).resized(*x.shape[-2:]).as_tuple()
    nets = {}
    with torch.no_grad():
        for batch in (4, 16):
            xb, rb = x[:batch], None if r is None else r[:batch]
            ab = None if altitude is None else altitude[:batch]
            for k in range(11):  # the first builds the fields' grid, as correct does once
                if k == 1:
                    torch.cuda.synchronize()
                    began = time.perf_counter()
                restore(model, xb, ab, rb, intrinsics, fields(rb, intrinsics) if fields is not None else None)
            torch.cuda.synchronize()
            nets[f"batch {batch}"] = round(10 * batch / (time.perf_counter() - began), 1)
    record["nets_alone_frames_per_s"] = nets
    print(f"the restorer's nets and water fields on CUDA, no files: {nets} frames/s", flush=True)
    return record


def images_only(timed) -> float:
    """``timed``'s RGB-D run on CUDA with correct's depth outputs (a 16-bit PNG and a .npy per frame) left out: what
    the depth files cost."""
    import watergan.restore_folder as correct

    own = correct._write

    def write_image(out, name, image_format, rgb, depth, bits):
        correct._write_image(correct._outputs(out, name, image_format)[0], rgb, bits)

    correct._write = write_image
    try:
        return timed(device="cuda", mode="rgb-d")
    finally:
        correct._write = own


def part_rates(ws: Path, images: Path, ranges: Path, out: Path, threads: int) -> dict:
    """Frames per second of correct's reading alone (image, range map, holes filled: ``_read_one``) and writing alone
    (the three output files: ``_write``), each on ``threads`` threads."""
    from concurrent.futures import ThreadPoolExecutor

    import watergan.restore_folder as correct

    paths = sorted(images.iterdir())
    chunk = correct.CorrectChunk(stage_folder(ws, "restorer"), tuple(paths), out, 4, "cuda", range_dir=ranges)
    rates = {"threads": threads}
    with ThreadPoolExecutor(threads) as pool:
        began = time.perf_counter()
        items = list(pool.map(lambda k: correct._read_one(chunk, k, paths[k]), range(len(paths))))
        rates["read"] = round(len(paths) / (time.perf_counter() - began), 1)
        began = time.perf_counter()
        list(pool.map(lambda k: correct._write(out, paths[k].name, "png", items[k][0], items[k][2] / 10.0, 8),
                      range(len(paths))))
        rates["write png"] = round(len(paths) / (time.perf_counter() - began), 1)
    return rates


def codec_rates(paths: list, threads: int) -> dict:
    """Frames per second decoding the PNG frames and encoding them as PNG and JPEG (quality 95) with OpenCV on
    ``threads`` threads, and with torchvision's nvJPEG on the GPU (batched) where torchvision is installed."""
    from concurrent.futures import ThreadPoolExecutor

    import cv2

    from watergan.io import JPEG_QUALITY

    data = [p.read_bytes() for p in paths]
    decoded = [cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR) for b in data]
    jpeg = [cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])[1] for im in decoded]

    def rate(fn, items) -> float:
        with ThreadPoolExecutor(threads) as pool:
            began = time.perf_counter()
            list(pool.map(fn, items))
            return round(len(items) / (time.perf_counter() - began), 1)

    rates = {"threads": threads,
             "opencv png decode": rate(lambda b: cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR), data),
             "opencv png encode": rate(lambda im: cv2.imencode(".png", im), decoded),
             "opencv jpeg encode": rate(lambda im: cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]),
                                        decoded),
             "opencv jpeg decode": rate(lambda b: cv2.imdecode(b, cv2.IMREAD_COLOR), jpeg)}
    try:
        import torchvision.io as tvio
    except ImportError:
        return {**rates, "torchvision": "not installed"}
    on_gpu = [torch.from_numpy(im).permute(2, 0, 1).contiguous().cuda() for im in decoded]
    as_tensors = [torch.from_numpy(j.reshape(-1)) for j in jpeg]
    for name, fn, items in (("nvjpeg encode", lambda b: tvio.encode_jpeg(b, quality=JPEG_QUALITY), on_gpu),
                            ("nvjpeg decode", lambda b: tvio.decode_jpeg(b, device="cuda"), as_tensors)):
        try:
            fn(items[:16])  # warm-up
            torch.cuda.synchronize()
            began = time.perf_counter()
            for k in range(0, len(items), 16):
                fn(items[k:k + 16])
            torch.cuda.synchronize()
            rates[name] = round(len(items) / (time.perf_counter() - began), 1)
        except (RuntimeError, TypeError) as exc:  # a torchvision built without nvJPEG
            rates[name] = f"failed: {exc}"
    return rates


def train_check(pairs: Path, out: Path) -> dict:
    """An RGB-D restorer trained on CUDA for 20 + 20 iterations."""
    from watergan.train_restorer import RestorerConfig, train_restorer

    torch.cuda.reset_peak_memory_stats()
    began = time.perf_counter()
    result = train_restorer(RestorerConfig(data_dir=pairs, out_dir=out, range_input=True, stage1_iterations=20,
                                           stage2_iterations=20, device="cuda", progress=False, val_fraction=0.25))
    return {"seconds": time.perf_counter() - began, "steps": list(result.steps), "loss": result.loss,
            "validation": result.validation, "peak_mib": torch.cuda.max_memory_allocated() / 2**20}


def patch_match_check(survey: Path, sfm: Path, out: Path) -> dict:
    """Patch-match depth maps of a simulated survey, each against its true depth."""
    import pycolmap

    import pipeline.dense as dense
    from eval.tracks import Tracks
    from watergan.io import read_depth

    dense._finish = lambda depths, pairs, coverage, skipped, *rest: (depths, coverage, skipped)  # fusion: open3d
    began = time.perf_counter()
    depths, coverage, skipped = dense.run_patch_match_folder(Tracks.load(sfm / "tracks.npz"), sfm / "sparse",
                                                             survey / "images", out, dense.DenseConfig())
    record = {"pycolmap": pycolmap.__version__, "has_cuda": bool(pycolmap.has_cuda),
              "auto_method": dense.dense_method("auto"), "seconds": time.perf_counter() - began, "skipped": skipped,
              "frames": {}}
    for name, depth in sorted(depths.items()):
        truth = read_depth(survey / "truth" / "depth" / name)
        ok = np.isfinite(depth) & (depth > 0) & (truth > 0)
        rel = np.abs(depth[ok] - truth[ok]) / truth[ok]
        record["frames"][name] = {"coverage": coverage[name], "median_rel_error": float(np.median(rel)),
                                  "p90_rel_error": float(np.percentile(rel, 90))}
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workspace", type=Path, required=True)
    parser.add_argument("--copies", type=int, default=0, help="also time correct's rate on the frames N times over")
    parser.add_argument("--pairs", type=Path, default=None)
    parser.add_argument("--small", type=Path, default=None)
    parser.add_argument("--small-sfm", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_gpu"))
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "gpu.json")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("bench_gpu: torch sees no CUDA device here")
    record = json.loads(args.json.read_text()) if args.json.is_file() else {}
    record.update({"device": torch.cuda.get_device_name(), "torch": torch.__version__,
                   "correct": correct_check(args.workspace, args.out / "correct")})
    print(json.dumps(record["correct"], indent=1), flush=True)
    if args.copies:
        record["correct_rate"] = rate_check(args.workspace, args.out / "rate", args.copies)
    if args.pairs is not None:
        record["train_restorer"] = train_check(args.pairs, args.out / "train")
        print(json.dumps(record["train_restorer"], indent=1), flush=True)
    if args.small is not None:
        record["patch_match"] = patch_match_check(args.small, args.small_sfm or args.small.parent / "sfm",
                                                  args.out / "patch_match")
        print(json.dumps(record["patch_match"], indent=1), flush=True)
    args.json.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
