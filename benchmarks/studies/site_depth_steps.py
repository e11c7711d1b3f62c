"""The site depth net's steps against its held-out comparison with the flat seafloor, on finished workspaces.

    PYTHONPATH=. .venv/bin/python benchmarks/studies/site_depth_steps.py WS [WS ...] [--steps 2000,1000]

For each workspace (a `watergan run` with its dense stage) and each step count,
:func:`pipeline.site_depth.fit_site_depth` trains the net into a temporary folder (the workspace is not changed) and
prints its seconds and its held-out RMSE as a ratio of the flat seafloor's, on relief pixels and on all pixels (below
1: the net beats the plane).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path


def main() -> None:
    from pipeline.site_depth import fit_site_depth
    from pipeline.workspace import Workspace
    from watergan.train_site_depth import SiteDepthConfig

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workspaces", nargs="+", type=Path)
    parser.add_argument("--steps", default="2000,1000")
    args = parser.parse_args()
    for root in args.workspaces:
        for steps in (int(s) for s in args.steps.split(",")):
            with tempfile.TemporaryDirectory() as folder:
                record = fit_site_depth(Workspace(root), SiteDepthConfig(steps=steps), Path(folder), progress=False)
            print(f"{root.name}: {steps} steps, {record['seconds']:.1f} s, held-out RMSE over the flat seafloor's: "
                  f"relief pixels {record['relief_rmse_ratio']:.3f}, all pixels {record['all_rmse_ratio']:.3f}",
                  flush=True)


if __name__ == "__main__":
    main()
