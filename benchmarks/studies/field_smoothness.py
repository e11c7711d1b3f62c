"""eta's and the veil's errors on benchmark workspaces at several weights of the fields' smoothness penalty
(``image_field.smoothness``; issue 52's choice of its default, benchmarks/RESULTS/water.md).

    python benchmarks/studies/field_smoothness.py WS [WS ...] [--smoothness 1e-4,1e-5,1e-6]

WS: workspaces prepared by ``bench_forms.py`` or ``bench_water.py`` (survey with its truth, SfM, dense). Each one's
water table is measured as ``forms_oracle_form.py`` measures it and fitted by
:func:`eval.water.estimate_observations` with
the water stage's defaults, the penalty at each weight, no structure alternative and no fine grid. Prints per
workspace and weight the relative errors (per cent) and whether the 95 % intervals cover the truth.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_forms  # noqa: E402  (the benchmarks folder is not a package)
from forms_oracle_form import errors, measured_table  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    from eval.water import estimate_observations

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspaces", type=Path, nargs="+")
    parser.add_argument("--smoothness", default="1e-4,1e-5,1e-6", help="comma-separated penalty weights")
    args = parser.parse_args(argv)
    bench_forms.load_forms()
    for ws in args.workspaces:
        obs, config, lights, truth = measured_table(ws)
        for weight in (float(w) for w in args.smoothness.split(",")):
            fields = ({"name": "image_field", "params": {"smoothness": weight}},)
            found = errors(estimate_observations(obs, replace(config, alternatives=(), initial=fields), lights),
                           truth)
            eta, veil = found["attenuation.eta_per_m"], found["veil"]
            print(f"{ws.name:14s} {weight:7.0e} eta {eta['error_pct']} covered {eta['covered']} "
                  f"veil {veil['error_pct']} covered {veil['covered']}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
