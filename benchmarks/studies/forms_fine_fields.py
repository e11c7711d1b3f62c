"""eta's error on benchmark workspaces with and without fine fields over the image fitted jointly with the water
(``WaterConfig.field_grid``; issue 52's fourth pass, benchmarks/RESULTS/water.md).

    python benchmarks/studies/forms_fine_fields.py WS [WS ...] [--grid 13x17]

WS: workspaces prepared by ``bench_forms.py`` or ``bench_water.py`` (survey with its truth, SfM, dense). Each one's
water table is measured as ``forms_oracle_form.py`` measures it and fitted by
:func:`eval.water.estimate_observations` with
the water stage's defaults, no structure alternative, no bootstrap and no fine grid after the water: once with the
degree-2 fields alone, once with the fine fields beside them. Prints per workspace and fit eta's relative errors
(per cent, R / G / B) and the fit's seconds.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_forms  # noqa: E402  (the benchmarks folder is not a package)
from forms_oracle_form import measured_table  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    from eval.water import estimate_observations
    from pipeline.cliargs import size_hw

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspaces", type=Path, nargs="+")
    parser.add_argument("--grid", type=size_hw, default=(13, 17), help="nodes of the fine fields, ROWSxCOLS")
    args = parser.parse_args(argv)
    bench_forms.load_forms()
    for ws in args.workspaces:
        obs, config, lights, truth = measured_table(ws)
        alone = replace(config, alternatives=(), fit=replace(config.fit, bootstrap=0))
        for label, grid in (("degree-2 fields", None), (f"fine fields {args.grid[0]}x{args.grid[1]}", args.grid)):
            began = time.perf_counter()
            water = estimate_observations(obs, replace(alone, field_grid=grid), lights)
            error = 100 * (np.asarray(water.params["attenuation.eta_per_m"].value) /
                           np.asarray(truth["attenuation.eta_per_m"]) - 1)
            print(f"{ws.name:14s} {label:22s} eta {' / '.join(f'{e:+.0f}' for e in error)} %  "
                  f"{time.perf_counter() - began:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
