"""The CUDA paths on a GPU machine: ``correct --device cuda`` against the CPU, ``train-restorer --device cuda``, and the
dense stage's patch-match stereo (pycolmap built with CUDA).

    python3 benchmarks/bench_gpu.py --workspace WS [--pairs DIR] [--small SURVEY --small-sfm SFM_DIR]

- ``--workspace``: a finished ``watergan run`` workspace (or a folder holding its ``05_restorer``, ``00_survey/images``
  with ``camera.json`` and ``survey.json``, and ``03_water/range``): its frames corrected on CUDA and on the CPU
  (best of 2 passes, file I/O and model load included), and the CUDA colours against the CPU's (levels of 8 bits);
  then in monocular mode on CUDA.
- ``--pairs``: a ``generate`` folder: an RGB-D restorer trained on it on CUDA for 20 + 20 iterations (time, peak
  memory, held-out RMSE).
- ``--small`` / ``--small-sfm``: a simulated survey and its sfm output (``tracks.npz``, ``sparse/``): patch-match depth
  maps through :func:`pipeline.dense.run_patch_match_folder` (the fusion after it is left out: it needs open3d), each
  against the simulator's true depth.

Writes ``benchmarks/results/gpu.json`` (or ``--json``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch


def correct_check(ws: Path, out: Path) -> dict:
    """Frames per second on CUDA and on the CPU, and how far the CUDA colours are from the CPU's."""
    import cv2

    from pipeline.correct import correct_folder

    record = {}
    for device in ("cuda", "cpu"):
        best = float("inf")
        for _ in range(2):
            began = time.perf_counter()
            result = correct_folder(ws / "05_restorer", ws / "00_survey" / "images", out / device, force=True,
                                    progress=False, range_dir=ws / "03_water" / "range", device=device)
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
    mono = correct_folder(ws / "05_restorer", ws / "00_survey" / "images", out / "mono", force=True, progress=False,
                          device="cuda", mode="monocular")
    record["cuda_monocular"] = {"mode": mono.mode, "frames": mono.corrected, "seconds": mono.seconds}
    return record


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
    parser.add_argument("--pairs", type=Path, default=None)
    parser.add_argument("--small", type=Path, default=None)
    parser.add_argument("--small-sfm", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_gpu"))
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "gpu.json")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("bench_gpu: torch sees no CUDA device here")
    record = {"device": torch.cuda.get_device_name(), "torch": torch.__version__,
              "correct": correct_check(args.workspace, args.out / "correct")}
    print(json.dumps(record["correct"], indent=1), flush=True)
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
