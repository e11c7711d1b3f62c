"""Site water from the survey's own geometry (issue 17): the estimate against the simulator's truth, and the
physics correction with the dense range against the oracle.

    .venv/bin/python benchmarks/bench_water.py [--out DIR] [--surveys demo0,demo1,mono0] [--bootstrap N]

For each survey (``demo0``/``demo1``: the demo preset with nothing hidden, seeds 0 and 1; ``mono0``: the demo
without the right camera, scale from the navigation altitude, dense range from SfM neighbours; ``offc0``: the demo
with ``vignetting_offcentre`` hidden, estimated with it added, as after ``--add vignetting_offcentre``; ``auv0``:
the auv preset, strobes declared in survey.json, the off-centre vignetting hidden; ``auv0_add``: it estimated with
that effect added; ``--no-light-rig``: the declared lights left out of the stack) it simulates the
survey, runs the pipeline's SfM, dense and range stages on it (reused when present), estimates the water with
:func:`eval.water.estimate_water` from the raw frames, the SfM poses, the dense range (its fine grid, as the water
stage's, on the range stage's maps where the dense has none: :class:`pipeline.range.MeshFilledFrames`) and the board
(pixel quads from the SfM poses) and prints per parameter the estimate, the truth (``truth/effects.json``), the
relative error and whether the 95 % interval covers the truth. Then it corrects every frame with
:func:`watergan.formation.inverse.correct_physics` with the water stage's range (dense, the fused mesh where the
dense range has none or disagrees; pixels with neither take the nearest valid pixel's range, as the evaluation does
for the range-based baselines; the mesh and filled fractions are printed) and measures
board CIEDE2000 (:func:`eval.colour.board_accuracy`), consistency per channel on the SfM tracks
(:func:`eval.colour.consistency`) and PSNR against the in-air truth (:func:`eval.fidelity.fidelity`), beside the
oracle (:func:`eval.baselines.oracle`, the true stack and the true geometry) and the true stack with the dense
range. Writes ``benchmarks/results/water.json``.

The RGB-D training set of the preset is shrunk to one view (the water estimate does not read it).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.stages import stage_folder

SURVEYS = {
    "demo0": {"seed": 0, "stereo": True},
    "demo1": {"seed": 1, "stereo": True},
    "mono0": {"seed": 0, "stereo": False},
    "offc0": {"seed": 0, "stereo": True, "hidden": ("vignetting_offcentre",), "add": ("vignetting_offcentre",)},
    # robustness: a form the estimator does not share (the off-centre falloff hidden and not added: offc0's survey,
    # before --add), and backscatter with beta equal to eta (a degenerate corner of the estimator's family)
    "offc0_before_add": {"seed": 0, "stereo": True, "hidden": ("vignetting_offcentre",), "workspace": "offc0"},
    "beta_eq_eta0": {"seed": 0, "stereo": True, "beta_equals_eta": True},
    # the auv preset (two strobes in darkness, declared in survey.json: modelled with the rig held) with the
    # off-centre vignetting hidden; ``auv0_add``: the same survey estimated with that effect added
    "auv0": {"preset": "auv", "seed": 0, "stereo": True, "hidden": ("vignetting_offcentre",)},
    "auv0_add": {"preset": "auv", "seed": 0, "stereo": True, "hidden": ("vignetting_offcentre",),
                 "add": ("vignetting_offcentre",), "workspace": "auv0"},
    # issue 28's robustness surveys: the demo with one effect of a form the stack does not share hidden
    # (benchmarks/plugins/robust_forms.py), estimated with the default stack and its fields over the image
    "offc1_before_add": {"seed": 1, "stereo": True, "hidden": ("vignetting_offcentre",)},
    "offc0_mono": {"seed": 0, "stereo": False, "hidden": ("vignetting_offcentre",)},
    "clip0": {"seed": 0, "stereo": True, "hidden": ("falloff_clipped",)},
    "clip1": {"seed": 1, "stereo": True, "hidden": ("falloff_clipped",)},
    "veil0": {"seed": 0, "stereo": True, "hidden": ("port_veil",)},
    "veil1": {"seed": 1, "stereo": True, "hidden": ("port_veil",)},
    "expo0": {"seed": 0, "stereo": True, "hidden": ("survey_exposure",)},
    "expo0_add": {"seed": 0, "stereo": True, "hidden": ("survey_exposure",), "add": ("survey_exposure",),
                  "workspace": "expo0"},
    "drift0": {"seed": 0, "stereo": True, "hidden": ("water_drift",)},
    # the same surveys with the hidden form added to the stack: what the fields' form costs the corrections
    "clip0_add": {"seed": 0, "stereo": True, "hidden": ("falloff_clipped",), "add": ("falloff_clipped",),
                  "workspace": "clip0"},
    "veil0_add": {"seed": 0, "stereo": True, "hidden": ("port_veil",), "add": ("port_veil",), "workspace": "veil0"},
    # issue 29: the demo (nothing hidden) seen through a wide lens (OpenCV k1 -0.2, k2 0.05), its distortion in
    # camera.json (the survey stage undistorts the frames), and the same frames with the distortion withheld
    "lens0": {"seed": 0, "stereo": True, "lens": (-0.2, 0.05, 0.0, 0.0, 0.0)},
    "lens0_withheld": {"seed": 0, "stereo": True, "lens": (-0.2, 0.05, 0.0, 0.0, 0.0), "withhold_lens": True},
    # the withheld survey's frames with the lens estimated by SfM in the survey stage (``--estimate-lens``), and the
    # demo through a fisheye (OpenCV's model; a 60-degree focal length, since at the pinhole's 70 the fisheye's wider
    # view sees past the site's edge), given, and with only its model declared and the lens estimated
    "lens0_estimated": {"seed": 0, "stereo": True, "lens": (-0.2, 0.05, 0.0, 0.0, 0.0), "withhold_lens": True,
                        "estimate_lens": True, "raw": "lens0_withheld"},
    "fish0": {"seed": 0, "stereo": True, "lens": (0.05, -0.02, 0.0, 0.0), "lens_model": "fisheye", "hfov_deg": 60.0},
    "fish0_estimated": {"seed": 0, "stereo": True, "lens": (0.05, -0.02, 0.0, 0.0), "lens_model": "fisheye",
                        "hfov_deg": 60.0, "withhold_lens": True, "estimate_lens": True, "raw": "fish0"},
}
#: The plugin holding the robustness surveys' hidden effects (loaded when a survey hides one of them).
ROBUST_PLUGIN = Path(__file__).parent / "plugins" / "robust_forms.py"


def load_robust_forms() -> None:
    """Register the robustness surveys' effects (``ROBUST_PLUGIN``) unless they are."""
    from watergan.formation import available, load_plugin

    if "falloff_clipped" not in available():
        load_plugin(ROBUST_PLUGIN)


def prepare(root: Path, name: str) -> Path:
    """Simulate the survey ``name`` into ``root/name/00_survey`` and run SfM, dense and the range maps (each skipped
    when done)."""
    from eval.synth import make_config, simulate_survey

    load_robust_forms()
    from pipeline.dense import DenseConfig
    from pipeline.range import RangeConfig
    from pipeline.sfm import SfmConfig
    from pipeline.workspace import Workspace

    spec = SURVEYS[name]
    ws = Workspace(root / spec.get("workspace", name))
    survey = ws.stage_dir("survey")
    if not (survey / "truth" / "config.json").is_file():
        cfg = make_config(spec.get("preset", "demo"), hidden=spec.get("hidden", ()), seed=spec["seed"])
        cfg = replace(cfg, trajectory=replace(cfg.trajectory, stereo=spec["stereo"]),
                      rgbd=replace(cfg.rgbd, n_scenes=1, views_per_scene=1))
        if spec.get("beta_equals_eta"):
            visible = [dict(e, params=dict(e.get("params", {}))) for e in cfg.formation.visible]
            eta = next(e for e in visible if e["name"] == "attenuation")["params"]["eta_per_m"]
            next(e for e in visible if e["name"] == "backscatter")["params"]["beta_per_m"] = list(eta)
            cfg = replace(cfg, formation=replace(cfg.formation, visible=tuple(visible)))
        if spec.get("lens"):  # simulated beside the workspace, then through the survey stage (it undistorts)
            from pipeline.survey import SurveyConfig
            from watergan.lens import LENS_KEYS

            model = spec.get("lens_model", "opencv")
            cfg = replace(cfg, camera=replace(cfg.camera, distortion=tuple(spec["lens"]), lens_model=model,
                                              hfov_deg=spec.get("hfov_deg", cfg.camera.hfov_deg)))
            raw = root / f"{spec.get('raw', name)}_raw_survey"
            if not (raw / "truth" / "config.json").is_file():
                simulate_survey(raw, cfg, force=True, progress=False)
            camera = json.loads((raw / "camera.json").read_text())
            if spec.get("withhold_lens"):  # the coefficients withheld; a fisheye's model stays declared
                camera = {k: v for k, v in camera.items() if k not in LENS_KEYS}
                camera.update({"lens_model": model} if model == "fisheye" else {})
            else:
                camera.update(cfg.camera.lens.to_json())
            (raw / "camera.json").write_text(json.dumps(camera))
            ws.run("survey", SurveyConfig(survey_dir=str(raw), estimate_lens=spec.get("estimate_lens", False),
                                          progress=False))
        else:
            simulate_survey(survey, cfg, force=True, progress=False)
    if not (ws.stage_dir("sfm") / "tracks.npz").is_file():  # reused when present, whatever made it
        ws.run("sfm", SfmConfig())
    if not (ws.stage_dir("dense") / "result.json").is_file():
        ws.run("dense", DenseConfig(progress=False))
    ws.run("range", RangeConfig(progress=False))
    return ws.root


def load_inputs(ws_root: Path):
    """(frames, K, tracks, board, sfm Tracks) of a prepared workspace: raw linear frames, dense range (camera z
    from ``02_dense/depth`` as ray length; 0 = none stays NaN), SfM poses; the board's pixel quads projected
    with the true poses (what a user's board file with detected corners gives)."""
    from eval.colour import truth_board
    from eval.observations import SparseTracks
    from eval.tracks import Tracks
    from pipeline.range import water_frames

    survey = stage_folder(ws_root, "survey")
    tracks = Tracks.load(stage_folder(ws_root, "sfm") / "tracks.npz")
    K = np.asarray(tracks.K, float)
    # read here, not timed
    frames = list(water_frames(tracks, survey / "images", stage_folder(ws_root, "dense") / "depth"))
    sparse = SparseTracks(xyz=tracks.xyz, obs_point=tracks.obs_point, obs_frame=tracks.obs_image,
                          obs_xy=tracks.obs_xy)
    return frames, K, sparse, truth_board(survey), tracks


def truth_params(survey: Path) -> dict[str, list | float]:
    """{"effect.param": value} of the survey's full true stack."""
    full = json.loads((survey / "truth" / "effects.json").read_text())["full"]
    return {f"{e['name']}.{k}": v for e in full for k, v in e["params"].items()}


def compare(params: dict, truth: dict) -> dict:
    """Per parameter of an estimate's ``params`` (water.json's): estimate, truth, relative error, interval, covered."""
    rows = {}
    for key, p in params.items():
        if key not in truth:
            continue
        p = p if isinstance(p, dict) else p.to_json()
        value, true = np.atleast_1d(p["value"]).astype(float), np.atleast_1d(truth[key]).astype(float)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(np.abs(true) > 1e-9, (value - true) / np.abs(true), np.nan)
        row = {"estimate": value.tolist(), "truth": true.tolist(), "rel_error": np.round(rel, 4).tolist(),
               "fitted": p["fitted"]}
        if p.get("low") is not None:
            low, high = np.atleast_1d(p["low"]), np.atleast_1d(p["high"])
            row.update(low=low.tolist(), high=high.tolist(),
                       covered=[bool(lo <= t <= hi) for lo, t, hi in zip(low, true, high, strict=True)])
        rows[key] = row
    return rows


def compare_veil(veil: dict | None, truth: dict) -> dict:
    """{"veil": row} as :func:`compare`'s for the estimate's veil at the views' median range r (water.json's
    ``veil``), its truth B_inf (1 - exp(-beta r)) from the true backscatter; {} without either."""
    from eval.water.fields import veil_at

    if not veil or "backscatter.b_inf" not in truth:
        return {}
    true = veil_at(truth["backscatter.b_inf"], truth["backscatter.beta_per_m"], veil["range_m"])
    entry = {"value": veil["value"], "fitted": True, **({"low": veil["low"], "high": veil["high"]}
                                                        if veil.get("low") is not None else {})}
    return {"veil": compare({"veil": entry}, {"veil": true.tolist()})["veil"]}


def correct_folders(ws_root: Path, frames, K, stack, out: Path, agreement: float) -> dict:
    """Every frame corrected three ways, written as 8-bit sRGB: the estimated water with the water stage's range
    (:func:`pipeline.range.correction_range`: dense, the fused mesh where the dense range has none or disagrees;
    'physics'), the true stack with that range ('true_water_dense_range') and the oracle (true stack, true
    geometry). Pixels with no range at all take the nearest pixel's (the stage writes them black; fractions
    reported)."""
    import torch

    from eval.baseline_runs import OracleGeometry, fill_nearest
    from eval.baselines import oracle
    from pipeline.range import correction_range
    from watergan.data import write_srgb8
    from watergan.formation import Stack
    from watergan.formation.inverse import correct_physics

    survey = stage_folder(ws_root, "survey")
    geometry = OracleGeometry(survey)
    true_stack = Stack.from_config(geometry.truth.effects["full"])
    folders = {name: out / name for name in ("physics", "true_water_dense_range", "oracle")}
    for folder in folders.values():
        folder.mkdir(parents=True, exist_ok=True)
    filled, from_mesh, seconds = [], [], 0.0
    torch.set_num_threads(1)
    scene = None
    for k, f in enumerate(frames):
        r, meshed, scene = correction_range(f, K, stage_folder(ws_root, "dense") / "fused_mesh.ply", agreement, scene)
        from_mesh.append(float(np.mean(meshed)))
        filled.append(float(np.mean(~np.isfinite(r))))
        r_full = fill_nearest(r)
        t = time.perf_counter()
        corrected, _ = correct_physics(f.image, r_full, stack, K, frame_index=k)
        seconds += time.perf_counter() - t
        write_srgb8(folders["physics"] / f.name, np.clip(np.nan_to_num(corrected), 0, 1))
        corrected, _ = correct_physics(f.image, r_full, true_stack, K)
        write_srgb8(folders["true_water_dense_range"] / f.name, np.clip(np.nan_to_num(corrected), 0, 1))
        write_srgb8(folders["oracle"] / f.name, oracle(f.image.astype(np.float64), geometry.state(f.name),
                                                       geometry.stack))
    return {"folders": folders, "filled_fraction": float(np.mean(filled)), "mesh_fraction": float(np.mean(from_mesh)),
            "physics_seconds_per_frame": seconds / max(len(frames), 1)}


def measure_corrections(ws_root: Path, tracks, board, folders: dict[str, Path], names: list[str]) -> dict:
    from eval.colour import board_accuracy, consistency
    from eval.fidelity import fidelities

    survey = stage_folder(ws_root, "survey")
    all_folders = {"raw": survey / "images", **folders}
    cons = consistency(tracks, all_folders)
    fid = fidelities(all_folders, survey / "truth" / "inair", names)
    rows = {}
    for label, folder in all_folders.items():
        b = board_accuracy(folder, board)
        psnr, ssim = fid[label]
        rows[label] = {"board_ciede2000": b.mean_ciede2000, "board_distance": b.mean_distance,
                       "consistency": cons.scores[label].variance, "psnr_db": psnr, "ssim": ssim}
    rows["consistency_points"] = cons.n_points
    return rows


def run_survey(root: Path, name: str, config, use_tracks: bool) -> dict:
    from eval.water import estimate_water

    t = time.perf_counter()
    ws_root = prepare(root, name)
    prep_seconds = time.perf_counter() - t
    t = time.perf_counter()
    frames, K, sparse, board, tracks = load_inputs(ws_root)
    load_seconds = time.perf_counter() - t
    sfm = json.loads((stage_folder(ws_root, "sfm") / "result.json").read_text())["result"]
    survey_record = stage_folder(ws_root, "survey") / "result.json"  # none where the survey was simulated in place
    survey = json.loads(survey_record.read_text())["result"] if survey_record.is_file() else {}
    config = replace(config, range_scale_sd=float(sfm.get("scale_spread", 0.0)))
    add = SURVEYS[name].get("add", ())
    if add:
        config = replace(config, effects=tuple(config.effects) + tuple(add))
    t = time.perf_counter()
    from pipeline.range import RangeConfig
    from pipeline.water import fine_grid_frames, survey_lights

    lights = survey_lights(stage_folder(ws_root, "survey"))
    estimate = estimate_water(frames, K, sparse if use_tracks else None, board, config, lights=lights,
                              grid_frames=fine_grid_frames(frames, K, stage_folder(ws_root, "range") / "range",
                                                           config, lights))
    water_seconds = time.perf_counter() - t
    truth = truth_params(stage_folder(ws_root, "survey"))
    params = compare(estimate.params, truth)
    params.update(compare_veil(estimate.veil, truth))
    print(f"\n== {name}: {estimate.summary()}")
    print(f"   sfm: reprojection {sfm['mean_reprojection_error_px']:.3f} px, scale spread "
          f"{100 * sfm['scale_spread']:.2f} %, refined k1 {sfm.get('lens_k1')}")
    if survey.get("undistorted"):
        print(f"   lens removed by the survey stage: {survey['undistorted']}"
              + (f" (estimated: {survey['lens_estimate']})" if survey.get("lens_estimate") else ""))
    print(f"   water estimate {water_seconds:.1f} s (+ {load_seconds:.1f} s reading frames and range; "
          f"{estimate.seconds}; {estimate.iterations} iterations, converged {estimate.converged}); "
          f"{estimate.n_points} points, {estimate.n_observations} views, "
          f"{estimate.n_board} board patch views, {estimate.n_frames} frames")
    for key, row in params.items():
        cover = "".join("y" if c else "N" for c in np.ravel(row.get("covered", []))) or "-"
        est = " ".join(f"{v:.4f}" for v in np.ravel(row["estimate"]))  # per-light parameters: rows flattened
        tru = " ".join(f"{v:.4f}" for v in np.ravel(row["truth"]))
        rel = " ".join(f"{100 * v:+.1f}%" if np.isfinite(v) else "n/a" for v in np.ravel(row["rel_error"]))
        print(f"   {key:32s} est {est:30s} truth {tru:30s} err {rel:24s} covered {cover}")
    if estimate.tradeoffs:
        print("   bootstrap trade-offs:", estimate.tradeoffs)
    if estimate.grid is not None:
        from eval.water.fields import field_size

        print(f"   fine grid after the water: {'carried' if estimate.grid['carried'] else 'flat, not carried'} "
              f"({field_size(estimate.grid)}, {estimate.grid['seconds']:.1f} s)")
    out = ws_root / f"water_bench_{name}"
    corr = correct_folders(ws_root, frames, K, estimate.stack, out, RangeConfig().agreement)
    names = [f.name for f in frames]
    metrics = measure_corrections(ws_root, tracks, board, corr["folders"], names)
    print(f"   correction ({100 * corr['mesh_fraction']:.1f} % of pixels ranged from the fused mesh, "
          f"{100 * corr['filled_fraction']:.1f} % from the nearest pixel with range; physics "
          f"{corr['physics_seconds_per_frame']:.2f} s/frame); consistency on {metrics['consistency_points']} points")
    for label in ("raw", "physics", "true_water_dense_range", "oracle"):
        m = metrics[label]
        print(f"   {label:24s} board CIEDE2000 {m['board_ciede2000']:6.3f}  consistency x1e-5 "
              + "/".join(f"{1e5 * v:.2f}" for v in m["consistency"]) + f"  PSNR {m['psnr_db']:.2f} dB")
    o, p = metrics["oracle"], metrics["physics"]
    targets = {
        "eta_within_10pct": all(abs(v) <= 0.10 for v in params["attenuation.eta_per_m"]["rel_error"]),
        "b_inf_within_20pct": all(abs(v) <= 0.20 for v in params["backscatter.b_inf"]["rel_error"]),
        "veil_within_20pct": "veil" in params and all(abs(v) <= 0.20 for v in params["veil"]["rel_error"]),
        "veil_covered": "veil" in params and all(params["veil"].get("covered", [False])),
        "eta_b_inf_covered": all(params[k].get("covered", [False]) and all(params[k]["covered"])
                                 for k in ("attenuation.eta_per_m", "backscatter.b_inf")),
        "board_ciede_le_2x_oracle": p["board_ciede2000"] <= 2 * o["board_ciede2000"],
        "consistency_le_1_5x_oracle": all(a <= 1.5 * b for a, b in zip(p["consistency"], o["consistency"],
                                                                       strict=True)),
        "psnr_within_3db": p["psnr_db"] >= o["psnr_db"] - 3.0,
        "water_le_90s": water_seconds + load_seconds <= 90.0,
    }
    print("   targets:", targets)
    return {"params": params, "estimate": estimate.to_json(), "correction": metrics,
            "filled_fraction": corr["filled_fraction"], "mesh_fraction": corr["mesh_fraction"], "targets": targets,
            "sfm": {k: sfm.get(k) for k in ("mean_reprojection_error_px", "scale_spread", "lens_k1")},
            "lens": {k: survey.get(k) for k in ("undistorted", "lens_estimate")},
            "seconds": {"prepare": round(prep_seconds, 1), "load": round(load_seconds, 2),
                        "water": round(water_seconds, 2),
                        "physics_per_frame": round(corr["physics_seconds_per_frame"], 3)}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_water"), help="workspaces (reused when present)")
    parser.add_argument("--surveys", default="demo0,demo1,mono0", help=f"comma-separated, of {', '.join(SURVEYS)}")
    parser.add_argument("--bootstrap", type=int, default=None, help="bootstrap replicates (default: WaterConfig's)")
    parser.add_argument("--tracks", action="store_true", help="also give the SfM tracks to the estimator")
    parser.add_argument("--field-degree", type=int, default=None,
                        help="degree of the fields over the image (default: WaterConfig's; 0: none)")
    parser.add_argument("--no-frame-gain", action="store_true", help="no gain per frame beside the stack")
    parser.add_argument("--no-light-rig", action="store_true", help="leave the declared lights out of the stack "
                        "(the estimate before the water stage modelled them)")
    parser.add_argument("--json", type=Path, default=Path(__file__).parent / "results" / "water.json")
    args = parser.parse_args(argv)

    from pipeline.water import WaterStage  # the estimate's options, as the water stage takes them

    config = WaterStage() if args.bootstrap is None else \
        WaterStage(fit=replace(WaterStage().fit, bootstrap=args.bootstrap))
    if args.no_light_rig:
        config = replace(config, light_rig=False)
    if args.field_degree is not None:
        config = replace(config, field_degree=args.field_degree)
    if args.no_frame_gain:
        config = replace(config, frame_gain=False)
    import sys

    command = "benchmarks/bench_water.py " + " ".join(argv if argv is not None else sys.argv[1:])
    results = {}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    for name in args.surveys.split(","):
        results[name] = run_survey(args.out, name, config, args.tracks)
        report = {"command": command, "config": dict(config.__dict__), "surveys": results}
        args.json.write_text(json.dumps(report, indent=2, default=str) + "\n")  # after each survey: a crash keeps them
    print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__" and __import__("sys").argv[1:2] == ["--prepare-only"]:
    import sys

    for n in sys.argv[3].split(","):
        t = time.perf_counter()
        prepare(Path(sys.argv[2]), n)
        print(n, "prepared in", round(time.perf_counter() - t, 1), "s", flush=True)
elif __name__ == "__main__":
    raise SystemExit(main())
