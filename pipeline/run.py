"""`watergan run`: every stage of the stage table (:mod:`pipeline.stages`) in order on a survey folder,
resumable.

    survey -> sfm -> dense -> water -> gan (train, generate) -> restorer -> correct -> eval -> mesh -> diagnose
           -> report

Each stage runs through :meth:`Workspace.run`: it is skipped when its ``result.json`` records the
hash of the same configuration on the same upstream results, so retraining the restorer reruns the
correction and everything after it, while an unchanged run finishes in seconds. ``force`` reruns
named stages (and, through their new hashes, the stages that read them).

Options: the common ones of :class:`RunOptions`, and every option of each stage's configuration
that the plan does not set itself, named ``STAGE_FIELD`` (``gan_budget_min``,
``restorer_head``, ``diagnose_measure_n_points``; on the command line ``--gan-budget-min``...),
see :func:`stage_options`. The same keys work in a TOML file (``--config run.toml``).
"""

from __future__ import annotations

import dataclasses
import time
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from watergan.errors import UserInputError
from watergan.io import atomic_write_json

from .cliargs import Option, build, convert, options, with_values
from .survey import SurveyConfig, check_survey
from .workspace import Workspace, config_hash


@dataclass(frozen=True)
class RunOptions:
    """Options of ``watergan run`` common to its stages (every field may be set in a TOML file; the
    CLI overrides it). Each stage's own options are in ``stages``."""

    survey_dir: str
    """The survey folder (images/, optional right/, camera.json, optional survey.json and rgbd/)."""
    workspace: str
    """The run folder (created); stages write only here."""
    rgbd_dir: str = ""
    """In-air RGB-D set for WaterGAN (rgb/ + depth/); empty: ``<survey>/rgbd``, else a generic
    seafloor set rendered by the simulator into the workspace."""
    add: tuple[str, ...] = ()
    """Effects added to WaterGAN's generator and to the diagnosed model (e.g. what `diagnose` found)."""
    scheduler: str = ""
    """Dask scheduler address (tcp://HOST:8786) for the per-image stages; empty: this machine."""
    seed: int = 0
    """Seed of every stage."""
    force: tuple[str, ...] = ()
    """Stages to rerun even when finished ('all': every stage)."""
    progress: bool = True
    """Progress bars."""
    stages: Mapping[str, Mapping[tuple[str, ...], Any]] = field(default_factory=dict)
    """Per stage option group, the options given (field path -> value): see :func:`stage_options`."""


# --------------------------------------------------------------------------- the stages' options
#: The gan stage's configuration holds two: its training (option group ``gan``) and the rendering of
#: its pairs (``generate``); (configuration class, fields the plan sets itself).
_GAN_GROUPS: dict[str, tuple[str, tuple[str, ...]]] = {
    "gan": ("watergan.train:GanConfig", ("rgbd_dir", "underwater_dir", "out_dir", "site_water", "seed", "resume",
                                         "device", "progress")),
    "generate": ("watergan.generate:GenerateConfig", ("model_dir", "rgbd_dir", "out_dir", "seed", "device",
                                                      "progress")),
}
#: RunOptions fields that every stage configuration having a field of the same name takes.
_COMMON = ("seed", "progress", "scheduler")


def _groups() -> dict[str, tuple[Any, tuple[str, ...]]]:
    """Per option group of ``watergan run`` (a stage; the gan stage gives two): (configuration class or
    its ``module:Class``, the fields the plan sets itself)."""
    from .stages import STAGES

    out: dict[str, tuple[Any, tuple[str, ...]]] = {}
    for name, stage in STAGES.items():
        if name == "gan":
            out.update(_GAN_GROUPS)
        elif name not in ("survey", "report"):  # the survey's options are RunOptions'; the report has none
            out[name] = (stage.config, stage.run_sets)
    return out


#: Where ``watergan run`` starts from other defaults than the stage's own (by option key).
RUN_DEFAULTS: dict[str, Any] = {"gan_budget_min": 4.0, "restorer_budget_min": 2.5,
                                "diagnose_measure_n_points": 1500}


def _config_class(group: str) -> type:
    from .stages import _load

    return _load(_groups()[group][0])


def stage_options() -> list[tuple[str, Option]]:
    """Every stage option of ``watergan run``: (group, option); the key is ``group_field``."""
    return [(group, o) for group, (config, plan_sets) in _groups().items()
            for o in options(_config_class(group), plan_sets)]


def run_defaults(group: str) -> dict[tuple[str, ...], Any]:
    """The defaults :data:`RUN_DEFAULTS` gives to one option group, by field path."""
    return {o.path: RUN_DEFAULTS[o.key(g)] for g, o in stage_options() if g == group and o.key(g) in RUN_DEFAULTS}


def run_options(values: Mapping[str, Any], where: str = "options") -> RunOptions:
    """RunOptions from flat keys (a TOML file's, or the command line's): common fields by name, the
    stages' options by their ``group_field`` key; every value converted and checked as the command line
    does (:func:`pipeline.cliargs.convert`; ``where`` names the source in errors)."""
    common = {o.key(): o for o in options(RunOptions, ("stages",))}
    by_key = {o.key(g): (g, o) for g, o in stage_options()}
    stages: dict[str, dict] = {}
    fields: dict[str, Any] = {}
    unknown = []
    for key, value in values.items():
        if key in common:
            fields[key] = convert(common[key], value, where)
        elif key in by_key:
            group, o = by_key[key]
            stages.setdefault(group, {})[o.path] = convert(dataclasses.replace(o, path=(key,)), value, where)
        else:
            unknown.append(key)
    if unknown:
        raise UserInputError(f"unknown option(s) {', '.join(sorted(unknown))}; known: {', '.join(sorted(common))} "
                             f"and the stages' options (`watergan run --help`)")
    return RunOptions(**fields, stages=stages)


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


def _configured(group: str, opts: RunOptions, **fixed: Any) -> Any:
    """The group's configuration: the plan's ``fixed`` fields (and RunOptions' common ``seed``,
    ``progress``, ``scheduler`` where the configuration has them), the run's defaults, the options given."""
    cls = _config_class(group)
    names = {f.name for f in dataclasses.fields(cls)}
    fixed = {**{k: getattr(opts, k) for k in _COMMON if k in names}, **fixed}
    values = {**run_defaults(group), **opts.stages.get(group, {})}
    return build(cls, {p: v for p, v in values.items() if p[0] not in fixed}, **fixed)


# ------------------------------------------------------------------------------------ the plan
def stage_plan(ws: Workspace, opts: RunOptions, survey) -> dict[str, Callable[[], Any]]:
    """Per stage after the survey (the stage table's order), a factory of its configuration; factories
    run when the stage is reached, so they can read the results of the stages before."""
    from watergan.site_water import SiteWater

    from .gan import GanStage
    from .stages import STAGES

    gan_dir = ws.stage_dir("gan")
    rgbd = Path(survey.rgbd_dir)

    def gan() -> GanStage:
        base = _configured("gan", opts, rgbd_dir=rgbd, underwater_dir=ws.stage_dir("survey") / "images",
                           out_dir=gan_dir / "model")
        if base.site_water_mode != SiteWater.learned:  # the water stage's estimate, held or under its prior
            base = dataclasses.replace(base, site_water=ws.path(ws.require("water", "WaterGAN").water_json))
        effects = tuple(dict.fromkeys(base.effects + opts.add))
        gan_given = opts.stages.get("gan", {})
        if ({("iterations",), ("epochs",)} & set(gan_given)) and ("budget_min",) not in gan_given:
            base = dataclasses.replace(base, budget_min=None)  # as train-gan: iterations or epochs alone stop it
        return GanStage(dataclasses.replace(base, effects=effects),
                        _configured("generate", opts, model_dir=gan_dir / "model", rgbd_dir=rgbd,
                                    out_dir=gan_dir / "generated"))

    def restorer():
        gan_result = ws.require("gan", "the restorer")
        cfg = _configured("restorer", opts, data_dir=ws.path(gan_result.generated), out_dir=ws.stage_dir("restorer"))
        given = opts.stages.get("restorer", {})
        if ("altitude",) not in given:  # the altimeter's altitude when the survey has it
            cfg = dataclasses.replace(cfg, altitude=survey.navigation)
        if ("range_input",) not in given:  # RGB-D when the water stage left each frame's range maps
            water = ws.result("water")
            cfg = dataclasses.replace(cfg, range_input=water is not None and bool(water.range_dir))
        return cfg

    def diagnose():
        cfg = _configured("diagnose", opts, add=opts.add)
        return with_values(cfg, {("measure", "seed"): opts.seed, ("fit", "seed"): opts.seed})

    def water():
        base = with_values(_configured("water", opts), {("measure", "seed"): opts.seed, ("fit", "seed"): opts.seed})
        return dataclasses.replace(base, effects=tuple(dict.fromkeys(base.effects + opts.add)))

    def mesh():
        """Textured with the physics-corrected frames when every pixel of them had a range, else the restorer's."""
        physics = ws.result("water")
        if physics is not None and physics.unresolved_fraction == 0.0:
            return _configured("mesh", opts, images_dir=str(ws.path(physics.images)))
        return _configured("mesh", opts, images_dir=str(ws.path(ws.require("correct", "the mesh").images)))

    special = {"gan": gan, "restorer": restorer, "water": water, "mesh": mesh, "diagnose": diagnose,
               "report": lambda: ws.stage("report").config_type()}
    return {name: special.get(name, lambda name=name: _configured(name, opts)) for name in STAGES if name != "survey"}


def survey_config(opts: RunOptions) -> SurveyConfig:
    """The survey stage's configuration, folders as absolute paths (``./S`` and ``S`` are the same survey)."""
    return SurveyConfig(str(Path(opts.survey_dir).resolve()),
                        str(Path(opts.rgbd_dir).resolve()) if opts.rgbd_dir else "", opts.seed)


def check_inputs(opts: RunOptions) -> None:
    """Every file the run reads from the user, checked before any stage runs: the survey folder
    (:func:`check_survey`, also when its stage finished earlier: the files may have changed since) and
    the board files the options name. A bad one is a :class:`UserInputError` naming it."""
    from eval.colour import load_board_json

    from .sfm import read_board_corners

    check_survey(Path(opts.survey_dir))
    sfm = opts.stages.get("sfm", {})
    if sfm.get(("board_json",)):
        read_board_corners(Path(sfm[("board_json",)]), sfm.get(("board_width_m",), 0.0),
                           sfm.get(("board_height_m",), 0.0))
    for group in ("water", "eval"):
        path = opts.stages.get(group, {}).get(("board_json",))
        if path:
            load_board_json(path)


def run_all(opts: RunOptions) -> dict:
    """Run (or skip) every stage; returns the summary written to ``WORKSPACE/run_summary.json``."""
    from .stages import STAGES

    unknown = sorted(set(opts.force) - set(STAGES) - {"all"})
    if unknown:
        raise UserInputError(f"--force: unknown stage(s) {', '.join(unknown)}; stages: {', '.join(STAGES)}, all")
    from watergan.formation import get

    gan_effects = opts.stages.get("gan", {}).get(("effects",), ())
    for name in (*gan_effects, *opts.add, *opts.stages.get("diagnose", {}).get(("effects",), ())):
        get(name)  # an unknown effect fails now, not after minutes of training
    check_inputs(opts)
    ws = Workspace(opts.workspace)
    forced = set(STAGES) if "all" in opts.force else set(opts.force)
    began = time.perf_counter()
    timings: list[dict] = []

    def step(stage: str, config: Any) -> Any:
        done = stage not in forced and ws.is_done(stage, config)
        status = "finished earlier, skipped" if done else "running"
        print(f"[{list(STAGES).index(stage) + 1}/{len(STAGES)}] {stage}: {status}", flush=True)
        started = time.perf_counter()
        result = ws.run(stage, config, force=stage in forced)
        seconds = time.perf_counter() - started
        timings.append({"stage": stage, "skipped": done, "seconds": round(seconds, 2)})
        if not done:
            print(f"      {stage} done in {seconds:.1f} s", flush=True)
        return result

    survey = step("survey", survey_config(opts))
    plan = stage_plan(ws, opts, survey)
    for stage in STAGES:
        if stage != "survey":
            step(stage, plan[stage]())
    report = ws.path(ws.result("report").report)
    summary = {"workspace": str(ws.root), "report": str(report), "seconds": round(time.perf_counter() - began, 2),
               "stages": timings, "options": _summary_options(opts), "options_hash": config_hash(opts)}
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
