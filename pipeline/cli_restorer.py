"""The restorer and correction commands of the `watergan` console script (options:
:class:`watergan.train_restorer.RestorerConfig`, :class:`watergan.restore_folder.CorrectConfig` and the workspace
stages' :class:`pipeline.gan.RestorerStage`, :class:`pipeline.correct.CorrectStage`).

    watergan train-restorer --data-dir DIR --out-dir DIR [--budget-min N] [--no-skip] [--head affine|direct]
                            [--no-altitude] [--seed N] [--resume] ...
    watergan correct-folder --model-dir DIR --images-dir DIR --out-dir DIR [--navigation FILE] [--force] ...
    watergan restorer --workspace WS [--budget-min N] [--head affine|direct] ...   the workspace's restorer stage
    watergan correct --workspace WS [--mode auto|rgb-d|monocular] ...              the workspace's correct stage

``pipeline/cli.py`` adds them with ``add_commands(sub, parents)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .cli_stage import add_stage_command
from .cliargs import add_config, config_from_args


def cmd_train_restorer(args: argparse.Namespace) -> int:
    from watergan.train_restorer import RestorerConfig, train_restorer

    result = train_restorer(config_from_args(RestorerConfig, args))
    print(f"trained {result.steps[0]} + {result.steps[1]} iterations (stage 1 + 2) in {result.seconds:.0f} s, "
          f"loss {result.loss:.4f}; {result.train_count} training, {result.val_count} held-out frames")
    print((Path(result.out_dir) / result.validation_md).read_text(), end="")
    print(f"model: {result.out_dir} (restorer.pt, validation.md, train_log.jsonl)")
    return 0


def cmd_correct(args: argparse.Namespace) -> int:
    from watergan.restore_folder import CorrectConfig, correct_folder

    c = config_from_args(CorrectConfig, args)
    result = correct_folder(c.model_dir, c.images_dir, c.out_dir, force=c.force, batch_size=c.batch_size,
                            device=c.device, scheduler=c.scheduler or None, navigation=c.navigation,
                            range_dir=c.range_dir, mode=str(c.mode), image_format=str(c.image_format),
                            fill_px=c.fill_px, far_max_gain=c.far_max_gain, far_range_pct=c.far_range_pct)
    print(f"corrected {result.corrected} ({result.mode} mode), already done {result.already_done}, "
          f"failed {len(result.failed)} in {result.seconds:.1f} s -> {result.out_dir} (images/, depth/, summary.json)")
    for line in result.failed:
        print(f"  {line}")
    if result.range_source:
        print(f"range: {result.range_source}" + (f" (site depth net: {result.range_why})" if result.range_why else ""))
    return 0


def print_restorer(ws, r) -> None:
    print(f"restorer: {r.steps[0]} + {r.steps[1]} iterations in {r.seconds:.0f} s, loss {r.loss:.4f}; "
          f"{r.train_count} training, {r.val_count} held-out frames")
    site = getattr(r, "site_depth", {})
    if site:
        print(f"site depth net: {site['why']}")
    print(f"model: {r.out_dir}")


def print_correct(ws, r) -> None:
    if r.physics:
        source = f", range from the {r.physics_range_source}" if r.physics_range_source else ""
        print(f"physics: {ws.path(r.physics_images)} ({100 * r.filled_fraction:.1f} % of the pixels ranged from "
              f"their neighbours, {100 * r.far_fraction:.1f} % at the far range {r.far_range_m:.2f} m{source}), "
              f"{r.physics_seconds:.1f} s")
    if r.restorer:
        source = f", range from the {r.range_source}" if r.range_source else ""
        print(f"restorer: {r.corrected} frames ({r.mode} mode{source}), {len(r.failed)} failed, {r.seconds:.1f} s "
              f"-> {ws.path(r.images)}")
        for line in r.failed:
            print(f"  {line}")
    print(f"the mesh textures with: {ws.path(r.mesh_images)}")


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add ``train-restorer``, ``correct-folder`` and the stages' ``restorer`` and ``correct`` to ``sub``."""
    from watergan.restore_folder import CorrectConfig
    from watergan.train_restorer import RestorerConfig

    p = sub.add_parser("train-restorer", parents=parents,
                       help="train the depth and colour nets on WaterGAN's synthetic pairs")
    add_config(p, RestorerConfig, exclude=("progress",))
    p.set_defaults(func=cmd_train_restorer)

    p = sub.add_parser("correct-folder", parents=parents, help="correct a folder of images with a trained restorer")
    add_config(p, CorrectConfig)
    p.set_defaults(func=cmd_correct)

    add_stage_command(sub, parents, "restorer", print_restorer)
    add_stage_command(sub, parents, "correct", print_correct)
