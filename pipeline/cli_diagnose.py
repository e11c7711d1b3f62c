"""The diagnosis commands of the `watergan` console script (options:
:class:`eval.diagnose.DiagnoseConfig`, nested ones prefixed: ``--measure-n-points``, ``--fit-iterations``).

    watergan diagnose FOLDER [--geometry auto|water|sfm|truth] [--effects A,B,...] [--add NAME[,NAME]] [--threads N]
                      [--candidates A,B,...] [--measure-n-points N] [--fit-iterations N] [--no-plots] [--force]
    watergan ledger FOLDER                (FOLDER: a workspace or a survey folder)

``pipeline/cli.py`` adds them with ``add_commands(sub, parents)``; ``--plugin FILE.py`` (from the
parents) registers a user's effects first, which then take part as candidates or via ``--add``.
"""

from __future__ import annotations

import argparse

from .cliargs import add_config, config_from_args


def cmd_diagnose(args: argparse.Namespace) -> int:
    from eval.diagnose import DiagnoseConfig
    from pipeline.diagnose import run_diagnose
    from watergan.progress import activity
    from watergan.threads import use_threads

    config = config_from_args(DiagnoseConfig, args)
    with use_threads(args.threads), activity("diagnose", config.progress is not False):
        result = run_diagnose(args.target, config, force=args.force)
    print(f"model: {' -> '.join(result.stack)}")
    print(f"{result.n_points} points, {result.n_obs} observations (geometry: {result.geometry}); "
          f"held-out RMSE {result.heldout_rmse:.5f} (linear)")
    if result.geometry.startswith("water"):
        print(f"measurements: {result.measurements} (the water estimate's own)")
    print("structure score per axis (about 1 = no structure): "
          + ", ".join(f"{axis} {score:.1f}" for axis, score in result.scores.items()))
    print("candidates (held-out error change, 95% CI, p, axis flattened; * accepted, ! implausible values):")
    for r in result.ranking:
        mark = "*" if r["significant"] else "!" if r["implausible"] else " "
        share = r.get("fields_explained")
        print(f" {mark} {r['name']:24} {r['change'] * 100:+6.1f}%  [{r['ci95'][0] * 100:+.1f}%, "
              f"{r['ci95'][1] * 100:+.1f}%]  p={r['p']:.3f}  {r['flattened']}"
              + (f"  (reproduces {share:.0%} of the water's fields)" if share is not None else ""))
    for name, reason in result.skipped.items():
        print(f"   skipped {name}: {reason}")
    print(f"\n{result.verdict}")
    print(f"\noutputs: {result.out_dir} (measurements.npz, fit.json, residuals.json, residual_*.png, "
          f"points_residual.ply, ranking.json, verdict.txt, model_ledger.jsonl, ledger.png)")
    if result.best:
        print(f"next: watergan diagnose {args.target} --add {result.best}")
    return 0


def cmd_ledger(args: argparse.Namespace) -> int:
    from eval.ledger import ledger_table, plot_ledger, read_ledger
    from pipeline.diagnose import ledger_path

    path = ledger_path(args.workspace)
    records = read_ledger(path)
    print(ledger_table(records))
    plot = path.parent / "ledger.png"  # the plot the diagnosis draws beside its ledger, redrawn
    plot_ledger(records, plot)
    print(f"\nplot: {plot}")
    return 0


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add ``diagnose`` and ``ledger`` to the subparsers ``sub``."""
    from eval.diagnose import DiagnoseConfig

    p = sub.add_parser("diagnose", parents=parents,
                       help="fit the formation model to multi-view measurements and name the missing effect")
    p.add_argument("target", metavar="FOLDER",
                   help="a workspace (its survey; output in its diagnose stage's folder) or a survey folder "
                        "(output in SURVEY/diagnose/)")
    p.add_argument("--force", action="store_true", help="rerun in a workspace even when done with the same options")
    p.add_argument("--threads", type=int, default=0, metavar="N",
                   help="threads of the numerical work (torch, OpenCV); 0: the cores no other job keeps busy "
                        "(default: 0)")
    add_config(p, DiagnoseConfig)
    p.set_defaults(func=cmd_diagnose)

    p = sub.add_parser("ledger", parents=parents, help="print the model ledger and plot the error per model version")
    p.add_argument("workspace", metavar="FOLDER",
                   help="workspace (or survey folder) that watergan diagnose wrote to")
    p.set_defaults(func=cmd_ledger)
