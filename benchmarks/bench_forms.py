"""The water against missing effects of random shape (issue 52): N seeded surveys, each with one effect the default
stack lacks, its form and parameters drawn at random, measured as a distribution.

    .venv/bin/python benchmarks/bench_forms.py [--draws 20] [--seed 0] [--out DIR] [--no-diagnose]

Each draw picks a family and draws its shape (:func:`draw_effect`; the forms are the plugins in
``benchmarks/plugins/forms/``, one effect per file, and ``water_drift`` / ``survey_exposure`` of
``benchmarks/plugins/robust_forms.py``):

- ``falloff``: a multiplicative falloff about a point anywhere in the image, per-channel strength 0-80 %, with a
  polynomial, clipped quadratic, Gaussian or cosine-power radial profile;
- ``spot``: light added about a point (position, width, colour), fading to zero in view or over a floor;
- ``ramp``: a veil growing across the image along a direction, starting inside the image (its zero level in view)
  or outside it;
- ``frame_gain``: gains per frame set along the survey, grey or per channel;
- ``auto_white_balance`` / ``auto_exposure``: gains the camera sets from each frame's own pixels (gray world, mean
  luminance), so correlated with the frame's range; the oracle inverts the gains each frame received
  (:func:`realise_content_gains`);
- ``water_drift``: the attenuation changing along the survey (a ramp or a wave per channel).

and the survey: stereo or monocular, the demo's sandy floor or a rocky one (:func:`survey_config`: the demo's water
and camera at 320x240, 3 lines of 6 frames at 2.5 m with a 0.5 m altitude wave). On each it runs the pipeline's SfM
dense and range stages, then the water stage itself (:func:`water_stage`: ``watergan water --workspace WS`` with its
defaults, :class:`pipeline.water.WaterStage`; no tracks; the fine grid on the range stage's maps) and measures its
water.json with bench_water's helpers: eta, B_inf and the veil at the views' median range against the truth
(relative error, 95 % interval covering it), and the physics correction's PSNR, consistency and affine-RMSE
(:func:`affine_rmse`) beside the oracle's and raw's. Then the diagnosis stage as ``watergan run`` runs it after the
water (:func:`pipeline.diagnose.run_diagnose`: the water's stack as its model, its fields over the image and gains per
frame read by the candidates' checks and the verdict; on the SfM tracks, the settings of tests/test_diagnose.py, in a
process without the plugins so that only the effect library is offered): none of the forms is in the library, so any
candidate accepted as the missing effect is a false acceptance; one accepted as a partial step (the verdict says the
rest is of another form: the diagnosis's ``partial`` flag) is counted apart (:func:`acceptance`).

Writes ``benchmarks/results/forms.json`` (after each draw): per draw the truth and the measurements, and a
``summary`` of fractions of the draws (eta within 10 % in every channel, eta covered in every channel, veil within
15 % in every channel, physics PSNR within 1.5 dB of the oracle's, physics PSNR below raw's), the count of false
acceptances and that of partial steps. Per draw also each structure alternative's held-out test and eta
(``structure``), and in the summary how often eta would be within 10 % had the estimate followed the structure the
survey prefers most (``eta_within_10pct_preferred_structure``: the alternative whose held-out interval lies below 0
with the largest gain, else the estimate). Workspaces go to ``--out`` and are reused when present.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from bench_water import (  # noqa: E402  (the benchmarks folder is not a package)
    compare,
    compare_veil,
    correct_folders,
    load_inputs,
    load_robust_forms,
    measure_corrections,
    truth_params,
)

from pipeline.stages import stage_folder  # noqa: E402

#: The folder of the drawn forms' effects, one per file named as the effect.
FORMS_DIR = Path(__file__).parent / "plugins" / "forms"
#: The families drawn, each as likely.
FAMILIES = ("falloff", "spot", "ramp", "frame_gain", "auto_white_balance", "auto_exposure", "water_drift")
#: The falloff's radial profiles: the effect of each.
FALLOFF_PROFILES = {"polynomial": "falloff_polynomial", "clipped": "falloff_clip", "gaussian": "falloff_gaussian",
                    "cosine_power": "falloff_cosine"}
#: Effects that set their gains from each frame's pixels: the oracle gets the gains each frame received.
CONTENT_GAINS = ("auto_white_balance", "auto_exposure")
#: The survey: lines x frames per line.
LINES, FRAMES_PER_LINE = 3, 6
TERRAINS = ("sand", "rocky")


def load_forms() -> None:
    """Register the drawn forms' effects (``FORMS_DIR``) and bench_water's robustness forms, unless they are."""
    from watergan.formation import available, load_plugin

    load_robust_forms()
    for path in sorted(FORMS_DIR.glob("*.py")):
        if path.stem not in available():
            load_plugin(path)


@dataclass(frozen=True)
class Draw:
    """One drawn survey: the hidden effect (``family``, ``effect``, its ``params``) and the survey's geometry."""

    index: int
    seed: int
    family: str
    effect: str
    params: dict
    stereo: bool
    terrain: str


def _round(values) -> list | float:
    return np.round(np.asarray(values, float), 4).tolist()


def draw_effect(rng: np.random.Generator, n_frames: int, eta_per_m: np.ndarray) -> tuple[str, str, dict]:
    """(family, effect name, parameters) of one missing effect drawn from ``FAMILIES`` (see the module's doc)."""
    family = str(rng.choice(FAMILIES))
    if family == "falloff":
        profile = str(rng.choice(list(FALLOFF_PROFILES)))
        params = {"centre_uv": _round(rng.uniform(0, 1, 2)), "strength": _round(rng.uniform(0, 0.8, 3))}
        params.update({"polynomial": {"power": _round(rng.uniform(1.0, 5.0))},
                       "clipped": {"width": _round(rng.uniform(0.3, 1.5))},
                       "gaussian": {"width": _round(rng.uniform(0.25, 1.2))},
                       "cosine_power": {"width": _round(rng.uniform(0.6, 2.0)),
                                        "power": _round(rng.uniform(1.0, 4.0))}}[profile])
        return f"falloff_{profile}", FALLOFF_PROFILES[profile], params
    if family == "spot":
        zero_in_view = bool(rng.random() < 0.5)
        return family, "additive_spot", {
            "centre_uv": _round(rng.uniform(0, 1, 2)), "amplitude": _round(rng.uniform(0.01, 0.08) * colour(rng)),
            "width": _round(rng.uniform(0.1, 0.4) if zero_in_view else rng.uniform(0.2, 1.0)),
            "floor": 0.0 if zero_in_view else _round(rng.uniform(0.1, 0.5))}
    if family == "ramp":
        zero_in_view = bool(rng.random() < 0.5)
        return family, "additive_ramp", {
            "angle_deg": _round(rng.uniform(-180, 180)), "amplitude": _round(rng.uniform(0.01, 0.06) * colour(rng)),
            "start": _round(rng.uniform(-0.3, 0.1) if zero_in_view else rng.uniform(-1.2, -0.8)),
            "width": _round(rng.uniform(0.3, 1.2))}
    if family == "frame_gain":
        sd = rng.uniform(0.05, 0.25)
        if rng.random() < 0.5:
            return "frame_gain_grey", "survey_exposure", {"log_gain": _round(rng.normal(0, sd, n_frames))}
        return "frame_gain_colour", "frame_colour_gain", {"log_gain": _round(rng.normal(0, sd, (n_frames, 3)))}
    if family == "auto_white_balance":
        return family, "auto_white_balance", {"alpha": _round(rng.uniform(0.5, 1.0))}
    if family == "auto_exposure":
        return family, "auto_exposure", {"target": _round(rng.uniform(0.08, 0.25)),
                                         "alpha": _round(rng.uniform(0.5, 1.0))}
    amplitude = rng.uniform(0.1, 0.3, 3) * eta_per_m  # water_drift: a ramp or a wave per channel
    t = np.linspace(-1.0, 1.0, n_frames)
    shape = t if rng.random() < 0.5 else np.sin(np.pi * t * rng.uniform(0.5, 2.0) + rng.uniform(0, 2 * np.pi))
    return family, "water_drift", {"delta_eta_per_m": _round(shape[:, None] * amplitude * rng.choice([-1, 1], 3))}


def colour(rng: np.random.Generator) -> np.ndarray:
    """A random colour of mean 1 (three channels drawn on the simplex, times 3)."""
    return 3.0 * rng.dirichlet(np.ones(3))


def draws(n: int, seed: int) -> list[Draw]:
    """The ``n`` draws of the seed ``seed``; draw k depends on (seed, k) alone."""
    from eval.synth.config import default_visible_stack

    eta = np.asarray(next(e for e in default_visible_stack() if e["name"] == "attenuation")["params"]["eta_per_m"])
    out = []
    for k in range(n):
        rng = np.random.default_rng([seed, 52, k])
        family, effect, params = draw_effect(rng, LINES * FRAMES_PER_LINE, eta)
        out.append(Draw(index=k, seed=1000 * seed + k, family=family, effect=effect, params=params,
                        stereo=bool(rng.random() < 0.5), terrain=str(rng.choice(TERRAINS))))
    return out


def survey_config(draw: Draw):
    """The draw's survey: the demo's water, camera (320x240) and site, 3 lines of 6 frames at 2.5 m with a 0.5 m
    altitude wave of period 7 frames, 10 mm texels (no aliasing at 11 mm per pixel), a one-view RGB-D set; on the
    ``rocky`` terrain 25 boulders 0.15-0.45 m high."""
    from eval.synth import make_config
    from eval.synth.camera import CameraConfig

    cfg = make_config("demo", seed=draw.seed)
    scene = replace(cfg.scene, texel_m=0.01)
    if draw.terrain == "rocky":
        scene = replace(scene, n_rocks=25, rock_radius_m=(0.2, 0.5), rock_height_m=(0.15, 0.45))
    return replace(cfg, camera=CameraConfig(width_px=320, height_px=240, hfov_deg=70.0), scene=scene,
                   trajectory=replace(cfg.trajectory, stereo=draw.stereo, n_lines=LINES,
                                      frames_per_line=FRAMES_PER_LINE, forward_overlap=0.75, altitude_wave_m=0.5,
                                      altitude_wave_frames=7.0),
                   rgbd=replace(cfg.rgbd, n_scenes=1, views_per_scene=1),
                   formation=replace(cfg.formation, hidden=({"name": draw.effect, "params": draw.params},)))


def realise_content_gains(survey: Path, effect: str) -> list[list[float]]:
    """Where the hidden effect sets each frame's gains from its own pixels (``CONTENT_GAINS``), the gains the frames
    of ``images/`` received: the frame rendered noise-free without it (true geometry and in-air image) gives its
    gains by the effect's own rule. The truth's hidden and full stacks then hold them as ``frame_colour_gain``
    (log gains per frame and channel), which the oracle can invert; returns the log gains."""
    import torch

    from eval.baseline_runs import OracleGeometry
    from watergan.formation import Stack

    truth_file = survey / "truth" / "effects.json"
    effects = json.loads(truth_file.read_text())
    geometry = OracleGeometry(survey)
    before = Stack.from_config([e for e in effects["full"] if e["name"] != effect])
    content = next(e for e in geometry.stack.effects if e.name == effect)
    log_gains = []
    with torch.no_grad():
        for name in geometry.truth.frames:
            state = geometry.state(name)
            image = before(state.replace(direct=state.direct.to(torch.float64))).image
            ratio = content(state.replace(direct=image, backscatter=torch.zeros_like(image))).direct / image
            log_gains.append(torch.log(ratio.mean(dim=(0, 2, 3))).tolist())
    entry = {"name": "frame_colour_gain", "params": {"log_gain": _round(log_gains)}}
    for key in ("hidden", "full"):
        effects[key] = [entry if e["name"] == effect else e for e in effects[key]]
    truth_file.write_text(json.dumps(effects, indent=1))
    return log_gains


def workspace_name(draw: Draw) -> str:
    """The draw's workspace under ``--out``."""
    return f"draw_{draw.index:02d}_{draw.seed}"


def prepare(root: Path, draw: Draw) -> Path:
    """Simulate the draw's survey into ``root/draw_<k>_<seed>/00_survey`` and run SfM, dense and the range maps
    (each skipped when done); returns the workspace's root."""
    from eval.synth import simulate_survey
    from pipeline.dense import DenseConfig
    from pipeline.range import RangeConfig
    from pipeline.sfm import SfmConfig
    from pipeline.workspace import Workspace

    ws = Workspace(root / workspace_name(draw))
    survey = ws.stage_dir("survey")
    if not (survey / "truth" / "config.json").is_file():
        simulate_survey(survey, survey_config(draw), force=True, progress=False)
        if draw.effect in CONTENT_GAINS:
            realise_content_gains(survey, draw.effect)
    if not (ws.stage_dir("sfm") / "tracks.npz").is_file():
        ws.run("sfm", SfmConfig())
    if not (ws.stage_dir("dense") / "result.json").is_file():
        ws.run("dense", DenseConfig(progress=False))
    ws.run("range", RangeConfig(progress=False))
    return ws.root


def affine_rmse(folder: Path, truth_dir: Path, names: list[str]) -> float:
    """Mean over frames of the RMSE (sRGB 0..1) of the in-air truth T against the corrected frame J after the best
    affine map per channel, min over (a_c, b_c) of sqrt(mean((a_c J_c + b_c - T_c)^2)): the corrections' shape over
    the image and range, whatever their level."""
    from eval.colour import read_rgb
    from watergan.io import frame_file

    errors = []
    for name in names:
        truth = read_rgb(frame_file(truth_dir, name), linear=False).reshape(-1, 3)
        image = read_rgb(frame_file(folder, name), linear=False).reshape(-1, 3)
        squared = 0.0
        for c in range(3):
            design = np.stack([image[:, c], np.ones(len(image))], axis=1)
            coef, *_ = np.linalg.lstsq(design, truth[:, c], rcond=None)
            squared += float(np.mean((design @ coef - truth[:, c]) ** 2))
        errors.append(math.sqrt(squared / 3))
    return float(np.mean(errors))


def water_stage(ws_root: Path):
    """The water stage on a prepared workspace, as ``watergan water --workspace WS`` runs it (its defaults: the SfM
    scale's spread, no tracks, the fine grid on the range stage's maps; skipped when done): (its result, its
    configuration)."""
    from pipeline.water import WaterStage
    from pipeline.workspace import Workspace

    config = WaterStage(progress=False)
    return Workspace(ws_root).run("water", config), config


def estimate(ws_root: Path):
    """The water of a prepared workspace by the water stage (:func:`water_stage`), so that the diagnosis after it
    sees what a user's does: water.json with its fields over the image and gains per frame, and the stage's
    measurement table. Returns (water.json's record, its stack, frames, K, board, tracks, the stage's
    configuration)."""
    from watergan.formation import Stack
    from watergan.water_record import read_water

    result, config = water_stage(ws_root)
    record = read_water(Path(ws_root) / result.water_json)
    frames, K, _, board, tracks = load_inputs(ws_root)
    return record, Stack.from_config(record.stack), frames, K, board, tracks, config


def diagnose(ws_root: Path) -> dict:
    """The diagnose stage after the water stage (:func:`water_stage`, run first where it has not), on the
    workspace's SfM tracks (the settings of tests/test_diagnose.py), in a process of its own where only the library's
    effects are registered: {"accepted": the best accepted candidate or None, "partial": whether it is accepted as a
    partial step, "verdict", "ranking": the first three candidates}."""
    from pipeline.workspace import release_workspaces

    water_stage(ws_root)  # a draw measured before the bench ran the water stage (--resume) gets it now
    release_workspaces()  # the stages run here hold the workspace's lock until released
    done = subprocess.run([sys.executable, __file__, "--diagnose-only", str(ws_root)], capture_output=True,
                          text=True, check=False)
    if done.returncode != 0:
        return {"accepted": None, "error": done.stderr.strip().splitlines()[-1:] or ["failed"]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def diagnose_only(ws_root: Path) -> dict:
    """:func:`diagnose`'s process: run the diagnosis and return its JSON line."""
    import shutil

    import torch

    from eval.diagnose import DiagnoseConfig
    from eval.diagnose_measure import MeasureConfig
    from eval.fit import FitConfig
    from pipeline.diagnose import run_diagnose

    torch.set_num_threads(1)
    for stale in (ws_root / "diagnose", stage_folder(ws_root, "diagnose")):
        shutil.rmtree(stale, ignore_errors=True)
    (ws_root / "model_ledger.jsonl").unlink(missing_ok=True)
    config = DiagnoseConfig(geometry="sfm", measure=MeasureConfig(n_points=600), fit=FitConfig(iterations=60),
                            bootstrap=500, plots=False)
    result = run_diagnose(ws_root, config, progress=False)
    accepted = next((r for r in result.ranking if r["name"] == result.best), {})
    return {"accepted": result.best, "partial": bool(accepted.get("partial")),
            "verdict": result.verdict.splitlines()[0],
            "ranking": [{k: r[k] for k in ("name", "change", "significant", "partial") if k in r}
                        for r in result.ranking[:3]]}


def run_draw(root: Path, draw: Draw, with_diagnosis: bool) -> dict:
    """Prepare, estimate, correct and measure one draw; its JSON record."""
    from pipeline.range import RangeConfig

    seconds = {}
    t = time.perf_counter()
    ws_root = prepare(root, draw)
    seconds["prepare"] = time.perf_counter() - t
    t = time.perf_counter()
    water, stack, frames, K, board, tracks, config = estimate(ws_root)
    seconds["water"] = time.perf_counter() - t
    truth = truth_params(stage_folder(ws_root, "survey"))
    params = compare(water.params, truth)
    params.update(compare_veil(water.veil, truth))
    t = time.perf_counter()
    corr = correct_folders(ws_root, frames, K, stack, ws_root / "forms_bench", RangeConfig().agreement)
    names = [f.name for f in frames]
    metrics = measure_corrections(ws_root, tracks, board, corr["folders"], names)
    folders = {"raw": stage_folder(ws_root, "survey") / "images", **corr["folders"]}
    truth_dir = stage_folder(ws_root, "survey") / "truth" / "inair"
    correction = {label: {"psnr_db": metrics[label]["psnr_db"], "consistency": metrics[label]["consistency"],
                          "board_ciede2000": metrics[label]["board_ciede2000"],
                          "affine_rmse": affine_rmse(folders[label], truth_dir, names)}
                  for label in ("raw", "physics", "oracle")}
    seconds["correct"] = time.perf_counter() - t
    keep = ("attenuation.eta_per_m", "backscatter.b_inf", "veil")
    eta_truth = np.asarray(truth["attenuation.eta_per_m"], float)
    structure = [{**a.to_json(), "eta_rel_error": _round(np.asarray(a.values[eta], float) / eta_truth - 1)}
                 for a in water.alternatives if (eta := "attenuation.eta_per_m") in a.values]
    record = {"truth": {**asdict(draw), "workspace": ws_root.name},
              "params": {k: params[k] for k in keep if k in params}, "structure": structure, "correction": correction,
              "diagnosis": None, "false_acceptance": False, "partial_step": False,
              "seconds": {k: round(v, 1) for k, v in seconds.items()}}
    return add_diagnosis(record, ws_root) if with_diagnosis else record


def acceptance(diagnosis: dict | None) -> str:
    """What the diagnosis of a draw (:func:`diagnose`'s record; None: not diagnosed) accepted: "full" (a library
    effect as the missing one: a false acceptance, no drawn form is in the library), "partial" (a library effect as
    a partial step, the rest of another form: a record without the flag counts as full) or "" (nothing)."""
    if not diagnosis or not diagnosis.get("accepted"):
        return ""
    return "partial" if diagnosis.get("partial") else "full"


def add_diagnosis(record: dict, ws_root: Path) -> dict:
    """``record`` with the diagnosis of its workspace (:func:`diagnose`), whether it accepted a library effect as
    the missing one (a false acceptance) or as a partial step (:func:`acceptance`), and its seconds."""
    t = time.perf_counter()
    diagnosis = diagnose(ws_root)
    seconds = {**record["seconds"], "diagnose": round(time.perf_counter() - t, 1)}
    kind = acceptance(diagnosis)
    return {**record, "diagnosis": diagnosis, "false_acceptance": kind == "full", "partial_step": kind == "partial",
            "seconds": seconds}


def draw_targets(record: dict) -> dict[str, bool]:
    """The summary's tests of one draw."""
    p, c = record["params"], record["correction"]

    def every(key: str, test) -> bool:
        return key in p and all(test(v) for v in np.ravel(p[key][("rel_error")]))

    preferred = [t for t in record.get("structure", []) if t.get("preferred")]
    chosen = min(preferred, key=lambda t: t["heldout_change_pct"])["eta_rel_error"] if preferred else \
        p.get("attenuation.eta_per_m", {}).get("rel_error", [np.inf])
    return {"eta_within_10pct": every("attenuation.eta_per_m", lambda v: abs(v) <= 0.10),
            "eta_within_10pct_preferred_structure": bool(np.all(np.abs(chosen) <= 0.10)),
            "eta_covered": "attenuation.eta_per_m" in p and all(p["attenuation.eta_per_m"].get("covered", [False])),
            "veil_within_15pct": every("veil", lambda v: abs(v) <= 0.15),
            "psnr_within_1p5db_of_oracle": c["physics"]["psnr_db"] >= c["oracle"]["psnr_db"] - 1.5,
            "worse_than_raw": c["physics"]["psnr_db"] < c["raw"]["psnr_db"]}


def summarise(records: list[dict]) -> dict:
    """Fractions of the draws meeting each of :func:`draw_targets`, the count of false acceptances (a library effect
    accepted as the missing one) and of partial steps (one accepted as a partial step; :func:`acceptance`)."""
    targets = [draw_targets(r) for r in records]
    out = {"draws": len(records)}
    for key in ("eta_within_10pct", "eta_covered", "veil_within_15pct", "psnr_within_1p5db_of_oracle",
                "worse_than_raw", "eta_within_10pct_preferred_structure"):
        out[key] = round(float(np.mean([t[key] for t in targets])), 3) if targets else None
    kinds = [acceptance(r["diagnosis"]) for r in records]
    out["false_acceptances"] = kinds.count("full")
    out["partial_steps"] = kinds.count("partial")
    out["diagnosed"] = sum(r["diagnosis"] is not None and "error" not in r["diagnosis"] for r in records)
    return out


def row(record: dict) -> str:
    """One line of the table printed as the draws go."""
    t, p, c = record["truth"], record["params"], record["correction"]

    def pct(key: str) -> str:
        if key not in p:
            return "n/a"
        cover = "".join("y" if v else "N" for v in p[key].get("covered", []))
        return "/".join(f"{100 * v:+.0f}" for v in np.ravel(p[key]["rel_error"])) + f" {cover}"

    diagnosis = record["diagnosis"]
    accepted = "-" if diagnosis is None else "error" if "error" in diagnosis else diagnosis["accepted"] or "none"
    accepted += " (partial step)" if acceptance(diagnosis) == "partial" else ""
    return (f"| {t['index']:2d} | {t['family']:22s} | {'stereo' if t['stereo'] else 'mono'} {t['terrain']:5s} "
            f"| {pct('attenuation.eta_per_m'):18s} | {pct('veil'):18s} | {c['physics']['psnr_db']:5.1f} "
            f"| {c['oracle']['psnr_db']:5.1f} | {c['raw']['psnr_db']:5.1f} | {c['physics']['affine_rmse']:.4f} "
            f"| {accepted} | {sum(record['seconds'].values()):4.0f} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=20, help="surveys drawn")
    parser.add_argument("--seed", type=int, default=0, help="seed of the draws")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_forms"), help="workspaces (reused)")
    parser.add_argument("--no-diagnose", action="store_true", help="skip the diagnosis on each draw")
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/forms.json"))
    parser.add_argument("--resume", action="store_true", help="reuse the draws --json already holds (same truth, "
                        "workspace kept) and run only what they lack: the diagnosis where it failed or was skipped")
    args = parser.parse_args(argv)
    from tqdm import tqdm

    load_forms()
    command = "benchmarks/bench_forms.py " + " ".join(argv if argv is not None else sys.argv[1:])
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=False,
                            cwd=Path(__file__).parent).stdout.strip()
    args.json.parent.mkdir(parents=True, exist_ok=True)
    print("| draw | family | survey | eta error R/G/B %, covered | veil error %, covered | physics PSNR | oracle "
          "| raw | physics affine-RMSE | accepted | s |\n|---|---|---|---|---|---|---|---|---|---|---|")
    previous = {}
    if args.resume and args.json.is_file():
        previous = {r["truth"]["workspace"]: r for r in json.loads(args.json.read_text())["draws"]}
    records, failed = [], []
    for draw in tqdm(draws(args.draws, args.seed), desc="draws", unit="survey"):
        try:
            record = previous.get(workspace_name(draw))
            kept = (stage_folder(args.out / workspace_name(draw), "survey") / "truth" / "config.json").is_file()
            same = record is not None and {**record["truth"], "workspace": None} == {**asdict(draw), "workspace": None}
            if not (same and kept):
                record = run_draw(args.out, draw, not args.no_diagnose)
            elif not args.no_diagnose and (record["diagnosis"] is None or "error" in record["diagnosis"]):
                record = add_diagnosis(record, args.out / workspace_name(draw))
            records.append(record)
            tqdm.write(row(records[-1]))
        except Exception as exc:  # a draw the pipeline cannot take (SfM fails, ...): recorded, not measured
            failed.append({"truth": asdict(draw), "error": f"{type(exc).__name__}: {exc}"})
            tqdm.write(f"| {draw.index:2d} | {draw.family} | failed: {failed[-1]['error']} |")
        report = {"command": command, "commit": commit, "summary": {**summarise(records), "failed": len(failed)},
                  "seconds_per_draw": round(float(np.mean([sum(r["seconds"].values()) for r in records])), 1)
                  if records else None, "draws": records, "failed": failed}
        args.json.write_text(json.dumps(report, indent=1, default=str) + "\n")  # after each draw
    print("\nsummary:", json.dumps(report["summary"]), f"\nseconds per draw: {report['seconds_per_draw']}",
          f"\nwrote {args.json}")
    return 0


if __name__ == "__main__" and sys.argv[1:2] == ["--diagnose-only"]:
    print(json.dumps(diagnose_only(Path(sys.argv[2])), default=str))
elif __name__ == "__main__":
    raise SystemExit(main())
