"""How well each bench_forms draw's survey pins the water when the model holds the missing effect's exact form
(issue 52: the limit a better estimator could reach, as ``oracle_limits.py`` is for the corrections).

    python benchmarks/studies/forms_oracle_form.py --out /tmp/bench_forms [--draws 0,3,13] \
        [--json benchmarks/results/forms_oracle_form.json]

For each draw of ``benchmarks/results/forms.json`` (its workspace under ``--out``, prepared by bench_forms.py) the
water's table is measured as bench_forms measures it and fitted twice:

- ``default``: :func:`eval.water.estimate_observations` with the water stage's defaults;
- ``exact_form``: the same stack with the drawn effect's own form added and started at the drawn truth (the effect
  of the plugin; for gains a camera sets from each frame's content, gains per frame free of the frames' ranges and
  carried, which is that form), every parameter fitted.

Prints and writes per draw eta's and the veil's relative errors and whether the 95 % intervals cover the truth.
Where the exact form leaves eta off by more than 10 %, the survey itself does not pin the water to the issue's
target: no estimator that must also find the form can do better.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import bench_forms  # noqa: E402  (the benchmarks folder is not a package)
from bench_water import compare, compare_veil, load_inputs, truth_params  # noqa: E402

from pipeline.stages import stage_folder  # noqa: E402

#: Drawn effects that are gains set from each frame's content: their exact form is the free gains per frame.
CONTENT_GAINS = bench_forms.CONTENT_GAINS


def exact_form(config, effect: str, truth: dict):
    """``config`` with the drawn ``effect``'s exact form (see the module docstring)."""
    if effect in CONTENT_GAINS:
        return replace(config, frame_gain_off_range=False, alternatives=())
    start = {k.split(".", 1)[1]: v for k, v in truth.items() if k.split(".", 1)[0] == effect}
    return replace(config, effects=(*config.effects, effect), initial=({"name": effect, "params": start},),
                   alternatives=())


def errors(water, truth: dict) -> dict:
    """eta's and the veil's relative errors (per cent) and coverage of a water estimate."""
    p = compare({k: v for k, v in water.params.items() if k in ("attenuation.eta_per_m", "backscatter.b_inf")},
                truth)
    p.update(compare_veil(water.veil, truth))
    return {key: {"error_pct": [round(100 * v, 1) for v in p[key]["rel_error"]],
                  "covered": p[key].get("covered")} for key in ("attenuation.eta_per_m", "veil")}


def measured_table(ws: Path):
    """(the water table of workspace ``ws`` as bench_forms measures it, the water stage's configuration without the
    fine grid, the declared lights, the survey's true parameters)."""
    from eval.observations import measure_frames
    from pipeline.water import WaterStage, survey_lights

    frames, K, _, board, _ = load_inputs(ws)
    sfm = json.loads((stage_folder(ws, "sfm") / "result.json").read_text())["result"]
    config = WaterStage(progress=False, range_scale_sd=float(sfm.get("scale_spread", 0.0)), correction_grid=None)
    obs = measure_frames(frames, K, None, board, config.measure, normals=False)
    return obs, config, survey_lights(stage_folder(ws, "survey")), truth_params(stage_folder(ws, "survey"))


def main(argv: list[str] | None = None) -> int:
    from eval.water import estimate_observations

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="bench_forms.py's workspaces")
    parser.add_argument("--forms", type=Path, default=Path("benchmarks/results/forms.json"))
    parser.add_argument("--draws", default="", help="comma-separated draw indices (default: all)")
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/forms_oracle_form.json"))
    args = parser.parse_args(argv)
    bench_forms.load_forms()
    records = json.loads(args.forms.read_text())["draws"]
    chosen = [int(i) for i in args.draws.split(",")] if args.draws else range(len(records))
    rows = json.loads(args.json.read_text())["draws"] if args.json.is_file() and args.draws else {}
    for i in chosen:
        draw = records[i]["truth"]
        obs, config, lights, truth = measured_table(args.out / draw["workspace"])
        rows[str(i)] = {"effect": draw["effect"], "stereo": draw["stereo"], "terrain": draw["terrain"]}
        for label, cfg in (("default", config), ("exact_form", exact_form(config, draw["effect"], truth))):
            rows[str(i)][label] = errors(estimate_observations(obs, cfg, lights), truth)
            e = rows[str(i)][label]["attenuation.eta_per_m"]
            print(f"{i:2d} {draw['effect']:20s} {label:10s} eta {e['error_pct']} covered {e['covered']} "
                  f"veil {rows[str(i)][label]['veil']['error_pct']}", flush=True)
    within = {label: float(np.mean([max(map(abs, r[label]["attenuation.eta_per_m"]["error_pct"])) <= 10
                                    for r in rows.values()])) for label in ("default", "exact_form")}
    out = {"command": "benchmarks/studies/forms_oracle_form.py " + " ".join(argv or sys.argv[1:]),
           "eta_within_10pct": within, "draws": rows}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=1))
    print("eta within 10 %:", within)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
