"""The physics correction's surface normals against the simulator's, on a workspace whose water stage ran on a
lit survey (e.g. the auv preset):

    PYTHONPATH=. .venv/bin/python benchmarks/studies/normals.py --workspace WS [--every 4]

Two ways to take the normals the strobes' irradiance reads:
- ``combined``: of the correction's range (:func:`pipeline.range.correction_range`: the dense range, the fused
  mesh's where the dense has none or disagrees), smoothed by the range stage's ``normal_smooth_px``;
- ``dense``: :func:`pipeline.range.correction_normals` (the dense range's, the combined range's where the dense
  has none), what the water stage uses.
For each it prints the normals' angle to the true ones (every pixel of every ``--every``-th frame, and the
board's pixels), and inverts every frame with the water stage's stack to give the board's CIEDE2000 and the
consistency across views. Adds an entry named after the workspace to ``benchmarks/results/normals.json``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from eval.baseline_runs import OracleGeometry
from eval.colour import board_accuracy, consistency, truth_board
from eval.tracks import Tracks
from pipeline.range import correction_normals, correction_range, water_frames
from pipeline.stages import stage_folder
from watergan.formation import Stack
from watergan.formation.inverse import correct_physics, normals_from_range
from watergan.io import write_srgb_png


def angle_deg(normals: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Angle between two (H,W,3) unit normal maps, degrees, at the pixels where both are finite."""
    ok = np.isfinite(normals).all(-1) & np.isfinite(truth).all(-1)
    return np.degrees(np.arccos(np.clip((normals[ok] * truth[ok]).sum(-1), -1.0, 1.0)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workspace", required=True, type=Path)
    parser.add_argument("--every", type=int, default=4, help="normals' error on every N-th frame")
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parents[1] / "results" / "normals.json")
    args = parser.parse_args()
    began = time.perf_counter()
    ws = args.workspace
    survey = stage_folder(ws, "survey")
    stack = Stack.from_config(json.loads((stage_folder(ws, "water") / "result.json").read_text())["result"]["stack"])
    config = json.loads((stage_folder(ws, "range") / "config.json").read_text())["config"]
    smooth_px, agreement = float(config["normal_smooth_px"]), float(config["agreement"])
    tracks = Tracks.load(stage_folder(ws, "sfm") / "tracks.npz")
    K = np.asarray(tracks.K, float)
    frames = water_frames(tracks, survey / "images", stage_folder(ws, "dense") / "depth")
    board = truth_board(survey)
    geometry = OracleGeometry(survey)
    mesh = stage_folder(ws, "dense") / "fused_mesh.ply"
    errors: dict[str, list[np.ndarray]] = {}
    scene = None
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        for k, f in enumerate(frames):
            r, _, scene = correction_range(f, K, mesh, agreement, scene)
            ways = {"combined": normals_from_range(r, K, smooth_px), "dense": correction_normals(f, r, K, smooth_px)}
            for way, normals in ways.items():
                corrected, valid = correct_physics(f.image, r, stack, K, frame_index=k, normals_cam=normals)
                write_srgb_png(out / way / "images" / f"{Path(f.name).stem}.png",
                               np.where(valid[..., None], corrected, 0.0))
            if k % args.every and f.name not in board.quads:
                continue
            truth = geometry.state(f.name).normals_cam[0].permute(1, 2, 0).numpy().astype(np.float64)
            on_board = np.zeros(r.shape, np.uint8)
            for quad in board.quads.get(f.name, []):
                cv2.fillConvexPoly(on_board, np.round(np.asarray(quad)).astype(np.int32), 1)
            for way, normals in ways.items():
                if k % args.every == 0:
                    errors.setdefault(way, []).append(angle_deg(normals, truth))
                errors.setdefault(f"{way} on the board", []).append(
                    angle_deg(np.where(on_board[..., None] > 0, normals, np.nan), truth))
        scores = consistency(tracks, {"raw": survey / "images", **{w: out / w / "images" for w in ways}})
        entry = {"normal_error_deg": {}, "board_ciede2000": {}, "consistency": {}}
        for key, values in errors.items():
            e = np.concatenate(values)
            entry["normal_error_deg"][key] = {"median": float(np.median(e)), "p90": float(np.percentile(e, 90)),
                                              "mean": float(e.mean())}
            print(f"{key:>20}: normals' error median {np.median(e):.2f}, p90 {np.percentile(e, 90):.2f}, "
                  f"mean {e.mean():.2f} degrees")
        for way in ways:
            entry["board_ciede2000"][way] = board_accuracy(out / way / "images", board).mean_ciede2000
            print(f"{way:>20}: board CIEDE2000 {entry['board_ciede2000'][way]:.3f}")
    for label, score in scores.scores.items():
        entry["consistency"][label] = [float(v) for v in score.variance]
        print(f"{label:>20}: consistency {' '.join(f'{v:.3e}' for v in score.variance)}")
    entry["seconds"] = time.perf_counter() - began
    results = json.loads(args.json.read_text()) if args.json.is_file() else {}
    results[ws.resolve().parent.name + "/" + ws.name] = entry
    args.json.write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
    print(f"{entry['seconds']:.0f} s; {args.json}")


if __name__ == "__main__":
    main()
