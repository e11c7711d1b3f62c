"""The diagnosis commands of the `watergan` console script.

    watergan diagnose WORKSPACE_OR_SURVEY [--geometry auto|truth|sfm] [--effects A,B,...] [--add NAME]
                      [--candidates A,B,...] [--points N] [--iterations N] [--seed N] [--no-plots]
    watergan ledger WORKSPACE

``pipeline/cli.py`` adds them with ``add_commands(sub, parents)``; ``--plugin FILE.py`` (from the
parents) registers a user's effects first, which then take part as candidates or via ``--add``.
"""

from __future__ import annotations

import argparse

from .cliargs import name_list


def cmd_diagnose(args: argparse.Namespace) -> int:
    from eval.diagnose import DiagnoseConfig, run_diagnose
    from eval.diagnose_fit import FitConfig
    from eval.diagnose_measure import MeasureConfig
    from watergan.formation import get

    effects, add, candidates = name_list(args.effects), args.add, name_list(args.candidates)
    for name in (*effects, *add, *candidates):
        get(name)  # unknown names fail before any data is read
    config = DiagnoseConfig(geometry=args.geometry, effects=tuple(effects), add=tuple(add),
                            candidates=tuple(candidates),
                            measure=MeasureConfig(n_points=args.points, seed=args.seed),
                            fit=FitConfig(iterations=args.iterations, seed=args.seed), plots=not args.no_plots)
    result = run_diagnose(args.target, config)
    print(f"model: {' -> '.join(result.stack)}")
    print(f"{result.n_points} points, {result.n_obs} observations (geometry: {result.geometry}); "
          f"held-out RMSE {result.heldout_rmse:.5f} (linear)")
    print("structure score per axis (about 1 = no structure): "
          + ", ".join(f"{axis} {score:.1f}" for axis, score in result.scores.items()))
    print("candidates (held-out error change, 95% CI, p, axis flattened):")
    for r in result.ranking:
        mark = "*" if r["significant"] else " "
        print(f" {mark} {r['name']:24} {r['change'] * 100:+6.1f}%  [{r['ci95'][0] * 100:+.1f}%, "
              f"{r['ci95'][1] * 100:+.1f}%]  p={r['p']:.3f}  {r['flattened']}")
    for name, reason in result.skipped.items():
        print(f"   skipped {name}: {reason}")
    print(f"\n{result.verdict}")
    print(f"\noutputs: {result.out_dir} (measurements.npz, fit.json, residuals.json, residual_*.png, "
          f"points_residual.ply, ranking.json, verdict.txt, ledger.png)")
    if result.best:
        print(f"next: watergan diagnose {args.target} --add {result.best}")
    return 0


def cmd_ledger(args: argparse.Namespace) -> int:
    from eval.diagnose import find_ledger, ledger_table, plot_ledger, read_ledger

    path = find_ledger(args.workspace)
    records = read_ledger(path)
    print(ledger_table(records))
    plot = path.with_suffix(".png")
    plot_ledger(records, plot)
    print(f"\nplot: {plot}")
    return 0


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add ``diagnose`` and ``ledger`` to the subparsers ``sub``."""
    p = sub.add_parser("diagnose", parents=parents,
                       help="fit the formation model to multi-view measurements and name the missing effect")
    p.add_argument("target", metavar="WORKSPACE_OR_SURVEY",
                   help="a workspace (its 00_survey/ is used, output in 08_diagnose/) or a survey folder "
                        "(output in SURVEY/diagnose/)")
    p.add_argument("--geometry", choices=("auto", "truth", "sfm"), default="auto",
                   help="3D points and views from the workspace's SfM tracks (sfm), the simulator's truth (truth), "
                        "or auto: sfm when WORKSPACE/04_sfm/tracks.npz exists, else truth (default)")
    p.add_argument("--effects", default="", metavar="A,B,...",
                   help="the model's effects (default: the survey's visible stack when simulated, else "
                        "attenuation,backscatter,vignetting,gain)")
    p.add_argument("--add", action="append", default=[], metavar="NAME",
                   help="add an effect to the model (repeatable; placed by its rank): the next model version")
    p.add_argument("--candidates", default="", metavar="A,B,...",
                   help="candidate effects to try (default: every registered effect that can act on points)")
    p.add_argument("--points", type=int, default=3000, help="3D points to sample (default 3000)")
    p.add_argument("--iterations", type=int, default=100,
                   help="L-BFGS iterations per fit, albedos projected out (default 100)")
    p.add_argument("--seed", type=int, default=0, help="seed of the point sampling and held-out split")
    p.add_argument("--no-plots", action="store_true", help="skip the residual plots and PLY")
    p.set_defaults(func=cmd_diagnose)

    p = sub.add_parser("ledger", parents=parents, help="print the model ledger and plot the error per model version")
    p.add_argument("workspace", help="workspace (or survey folder) that `watergan diagnose` wrote to")
    p.set_defaults(func=cmd_ledger)
