"""A workspace stage as a command: ``watergan COMMAND --workspace WS [--survey DIR] [--force] [--threads N] [OPTIONS]``.

Every stage of the stage table with a ``command`` gets one, made here the same way: its options are
the stage's configuration fields (:mod:`pipeline.cliargs`) but those the stage finds itself in the
workspace (the table's ``found``); an empty path option means the upstream stage's result. The
stage runs through :meth:`Workspace.run`, so its record is the one ``watergan run`` writes for the
same options and upstream results (a standalone ``watergan sfm`` is skipped by a later ``watergan
run``, and the other way round). ``--survey DIR`` runs the survey stage first (check and link the
survey folder, as ``watergan run DIR`` does), for a workspace that has none yet; the survey stage's own command
takes its folder as ``--survey DIR`` too. The stage runs with ``--threads`` threads
(:func:`watergan.threads.use_threads`) inside a heartbeat (:func:`watergan.progress.activity`).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any


def run_stage_command(args: argparse.Namespace) -> int:
    from watergan.progress import activity
    from watergan.threads import use_threads

    from .cliargs import config_from_args
    from .survey import SurveyConfig
    from .workspace import Workspace

    ws = Workspace(args.workspace)
    spec = ws.stage(args.stage)
    config = config_from_args(spec.config_type, args, exclude=spec.found)
    with use_threads(args.threads):
        if getattr(args, "survey", ""):
            ws.run("survey", SurveyConfig(args.survey))
        with activity(args.command, getattr(config, "progress", True) is not False):
            result = ws.run(args.stage, config, force=args.force)
    args.printer(ws, result)
    return 0


def add_stage_command(sub, parents: list[argparse.ArgumentParser], stage: str, printer: Callable[[Any, Any], None],
                      command: str = "", help_text: str = "", exclude: tuple[str, ...] = ()) -> None:
    """Add ``command`` (default: the stage table's) running the workspace stage ``stage``, its options from the
    stage's config, its help the table's unless ``help_text``."""
    from .cli_help import alias
    from .cliargs import add_options, options
    from .stages import STAGES

    spec = STAGES[stage]
    p = sub.add_parser(command or spec.command, parents=parents, help=help_text or spec.help)
    p.add_argument("--workspace", required=True, metavar="WS", help="workspace folder (the stage reads the results "
                                                                   "of the stages before it there)")
    opts = options(spec.config_type, (*spec.found, *exclude))
    survey = [o for o in opts if o.path == ("survey_dir",)]
    opts = [o for o in opts if o.path != ("survey_dir",)]
    if spec.reads:  # the survey folder is the workspace's: --survey links one first
        p.add_argument("--survey", default="", metavar="DIR",
                       help="survey folder to check and link into the workspace first (as watergan run DIR does)")
    elif survey:  # the survey stage: its survey folder is --survey too (--survey-dir, its older name, still works)
        action = add_options(p, survey)[0]
        alias(p, action, "--survey")
        action.metavar = "DIR"
    p.add_argument("--force", action="store_true", help="redo the stage even when done with the same options")
    p.add_argument("--threads", type=int, default=0, metavar="N",
                   help="threads of the stage's numerical work (torch, OpenCV); 0: the cores no other job keeps busy "
                        "(default: 0)")
    add_options(p, opts)
    p.set_defaults(func=run_stage_command, stage=stage, printer=printer)
