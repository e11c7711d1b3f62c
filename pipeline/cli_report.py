"""The evaluation and report subcommands of the `watergan` console script (wired in by pipeline.cli):

    watergan evaluate --workspace WS [--survey-dir DIR] [--images-dir DIR] [--range-source auto|truth|dense]
                      [--methods raw,histeq,...] [--ours-dir DIR] [--jaffe-stack FILE] [--board-json FILE] [--force]
    watergan report WORKSPACE

evaluate is the eval workspace stage (options: :class:`eval.tables.EvaluateConfig`; skipped when done
with the same options unless --force): every baseline and the restorer on the same SfM points and
board, the paper's tables and a plain verdict. report writes ``report.html`` (self-contained),
``report.json`` and ``report.md`` into the workspace's report folder.
"""

from __future__ import annotations

import argparse

from .cli_stage import add_stage_command


def print_evaluate(ws, r) -> None:
    print(f"evaluate: {len(r.methods)} methods on the same points and board "
          f"(range from {r.range_source}), {r.seconds:.1f} s")
    for method, why in r.skipped.items():
        print(f"  skipped {method}: {why}")
    for line in r.verdict:
        print(f"  - {line}")
    print(f"tables: {ws.path(r.tables_md)}")


def cmd_report(args: argparse.Namespace) -> int:
    from pipeline.report import write_report

    print(write_report(args.workspace))
    return 0


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add ``evaluate`` and ``report`` to an argparse subparsers object; each sets ``func``."""
    add_stage_command(sub, parents, "eval", print_evaluate)
    p = sub.add_parser("report", parents=parents, help="write the workspace's HTML report (report/report.html)")
    p.add_argument("workspace", help="workspace folder")
    p.set_defaults(func=cmd_report)
