"""What the pool footage's per-pixel tile test and black pixels answer to (issue 51): the far band's blur, or the
dark pixels and the veil.

    PYTHONPATH=. .venv/bin/python benchmarks/studies/real_dark_pixels.py WS [--every 4]

On a ``bench_real.py`` workspace ``WS``:

- the near band of the tile test (``bench_real.NEAR_ROWS``, the middle ``MIDDLE`` of the width, the raw frames),
  area-downsampled by 1.5, 2 and 3 (a blur like the far band's, where tile and grout mix in a pixel): how far its
  per-pixel mean chromaticity moves, beside the raw far band's distance from it;
- the water stage's veil C (the stack's additive field at each pixel's range:
  :func:`watergan.formation.inverse.inverse_fields`) against the raw pixel I over the scene's ranged pixels of
  every ``--every``-th frame: the share below it per channel and in all three (what the physics correction can only
  floor), and per range bin the 0.1st, 1st, 5th and 50th percentiles of I / C (Sea-thru reads backscatter off the
  darkest percent of each range bin; pixels where the additive field is not positive, near the camera where the
  fields over the image lower it, left out).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "benchmarks" / "studies"))

RANGE_BINS_M = (0.3, 0.5, 0.7, 0.9, 1.2, 1.6, 2.2, 3.5)


def chromaticity_mean(pixels: np.ndarray) -> np.ndarray:
    """The mean over (N,3) linear pixels of RGB / (R + G + B)."""
    return (pixels / np.maximum(pixels.sum(1, keepdims=True), 1e-6)).mean(0)


def main() -> None:
    from bench_real import FAR_ROWS, MIDDLE, NEAR_ROWS
    from real_correction_parts import water_inputs

    from pipeline.workspace import Workspace
    from watergan.formation.inverse import inverse_fields
    from watergan.io import read_image, read_millimetres, read_scene_mask

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--every", type=int, default=4, help="every N-th frame for the veil's share")
    args = parser.parse_args()
    ws = Workspace(args.workspace)
    images, water, stack, tracks, names = water_inputs(ws)
    mask = read_scene_mask(ws.stage_dir("survey") / "scene_mask.png")

    factors = (1.0, 1.5, 2.0, 3.0)
    near = {f: [] for f in factors}
    far = []
    for name in names:
        image = read_image(images / name)
        h, w = image.shape[:2]
        columns = slice(int(w * (1 - MIDDLE) / 2), int(w * (1 + MIDDLE) / 2))
        band = image[int(h * NEAR_ROWS[0]):int(h * NEAR_ROWS[1]), columns]
        for f in factors:
            scaled = band if f == 1.0 else cv2.resize(band, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
            near[f].append(scaled.reshape(-1, 3))
        far.append(image[int(h * FAR_ROWS[0]):int(h * FAR_ROWS[1]), columns].reshape(-1, 3))
    base = chromaticity_mean(np.concatenate(near[1.0]))
    for f in factors[1:]:
        moved = np.linalg.norm(chromaticity_mean(np.concatenate(near[f])) - base)
        print(f"near band downsampled {f:g}x: per-pixel mean chromaticity moves by {moved:.4f}")
    print(f"raw far band against the near band: {np.linalg.norm(chromaticity_mean(np.concatenate(far)) - base):.4f}")

    below, all_below, count = np.zeros(3), 0, 0
    ratios = [[] for _ in RANGE_BINS_M[1:]]
    for k in range(0, len(names), args.every):
        r = read_millimetres(ws.path(ws.result("range").range_dir) / f"{Path(names[k]).stem}.png") / 1000.0
        image = read_image(images / names[k]).astype(np.float64)
        _, c, valid = inverse_fields(np.where(r > 0, r, np.nan), stack, tracks.K, k)
        c = c[0].permute(1, 2, 0).numpy()
        scene = valid & mask
        under = image[scene] < c[scene]
        below += under.sum(0)
        all_below += int(under.all(1).sum())
        count += int(scene.sum())
        for b in range(len(ratios)):
            sel = scene & (r >= RANGE_BINS_M[b]) & (r < RANGE_BINS_M[b + 1]) & (c > 1e-4).all(2)
            if sel.sum() > 1000:
                ratios[b].append(image[sel] / c[sel])
    print("ranged scene pixels below the veil, R / G / B: " + " / ".join(f"{100 * v:.2f} %" for v in below / count)
          + f"; in all three: {100 * all_below / count:.3f} %")
    for b, parts in enumerate(ratios):
        if parts:
            q = np.percentile(np.concatenate(parts), [0.1, 1, 5, 50], axis=0)
            print(f"range {RANGE_BINS_M[b]:.1f}-{RANGE_BINS_M[b + 1]:.1f} m: I / veil percentiles 0.1 / 1 / 5 / 50 "
                  f"(R; G; B) " + "; ".join(" / ".join(f"{v:.2f}" for v in q[:, ch]) for ch in range(3)))


if __name__ == "__main__":
    main()
