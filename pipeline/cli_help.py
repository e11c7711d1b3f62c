"""The help of the `watergan` console script, written for someone who has not read the code.

- :func:`clean_help`: option help from a field's docstring, rendered as plain text (a Sphinx role such as
  ``:func:`name``` becomes ``name``, a ``literal`` its text); the docstrings are written without them, this is
  the net under a leftover one.
- :func:`grouped_commands`: ``watergan --help``'s list of commands by what a user wants (the main job, one
  stage at a time, tools, low-level), from the commands the parser has: a command in no group is listed
  under "other", so every command stays listed.
- :func:`alias`: a second, hidden name of an option (an old name kept working).
- :func:`add_sections`: hidden sections of options (``watergan run``'s per-stage ones), each shown by its own
  ``--help-NAME``, all of them by ``--help-all``; the options are accepted whether shown or not.
"""

from __future__ import annotations

import argparse
import copy
import re
import textwrap
from typing import Any

_ROLE = re.compile(r":(?:[a-z]+:)?[a-z]+:`~?([^`<]*?)(?:\s*<[^>]*>)?`")
_LITERAL = re.compile(r"``(.+?)``")


def clean_help(text: str) -> str:
    """``text`` without reStructuredText markup: ``:func:`pkg.mod.name``` -> ``name`` (the last dotted part),
    ``literal`` -> its text."""
    text = _ROLE.sub(lambda m: m.group(1).rsplit(".", 1)[-1], text)
    return _LITERAL.sub(r"\1", text)


#: ``watergan --help``'s groups of commands, in the order listed: a title and its commands; None: the workspace
#: stages' commands, in run order (those pipeline.cli_stage made). A command named in none is listed under "Other".
COMMAND_GROUPS: tuple[tuple[str, tuple[str, ...] | None], ...] = (
    ("The main job (every stage, resumable)", ("run", "demo")),
    ("One stage at a time, in a workspace (in run order; watergan run runs them all)", None),
    ("Tools", ("frames", "diagnose", "ledger", "effects", "simulate", "consistency", "depth-compare")),
    ("Low-level: one step on plain folders, outside a workspace",
     ("train-gan", "generate", "train-restorer", "correct-folder")),
)


def command_groups(sub: argparse._SubParsersAction) -> list[tuple[str, tuple[str, ...]]]:
    """:data:`COMMAND_GROUPS` with the stage commands filled in, and "Other" for any command left out."""
    from .stages import STAGES

    order = list(STAGES)
    stages = sorted((name for name, p in sub.choices.items() if p.get_default("stage") in STAGES and
                     name not in {n for _, names in COMMAND_GROUPS if names for n in names}),
                    key=lambda name: order.index(sub.choices[name].get_default("stage")))
    groups = [(title, tuple(stages) if names is None else names) for title, names in COMMAND_GROUPS]
    listed = {name for _, names in groups for name in names}
    other = tuple(name for name in sub.choices if name not in listed)
    return groups + ([("Other", other)] if other else [])


def grouped_commands(sub: argparse._SubParsersAction) -> str:
    """The commands of the subparsers ``sub`` with their one-line help, by :func:`command_groups`."""
    helps = {action.dest: action.help or "" for action in sub._choices_actions}
    width = max(map(len, helps)) + 4
    lines = []
    for title, names in command_groups(sub):
        names = tuple(name for name in names if name in helps)
        if not names:
            continue
        lines.append(f"{title}:")
        for name in names:
            text = textwrap.wrap(helps[name], 100 - width) or [""]
            lines.append(f"  {name:{width - 2}}{text[0]}")
            lines += [" " * width + more for more in text[1:]]
        lines.append("")
    return "\n".join(lines).rstrip()


class _ShowSections(argparse.Action):
    """``--help-NAME`` / ``--help-all``: print the named hidden sections (their options' help) and exit."""

    def __init__(self, option_strings: list[str], dest: str, sections: dict[str, tuple[str, str, list]],
                 names: tuple[str, ...] | None = None, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)
        self.sections, self.names = sections, names

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        print(format_sections(parser, self.sections, self.names), end="")
        parser.exit()


def format_sections(parser: argparse.ArgumentParser, sections: dict[str, tuple[str, str, list]],
                    names: tuple[str, ...] | None = None) -> str:
    """The usage and the options of the hidden ``sections`` (name -> (title, description, actions)) named
    ``names`` (None: every one)."""
    formatter = parser._get_formatter()
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
    for name in names or tuple(sections):
        title, description, actions = sections[name]
        formatter.start_section(title)
        formatter.add_text(description)
        formatter.add_arguments([_shown(action) for action in actions])
        formatter.end_section()
    return formatter.format_help()


def _shown(action: argparse.Action) -> argparse.Action:
    shown = copy.copy(action)
    shown.help = action.hidden_help  # type: ignore[attr-defined]
    return shown


def hide(actions: list[argparse.Action]) -> list[argparse.Action]:
    """``actions`` taken out of the default help (still parsed); their help kept for :func:`format_sections`."""
    for action in actions:
        action.hidden_help = action.help  # type: ignore[attr-defined]
        action.help = argparse.SUPPRESS
    return actions


def add_sections(parser: argparse.ArgumentParser, sections: dict[str, tuple[str, str, list]], title: str,
                 description: str) -> None:
    """A ``--help-NAME`` per section (name -> (its title, one line on what it holds, its hidden actions)) under
    ``title``, and ``--help-all`` for every section."""
    group = parser.add_argument_group(title, description)
    group.add_argument("--help-all", action=_ShowSections, sections=sections,
                       help="show the options of every section below (long), then exit")
    for name, (_, line, actions) in sections.items():
        group.add_argument(f"--help-{name}", action=_ShowSections, sections=sections, names=(name,),
                           help=f"{line} ({len(actions)} option{'s' if len(actions) != 1 else ''})")


def alias(parser: argparse.ArgumentParser, action: argparse.Action, flag: str) -> None:
    """Make ``flag`` the shown name of ``action`` (an option of ``parser``), its old names hidden aliases: parsed
    as before, satisfying a required option, never shown (argparse keeps no hidden names of its own)."""
    parser._option_string_actions[flag] = action
    action.option_strings = [flag]
