"""The restorer commands of the `watergan` console script.

    watergan train-restorer --data DIR --out DIR [--budget-min N] [--no-skip] [--head affine|direct] [--no-altitude]
                            [--seed N] [--resume]
    watergan correct --model DIR --images DIR --out DIR [--navigation FILE] [--force] [--batch-size N]

``pipeline/cli.py`` adds them with ``add_commands(sub, parents)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .cliargs import scheduler_parent


def cmd_train_restorer(args: argparse.Namespace) -> int:
    from watergan.train_restorer import RestorerConfig, train_restorer

    config = RestorerConfig(data_dir=Path(args.data), out_dir=Path(args.out), widths=args.widths,
                            skip=not args.no_skip, head=args.head, altitude=not args.no_altitude,
                            budget_min=args.budget_min, seed=args.seed, resume=args.resume,
                            batch_size=args.batch_size, device=args.device)
    result = train_restorer(config)
    print(f"trained {result.steps[0]} + {result.steps[1]} iterations (stage 1 + 2) in {result.seconds:.0f} s, "
          f"loss {result.loss:.4f}; {result.train_count} training, {result.val_count} held-out frames")
    print((Path(result.out_dir) / result.validation_md).read_text(), end="")
    print(f"model: {result.out_dir} (restorer.pt, validation.md, train_log.jsonl)")
    return 0


def cmd_correct(args: argparse.Namespace) -> int:
    from pipeline.correct import correct_folder

    result = correct_folder(args.model, args.images, args.out, force=args.force, batch_size=args.batch_size,
                            device=args.device, scheduler=args.scheduler or None, navigation=args.navigation)
    print(f"corrected {result.corrected}, already done {result.already_done}, failed {len(result.failed)} "
          f"in {result.seconds:.1f} s -> {result.out_dir} (images/, depth/, summary.json)")
    for line in result.failed:
        print(f"  {line}")
    return 0


def _device(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="auto: CUDA when available, else CPU")


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add ``train-restorer`` and ``correct`` to the subparsers ``sub``."""
    p = sub.add_parser("train-restorer", parents=parents,
                       help="train the depth and colour nets on WaterGAN's synthetic pairs")
    p.add_argument("--data", required=True, help="a `watergan generate` output folder (underwater/, inair/, depth/)")
    p.add_argument("--out", required=True, help="model folder (restorer.pt, checkpoint, log, validation tables)")
    p.add_argument("--budget-min", type=float, default=None,
                   help="time budget in minutes, half for each stage (default: the iteration counts only)")
    p.add_argument("--no-skip", action="store_true", help="ablation: colour net without full-resolution skips")
    p.add_argument("--head", choices=("affine", "direct"), default="affine",
                   help="colour core output: per-channel gain and offset fields (affine, default) or colours "
                        "(direct, as the paper)")
    p.add_argument("--no-altitude", action="store_true",
                   help="the colour net takes the image alone, not also its altitude above the seafloor (for surveys "
                        "without an altimeter's nav_altitude_m)")
    p.add_argument("--widths", choices=["cpu", "paper"], default="cpu",
                   help="net widths: cpu (small, default) or paper (SegNet-sized, for a GPU)")
    p.add_argument("--batch-size", type=int, default=8, help="images per batch (default 8)")
    p.add_argument("--seed", type=int, default=0, help="random seed of split, init and batches (default 0)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    _device(p)
    p.set_defaults(func=cmd_train_restorer)

    p = sub.add_parser("correct", parents=[*parents, scheduler_parent()],
                       help="correct an image sequence with a trained restorer")
    p.add_argument("--model", required=True, help="train-restorer output folder")
    p.add_argument("--images", required=True, help="folder of images to correct (PNG, JPEG, TIFF)")
    p.add_argument("--out", required=True, help="output folder (images/, depth/, summary.json)")
    p.add_argument("--navigation", default=None,
                   help="survey file with nav_altitude_m per frame, for a restorer that takes altitude (default: "
                        "survey.json beside the images folder)")
    p.add_argument("--force", action="store_true", help="redo images already corrected")
    p.add_argument("--batch-size", type=int, default=4, help="images per batch (default 4)")
    _device(p)
    p.set_defaults(func=cmd_correct)
