"""SfM's mappers on one survey: seconds, images registered, and the cameras' error against the simulator's truth.

    .venv/bin/python benchmarks/bench_sfm.py --survey SURVEY [--mappers incremental,global] [--out /tmp/bench_sfm]

Each mapper runs :func:`pipeline.sfm.run_sfm_folder` on the survey's images (features, matching and mapping, the
survey frame and scale: the whole stage) into ``--out/<mapper>``, one after the other on a quiet machine. The camera
centres are compared with the truth (``truth/poses.json`` of a simulated survey) after the least-squares similarity
(:func:`pipeline.scale.similarity_align`): its scale (1 for a metric model) and the centres' RMS and largest error as a
share of the survey's extent. Writes ``benchmarks/results/sfm.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.scale import similarity_align
from pipeline.sfm import SfmConfig, Tracks, run_sfm_folder

ROOT = Path(__file__).resolve().parents[1]  # the repository: result files name paths relative to it


def camera_error(survey: Path, tracks: Tracks) -> dict:
    """The registered cameras' centres against the truth after a similarity: its scale, RMS and largest error as
    shares of the true centres' extent."""
    from eval.synth import load_truth

    truth = load_truth(survey)
    index = {name: k for k, name in enumerate(truth.frames)}
    est = tracks.world_from_cam[tracks.registered, :3, 3]
    true = truth.world_from_cam[[index[str(n)] for n in np.asarray(tracks.image_names)[tracks.registered]], :3, 3]
    s, R, t = similarity_align(est, true)
    error = np.linalg.norm(s * est @ R.T + t - true, axis=1)
    extent = float(np.linalg.norm(true.max(0) - true.min(0)))
    return {"similarity_scale": round(float(s), 4), "rms_share": float(np.sqrt(np.mean(error**2)) / extent),
            "max_share": float(error.max() / extent), "extent_m": round(extent, 2)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--survey", type=Path, required=True)
    parser.add_argument("--mappers", default="incremental,global")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_sfm"))
    args = parser.parse_args()
    rows = {}
    for mapper in args.mappers.split(","):
        began = time.perf_counter()
        result = run_sfm_folder(args.survey / "images", args.out / mapper, SfmConfig(mapper=mapper, progress=False))
        seconds = time.perf_counter() - began
        rows[mapper] = {"seconds": round(seconds, 1), "images": result.n_images, "registered": result.n_registered,
                        "points": result.n_points, "scale_method": result.scale_method,
                        "mean_reprojection_error_px": round(result.mean_reprojection_error_px, 3),
                        **camera_error(args.survey, Tracks.load(Path(result.tracks)))}
        row = rows[mapper]
        print(f"{mapper}: {seconds:.0f} s, {row['registered']}/{row['images']} registered, {row['points']} points, "
              f"reprojection {row['mean_reprojection_error_px']:.2f} px, centres {100 * row['rms_share']:.3f} % RMS "
              f"of the extent (largest {100 * row['max_share']:.3f} %), scale x{row['similarity_scale']}", flush=True)
    path = Path(__file__).resolve().parent / "results" / "sfm.json"
    record = {"command": "benchmarks/bench_sfm.py " + " ".join(sys.argv[1:]),
              "survey": os.path.relpath(args.survey, ROOT), "mappers": rows}
    path.write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
