"""The simulator's JSON files: indented, keys in the order given, so the same seed gives byte-identical
files. Images, depth maps, sRGB encoding and quantising are :mod:`watergan.io`'s."""

from __future__ import annotations

import json
from pathlib import Path

# The names below are :mod:`watergan.io`'s, kept here only for callers that still import them from this
# module (pipeline/water.py, eval/diagnose_measure.py); new code imports them from watergan.io.
from watergan.io import linear_to_srgb as srgb_encode  # noqa: F401
from watergan.io import quantise, read_png  # noqa: F401
from watergan.io import srgb_to_linear as srgb_decode  # noqa: F401


def write_json(path: Path, obj) -> None:
    """Indented JSON with a trailing newline (key order as given, so output is reproducible)."""
    path.write_text(json.dumps(obj, indent=2) + "\n")
