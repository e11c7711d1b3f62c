"""The evaluation and report subcommands of the `watergan` console script (wired in by pipeline.cli):

    watergan evaluate --workspace WS [--survey DIR] [--images DIR] [--range auto|truth|dense]
                      [--methods raw,histeq,...] [--ours DIR] [--jaffe-stack FILE] [--board FILE] [--force]
    watergan report WORKSPACE

evaluate is a workspace stage (``06_eval``; skipped when done with the same options unless
--force): every baseline and the restorer on the same SfM points and board, the paper's tables and a
plain verdict. report writes ``WORKSPACE/report/report.html`` (self-contained) and ``report.json``.
"""

from __future__ import annotations

import argparse

from .cliargs import scheduler_parent


def cmd_evaluate(args: argparse.Namespace) -> int:
    from eval.baselines import BASELINES
    from eval.tables import EvaluateConfig, run_evaluate
    from pipeline.workspace import Workspace
    from watergan.errors import UserInputError

    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip()) if args.methods else tuple(BASELINES)
    unknown = [m for m in methods if m not in BASELINES]
    if unknown:
        raise UserInputError(f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(BASELINES)}")
    cfg = EvaluateConfig(survey_dir=args.survey or "", images_dir=args.images or "", methods=methods,
                         ours_dir=args.ours or "", range_source=args.range, jaffe_stack=args.jaffe_stack or "",
                         board_json=args.board or "", patch_px=args.patch_px, min_views=args.min_views,
                         scheduler=args.scheduler)
    ws = Workspace(args.workspace)
    r = ws.run("eval", cfg, run_evaluate, force=args.force)["result"]
    print(f"evaluate: {len(r['methods'])} methods on the same points and board "
          f"(range from {r['range_source']}), {r['seconds']:.1f} s")
    for method, why in r["skipped"].items():
        print(f"  skipped {method}: {why}")
    for line in r["verdict"]:
        print(f"  - {line}")
    print(f"tables: {ws.path(r['tables_md'])}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from eval.report import write_report

    print(write_report(args.workspace))
    return 0


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add ``evaluate`` and ``report`` to an argparse subparsers object; each sets ``func``."""
    p = sub.add_parser("evaluate", parents=[*parents, scheduler_parent()],
                       help="baselines and the restorer on the same SfM points and board: the paper's tables")
    p.add_argument("--workspace", required=True, help="workspace with a finished sfm stage")
    p.add_argument("--survey", help="survey folder (default: the workspace's 00_survey)")
    p.add_argument("--images", help="the raw frames SfM ran on (default: SURVEY/images)")
    p.add_argument("--range", choices=["auto", "truth", "dense"], default="auto",
                   help="range for Jaffe-McGlamery and Sea-thru: the dense stage's depth or the simulator's truth "
                        "(auto: dense when it ran, else truth)")
    p.add_argument("--methods", help="comma-separated baselines (default: all: raw, histeq, clahe, gray_world, "
                                     "jaffe, seathru, oracle)")
    p.add_argument("--ours", help="the restorer's corrected frames (default: the workspace's 03_correct/images)")
    p.add_argument("--jaffe-stack", help="formation-stack JSON with the Jaffe-McGlamery coefficients "
                                         "(default: the simulated survey's true stack)")
    p.add_argument("--board", help="board JSON with per-image pixel corners and true colours "
                                   "(default: the simulated survey's board)")
    p.add_argument("--patch-px", type=int, default=5, help="side of the averaged patch at each SfM observation")
    p.add_argument("--min-views", type=int, default=3, help="points seen in fewer views are left out")
    p.add_argument("--force", action="store_true", help="redo the evaluation even when done with the same options")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("report", parents=parents, help="write the workspace's HTML report (report/report.html)")
    p.add_argument("workspace", help="workspace folder")
    p.set_defaults(func=cmd_report)
