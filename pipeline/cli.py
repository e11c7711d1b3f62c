"""The `watergan` console script.

    watergan effects                      list every registered effect, its parameters and signature
    watergan simulate --out DIR [--preset demo|reef|auv|tiny|small] [--hidden NAME[,NAME]] [--seed N] [--force]
    watergan run SURVEY --workspace WS    every stage, resumable (see pipeline/cli_run.py); SURVEY may be a video
    watergan frames VIDEO... --out DIR    a survey folder of frames from video clips (see pipeline/video.py)
    watergan demo [--out DIR]             simulate the built-in default survey and run every stage on it
    watergan survey / sfm / dense / range / water / gan / restorer / correct / evaluate / texture / mosaic / report
             --workspace WS               one stage of the workspace (pipeline/cli_stage.py), as `run` runs it
    watergan train-gan / generate         WaterGAN on folders (see pipeline/cli_gan.py)
    watergan train-restorer / correct-folder   the restorer on folders (see pipeline/cli_restorer.py)
    watergan consistency / depth-compare  measurements of any folders (see pipeline/cli_3d.py)
    watergan diagnose / ledger            the discovery loop (see pipeline/cli_diagnose.py)

Every command takes ``--plugin FILE.py`` (repeatable) to register a user's own effects first. The
options of each command are generated from its configuration dataclass (:mod:`pipeline.cliargs`):
``watergan COMMAND --help`` lists them with their defaults and the fields' docstrings.
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import sys
import time
import zlib  # noqa: F401  load before pycolmap: importing pycolmap first makes Python's zlib corrupt the heap
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

from eval.synth.presets import PRESETS

from .cli_help import grouped_commands
from .cliargs import add_config, config_from_args

PLUGIN_HELP = "a Python file that registers effects with @watergan.formation.register (repeatable)"


def _plugin_parent() -> argparse.ArgumentParser:
    """``--plugin`` for every subcommand (the top-level one has its own destination: argparse lets a
    subparser's default overwrite a value given before the subcommand)."""
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument("--plugin", action="append", default=[], metavar="FILE.py", help=PLUGIN_HELP)
    return parent


def cmd_effects(args: argparse.Namespace) -> int:
    from watergan.formation import available

    effects = available()
    print(f"{len(effects)} registered effects (equations: `help(watergan.formation.effects.<name>)`)\n")
    for cls in effects.values():
        print(cls.describe())
        print()
    return 0


#: The simulator's built-in surveys: one member per entry of eval.synth.PRESETS.
Preset = StrEnum("Preset", {name: name for name in PRESETS})


@dataclass(frozen=True)
class SimulateOptions:
    """``watergan simulate``."""

    out: Path
    """Output folder (must not exist or be empty, unless --force)."""
    preset: Preset = Preset.demo
    """demo: 44 stereo frames of 640x480; reef: 60 frames of a diver's rig over a colourful reef in 5 m of
    water; auv: 60 frames of an AUV at 2-4 m altitude in darkness with two strobes; tiny: a few small frames
    for tests; small: 10 frames of 320x240."""
    hidden: tuple[str, ...] = ()
    """Effects applied to the images but left out of the visible model."""
    seed: int = 0
    """Random seed (same seed: same bytes)."""
    force: bool = False
    """Replace an existing output folder."""
    stereo: bool = True
    """Write the rig's right frames (right/, baseline_m); --no-stereo: a monocular survey, scale from the
    navigation altitude (nav_altitude_m in survey.json) and range from multi-view stereo."""
    frames: int = 0
    """Survey length: at least this many frames, the preset's lines and frames per line grown alike over a site
    grown with them (0: the preset's)."""


def simulate(opts: SimulateOptions) -> int:
    from eval.synth import make_config, simulate_survey, with_frames

    config = make_config(opts.preset.value, hidden=list(opts.hidden), seed=opts.seed)
    if opts.frames:
        config = with_frames(config, opts.frames)
    if not opts.stereo:
        config = dataclasses.replace(config, trajectory=dataclasses.replace(config.trajectory, stereo=False))
    start = time.perf_counter()
    summary = simulate_survey(opts.out, config, force=opts.force)
    seconds = time.perf_counter() - start
    print(f"simulated {summary.frames} frames of {summary.width}x{summary.height} "
          f"({opts.preset.value}, hidden: {', '.join(opts.hidden) or 'none'}, seed {opts.seed}) in {seconds:.1f} s")
    print(f"survey:  {opts.out / 'images'}  (what a user has: images, camera.json, survey.json, rgbd/)")
    print(f"truth:   {opts.out / 'truth'}  (in-air images, depth, range, poses, effects incl. hidden, board)")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    return simulate(config_from_args(SimulateOptions, args))


def build_parser() -> argparse.ArgumentParser:
    plugin = _plugin_parent()
    parser = argparse.ArgumentParser(prog="watergan", usage="watergan [--plugin FILE.py] COMMAND [OPTIONS]",
                                     description="Underwater survey colour correction, 3D and physics diagnosis.\n\n"
                                                 "Start with: watergan demo, or watergan run SURVEY --workspace WS.",
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--plugin", dest="plugin_first", action="append", default=[], metavar="FILE.py",
                        help=PLUGIN_HELP)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", help=argparse.SUPPRESS,
                                prog="watergan")  # the commands are listed by group in the epilog

    p = sub.add_parser("effects", parents=[plugin], help="list registered effects")
    p.set_defaults(func=cmd_effects)

    p = sub.add_parser("simulate", parents=[plugin], help="render a simulated survey with known truth")
    add_config(p, SimulateOptions)
    p.set_defaults(func=cmd_simulate)

    from . import cli_3d, cli_diagnose, cli_gan, cli_report, cli_restorer, cli_run

    cli_gan.add_commands(sub, [plugin])
    cli_restorer.add_commands(sub, [plugin])
    cli_3d.add_commands(sub, [plugin])
    cli_diagnose.add_commands(sub, [plugin])
    cli_report.add_commands(sub, [plugin])
    cli_run.add_commands(sub, [plugin])
    parser.epilog = (grouped_commands(sub) + "\n\nwatergan COMMAND --help: a command's options (watergan run "
                     "--help: the common ones, and how to see each stage's).")
    return parser


def main(argv: list[str] | None = None) -> int:
    from watergan.errors import UserInputError
    from watergan.formation import UnknownEffectError, load_plugin
    from watergan.io import WriteError

    args = build_parser().parse_args(argv)
    try:
        for path in args.plugin_first + args.plugin:
            names = load_plugin(path)
            print(f"plugin {path}: registered {', '.join(names)}", file=sys.stderr)
        return args.func(args)
    # exit codes: 2 the input (or the command line) is wrong, 3 an output cannot be written, 130 interrupted
    except WriteError as exc:
        print(f"watergan: error: {exc}", file=sys.stderr)
        return 3
    except (UserInputError, UnknownEffectError) as exc:
        print(f"watergan: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk or a read-only place under a writer that is not ours (open3d, SQLite)
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS):
            raise
        fix = "free some space" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else "check the folder can be written"
        print(f"watergan: error: cannot write {exc.filename or 'an output'}: {exc.strerror}; {fix} and rerun "
              f"(finished stages are kept, the one that failed runs again)", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print("\nwatergan: interrupted: finished stages are kept (every file is written whole or not at all); the "
              "same command goes on from the stage that was running", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
