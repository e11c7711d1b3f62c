"""The one-command subcommands of the `watergan` console script (wired in by pipeline.cli):

    watergan run SURVEY --workspace WS [--config run.toml] [--add LIST] [--seed N] [--force STAGE]...
                 [--STAGE-OPTION VALUE]...        e.g. --gan-budget-min 4 --restorer-head direct
    watergan demo [--out demo_out] [--preset demo|reef|auv|tiny|small] [same options]
    watergan frames VIDEO... --out SURVEY [--overlap 0.8] [--max-step-s 2] [--camera-json FILE] ...

``demo`` simulates the built-in default survey (one effect hidden) into the survey stage's folder
of ``OUT`` and runs every stage on it. Both print progress per stage, a summary and the report's
path; a second run skips the finished stages. The options are RunOptions' common fields and every
stage's own options (:func:`pipeline.run.stage_options`), all generated from the dataclasses.
``run``'s SURVEY may be a video file or a folder of clips (:mod:`pipeline.video`: its frames are extracted into
the workspace first, ``--video-*`` options); ``frames`` extracts a survey folder from video alone.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .cliargs import add_config, add_options, config_from_args, list_option, options
from .run import NOT_OPTIONS

#: The effect the demo survey hides from the visible model (the diagnosis should find it).
DEMO_HIDDEN = "vignetting_offcentre"
#: RunOptions fields the commands set from their own arguments (and those that are no options at all).
_POSITIONAL = ("survey_dir", "workspace", "force", *NOT_OPTIONS)


def _options(args: argparse.Namespace, survey_dir: str, workspace: str):
    """RunOptions from the TOML file (when given), overridden by the options given on the command line."""
    from .run import RunOptions, load_options_file, run_options, stage_options

    values: dict = load_options_file(args.config) if args.config else {}
    keys = [o.key() for o in options(RunOptions, _POSITIONAL)] + [o.key(g) for g, o in stage_options()]
    values.update({k: getattr(args, k) for k in keys if hasattr(args, k)})
    if args.force:
        values["force"] = tuple(args.force)
    values.update(survey_dir=survey_dir, workspace=workspace)
    return run_options(values)


def cmd_run(args: argparse.Namespace) -> int:
    from .run import print_summary, run_all

    print_summary(run_all(_options(args, args.survey, args.workspace)))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from eval.synth import make_config, simulate_survey

    from .run import print_summary, run_all
    from .stages import STAGES

    out = Path(args.out)
    survey = out / STAGES["survey"].folder
    if (survey / "truth" / "config.json").is_file() and "survey" not in args.force and "all" not in args.force:
        print(f"demo survey already simulated in {survey}")
    else:
        print(f"watergan demo: simulating the built-in survey with one hidden effect ({DEMO_HIDDEN}) into {survey}")
        simulate_survey(survey, make_config(args.preset, hidden=[DEMO_HIDDEN], seed=getattr(args, "seed", 0)),
                        force=True)
    print_summary(run_all(_options(args, str(survey), str(out))))
    return 0


def cmd_frames(args: argparse.Namespace) -> int:
    from .video import VideoConfig, clips_of, frames_from_video

    videos = clips_of([Path(v) for v in args.videos])
    frames = frames_from_video(videos, Path(args.out), config_from_args(VideoConfig, args))
    done = "extracted earlier, kept" if frames.reused else "kept"
    print(f"frames: {len(frames.frames)} frames of {frames.width}x{frames.height} {done} from {frames.video_s:.1f} s "
          f"of video ({len(videos)} clip{'s' if len(videos) > 1 else ''}) in {frames.survey_dir}")
    return 0


def _common(p: argparse.ArgumentParser, exclude: tuple[str, ...] = ()) -> None:
    """The options ``run`` and ``demo`` share: the common ones shown, the video's and each stage's behind
    ``--help-video``, ``--help-STAGE`` and ``--help-all`` (all accepted, shown or not)."""
    from .cli_help import add_sections, hide
    from .run import RunOptions, run_default_keys, stage_options
    from .stages import STAGES

    p.add_argument("--config", metavar="FILE.toml", help="options file (keys: the options, stages' ones included, "
                   "with _ for -, e.g. gan_budget_min = 5); the command line wins")
    p.add_argument("--force", **list_option("rerun finished stages (and those after them that read them); "
                                            "'all' for every stage", "STAGE"), default=[])
    common = options(RunOptions, (*_POSITIONAL, *exclude))
    add_options(p, [o for o in common if o.path[0] != "video"])
    sections: dict[str, tuple[str, str, list]] = {}
    video = [o for o in common if o.path[0] == "video"]
    if video:
        sections["video"] = ("video options", "how frames are taken from a video given as the survey",
                             hide(add_options(p, video)))
    groups: dict[str, list] = {}
    for group, o in stage_options():
        groups.setdefault(group, []).append(o)
    for group, opts in groups.items():
        sections[group] = (f"{group} options", STAGES[group].help,
                           hide(add_options(p, opts, prefix=group, defaults=run_default_keys())))
    add_sections(p, sections, "each stage's options",
                 "Every option of every stage is an option of this command too, named --STAGE-FIELD (e.g. "
                 "--gan-budget-min 4, or gan_budget_min = 4 in the --config file). One stage's: --help-STAGE "
                 "below; all of them: --help-all.")


def print_survey(ws, r) -> None:
    print(f"survey: {r.n_images} frames of {r.width}x{r.height}{', stereo' if r.stereo else ''}"
          f"{', simulated' if r.simulated else ''}; in-air RGB-D set "
          f"{r.rgbd_dir or 'none (the gan stage renders a generic seafloor set)'}")
    if r.undistorted:
        lens = ", ".join(f"{k} {v:+.4f}" for k, v in r.undistorted.items() if k != "lens_model" and v)
        source = ", estimated by SfM" if r.lens_estimate else ""
        print(f"survey: frames undistorted ({r.undistorted.get('lens_model', 'opencv')} lens{source}: {lens}); every "
              f"later stage works in the pinhole geometry")


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add ``run``, ``demo`` and the survey stage's ``survey`` to the subparsers ``sub``."""
    from .cli_stage import add_stage_command

    add_stage_command(sub, parents, "survey", print_survey)
    from .stages import STAGES

    p = sub.add_parser("run", parents=parents, help="every stage on a survey folder (resumable)",
                       description=f"Every stage on a survey folder, in order ({', '.join(STAGES)}), into the "
                                   f"workspace WS; a second run skips the stages already finished with the same "
                                   f"options and inputs.",
                       usage="watergan run SURVEY --workspace WS [--config FILE.toml] [--force STAGE] [OPTIONS] "
                             "[--STAGE-FIELD VALUE ...]")
    p.add_argument("survey", metavar="SURVEY", help="survey folder: images/, optional right/, camera.json, optional "
                   "rgbd/; or a video file, or a folder of video clips (frames extracted into WS/video_frames)")
    p.add_argument("--workspace", required=True, metavar="WS", help="the run folder (created; the stages write "
                                                                   "only there)")
    _common(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("demo", parents=parents, help="simulate the built-in survey and run every stage on it",
                       description="Simulate the built-in survey (one effect hidden from the visible model, for the "
                                   "diagnosis to find) and run every stage on it, as watergan run does.",
                       usage="watergan demo [--out DIR] [--preset NAME] [OPTIONS] [--STAGE-FIELD VALUE ...]")
    p.add_argument("--out", default="demo_out", metavar="DIR", help="workspace folder (default: demo_out)")
    from eval.synth.presets import PRESETS

    p.add_argument("--preset", choices=list(PRESETS), default="demo",
                   help="the simulated survey (as `watergan simulate --preset`): demo, 44 stereo frames of 640x480 "
                        "(the default); reef and auv, 60 field-like frames; tiny and small, for tests")
    _common(p, exclude=("video",))
    p.set_defaults(func=cmd_demo)

    from .video import VideoConfig

    p = sub.add_parser("frames", parents=parents, help="a survey folder of frames from video clips, chosen by "
                                                       "overlap and sharpness")
    p.add_argument("videos", nargs="+", metavar="VIDEO", help="video files, or folders of clips (taken in name order)")
    p.add_argument("--out", required=True, help="the survey folder to write (images/, survey.json, camera.json)")
    add_config(p, VideoConfig)
    p.set_defaults(func=cmd_frames)
