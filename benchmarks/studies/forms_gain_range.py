"""Gains per frame kept off the frames' mean ranges, or only off their constant: the water on bench_forms' draws
(issue 52).

    PYTHONPATH=. .venv/bin/python benchmarks/studies/forms_gain_range.py ROOT [--draws draw_03_3,...]

On workspaces ``bench_forms.py --out ROOT`` prepared, estimates the water as bench_forms does
(:func:`bench_forms.estimate`) twice: as the water stage does (:func:`eval.fields.decorrelate_frames`: the gains per
frame orthogonal to the constant and to each frame's mean range, so that what is linear in the frames' ranges is the
water's), and with the gains orthogonal to the constant alone (eta then pinned by the ranges within frames: a camera
that sets its gain from each frame's content makes the gains follow the frames' ranges). Prints eta's and the
veil's relative errors against the truth and whether eta's 95 % interval covers it, per draw. Writes nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def constant_only(stack, obs) -> None:
    """:func:`eval.fields.decorrelate_frames` with the constant alone (the gains keep no mean, nothing else)."""
    from eval.fields import FRAME_EFFECT

    if FRAME_EFFECT not in stack.names:
        return
    effect = stack[FRAME_EFFECT]
    n = effect.param("log_gain").shape[0]
    effect.set_values(orthogonal_to=np.stack([np.ones(n) / np.sqrt(n), np.zeros(n)], 1))  # the second: none


def main() -> None:
    import bench_forms
    from bench_water import compare, compare_veil, truth_params

    import eval.fields
    import eval.water
    from pipeline.stages import stage_folder

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path)
    parser.add_argument("--draws", default="")
    args = parser.parse_args()
    bench_forms.load_forms()
    names = args.draws.split(",") if args.draws else sorted(p.name for p in args.root.iterdir() if p.is_dir())
    original = eval.fields.decorrelate_frames
    for name in names:
        ws_root = args.root / name
        truth = truth_params(stage_folder(ws_root, "survey"))
        for label, rule in (("off range", original), ("off constant", constant_only)):
            eval.water.decorrelate_frames = rule
            water = bench_forms.estimate(ws_root)[0]
            p = compare(water.params, truth)
            p.update(compare_veil(water.veil, truth))
            eta, veil = p["attenuation.eta_per_m"], p.get("veil", {})
            print(f"{name:12s} {label:12s} eta {' '.join(f'{100 * v:+6.1f}%' for v in eta['rel_error'])} covered "
                  f"{''.join('y' if c else 'N' for c in eta.get('covered', []))}  veil "
                  f"{' '.join(f'{100 * v:+6.1f}%' for v in veil.get('rel_error', []))}", flush=True)
    eval.water.decorrelate_frames = original


if __name__ == "__main__":
    main()
