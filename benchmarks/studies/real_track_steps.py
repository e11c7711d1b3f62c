"""Where the pool crawler's track and its SfM model disagree, step by step (issue 51's held-out scale).

    PYTHONPATH=. .venv/bin/python benchmarks/studies/real_track_steps.py WS

On a ``bench_real.py`` workspace ``WS``: for each step between consecutive frames, the time between them (from the
frame names, ``frame_HH_MM_SS.sss``), the track's step |P_i+1 - P_i| and the model's |C_i+1 - C_i| (its camera
centres in the plane of their two principal directions, metres after the track's scale), and their ratio. Prints the
steps, then per half of the survey the median ratio over the steps two seconds long (the recording's regular
spacing) and over the longer ones (the recording's gaps), the median speeds over the gaps, and the model's own
scale drift read from the camera's height over the floor (:func:`bench_real.model_height_halves`).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def frame_seconds(name: str) -> float:
    """The time in a frame name ``..._HH_MM_SS.sss...``, seconds."""
    h, m, s = re.search(r"(\d\d)_(\d\d)_(\d\d(?:\.\d+)?)", name).groups()
    return 3600 * int(h) + 60 * int(m) + float(s)


def main() -> None:
    import json

    from bench_real import model_height_halves

    from eval.tracks import Tracks
    from pipeline.scale import _in_plane
    from pipeline.workspace import Workspace

    ws = Workspace(Path(sys.argv[1]))
    tracks = Tracks.load(ws.path(ws.result("sfm").tracks))
    survey = json.loads((ws.stage_dir("survey") / "survey.json").read_text())
    position = dict(zip(survey["frames"], survey["nav_position_m"], strict=True))
    names = [str(n) for n in tracks.image_names]
    keep = [k for k in np.flatnonzero(tracks.registered) if names[k] in position]
    track = np.array([position[names[k]] for k in keep], float)
    model = _in_plane(tracks.world_from_cam[keep, :3, 3], track.shape[1])
    seconds = np.diff([frame_seconds(names[k]) for k in keep])
    step_track = np.linalg.norm(np.diff(track, axis=0), axis=1)
    step_model = np.linalg.norm(np.diff(model, axis=0), axis=1)
    ratio = step_track / np.maximum(step_model, 1e-9)
    print("step  seconds  track_m  model_m  track/model")
    for i in range(len(ratio)):
        print(f"{i:4d}  {seconds[i]:7.1f}  {step_track[i]:7.3f}  {step_model[i]:7.3f}  {ratio[i]:8.2f}")
    half = len(keep) // 2
    for label, steps in (("first half", slice(0, half - 1)), ("second half", slice(half, None))):
        regular, gap = seconds[steps] <= 2.5, seconds[steps] > 2.5
        print(f"{label}: track/model median {np.median(ratio[steps][regular]):.3f} over {regular.sum()} two-second "
              f"steps, {np.median(ratio[steps][gap]) if gap.any() else float('nan'):.3f} over {gap.sum()} gaps; "
              f"speed over the gaps: track {np.median((step_track / seconds)[steps][gap]):.4f} m/s, model "
              f"{np.median((step_model / seconds)[steps][gap]):.4f} m/s (two-second steps: track "
              f"{np.median((step_track / seconds)[steps][regular]):.4f}, model "
              f"{np.median((step_model / seconds)[steps][regular]):.4f})")
    print(f"the model's camera height over the floor, halves' scales differ by "
          f"{model_height_halves(ws)['heldout_pct']:.1f} %")


if __name__ == "__main__":
    main()
