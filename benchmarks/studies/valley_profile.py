"""The water fit's loss along one channel of B_inf, every other parameter refitted (issue 28: would a profile
likelihood cover the truth where the bootstrap does not?).

    PYTHONPATH=. .venv/bin/python benchmarks/studies/valley_profile.py TABLE WS [--channel 0] [--iterations 300]

``TABLE``: a measurement table (``water_on_workspace.py --table``); ``WS``: the simulated survey's workspace it was
measured on (its 00_survey truth and lights, its SfM scale spread). Fits the water with the default
:class:`eval.water.WaterConfig` as the water stage does, then holds B_inf of ``--channel`` at the truth, midway to the
interval's low end, the interval's ends and the estimate in turn (its gradient zeroed) and refits every other parameter
from the fit by ``--iterations`` L-BFGS iterations; prints each value's loss above the fit's, in per cent, and the
refitted beta of that channel.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_water import compare, truth_params  # noqa: E402

from pipeline.stages import stage_folder  # noqa: E402


def main() -> None:
    import eval.water as ew
    from eval.observations import Observations
    from pipeline.water import survey_lights

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("table", type=Path)
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--channel", type=int, default=0)
    parser.add_argument("--iterations", type=int, default=300)
    args = parser.parse_args()
    ws, channel = args.workspace, args.channel
    record = json.loads((stage_folder(ws, "sfm") / "result.json").read_text())
    config = replace(ew.WaterConfig(), range_scale_sd=float(record["result"]["scale_spread"]))
    fitted = {}
    bootstrap = ew.bootstrap

    def keep_fit(problem, *rest, **kwargs):  # the fitted problem at its optimum, as the bootstrap starts from it
        fitted["problem"], fitted["x"] = problem, problem.flat().clone()
        return bootstrap(problem, *rest, **kwargs)

    ew.bootstrap = keep_fit
    estimate = ew.estimate_observations(Observations.load(args.table), config,
                                   lights=survey_lights(stage_folder(ws, "survey")))
    row = compare(estimate.params, truth_params(stage_folder(ws, "survey")))["backscatter.b_inf"]
    print("B_inf estimate", row["estimate"], "truth", row["truth"], "interval", row["low"], row["high"])
    problem, x0 = fitted["problem"], fitted["x"]
    index = problem.stack.names.index("backscatter")
    raw = problem.theta[problem.names.index(f"effects.{index}.raw.b_inf")]
    spec = problem.stack.effects[index]._spec("b_inf")
    problem.set_flat(x0)
    with torch.no_grad():
        best = float(problem.loss())
    truth, low = float(row["truth"][channel]), float(row["low"][channel])
    for value in sorted({truth, (truth + low) / 2, low, float(row["estimate"][channel]), float(row["high"][channel])}):
        problem.set_flat(x0)
        with torch.no_grad():
            physical = spec.to_value(raw.detach()).clone()
            physical[channel] = value
            raw.copy_(spec.to_raw(physical))
        problem.take_gradients()
        hook = raw.register_hook(lambda g: g.index_fill(0, torch.tensor([channel]), 0.0))
        problem.minimise(args.iterations)
        hook.remove()
        with torch.no_grad():
            loss = float(problem.loss())
        beta = problem.physical()[f"effects.{index}.raw.beta_per_m"][channel]
        print(f"B_inf[{channel}] {value:.4f}: loss {100 * (loss - best) / best:+.2f} % above the fit's, "
              f"beta {float(np.asarray(beta)):.3f}", flush=True)


if __name__ == "__main__":
    main()
