"""A workspace stage as a command: ``watergan COMMAND --workspace WS [--survey DIR] [--force] [OPTIONS]``.

Every stage of the stage table with a ``command`` gets one, made here the same way: its options are
the stage's configuration fields (:mod:`pipeline.cliargs`) but those the stage finds itself in the
workspace (the table's ``found``); an empty path option means the upstream stage's result. The
stage runs through :meth:`Workspace.run`, so its record is the one ``watergan run`` writes for the
same options and upstream results (a standalone ``watergan sfm`` is skipped by a later ``watergan
run``, and the other way round). ``--survey DIR`` runs the survey stage first (check and link the
survey folder, as ``watergan run DIR`` does), for a workspace that has none yet.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any


def run_stage_command(args: argparse.Namespace) -> int:
    from .cliargs import config_from_args
    from .survey import SurveyConfig
    from .workspace import Workspace

    ws = Workspace(args.workspace)
    if getattr(args, "survey", ""):
        ws.run("survey", SurveyConfig(args.survey))
    spec = ws.stage(args.stage)
    config = config_from_args(spec.config_type, args, exclude=spec.found)
    result = ws.run(args.stage, config, force=args.force)
    args.printer(ws, result)
    return 0


def add_stage_command(sub, parents: list[argparse.ArgumentParser], stage: str, printer: Callable[[Any, Any], None],
                      command: str = "", help_text: str = "", exclude: tuple[str, ...] = ()) -> None:
    """Add ``command`` (default: the stage table's) running the workspace stage ``stage``, its options from the
    stage's config, its help the table's unless ``help_text``."""
    from .cliargs import add_config
    from .stages import STAGES

    spec = STAGES[stage]
    p = sub.add_parser(command or spec.command, parents=parents, help=help_text or spec.help)
    p.add_argument("--workspace", required=True, help="workspace folder (the stage reads the results of the stages "
                                                      "before it there)")
    if spec.reads:
        p.add_argument("--survey", default="", metavar="DIR",
                       help="survey folder to check and link into the workspace first (as `watergan run DIR` does)")
    p.add_argument("--force", action="store_true", help="redo the stage even when done with the same options")
    add_config(p, spec.config_type, exclude=(*spec.found, *exclude))
    p.set_defaults(func=run_stage_command, stage=stage, printer=printer)
