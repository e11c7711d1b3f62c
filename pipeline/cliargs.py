"""Argument parsing shared by the `watergan` subcommands."""

from __future__ import annotations


def name_list(text: str) -> list[str]:
    """Names from a comma-separated option value: "a, b,,c" -> ["a", "b", "c"]."""
    return [name.strip() for name in text.split(",") if name.strip()]


SCHEDULER_HELP = ("Dask scheduler address (tcp://HOST:8786) to run the per-image work on its workers; the data "
                  "must be on a file system they share (default: this machine)")


def scheduler_parent():
    """An argparse parent adding ``--scheduler ADDRESS`` (empty string when not given)."""
    import argparse

    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument("--scheduler", default="", metavar="ADDRESS", help=SCHEDULER_HELP)
    return parent
