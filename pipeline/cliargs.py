"""Argument parsing shared by the `watergan` subcommands."""

from __future__ import annotations


def name_list(text: str) -> list[str]:
    """Names from a comma-separated option value: "a, b,,c" -> ["a", "b", "c"]."""
    return [name.strip() for name in text.split(",") if name.strip()]
