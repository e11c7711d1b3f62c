"""The WaterGAN commands of the `watergan` console script (options: :class:`watergan.train.GanConfig`
and :class:`watergan.generate.GenerateConfig`, see ``--help``).

    watergan train-gan --rgbd-dir DIR --underwater-dir DIR --out-dir DIR [--effects A,B] [--add NAME]
                       [--budget-min N] [--iterations N] [--epochs N] [--seed N] [--resume] ...
    watergan generate --model-dir DIR --rgbd-dir DIR --out-dir DIR [--size-hw HxW] [--recolour-fraction F] ...
    watergan gan --workspace WS [--budget-min N] [--effects A,B] [--add NAME] ...   the workspace's gan stage

``pipeline/cli.py`` adds them with ``add_commands(sub, parents)``.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from watergan.errors import UserInputError

from .cli_stage import add_stage_command
from .cliargs import add_config, check_effects, config_from_args, list_option


def cmd_train_gan(args: argparse.Namespace) -> int:
    from watergan.train import GanConfig, train_gan

    config = config_from_args(GanConfig, args)
    effects = tuple(dict.fromkeys(config.effects + check_effects(args.add)))
    limits = [k for k in ("budget_min", "iterations", "epochs") if hasattr(args, k)]
    budget = None if limits and "budget_min" not in limits else config.budget_min  # iterations or epochs alone
    config = dataclasses.replace(config, effects=effects, budget_min=budget)
    result = train_gan(config)
    print(f"trained {result.steps} iterations ({result.iterations_per_s:.2f} it/s, stopped by {result.stopped_by}) "
          f"in {result.seconds:.0f} s; losses D {result.d_loss:.3f}, G {result.g_loss:.3f}")
    for name, value in result.params.items():
        print(f"  {name} = {value}")
    if result.skipped:
        print(f"skipped {len(result.skipped)} bad file(s) (listed above)")
    print(f"model: {result.out_dir} (stack.json, checkpoint.pt, training.png, samples/)")
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
    from watergan.generate import GenerateConfig, generate

    config = config_from_args(GenerateConfig, args)
    if not Path(config.model_dir).is_dir():
        raise UserInputError(f"model folder {config.model_dir} does not exist: run `watergan train-gan` first")
    result = generate(config)
    print(f"generated {result.count} underwater images in {result.seconds:.1f} s -> {result.out_dir} "
          f"(inair/, depth/, range/, underwater/, manifest.json)")
    if result.skipped:
        print(f"skipped {len(result.skipped)} bad file(s):\n  " + "\n  ".join(result.skipped))
    return 0


def print_gan(ws, r) -> None:
    train = r.train
    print(f"WaterGAN: {train.get('steps')} iterations in {train.get('seconds', 0.0):.0f} s, stopped by "
          f"{train.get('stopped_by')}; {r.generated_count} pairs rendered in {r.generate_seconds:.1f} s")
    print(f"model: {ws.path(r.model)}\npairs: {ws.path(r.generated)}")


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add ``train-gan``, ``generate`` and the gan stage's ``gan`` to the subparsers ``sub``."""
    from watergan.generate import GenerateConfig
    from watergan.train import GanConfig

    p = sub.add_parser("train-gan", parents=parents, help="learn the site's water: train a WaterGAN")
    add_config(p, GanConfig, exclude=("progress",))
    p.add_argument("--add", **list_option("effects added to the generator's (placed by their rank)"), default=[])
    p.set_defaults(func=cmd_train_gan)

    p = sub.add_parser("generate", parents=parents,
                       help="render full-resolution synthetic underwater images with a trained WaterGAN")
    add_config(p, GenerateConfig, exclude=("progress",))
    p.set_defaults(func=cmd_generate)

    add_stage_command(sub, parents, "gan", print_gan)
