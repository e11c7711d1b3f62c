"""The evaluation and report subcommands of the `watergan` console script (wired in by pipeline.cli):

    watergan evaluate --workspace WS [--survey DIR] [--images-dir DIR] [--range-source auto|truth|dense]
                      [--methods raw,histeq,...] [--ours-dir DIR] [--jaffe-stack FILE] [--board-json FILE] [--force]
    watergan report --workspace WS

evaluate is the eval workspace stage (options: :class:`eval.tables.EvaluateConfig`; skipped when done
with the same options unless --force): every baseline and the restorer on the same SfM points and
board, the paper's tables and a plain verdict. report is the report stage: ``report.html``
(self-contained), ``report.json`` and ``report.md`` in its folder.
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


def print_report(ws, r) -> None:
    print(ws.path(r.report))


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add ``evaluate`` and ``report`` to an argparse subparsers object; each sets ``func``."""
    add_stage_command(sub, parents, "eval", print_evaluate)
    add_stage_command(sub, parents, "report", print_report)
