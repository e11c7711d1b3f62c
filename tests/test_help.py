"""The console script's help, as a newcomer reads it: commands grouped, `run --help` short, every stage's options
behind --help-STAGE and --help-all (and still accepted), no reStructuredText markup or internal names anywhere."""

import argparse
import re

import pytest

from pipeline.cli import build_parser
from pipeline.cli_help import COMMAND_GROUPS, clean_help, command_groups

ROLE = re.compile(r":(?:func|mod|class|data|meth|attr):`")
CONSTANT = re.compile(r"\b[A-Z][A-Z0-9]*_[A-Z0-9_]+\b")


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def _shown(parser: argparse.ArgumentParser, argv: list[str], capsys) -> str:
    """What ``watergan ARGV`` prints before it exits (a help)."""
    with pytest.raises(SystemExit) as stop:
        parser.parse_args(argv)
    assert stop.value.code == 0, argv
    return capsys.readouterr().out


def _every_help(capsys) -> dict[str, str]:
    """Every help the script prints: the top level, each command's, and run's and demo's per-stage sections."""
    parser = build_parser()
    helps = {"watergan --help": parser.format_help()}
    for name, command in _commands(parser).items():
        helps[f"{name} --help"] = command.format_help()
    for name in ("run", "demo"):
        flags = [s for a in _commands(parser)[name]._actions for s in a.option_strings if s.startswith("--help-")]
        for flag in flags:
            helps[f"{name} {flag}"] = _shown(parser, [name, flag], capsys)
    return helps


def _offences(helps: dict[str, str]) -> list[str]:
    """Each offending string with its line and the helps that show it."""
    found: dict[tuple[str, str], list[str]] = {}
    for where, text in helps.items():
        for line in text.splitlines():
            for bad in (*ROLE.findall(line), *(["``"] if "``" in line else []), *CONSTANT.findall(line)):
                found.setdefault((bad, line.strip()), []).append(where)
    return [f"{bad!r} in {line!r} ({', '.join(where)})" for (bad, line), where in found.items()]


def _flags(command: argparse.ArgumentParser) -> set[str]:
    """The option names a command's help shows."""
    return {flag for action in command._actions if action.help != argparse.SUPPRESS for flag in action.option_strings}


def test_no_help_holds_markup_or_internal_names(capsys):
    offences = _offences(_every_help(capsys))
    assert not offences, f"{len(offences)} offending strings:\n" + "\n".join(offences)


def test_the_option_docstrings_are_plain_text_at_their_source(capsys, monkeypatch):
    """The same walk with the markup net removed: the fields' docstrings themselves hold no role or literal."""
    monkeypatch.setattr("pipeline.cli_help.clean_help", lambda text: text)
    offences = _offences(_every_help(capsys))
    assert not offences, f"{len(offences)} offending strings:\n" + "\n".join(offences)


def test_markup_left_in_a_docstring_renders_as_its_name():
    assert clean_help("see :func:`decorrelate_frames` and :mod:`eval.eta_profile`") == \
        "see decorrelate_frames and eta_profile"
    assert clean_help("(:func:`~watergan.gan_statistics.texture_contrast`), ``lr`` or ``<survey>/rgbd``") == \
        "(texture_contrast), lr or <survey>/rgbd"
    assert clean_help("no markup: a*b, `diagnose`") == "no markup: a*b, `diagnose`"


def test_the_top_level_help_lists_every_command_in_its_group():
    parser = build_parser()
    text = parser.format_help()
    commands = _commands(parser)
    groups = command_groups(next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)))
    assert [title for title, _ in groups] == [title for title, _ in COMMAND_GROUPS], "no command left out"
    grouped = [name for _, names in groups for name in names]
    assert sorted(grouped) == sorted(commands), "every command in exactly one group"
    assert groups[1][1][:3] == ("survey", "sfm", "dense") and "texture" in groups[1][1] and "train-gan" in groups[3][1]
    for title, names in groups:
        assert f"\n{title}:\n" in text
        block = text.split(f"\n{title}:\n", 1)[1].split("\n\n", 1)[0]
        for name in names:
            assert re.search(rf"^  {re.escape(name)} ", block, re.M), (title, name)
    assert text.index("run ") < text.index("sfm ") < text.index("train-gan ")
    assert "{effects,simulate" not in text, "no flat list of choices"


def test_run_help_is_short_and_every_stage_option_is_behind_help_all_and_still_accepted(capsys):
    from pipeline.run import stage_options

    parser = build_parser()
    stage_flags = {option.flag(stage) for stage, option in stage_options()}
    for name in ("run", "demo"):
        short = _commands(parser)[name].format_help()
        assert len(short.splitlines()) <= 120, (name, len(short.splitlines()))
        assert "--threads" in _flags(_commands(parser)[name]) and not stage_flags & _flags(_commands(parser)[name])
    short = _commands(parser)["run"].format_help()
    full = _shown(parser, ["run", "--help-all"], capsys)
    water = _shown(parser, ["run", "--help-water"], capsys)
    for stage, option in stage_options():
        assert f"--help-{stage}" in short
        assert option.flag(stage) in full
        assert (option.flag(stage) in water) == (stage == "water"), option.flag(stage)
    assert "--video-overlap" in full and "--video-overlap" not in short
    args = parser.parse_args(["run", "S", "--workspace", "W", "--gan-budget-min", "2", "--water-fit-iterations", "3",
                              "--video-overlap", "0.5", "--threads", "1"])
    assert (args.gan_budget_min, args.water_fit_iterations, args.video_overlap, args.threads) == (2.0, 3, 0.5, 1)


def test_the_survey_folder_is_survey_everywhere():
    parser = build_parser()
    commands = _commands(parser)
    for name in ("survey", "sfm", "dense", "water", "evaluate", "report"):
        assert "--survey" in _flags(commands[name]) and "--survey-dir" not in _flags(commands[name]), name
        assert "--survey-dir" not in commands[name].format_help(), name
    assert parser.parse_args(["survey", "--workspace", "W", "--survey", "S"]).survey_dir == "S"
    assert parser.parse_args(["survey", "--workspace", "W", "--survey-dir", "S"]).survey_dir == "S", "the old name"
    with pytest.raises(SystemExit):
        parser.parse_args(["survey", "--workspace", "W"])


def test_correct_mode_names_no_option_the_command_lacks():
    commands = _commands(build_parser())
    for name in ("correct", "correct-folder"):
        helps = " ".join(a.help for a in commands[name]._actions if a.help != argparse.SUPPRESS)
        assert "--range-dir" not in helps or "--range-dir" in _flags(commands[name]), name
