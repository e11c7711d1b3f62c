"""`watergan run`: every stage of the stage table (:mod:`pipeline.stages`) in order on a survey folder,
resumable.

    survey -> sfm -> dense -> range -> water -> gan (train, generate) -> restorer -> correct -> eval -> mesh
           -> diagnose -> report

A loop over the table: each stage's configuration is built the same way (:func:`stage_config`) and
run through :meth:`Workspace.run`; the stage finds its inputs in the workspace itself. A stage is
skipped when its ``result.json`` records the hash of the same configuration on the same upstream
results, so retraining the restorer reruns the correction and everything after it, while an
unchanged run finishes in seconds. ``force`` reruns named stages (and, through their new hashes,
the stages that read them).

Options: the common ones of :class:`RunOptions` (each sets the field of that name in every stage's
configuration, nested ones included, but the stage's ``local`` ones), and every other option of each
stage's configuration, named ``STAGE_FIELD`` (``gan_budget_min``, ``restorer_head``,
``diagnose_measure_n_points``; on the command line ``--gan-budget-min``...), see :func:`stage_options`.
The same keys work in a TOML file (``--config run.toml``). The run sets its threads first
(:func:`watergan.threads.use_threads`, ``--threads``; 0: the cores not busy) and runs each stage inside a heartbeat
(:func:`watergan.progress.activity`: a line every 30 s unless a progress bar printed).

A survey argument that is a video file or a folder of video clips is extracted into the workspace's
``video_frames`` folder first (:func:`pipeline.video.video_survey`, the ``video`` options), and the run goes on
with that folder as the survey (one folder per clips and options: other frames are another survey, so every
stage reruns on them).
"""

from __future__ import annotations

import dataclasses
import time
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from watergan.errors import UserInputError
from watergan.io import atomic_write_json
from watergan.progress import activity
from watergan.threads import threads_line, use_threads

from .cliargs import Option, build, convert, field_paths, options
from .video import VideoConfig, video_survey
from .workspace import Workspace, config_hash

if TYPE_CHECKING:
    from .stages import Stage


@dataclass(frozen=True)
class RunOptions:
    """Options of ``watergan run`` common to its stages (every field may be set in a TOML file; the
    CLI overrides it). Each stage's own options are in ``stages``."""

    survey_dir: str
    """The survey folder (images/, optional right/, camera.json, optional survey.json and rgbd/), or a video
    file or a folder of video clips (extracted into WORKSPACE/video_frames first)."""
    workspace: str
    """The run folder (created); stages write only here."""
    rgbd_dir: str = ""
    """In-air RGB-D set for WaterGAN (rgb/ + depth/); empty: the survey's rgbd/ folder, else a generic seafloor set
    rendered by the simulator into the gan stage's folder."""
    add: tuple[str, ...] = ()
    """Effects added to the water's stack, to WaterGAN's generator and to the diagnosed model (e.g. what
    `diagnose` found)."""
    scheduler: str = ""
    """Dask scheduler address (tcp://HOST:8786) for the per-image stages; empty: this machine."""
    seed: int = 0
    """Seed of every stage."""
    force: tuple[str, ...] = ()
    """Stages to rerun even when finished ('all': every stage)."""
    progress: bool = True
    """Progress bars, and a line at least every 30 s saying what a long stage is doing."""
    threads: int = field(default=0, metadata={"hash": False})
    """Threads of the stages' numerical work (torch, OpenCV); 0: the cores no other job keeps busy (the cores less
    the machine's load average), at least 1."""
    video: VideoConfig = field(default_factory=VideoConfig)
    """How frames are taken from a video given as the survey; its progress is the run's."""
    stages: Mapping[str, Mapping[tuple[str, ...], Any]] = field(default_factory=dict)
    """Per stage, the options given (field path -> value), by the keys of stage_options()."""


#: RunOptions fields that are not options (of a file or of the command line): the stages' own are given by key, and
#: the video's progress bar is the run's.
NOT_OPTIONS = ("stages", "video.progress")
#: RunOptions fields that set the field of the same name in every stage configuration having one.
COMMON = ("survey_dir", "rgbd_dir", "add", "scheduler", "seed", "progress")


def _common_paths(stage: Stage) -> dict[tuple[str, ...], str]:
    """The stage configuration's fields that RunOptions' common fields set (path -> RunOptions field)."""
    skip = {*stage.found, *stage.local}
    return {p: p[-1] for p in field_paths(stage.config_type, COMMON) if ".".join(p) not in skip}


def stage_options() -> list[tuple[str, Option]]:
    """Every stage option of ``watergan run``: (stage, option); the key is ``stage_field``. The fields the
    stage finds itself, its ``local`` ones and those the common options set are not options of the run."""
    from .stages import STAGES

    out = []
    for name, stage in STAGES.items():
        exclude = (*stage.found, *stage.local, *(".".join(p) for p in _common_paths(stage)))
        out += [(name, o) for o in options(stage.config_type, exclude)]
    return out


def run_defaults(stage: str) -> dict[tuple[str, ...], Any]:
    """The defaults ``watergan run`` gives to one stage's fields (the stage table's ``run_defaults``), by path."""
    from .stages import STAGES

    return {tuple(path.split(".")): value for path, value in STAGES[stage].run_defaults}


def run_default_keys() -> dict[str, Any]:
    """The run's own defaults by option key (for the help)."""
    keys = {(g, o.path): o.key(g) for g, o in stage_options()}
    from .stages import STAGES

    return {keys[(name, path)]: value for name in STAGES for path, value in run_defaults(name).items()
            if (name, path) in keys}


def run_options(values: Mapping[str, Any], where: str = "options") -> RunOptions:
    """RunOptions from flat keys (a TOML file's, or the command line's): common fields by name, the
    stages' options by their ``stage_field`` key; every value converted and checked as the command line
    does (:func:`pipeline.cliargs.convert`, effect names included; ``where`` names the source in errors)."""
    common = {o.key(): o for o in options(RunOptions, NOT_OPTIONS)}
    by_key = {o.key(g): (g, o) for g, o in stage_options()}
    stages: dict[str, dict] = {}
    fields: dict[str, Any] = {}
    unknown = []
    for key, value in values.items():
        if key in common:
            fields[common[key].path] = convert(common[key], value, where)
        elif key in by_key:
            group, o = by_key[key]
            stages.setdefault(group, {})[o.path] = convert(dataclasses.replace(o, name=(key,)), value, where)
        else:
            unknown.append(key)
    if unknown:
        raise UserInputError(f"unknown option(s) {', '.join(sorted(unknown))}; known: {', '.join(sorted(common))} "
                             f"and the stages' options (`watergan run --help`)")
    return build(RunOptions, fields, stages=stages)


def load_options_file(path: str | Path) -> dict:
    """Options from a TOML file: keys are RunOptions' common fields and the stages' option keys
    (``gan_budget_min``, ``restorer_head``...); an unknown key is an error naming it."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise UserInputError(f"configuration file {path} does not exist") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise UserInputError(f"configuration file {path} is not valid TOML: {exc}") from exc
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
    run_options({"survey_dir": "", "workspace": "", **values}, where=f"configuration file {path}")
    return values


def stage_config(stage: str, opts: RunOptions) -> Any:
    """The stage's configuration in this run: the common options where it has their fields, the run's
    defaults (``run_defaults``), the options given; the rest its own defaults."""
    from .stages import STAGES

    spec = STAGES[stage]
    common = {path: getattr(opts, name) for path, name in _common_paths(spec).items()}
    return build(spec.config_type, {**run_defaults(stage), **opts.stages.get(stage, {}), **common})


def check_inputs(opts: RunOptions) -> None:
    """Every file the run reads from the user, checked before any stage runs (also for a stage that
    finished earlier: the files may have changed since): each stage's ``check`` of its configuration
    (the survey folder, the board files the options name). A bad one is a :class:`UserInputError` naming it."""
    from .stages import STAGES, _load

    for name, stage in STAGES.items():
        if stage.check:
            _load(stage.check)(stage_config(name, opts))


def run_all(opts: RunOptions) -> dict:
    """Run (or skip) every stage; returns the summary written to ``WORKSPACE/run_summary.json``."""
    from .stages import STAGES

    unknown = sorted(set(opts.force) - set(STAGES) - {"all"})
    if unknown:
        raise UserInputError(f"--force: unknown stage(s) {', '.join(unknown)}; stages: {', '.join(STAGES)}, all")
    with use_threads(opts.threads) as threads:
        print(threads_line(threads, opts.threads), flush=True)
        return _run_stages(opts)


def _run_stages(given: RunOptions) -> dict:
    """run_all's work once the threads are set."""
    from .stages import STAGES

    opts = given
    frames = video_survey(Path(opts.survey_dir), Path(opts.workspace),
                          dataclasses.replace(opts.video, progress=opts.progress))
    if frames is not None:
        opts = dataclasses.replace(opts, survey_dir=str(frames.survey_dir))
    check_inputs(opts)
    ws = Workspace(opts.workspace)
    forced = set(STAGES) if "all" in opts.force else set(opts.force)
    began = time.perf_counter()
    timings: list[dict] = []
    for k, stage in enumerate(STAGES):
        config = stage_config(stage, opts)
        done = stage not in forced and ws.is_done(stage, config)
        label = f"[{k + 1}/{len(STAGES)}] {stage}"
        print(f"{label}: {'finished earlier, skipped' if done else 'running'}", flush=True)
        started = time.perf_counter()
        with activity(label, opts.progress and not done):
            ws.run(stage, config, force=stage in forced)
        seconds = time.perf_counter() - started
        timings.append({"stage": stage, "skipped": done, "seconds": round(seconds, 2)})
        if not done:
            print(f"      {stage} done in {seconds:.1f} s", flush=True)
    report = ws.path(ws.result("report").report)
    summary = {"workspace": str(ws.root), "report": str(report), "seconds": round(time.perf_counter() - began, 2),
               "stages": timings, "options": _summary_options(given), "options_hash": config_hash(given)}
    atomic_write_json(ws.root / "run_summary.json", summary)
    return summary


def _summary_options(opts: RunOptions) -> dict:
    """The options as flat keys (as a TOML file gives them)."""
    flat = {f.name: getattr(opts, f.name) for f in dataclasses.fields(opts) if f.name != "stages"}
    for group, values in opts.stages.items():
        flat.update({"_".join((group, *path)): value for path, value in values.items()})
    return flat


def print_summary(summary: dict) -> None:
    from .stages import STAGES

    print("\nstage        status     seconds")
    for t in summary["stages"]:
        print(f"{STAGES[t['stage']].folder:12} {'skipped' if t['skipped'] else 'ran':9} {t['seconds']:8.1f}")
    print(f"total {summary['seconds']:.1f} s")
    print(f"report: {summary['report']}")
