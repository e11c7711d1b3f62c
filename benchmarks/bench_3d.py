"""3D benchmark on the demo survey: seconds per stage and the issue's figures.

    .venv/bin/python benchmarks/bench_3d.py [--out DIR] [--json FILE] [--reuse-sfm]

Figures: % of frames registered; camera-centre error as % of the survey extent after a
similarity (Umeyama) alignment to the true centres, and the recovered scale; stereo depth
coverage and median absolute error against the rendered truth depth; consistency of the in-air
truth vs the raw images (ratio of mean variances) and board accuracy; render-back PSNR of the
mesh textured with the in-air truth images, rendered from the survey poses and compared with those
in-air images (mean over 11 frames; pixels without surface or texture are left out).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench_3d_out", help="workspace folder (the survey is reused when present)")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    parser.add_argument("--reuse-sfm", action="store_true",
                        help="keep a finished SfM stage with the same configuration instead of rerunning it")
    args = parser.parse_args(argv)

    import cv2

    from eval.colour import board_accuracy, consistency, truth_board
    from eval.depth import read_depth
    from eval.synth import load_truth, make_config, simulate_survey
    from pipeline.dense import DenseConfig
    from pipeline.mesh import MeshConfig, height_mesh, render_back
    from pipeline.scale import similarity_align
    from pipeline.sfm import SfmConfig, Tracks
    from pipeline.workspace import Workspace

    ws = Workspace(args.out)
    survey = ws.stage_dir("survey")
    seconds: dict[str, float] = {}
    figures: dict[str, float] = {}

    t = time.perf_counter()
    if not (survey / "truth" / "config.json").is_file():
        simulate_survey(survey, make_config("demo"), force=True)
    seconds["simulate"] = time.perf_counter() - t
    truth = load_truth(survey)
    index = {name: k for k, name in enumerate(truth.frames)}

    t = time.perf_counter()
    sfm = ws.run("sfm", SfmConfig(), force=not args.reuse_sfm)["result"]
    seconds["sfm"] = time.perf_counter() - t
    tracks = Tracks.load(ws.path(sfm["tracks"]))
    figures["registered_pct"] = 100 * sfm["n_registered"] / sfm["n_images"]
    reg = np.flatnonzero(tracks.registered)
    est = tracks.world_from_cam[reg, :3, 3]
    true = truth.world_from_cam[[index[str(n)] for n in tracks.image_names[reg]], :3, 3]
    s, R, tr = similarity_align(est, true)
    err = np.linalg.norm(s * est @ R.T + tr - true, axis=1)
    extent = float(np.linalg.norm(true.max(0) - true.min(0)))
    figures["centre_error_mean_pct_extent"] = 100 * float(err.mean()) / extent
    figures["centre_error_max_pct_extent"] = 100 * float(err.max()) / extent
    figures["alignment_scale"] = s
    figures["scale_method"] = sfm["scale_method"]

    t = time.perf_counter()
    dense = ws.run("dense", DenseConfig(), force=True)["result"]
    seconds["dense"] = time.perf_counter() - t
    coverage, abs_err = [], []
    for name in dense["pairs"]:
        depth = read_depth(ws.path(dense["depth_dir"]) / name)
        ref = read_depth(survey / "truth" / "depth" / name)
        valid = np.isfinite(depth) & np.isfinite(ref)
        coverage.append(valid.mean())
        abs_err.append(np.abs(depth[valid] - ref[valid]))
    abs_err = np.concatenate(abs_err)
    figures["stereo_coverage_pct"] = 100 * float(np.mean(coverage))
    figures["stereo_median_abs_error_m"] = float(np.median(abs_err))

    t = time.perf_counter()
    cons = consistency(tracks, {"raw": survey / "images", "inair": survey / "truth" / "inair"})
    board = truth_board(survey)
    board_raw = board_accuracy(survey / "images", board)
    board_inair = board_accuracy(survey / "truth" / "inair", board)
    seconds["colour_eval"] = time.perf_counter() - t
    figures["consistency_raw"] = cons.scores["raw"].mean_variance
    figures["consistency_inair"] = cons.scores["inair"].mean_variance
    figures["consistency_inair_over_raw"] = cons.scores["inair"].mean_variance / cons.scores["raw"].mean_variance
    figures["consistency_points"] = cons.n_points
    figures["board_distance_raw"], figures["board_distance_inair"] = board_raw.mean_distance, board_inair.mean_distance
    figures["board_ciede2000_raw"], figures["board_ciede2000_inair"] = board_raw.mean_ciede2000, \
        board_inair.mean_ciede2000

    t = time.perf_counter()
    inair = survey / "truth" / "inair"
    mesh_result = ws.run("mesh", MeshConfig(images_dir=str(inair)), force=True)["result"]
    seconds["mesh"] = time.perf_counter() - t
    import open3d as o3d

    points = np.asarray(o3d.io.read_point_cloud(str(ws.stage_dir("dense") / "fused_points.ply")).points)
    extent_xy = float((np.percentile(points[:, :2], 99, 0) - np.percentile(points[:, :2], 1, 0)).max())
    mesh = height_mesh(points, extent_xy / 150).on_texel_grid(mesh_result["texel_m"])  # as the stage made it
    texture = cv2.imread(str(ws.path(mesh_result["mosaic_png"])))[..., ::-1]
    psnr = []
    for k in reg[:: max(1, len(reg) // 11)]:
        rendered = render_back(mesh, texture, tracks.world_from_cam[k], tracks.K, tracks.width, tracks.height)
        image = cv2.imread(str(inair / str(tracks.image_names[k])))[..., ::-1].astype(float)
        valid = np.isfinite(rendered).all(-1) & (rendered.sum(-1) > 0)
        psnr.append(10 * np.log10(255.0**2 / np.mean((rendered[valid] - image[valid]) ** 2)))
    figures["render_back_psnr_db"] = float(np.mean(psnr))
    figures["mosaic_coverage_pct"] = 100 * mesh_result["mosaic_coverage"]

    report = {"seconds": {k: round(v, 2) for k, v in seconds.items()},
              "figures": {k: (round(v, 6) if isinstance(v, float) else v) for k, v in figures.items()}}
    print(json.dumps(report, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
