"""File formats of the simulator: sRGB encoding, PNG images, depth maps in millimetres, JSON.

Every writer is deterministic (no timestamps), so the same seed gives byte-identical files.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from watergan.data import linear_to_srgb, srgb_to_linear

#: Largest depth a 16-bit millimetre PNG holds, metres.
MAX_DEPTH_PNG_M = 65.535


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


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an (H,W) or (H,W,3) RGB uint8/uint16 array as PNG (cv2 stores BGR, so channels are
    swapped here)."""
    if image.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"PNG images must be uint8 or uint16, got {image.dtype}")
    data = image[..., ::-1] if image.ndim == 3 else image
    if not cv2.imwrite(str(path), np.ascontiguousarray(data)):
        raise OSError(f"could not write PNG {path}")


def read_png(path: str | Path) -> np.ndarray:
    """Read a PNG written by :func:`write_png` (RGB order, original bit depth)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FileNotFoundError(f"could not read image {path}")
    return image[..., ::-1].copy() if image.ndim == 3 else image


def write_srgb_png(path: Path, linear_rgb: np.ndarray, bit_depth: int = 8) -> None:
    """Linear RGB (H,W,3), 0..1, sRGB-encoded and quantised to ``bit_depth`` bits."""
    write_png(path, quantise(srgb_encode(linear_rgb), bit_depth))


def write_depth_png(path: Path, metres: np.ndarray) -> None:
    """Distances in metres as a 16-bit PNG of millimetres (0 = no value; rounded to 1 mm, so the
    stored value is within 0.5 mm of the true one; at most 65.535 m)."""
    finite = np.isfinite(metres) & (metres > 0)
    if (metres[finite] > MAX_DEPTH_PNG_M).any():
        raise ValueError(f"distance above {MAX_DEPTH_PNG_M} m cannot be stored in a 16-bit millimetre PNG")
    write_png(path, np.where(finite, np.rint(np.where(finite, metres, 0.0) * 1000.0), 0).astype(np.uint16))


def read_depth_png(path: str | Path) -> np.ndarray:
    """A 16-bit millimetre PNG as metres (float64); 0 marks pixels without a value."""
    return read_png(path).astype(np.float64) / 1000.0


def write_json(path: Path, obj) -> None:
    """Indented JSON with a trailing newline (key order as given, so output is reproducible)."""
    path.write_text(json.dumps(obj, indent=2) + "\n")


def read_json(path: str | Path):
    return json.loads(Path(path).read_text())
