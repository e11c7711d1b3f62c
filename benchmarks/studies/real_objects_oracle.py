"""How far any water of the stack's form could take the pool's labelled objects (issue 62): the objects' own fit.

    PYTHONPATH=. .venv/bin/python benchmarks/studies/real_objects_oracle.py \
        [benchmarks/results/real_run4.json ...] [--json benchmarks/results/real_objects_oracle.json]

From the raw frames' per-object series of a ``bench_real.py`` JSON (``methods.raw.objects``: each labelled object's
mean linear colour I_of and median range r_of per frame f), per channel c the form

    I_ofc = exp(g_fc) (a_oc exp(-eta_c r_of) + V_c(r_of)),   V_c(r) = B_c (1 - exp(-beta_c r))

(a_oc the object's albedo through the sensor, V the veil through the sensor gain, g_fc a gain per frame and channel
or none) is fitted by least squares on ln I (each object-frame counts alike, dark or bright; a ridge of
``GAIN_RIDGE`` on g), and each object is corrected as the physics correction would,
J_ofc = max(I_ofc exp(-g_fc) - V_c(r_of), 0) exp(eta_c r_of), then judged as ``bench_real`` judges it
(:func:`eval.objects.chromaticity_spread`, the median over objects over raw's). Variants:

- ``water_as_estimated``: eta, B_inf, beta and the sensor gain from the JSON's water (k from its veil), no g: the
  range terms the corrections invert, without their fields over the image or gains per frame;
- ``objects_fit`` and ``objects_fit_gains``: the form fitted on every object, without and with g (in sample: the
  water and gains chosen on the very objects that judge them, a bound on what the form can reach);
- ``leave_one_object_out`` and ``..._gains``: each object corrected with the form fitted on the other objects (its
  gains in a frame come from the other objects in that frame; 0 where it is alone).

Printed per variant: the median spread over raw's, each object's spread over raw's, eta and the veil's slope at
the camera B beta per channel, and per object the share of its channel-frames J clipped to 0 (a channel at 0
in every frame makes a spread of 0 that says nothing); with ``--json`` the same as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from eval.objects import chromaticity_spread  # noqa: E402

#: Weight of the ridge sum g_fc^2 on the gains per frame, against residuals in ln I (a gain of 5 % costs as much as
#: a 0.25 % misfit).
GAIN_RIDGE = 0.05
#: Bounds of (eta per m, B, beta per m, ln a, g) in the fits.
BOUNDS = ((0.0, 3.0), (0.0, 2.0), (1e-3, 5.0), (-12.0, 3.0), (-2.0, 2.0))


class ObjectRows:
    """The raw object-frames with a range: object index ``obj``, frame index ``frame``, ``range_m``, ``rgb`` (N,3)."""

    def __init__(self, raw_objects: dict):
        self.names = list(raw_objects)
        rows = [(i, f, float(r), c) for i, name in enumerate(self.names)
                for f, r, c in zip(raw_objects[name]["frames"], raw_objects[name]["range_m"],
                                   raw_objects[name]["mean_linear_rgb"], strict=True) if r is not None]
        self.frames = sorted({f for _, f, _, _ in rows})
        index = {f: k for k, f in enumerate(self.frames)}
        self.obj = np.array([i for i, *_ in rows])
        self.frame = np.array([index[f] for _, f, _, _ in rows])
        self.range_m = np.array([r for *_, r, _ in rows])
        self.rgb = np.array([c for *_, c in rows], float)

    def spreads(self, rgb: np.ndarray) -> dict[str, float]:
        return {name: chromaticity_spread(rgb[self.obj == i]) for i, name in enumerate(self.names)}


def fit_channel(rows: ObjectRows, c: int, use: np.ndarray, gains: bool) -> tuple[np.ndarray, np.ndarray]:
    """(eta, B, beta) and the gains g (frames,) of channel ``c`` fitted on the rows ``use``."""
    n_obj, n_gain = len(rows.names), len(rows.frames) if gains else 0
    y = np.log(np.clip(rows.rgb[:, c], 1e-5, None))
    albedo0 = [np.log(max(rows.rgb[use & (rows.obj == i), c].mean(), 1e-3)) if (use & (rows.obj == i)).any()
               else np.log(0.1) for i in range(n_obj)]
    sizes = (1, 1, 1, n_obj, n_gain)
    low = np.concatenate([np.full(n, lo) for n, (lo, _) in zip(sizes, BOUNDS, strict=True)])
    high = np.concatenate([np.full(n, hi) for n, (_, hi) in zip(sizes, BOUNDS, strict=True)])
    p0 = np.clip(np.r_[0.2, 0.1, 0.5, albedo0, np.zeros(n_gain)], low + 1e-6, high - 1e-6)

    def residuals(p):
        eta, b, beta, a = p[0], p[1], p[2], np.exp(p[3:3 + n_obj])
        g = p[3 + n_obj:][rows.frame] if gains else 0.0
        model = np.exp(g) * (a[rows.obj] * np.exp(-eta * rows.range_m) + b * -np.expm1(-beta * rows.range_m))
        return np.r_[(np.log(model) - y)[use], GAIN_RIDGE * p[3 + n_obj:]]

    p = least_squares(residuals, p0, bounds=(low, high)).x
    return p[:3], (p[3 + n_obj:] if gains else np.zeros(len(rows.frames)))


def fit_form(rows: ObjectRows, use: np.ndarray, gains: bool) -> tuple[np.ndarray, np.ndarray]:
    """The water (3, 3) of (eta, B, beta) per channel and the gains (frames, 3) fitted on the rows ``use``."""
    fits = [fit_channel(rows, c, use, gains) for c in range(3)]
    return np.stack([f[0] for f in fits]), np.stack([f[1] for f in fits], 1)


def correct(rows: ObjectRows, water: np.ndarray, gains: np.ndarray, which: np.ndarray, out: np.ndarray) -> None:
    """``out[which]`` = J of the module docstring for the rows ``which``; ``water`` (3, 3) of (eta, B, beta) per
    channel, ``gains`` (frames, 3)."""
    r = rows.range_m[which, None]
    eta, b, beta = water[:, 0], water[:, 1], water[:, 2]
    signal = rows.rgb[which] * np.exp(-gains[rows.frame[which]]) - b * -np.expm1(-beta * r)
    out[which] = np.maximum(signal, 0.0) * np.exp(eta * r)


def estimated_water(water: dict) -> np.ndarray:
    """(eta, k B_inf, beta) per channel from a ``bench_real`` JSON's water (k from its veil at its range)."""
    eta = np.asarray(water["attenuation.eta_per_m"]["value"], float)
    b_inf = np.asarray(water["backscatter.b_inf"]["value"], float)
    beta = np.asarray(water["backscatter.beta_per_m"]["value"], float)
    veil = water["veil"]
    k = np.asarray(veil["value"], float) / (b_inf * -np.expm1(-beta * veil["range_m"]))
    return np.stack([eta, k * b_inf, beta], 1)


def variants(rows: ObjectRows, water: dict) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """Per variant of the module docstring, the corrected rows J (N,3) and its water (3, 3) (None: one per object)."""
    everything = np.ones(len(rows.obj), bool)
    out = {}
    J = np.zeros_like(rows.rgb)
    w = estimated_water(water)
    correct(rows, w, np.zeros((len(rows.frames), 3)), everything, J)
    out["water_as_estimated"] = (J, w)
    for gains in (False, True):
        suffix = "_gains" if gains else ""
        w, g = fit_form(rows, everything, gains)
        J = np.zeros_like(rows.rgb)
        correct(rows, w, g, everything, J)
        out["objects_fit" + suffix] = (J, w)
        J = np.zeros_like(rows.rgb)
        for i in range(len(rows.names)):
            correct(rows, *fit_form(rows, rows.obj != i, gains), rows.obj == i, J)
        out["leave_one_object_out" + suffix] = (J, None)
    return out


def study(path: Path) -> dict:
    figures = json.loads(path.read_text())
    rows = ObjectRows(figures["methods"]["raw"]["objects"])
    raw = rows.spreads(rows.rgb)
    raw_median = float(np.median(list(raw.values())))
    measured = {m: figures["objects"]["median_spread_over_raw"][m] for m in ("physics", "restorer", "gray_world")}
    out = {"source": str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path),
           "object_frames": int(len(rows.obj)), "raw_median_spread": round(raw_median, 5),
           "measured_median_over_raw": measured, "variants": {}}
    for name, (J, w) in variants(rows, figures["water"]).items():
        s = rows.spreads(J)
        entry = {"median_over_raw": round(float(np.median(list(s.values()))) / raw_median, 4),
                 "over_raw": {o: round(s[o] / raw[o], 3) for o in rows.names},
                 "objects_above_raw": [o for o in rows.names if s[o] > raw[o]],
                 "clipped_pct": {o: round(100 * float((J[rows.obj == i] <= 0).mean()), 1)
                                 for i, o in enumerate(rows.names)}}
        if w is not None:
            entry["eta_per_m"] = np.round(w[:, 0], 4).tolist()
            entry["veil_slope_at_camera_per_m"] = np.round(w[:, 1] * w[:, 2], 5).tolist()
        out["variants"][name] = entry
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="*", type=Path, default=[ROOT / "benchmarks/results/real_run4.json"])
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    results = [study(p) for p in args.runs]
    for res in results:
        print(f"{res['source']}: {res['object_frames']} object-frames; measured median over raw "
              + ", ".join(f"{m} {v:.2f}" for m, v in res["measured_median_over_raw"].items()))
        for name, v in res["variants"].items():
            water = (f"  eta {v['eta_per_m']}  veil slope {v['veil_slope_at_camera_per_m']}"
                     if "eta_per_m" in v else "")
            print(f"  {name:26s} {v['median_over_raw']:.3f}  above raw: {', '.join(v['objects_above_raw']) or '-'}"
                  + water)
            clipped = {o: f" ({c:.0f} % clipped)" if c else "" for o, c in v["clipped_pct"].items()}
            print("      " + " ".join(f"{o}={x:.2f}{clipped[o]}" for o, x in v["over_raw"].items()))
    if args.json:
        tmp = args.json.with_suffix(".json.tmp")
        tmp.write_text(json.dumps({"runs": results, "gain_ridge": GAIN_RIDGE}, indent=1) + "\n")
        tmp.replace(args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
