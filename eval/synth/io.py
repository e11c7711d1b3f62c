"""File formats of the simulator: sRGB encoding, PNG images, depth maps in millimetres, JSON
(PNG and depth I/O are :mod:`watergan.io`'s, with its conventions).

Every writer is deterministic (no timestamps), so the same seed gives byte-identical files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from watergan.io import (  # noqa: F401  (the simulator's files use the shared formats)
    MAX_DEPTH_PNG_M,
    linear_to_srgb,
    read_depth,
    read_png,
    srgb_to_linear,
    write_depth_png,
    write_png,
)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) on values clipped to 0..1 (:func:`watergan.data.linear_to_srgb`;
    float32 stays float32, anything else becomes float64)."""
    x = np.asarray(linear)
    return linear_to_srgb(x if x.dtype in (np.float32, np.float64) else x.astype(np.float64))


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Inverse of :func:`srgb_encode`, in float64 (:func:`watergan.data.srgb_to_linear`)."""
    return srgb_to_linear(np.asarray(encoded, dtype=np.float64))


def quantise(values: np.ndarray, bit_depth: int) -> np.ndarray:
    """Values in 0..1 rounded to unsigned integers of ``bit_depth`` (8 or 16) bits."""
    if bit_depth not in (8, 16):
        raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth}")
    top = 2**bit_depth - 1
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    return np.rint(np.clip(values, 0.0, 1.0) * top).astype(dtype)


def write_srgb_png(path: Path, linear_rgb: np.ndarray, bit_depth: int = 8) -> None:
    """Linear RGB (H,W,3), 0..1, sRGB-encoded and quantised to ``bit_depth`` bits."""
    write_png(path, quantise(srgb_encode(linear_rgb), bit_depth))


def write_json(path: Path, obj) -> None:
    """Indented JSON with a trailing newline (key order as given, so output is reproducible)."""
    path.write_text(json.dumps(obj, indent=2) + "\n")


def read_json(path: str | Path):
    return json.loads(Path(path).read_text())
