"""The WaterGAN commands of the `watergan` console script.

    watergan train-gan --rgbd DIR --underwater DIR --out DIR [--effects a,b,...] [--add NAME]
                       [--budget-min N] [--iterations N] [--epochs N] [--seed N] [--resume]
    watergan generate --model DIR --rgbd DIR --out DIR [--size HxW] [--recolour-fraction F] [--seed N]

``pipeline/cli.py`` adds them with ``add_commands(sub, parents)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from watergan.errors import UserInputError

from .cliargs import name_list


def _size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be HEIGHTxWIDTH, e.g. 480x640, got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return h, w


def cmd_train_gan(args: argparse.Namespace) -> int:
    from watergan.formation import get
    from watergan.nets.generator import DEFAULT_EFFECTS
    from watergan.train import GanConfig, train_gan

    effects = name_list(args.effects) if args.effects else list(DEFAULT_EFFECTS)
    effects += [name for name in args.add if name not in effects]
    for name in effects:
        get(name)  # unknown names fail before any data is read
    budget = args.budget_min
    if budget is None and args.iterations is None and args.epochs is None:
        budget = 5.0
    config = GanConfig(rgbd_dir=Path(args.rgbd), underwater_dir=Path(args.underwater), out_dir=Path(args.out),
                       effects=tuple(effects), iterations=args.iterations, epochs=args.epochs, budget_min=budget,
                       seed=args.seed, resume=args.resume, skip_bad=args.skip_bad, disc_width=args.disc_width,
                       adversarial_physics=args.adversarial_physics,
                       batch_size=args.batch_size, encoding=args.encoding, device=args.device)
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

    if not Path(args.model).is_dir():
        raise UserInputError(f"model folder {args.model} does not exist: run `watergan train-gan` first")
    result = generate(GenerateConfig(model_dir=Path(args.model), rgbd_dir=Path(args.rgbd), out_dir=Path(args.out),
                                     size_hw=args.size, seed=args.seed, skip_bad=args.skip_bad,
                                     recolour_fraction=args.recolour_fraction,
                                     encoding=args.encoding, device=args.device))
    print(f"generated {result.count} underwater images in {result.seconds:.1f} s -> {result.out_dir} "
          f"(inair/, depth/, underwater/, manifest.json)")
    if result.skipped:
        print(f"skipped {len(result.skipped)} bad file(s):\n  " + "\n  ".join(result.skipped))
    return 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--skip-bad", action="store_true", help="skip and report bad or unpaired files")
    p.add_argument("--encoding", choices=["srgb", "linear"], default="srgb",
                   help="encoding of the image files (default srgb, decoded to linear)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="auto: CUDA when available, else CPU")


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add ``train-gan`` and ``generate`` to the subparsers ``sub``."""
    from watergan.generate import GenerateConfig  # option defaults come from the configs
    from watergan.train import GanConfig
    p = sub.add_parser("train-gan", parents=parents, help="learn the site's water: train a WaterGAN")
    p.add_argument("--rgbd", required=True, help="in-air RGB-D folder (rgb/ + depth/, paired by file stem)")
    p.add_argument("--underwater", required=True, help="folder of the survey's underwater images")
    p.add_argument("--out", required=True, help="model folder (checkpoint, stack.json, log, plots)")
    p.add_argument("--effects", default="", metavar="A,B,...",
                   help="effects of the generator (default attenuation,backscatter_conv,vignetting,gain)")
    p.add_argument("--add", action="append", default=[], metavar="NAME",
                   help="add a registered effect to the generator (repeatable; placed by its rank)")
    p.add_argument("--budget-min", type=float, default=None,
                   help="time budget in minutes (default 5 when no --iterations or --epochs is given)")
    p.add_argument("--iterations", type=int, default=None, help="stop after N iterations")
    p.add_argument("--epochs", type=int, default=None, help="stop after N epochs")
    p.add_argument("--batch-size", type=int, default=GanConfig.batch_size,
                   help=f"batch size (default {GanConfig.batch_size})")
    p.add_argument("--disc-width", type=int, default=GanConfig.disc_width,
                   help=f"channels of the discriminator's first conv (paper 64; default {GanConfig.disc_width} "
                        f"for the CPU)")
    p.add_argument("--adversarial-physics", action="store_true",
                   help="let the discriminator move the physical parameters too, as the paper does (default: "
                        "they follow the colour statistics; see GanConfig.adversarial_physics)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    _common(p)
    p.set_defaults(func=cmd_train_gan)

    p = sub.add_parser("generate", parents=parents,
                       help="render full-resolution synthetic underwater images with a trained WaterGAN")
    p.add_argument("--model", required=True, help="train-gan output folder")
    p.add_argument("--rgbd", required=True, help="in-air RGB-D folder (rgb/ + depth/)")
    p.add_argument("--out", required=True, help="output folder (inair/, depth/, underwater/, manifest.json)")
    p.add_argument("--size", type=_size, default=None, metavar="HxW",
                   help="output size, e.g. 480x640 (default: each in-air image's size)")
    p.add_argument("--recolour-fraction", type=float, default=GenerateConfig.recolour_fraction, metavar="F",
                   help="fraction of in-air images given random hues and saturation before rendering, so the "
                        f"restorer sees colours a sediment set lacks (default {GenerateConfig.recolour_fraction})")
    _common(p)
    p.set_defaults(func=cmd_generate)
