"""The one-command subcommands of the `watergan` console script (wired in by pipeline.cli):

    watergan run SURVEY --workspace WS [--config run.toml] [--effects LIST] [--add LIST]
                 [--gan-budget-min M] [--restorer-budget-min M] [--scheduler ADDRESS] [--force STAGE]...
    watergan demo [--out demo_out] [--force STAGE]...

``demo`` simulates the built-in default survey (one effect hidden) into ``OUT/00_survey`` and runs
every stage on it. Both print progress per stage, a summary and the report's path; a second run
skips the finished stages.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from .cliargs import name_list

#: The effect the demo survey hides from the visible model (the diagnosis should find it).
DEMO_HIDDEN = "vignetting_offcentre"


def _options(args: argparse.Namespace, survey_dir: str, workspace: str):
    """RunOptions from the TOML file (when given), overridden by the options given on the command line."""
    from .run import RunOptions, load_options_file

    values: dict = load_options_file(args.config) if getattr(args, "config", None) else {}
    values.update(survey_dir=survey_dir, workspace=workspace)
    for name in ("gan_budget_min", "restorer_budget_min", "scheduler", "diagnose_points", "seed"):
        value = getattr(args, name, None)
        if value is not None:
            values[name] = value
    for name in ("effects", "add", "diagnose_candidates"):
        value = getattr(args, name, None)
        if value is not None:
            values[name] = tuple(name_list(value))
    if args.force:
        values["force"] = tuple(args.force)
    if getattr(args, "no_progress", False):
        values["progress"] = False
    fields = {f.name for f in dataclasses.fields(RunOptions)}
    return RunOptions(**{k: v for k, v in values.items() if k in fields})


def cmd_run(args: argparse.Namespace) -> int:
    from .run import print_summary, run_all

    print_summary(run_all(_options(args, args.survey, args.workspace)))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from eval.synth import make_config, simulate_survey

    from .run import print_summary, run_all

    out = Path(args.out)
    survey = out / "00_survey"
    if (survey / "truth" / "config.json").is_file() and "survey" not in args.force and "all" not in args.force:
        print(f"demo survey already simulated in {survey}")
    else:
        print(f"watergan demo: simulating the built-in survey with one hidden effect ({DEMO_HIDDEN}) into {survey}")
        simulate_survey(survey, make_config(args.preset, hidden=[DEMO_HIDDEN], seed=args.seed or 0), force=True)
    print_summary(run_all(_options(args, str(survey), str(out))))
    return 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE.toml", help="options file (keys as RunOptions); the command line wins")
    p.add_argument("--effects", metavar="LIST", help="WaterGAN generator effects (default: "
                   "attenuation,backscatter_conv,vignetting,gain)")
    p.add_argument("--add", metavar="LIST", help="effects added to WaterGAN and the diagnosed model")
    p.add_argument("--gan-budget-min", type=float, help="WaterGAN training minutes (default 4)")
    p.add_argument("--restorer-budget-min", type=float, help="restorer training minutes (default 2.5)")
    p.add_argument("--diagnose-points", type=int, help="3D points sampled by the diagnosis (default 1500)")
    p.add_argument("--diagnose-candidates", metavar="LIST", help="candidate effects the diagnosis tries "
                   "(default: every one that qualifies)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler (tcp://HOST:8786) for per-image stages")
    p.add_argument("--seed", type=int)
    p.add_argument("--force", action="append", default=[], metavar="STAGE",
                   help="rerun a finished stage (repeatable; 'all' for every stage)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("run", parents=parents, help="every stage on a survey folder (resumable)")
    p.add_argument("survey", help="survey folder: images/, optional right/, camera.json, optional rgbd/")
    p.add_argument("--workspace", required=True, help="run folder")
    _common(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("demo", parents=parents, help="simulate the built-in survey and run every stage on it")
    p.add_argument("--out", default="demo_out", help="workspace folder (default: demo_out)")
    p.add_argument("--preset", choices=["demo", "small"], default="demo",
                   help="demo: 44 stereo frames of 640x480 (the default); small: 10 frames of 320x240, for tests")
    _common(p)
    p.set_defaults(func=cmd_demo)
