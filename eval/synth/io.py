"""The simulator's JSON files: indented, keys in the order given, so the same seed gives byte-identical
files. Images, depth maps, sRGB encoding and quantising are :mod:`watergan.io`'s."""

from __future__ import annotations

import json
from pathlib import Path


def write_json(path: Path, obj) -> None:
    """Indented JSON with a trailing newline (key order as given, so output is reproducible)."""
    path.write_text(json.dumps(obj, indent=2) + "\n")
