"""The water stage, then the diagnose stage with the built-in candidates, on a workspace that
``benchmarks/bench_water.py`` prepared (survey, SfM and dense done): how the diagnosis reads a robustness survey.

    PYTHONPATH=. .venv/bin/python benchmarks/studies/diagnose_bench_workspace.py /tmp/bench_water/veil0 [--force]

The robustness surveys' effects (``benchmarks/plugins/robust_forms.py``) are registered so that the survey's truth
reads, but they are not candidates: the candidates are the built-in effects, less the nuisance fields and
``ambient_depth`` (which the albedo absorbs). Prints the water's summary, the diagnosis's seconds (stage and base
fit) and the verdict. ``--force``: rerun the diagnosis when it is done with the same configuration.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def main() -> None:
    from benchmarks.bench_water import load_robust_forms
    from eval.diagnose import DiagnoseConfig
    from pipeline.water import WaterStage
    from pipeline.workspace import Workspace
    from watergan.formation import builtin_effects

    load_robust_forms()
    ws = Workspace(Path(sys.argv[1]))
    began = time.perf_counter()
    water = ws.run("water", WaterStage(progress=False))
    print(f"{water.summary} ({time.perf_counter() - began:.0f} s)", flush=True)
    names = tuple(n for n, c in builtin_effects().items() if not c.nuisance and n != "ambient_depth")
    began = time.perf_counter()
    diagnosed = ws.run("diagnose", DiagnoseConfig(progress=False, candidates=names), force="--force" in sys.argv)
    fit = json.loads((Path(diagnosed.out_dir) / "fit.json").read_text())
    print(f"diagnosis {time.perf_counter() - began:.1f} s, its base fit {fit['seconds']:.1f} s")
    print((Path(diagnosed.out_dir) / "verdict.txt").read_text())


if __name__ == "__main__":
    main()
