"""`watergan run`: every stage in order on a survey folder, resumable.

    survey -> gan (train, generate) -> restorer -> correct -> sfm -> dense -> eval -> mesh -> diagnose -> report

Each stage is a plain function ``fn(ws, config)`` run through :meth:`Workspace.run`: it is skipped
when its ``result.json`` records the hash of the same configuration. A stage's configuration holds
the hashes of the results of the stages it reads (``upstream``), so retraining the restorer reruns
the correction and everything after it, while an unchanged run finishes in seconds. ``force`` reruns named stages
(and, through their new hashes, the stages that read them).

The survey folder is what a user has: ``images/`` (one camera), optional ``right/`` (the stereo
rig's right frames, same names), ``camera.json`` (intrinsics, optional ``baseline_m``), optional
``survey.json`` and optional ``rgbd/`` (an in-air RGB-D set: ``rgb/`` + ``depth/``). It is checked
before any training starts, and never written to: the workspace's ``00_survey`` links to it.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from watergan.data import IMAGE_SUFFIXES, DataError, list_files, read_image
from watergan.errors import UserInputError
from watergan.nets.generator import DEFAULT_EFFECTS

from .workspace import STAGE_DIRS, Workspace, atomic_write_json, config_hash

STAGES = ("survey", "gan", "restorer", "correct", "sfm", "dense", "eval", "mesh", "diagnose", "report")


@dataclass(frozen=True)
class RunOptions:
    """Options of ``watergan run`` (every field may be set in a TOML file; the CLI overrides it)."""

    survey_dir: str
    """The survey folder (images/, optional right/, camera.json, optional survey.json and rgbd/)."""
    workspace: str
    """The run folder (created); stages write only here."""
    rgbd_dir: str = ""
    """In-air RGB-D set for WaterGAN (rgb/ + depth/); empty: ``<survey>/rgbd``, else a generic
    seafloor set rendered by the simulator into the workspace."""
    effects: tuple[str, ...] = DEFAULT_EFFECTS
    """Effects of WaterGAN's generator."""
    add: tuple[str, ...] = ()
    """Effects added to the generator and to the diagnosed model (e.g. what `diagnose` found)."""
    gan_budget_min: float = 4.0
    """WaterGAN training time, minutes."""
    restorer_budget_min: float = 2.5
    """Restorer training time, minutes."""
    diagnose_points: int = 1500
    """3D points the diagnosis samples."""
    diagnose_candidates: tuple[str, ...] = ()
    """Candidate effects the diagnosis tries (empty: every registered effect that qualifies)."""
    scheduler: str = ""
    """Dask scheduler address (tcp://HOST:8786) for the per-image stages; empty: this machine."""
    seed: int = 0
    """Seed of every stage."""
    force: tuple[str, ...] = ()
    """Stages to rerun even when finished."""
    progress: bool = True
    """Progress bars."""


@dataclass(frozen=True)
class Staged:
    """A stage's own configuration plus the hashes of the stage results it reads (``upstream``)."""

    config: Any
    upstream: dict[str, str] = field(default_factory=dict)


def load_options_file(path: str | Path) -> dict:
    """Options from a TOML file (keys: RunOptions field names)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise UserInputError(f"configuration file {path} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserInputError(f"configuration file {path} is not valid TOML: {exc}") from exc
    known = {f.name for f in dataclasses.fields(RunOptions)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise UserInputError(f"configuration file {path}: unknown option(s) {', '.join(unknown)}; "
                             f"known: {', '.join(sorted(known))}")
    return {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}


# ------------------------------------------------------------------------------------------ survey
def check_survey(survey_dir: Path) -> dict:
    """Refuse a survey folder that cannot be processed, before any training starts: a missing
    ``images/`` folder, fewer than 3 images, unreadable or truncated files, images of different
    sizes, ``right/`` frames that do not pair with ``images/`` by name. Returns a summary."""
    survey_dir = Path(survey_dir)
    images_dir = survey_dir / "images"
    if not survey_dir.is_dir():
        raise UserInputError(f"survey folder {survey_dir} does not exist")
    if not images_dir.is_dir():
        raise UserInputError(f"survey folder {survey_dir} has no images/ folder: put the frames in {images_dir}")
    files = list_files(images_dir, IMAGE_SUFFIXES)
    if len(files) < 3:
        raise UserInputError(f"{images_dir} holds {len(files)} image(s) (PNG, JPEG or TIFF); a survey needs at least 3")
    sizes: dict[tuple[int, int], list[str]] = {}
    bad = []
    for path in files:
        try:
            image = read_image(path)
        except DataError as exc:
            bad.append(str(exc))
            continue
        sizes.setdefault(image.shape[:2], []).append(path.name)
    if bad:
        raise UserInputError(f"{len(bad)} unreadable image(s) in {images_dir}; fix or remove them:\n  "
                             + "\n  ".join(bad))
    if len(sizes) > 1:
        listing = "; ".join(f"{w}x{h}: {len(n)} (e.g. {n[0]})" for (h, w), n in sizes.items())
        raise UserInputError(f"images in {images_dir} have different sizes ({listing}); one camera per survey")
    right_dir = survey_dir / "right"
    stereo = right_dir.is_dir()
    if stereo:
        left = {p.name for p in files}
        right = {p.name for p in list_files(right_dir, IMAGE_SUFFIXES)}
        if left != right:
            missing = sorted(left ^ right)[:5]
            raise UserInputError(f"right/ and images/ in {survey_dir} do not pair by file name (e.g. "
                                 f"{', '.join(missing)}); remove right/ for a single camera")
    if not (survey_dir / "camera.json").is_file():
        raise UserInputError(f"{survey_dir} has no camera.json (fx, fy, cx, cy, width, height): SfM and the "
                             f"range of each pixel need the intrinsics")
    (h, w), = sizes
    return {"n_images": len(files), "width": w, "height": h, "stereo": stereo,
            "simulated": (survey_dir / "truth" / "effects.json").is_file()}


@dataclass(frozen=True)
class SurveyStage:
    survey_dir: str
    rgbd_dir: str
    seed: int


def run_survey(ws: Workspace, cfg: SurveyStage) -> dict:
    """Check the survey and link it into ``00_survey`` (nothing of the user's is copied or changed);
    render a generic in-air RGB-D set when none is given."""
    survey, target = Path(cfg.survey_dir).resolve(), ws.stage_dir("survey").resolve()
    summary = check_survey(survey)
    if survey != target:
        for name in ("images", "right", "camera.json", "survey.json", "truth"):
            src, dst = survey / name, target / name
            if dst.is_symlink() and dst.resolve() != src.resolve():
                dst.unlink()  # a link left by a run on another survey folder
            if src.exists() and not dst.exists():
                dst.symlink_to(src)
    rgbd = Path(cfg.rgbd_dir) if cfg.rgbd_dir else survey / "rgbd"
    if not (rgbd / "rgb").is_dir():
        if cfg.rgbd_dir:
            raise UserInputError(f"in-air RGB-D folder {rgbd} has no rgb/ folder (rgb/ + depth/, paired by name)")
        from eval.synth.presets import PRESETS
        from eval.synth.rgbd import write_rgbd_set

        rgbd = ws.stage_dir("survey") / "generic_rgbd"
        if rgbd.exists():
            shutil.rmtree(rgbd)
        print(f"run: no in-air RGB-D set in {survey}: rendering a generic seafloor set into {rgbd}", file=sys.stderr)
        write_rgbd_set(rgbd, PRESETS["demo"].rgbd, cfg.seed)
    summary["rgbd_dir"] = str(rgbd)
    summary["survey_dir"] = str(survey)
    return summary


# ------------------------------------------------------------------------------------ the stages
@dataclass(frozen=True)
class GanStage:
    """WaterGAN's training and the rendering of the paired set: both settings enter the stage's hash."""

    train: Any
    """A :class:`watergan.train.GanConfig`."""
    generate: Any
    """A :class:`watergan.generate.GenerateConfig` (its model folder is the training's output)."""


def run_gan_stage(ws: Workspace, cfg: GanStage) -> dict:
    """Train WaterGAN, then render the paired set (in-air, depth, underwater) for the restorer."""
    from watergan.generate import generate
    from watergan.train import train_gan

    result = train_gan(cfg.train)
    gen = generate(cfg.generate)
    return {"train": result.to_json(), "generated": ws.relative(Path(cfg.generate.out_dir)),
            "generated_count": gen.count, "generate_seconds": gen.seconds}


def run_restorer_stage(ws: Workspace, cfg) -> dict:
    from watergan.train_restorer import train_restorer

    return train_restorer(cfg).to_json()


@dataclass(frozen=True)
class CorrectStage:
    images_dir: str
    batch_size: int = 4
    scheduler: str = field(default="", metadata={"hash": False})
    progress: bool = field(default=True, metadata={"hash": False})


def run_correct_stage(ws: Workspace, cfg: CorrectStage) -> dict:
    from .correct import correct_folder

    result = correct_folder(ws.stage_dir("restorer"), cfg.images_dir, ws.stage_dir("correct"), force=True,
                            batch_size=cfg.batch_size, progress=cfg.progress, scheduler=cfg.scheduler or None)
    return {"corrected": result.corrected, "failed": result.failed, "seconds": result.seconds,
            "images": ws.relative(ws.stage_dir("correct") / "images"),
            "fps": result.corrected / max(result.seconds, 1e-9)}


def run_diagnose_stage(ws: Workspace, cfg) -> dict:
    from eval.diagnose import run_diagnose

    r = run_diagnose(ws.root, cfg)
    return {"verdict": r.verdict, "heldout_rmse": r.heldout_rmse, "geometry": r.geometry,
            "best": r.best, "seconds": r.seconds}


def run_report_stage(ws: Workspace, cfg) -> dict:
    from eval.report import write_report

    return {"report": ws.relative(write_report(ws))}


def _has_nav_altitude(ws: Workspace) -> bool:
    """Whether the survey's navigation gives each frame's altitude (then the restorer takes it)."""
    path = ws.stage_dir("survey") / "survey.json"
    return path.is_file() and "nav_altitude_m" in json.loads(path.read_text())


def _stage_plan(ws: Workspace, opts: RunOptions, survey: dict) -> list[tuple[str, Callable[[], Any], Callable]]:
    """(stage, config factory, function) in order; factories run when the stage is reached, so they
    can read the results of the stages before."""
    from eval.diagnose import DiagnoseConfig
    from eval.diagnose_measure import MeasureConfig
    from eval.tables import EvaluateConfig
    from watergan.generate import GenerateConfig
    from watergan.train import GanConfig
    from watergan.train_restorer import RestorerConfig

    from .dense import DenseConfig
    from .mesh import MeshConfig
    from .sfm import SfmConfig

    images = str(ws.stage_dir("survey") / "images")
    effects = tuple(dict.fromkeys(opts.effects + opts.add))
    return [
        ("gan", lambda: GanStage(
            GanConfig(rgbd_dir=Path(survey["rgbd_dir"]), underwater_dir=Path(images),
                      out_dir=ws.stage_dir("gan") / "model", effects=effects, budget_min=opts.gan_budget_min,
                      seed=opts.seed, progress=opts.progress),
            GenerateConfig(model_dir=ws.stage_dir("gan") / "model", rgbd_dir=Path(survey["rgbd_dir"]),
                           out_dir=ws.stage_dir("gan") / "generated", seed=opts.seed, progress=opts.progress)),
         run_gan_stage),
        ("restorer", lambda: RestorerConfig(data_dir=ws.stage_dir("gan") / "generated",
                                            out_dir=ws.stage_dir("restorer"), budget_min=opts.restorer_budget_min,
                                            altitude=_has_nav_altitude(ws), seed=opts.seed, progress=opts.progress),
         run_restorer_stage),
        ("correct", lambda: CorrectStage(images_dir=images, scheduler=opts.scheduler, progress=opts.progress),
         run_correct_stage),
        ("sfm", lambda: SfmConfig(images_dir=images, seed=opts.seed), None),
        ("dense", lambda: DenseConfig(images_dir=images, scheduler=opts.scheduler, progress=opts.progress), None),
        ("eval", lambda: EvaluateConfig(survey_dir=str(ws.stage_dir("survey")), scheduler=opts.scheduler,
                                        progress=opts.progress), None),
        ("mesh", lambda: MeshConfig(images_dir=str(ws.stage_dir("correct") / "images"), progress=opts.progress),
         None),
        ("diagnose", lambda: DiagnoseConfig(add=opts.add, candidates=opts.diagnose_candidates,
                                            measure=MeasureConfig(n_points=opts.diagnose_points, seed=opts.seed)),
         run_diagnose_stage),
        ("report", lambda: "report", run_report_stage),
    ]


#: The stages each stage reads (their result hashes enter its configuration).
UPSTREAM = {
    "gan": ("survey",), "restorer": ("gan",), "correct": ("restorer",), "sfm": ("survey",), "dense": ("sfm",),
    "eval": ("correct", "dense", "restorer"), "mesh": ("correct", "dense"), "diagnose": ("sfm",),
    "report": ("gan", "restorer", "correct", "sfm", "dense", "eval", "mesh", "diagnose"),
}


def _stage_fn(stage: str) -> Callable:
    """The workspace function of the stages defined in their own modules."""
    if stage == "sfm":
        from .sfm import run_sfm
        return run_sfm
    if stage == "dense":
        from .dense import run_dense
        return run_dense
    if stage == "mesh":
        from .mesh import run_mesh
        return run_mesh
    if stage == "eval":
        from eval.tables import run_evaluate
        return run_evaluate
    raise KeyError(stage)


def _upstream(ws: Workspace, stage: str) -> dict[str, str]:
    """Per stage read by ``stage``: the hash of its whole result record, which changes whenever it
    reran (its timings differ), so a forced rerun upstream reruns the stages that read it."""
    return {s: config_hash(ws.load_result(s) or {}) for s in UPSTREAM.get(stage, ())}


def run_all(opts: RunOptions) -> dict:
    """Run (or skip) every stage; returns the summary written to ``WORKSPACE/run_summary.json``."""
    unknown = sorted(set(opts.force) - set(STAGES) - {"all"})
    if unknown:
        raise UserInputError(f"--force: unknown stage(s) {', '.join(unknown)}; stages: {', '.join(STAGES)}, all")
    from watergan.formation import get

    for name in opts.effects + opts.add:
        get(name)  # an unknown effect fails now, not after minutes of training
    ws = Workspace(opts.workspace)
    forced = set(STAGES) if "all" in opts.force else set(opts.force)
    began = time.perf_counter()
    timings: list[dict] = []

    def step(stage: str, config: Any, fn: Callable) -> dict:
        staged = Staged(config, _upstream(ws, stage))
        done = stage not in forced and ws.is_done(stage, staged)
        status = "finished earlier, skipped" if done else "running"
        print(f"[{STAGES.index(stage) + 1}/{len(STAGES)}] {stage}: {status}", flush=True)
        started = time.perf_counter()
        record = ws.run(stage, staged, lambda w, s: fn(w, s.config), force=stage in forced)
        seconds = time.perf_counter() - started
        timings.append({"stage": stage, "skipped": done, "seconds": round(seconds, 2)})
        if not done:
            print(f"      {stage} done in {seconds:.1f} s", flush=True)
        return record

    survey = step("survey", SurveyStage(str(opts.survey_dir), opts.rgbd_dir, opts.seed), run_survey)["result"]
    for stage, make_config, fn in _stage_plan(ws, opts, survey):
        step(stage, make_config(), fn or _stage_fn(stage))
    report = ws.path(ws.load_result("report")["result"]["report"])
    summary = {"workspace": str(ws.root), "report": str(report), "seconds": round(time.perf_counter() - began, 2),
               "stages": timings, "options": dataclasses.asdict(opts), "options_hash": config_hash(opts)}
    atomic_write_json(ws.root / "run_summary.json", summary)
    return summary


def print_summary(summary: dict) -> None:
    print("\nstage        status     seconds")
    for t in summary["stages"]:
        print(f"{STAGE_DIRS[t['stage']]:12} {'skipped' if t['skipped'] else 'ran':9} {t['seconds']:8.1f}")
    print(f"total {summary['seconds']:.1f} s")
    print(f"report: {summary['report']}")


def stage_seconds(workspace: str | Path) -> dict[str, float]:
    """Seconds each stage took when it last ran (from run_summary.json entries that ran)."""
    data = json.loads((Path(workspace) / "run_summary.json").read_text())
    return {t["stage"]: t["seconds"] for t in data["stages"] if not t["skipped"]}

