"""Command-line options generated from configuration dataclasses: one source for names, defaults,
help and choices.

A field ``budget_min: float = 4.0`` with the docstring below it becomes ``--budget-min`` (or
``--PREFIX-budget-min``) with its type, its default in the help and the docstring as the help.
Types: ``bool`` -> ``--name`` / ``--no-name``; ``int``, ``float``, ``str``, ``Path`` (``X | None``
takes ``none`` too); an ``enum.Enum`` (our choices are ``StrEnum``s) -> its values as choices;
``tuple[str, ...]`` -> a list, written one way everywhere: comma-separated and/or repeated
(``--add a,b --add c``); ``tuple[int, int]`` -> ``HxW`` (``480x640``). A field holding a nested
dataclass gives its fields with the field's name as a prefix (``--measure-n-points``), or without one
when the field's metadata says ``{"flatten": True}``; their defaults are those of the field's default
instance. Options not given stay out of the parsed values, so the dataclass's own defaults apply.

Effect names are checked in one place, when an option's value is taken (:func:`given` for the
command line, :func:`convert` for a file): a list option named in :data:`EFFECT_FIELDS` must name
registered effects (``--plugin`` files are loaded before), else :class:`UnknownEffectError`.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import enum
import functools
import inspect
import textwrap
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

_REQUIRED = object()
#: List options whose values are effect names, checked against the registry when given.
EFFECT_FIELDS = ("effects", "add", "candidates", "hidden", "fixed_effects")


def name_list(text: str) -> list[str]:
    """Names from a comma-separated option value: "a, b,,c" -> ["a", "b", "c"]."""
    return [name.strip() for name in text.split(",") if name.strip()]


def list_option(help_text: str, metavar: str = "A,B") -> dict:
    """argparse keywords of a list option (comma-separated and/or repeated): the one list syntax."""
    return {"type": name_list, "action": "extend", "metavar": metavar, "help": help_text}


def size_hw(text: str) -> tuple[int, int]:
    """``HEIGHTxWIDTH`` (e.g. ``480x640``) as (height, width)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be HEIGHTxWIDTH, e.g. 480x640, got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return h, w


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass (the string literal after its annotation)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, after in zip(body, body[1:], strict=False):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr)
                    and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
                docs[node.target.id] = " ".join(after.value.value.split())
    return docs


@dataclass(frozen=True)
class Option:
    """One command-line option: a (possibly nested) field of a configuration dataclass."""

    path: tuple[str, ...]
    """Field names from the configuration down (nested dataclasses)."""
    hint: Any
    """The field's type."""
    default: Any
    help: str
    name: tuple[str, ...] = ()
    """The names its key joins: ``path`` less the flattened nested fields (empty: ``path``)."""

    def key(self, prefix: str = "") -> str:
        """``prefix_name_joined``: the TOML key and argparse destination."""
        name = self.name or self.path
        return "_".join([prefix, *name] if prefix else name)

    def check(self, value: Any) -> Any:
        """``value``, its effect names checked when the option holds effect names (:data:`EFFECT_FIELDS`)."""
        if self.path[-1] in EFFECT_FIELDS and isinstance(value, tuple | list):
            check_effects(value)
        return value

    def flag(self, prefix: str = "") -> str:
        return "--" + self.key(prefix).replace("_", "-")


def check_effects(names: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """``names`` as a tuple, each a registered effect (else :class:`UnknownEffectError` naming the close ones)."""
    from watergan.formation import get

    for name in names:
        get(name)
    return tuple(names)


def _unoptional(hint: Any) -> tuple[Any, bool]:
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return hint, False


def _supported(hint: Any) -> bool:
    hint, _ = _unoptional(hint)
    if hint in (bool, int, float, str, Path) or (isinstance(hint, type) and issubclass(hint, enum.Enum)):
        return True
    return typing.get_origin(hint) is tuple and typing.get_args(hint) in ((str, ...), (int, int))


def options(cls: type, exclude: tuple[str, ...] = (), instance: Any = None) -> list[Option]:
    """The options of a configuration dataclass (``exclude``: dotted field paths left out, e.g.
    fields a caller sets itself; ``instance``: whose values are the defaults, else the fields' own).
    Fields of unsupported types (dicts, arrays) are not options."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    out = []
    for f in dataclasses.fields(cls):
        if f.name in exclude:
            continue
        hint = hints[f.name]
        default = getattr(instance, f.name) if instance is not None else \
            f.default if f.default is not dataclasses.MISSING else \
            f.default_factory() if f.default_factory is not dataclasses.MISSING else _REQUIRED
        if dataclasses.is_dataclass(hint) and dataclasses.is_dataclass(default):
            inner = tuple(e.split(".", 1)[1] for e in exclude if e.startswith(f.name + "."))
            flat = f.metadata.get("flatten", False)
            out += [dataclasses.replace(o, path=(f.name, *o.path), name=(o.name or o.path) if flat else
                                        (f.name, *(o.name or o.path))) for o in options(hint, inner, default)]
        elif _supported(hint):
            out.append(Option((f.name,), hint, default, docs.get(f.name, "")))
    return out


def field_paths(cls: type, names: tuple[str, ...]) -> list[tuple[str, ...]]:
    """The paths of every field of ``cls`` named one of ``names``, nested dataclasses included."""
    hints = typing.get_type_hints(cls)
    out: list[tuple[str, ...]] = []
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            out += [(f.name, *p) for p in field_paths(hints[f.name], names)]
        elif f.name in names:
            out.append((f.name,))
    return out


def _format_default(value: Any) -> str:
    if isinstance(value, enum.Enum):
        return str(value.value)
    if isinstance(value, tuple):
        return "x".join(map(str, value)) if value and all(isinstance(v, int) for v in value) else ",".join(value)
    return "none" if value is None else str(value)


def _or_none(convert):
    def parse(text: str):
        return None if text.lower() == "none" else convert(text)
    parse.__name__ = getattr(convert, "__name__", "value")
    return parse


def add_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup, opts: list[Option], prefix: str = "",
                defaults: dict[str, Any] | None = None) -> list[argparse.Action]:
    """Add ``opts`` to ``parser`` (flags ``--PREFIX-FIELD``; their help the fields' docstrings as plain text,
    :func:`pipeline.cli_help.clean_help`); returns the actions added. ``defaults`` (by key) replaces the
    dataclass's default in the help where a caller (``watergan run``) applies its own; an empty default
    (the docstring says what empty means) is not shown."""
    from .cli_help import clean_help

    defaults = defaults or {}
    actions = []
    for o in opts:
        key = o.key(prefix)
        default = defaults.get(key, o.default)
        hint, optional = _unoptional(o.hint)
        text = clean_help(o.help) or key.replace("_", " ")
        kwargs: dict[str, Any] = {"dest": key, "default": argparse.SUPPRESS}
        if default is _REQUIRED:
            kwargs["required"] = True
        elif hint is not bool and default not in ("", ()):
            text += f" (default: {_format_default(default)})"
        if hint is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
            text += f" (default: {'auto' if default is None else 'on' if default else 'off'})"
        elif typing.get_origin(hint) is tuple and typing.get_args(hint) == (str, ...):
            kwargs.update(list_option(text))
        elif typing.get_origin(hint) is tuple:
            kwargs.update(type=_or_none(size_hw) if optional else size_hw, metavar="HxW")
        elif isinstance(hint, type) and issubclass(hint, enum.Enum):
            kwargs.update(type=hint, choices=list(hint), metavar="{" + ",".join(e.value for e in hint) + "}")
        else:
            kwargs["type"] = _or_none(hint) if optional else hint
            kwargs["metavar"] = {int: "N", float: "X", Path: "PATH"}.get(hint, key.rsplit("_", 1)[-1].upper())
        kwargs.setdefault("help", text.replace("%", "%%"))
        actions.append(parser.add_argument(o.flag(prefix), **kwargs))
    return actions


def convert(o: Option, value: Any, where: str) -> Any:
    """A value for option ``o`` from a file (TOML) as the command line would parse it: enums from their
    values, ``HxW`` or [h, w] sizes, lists from lists or comma-separated text, int/float/bool checked;
    anything else is an error naming ``where`` and the option."""
    from watergan.errors import UserInputError

    hint, optional = _unoptional(o.hint)

    def bad(expected: str) -> UserInputError:
        return UserInputError(f"{where}: {o.key()} must be {expected}, got {value!r}")

    if value is None or (optional and isinstance(value, str) and value.lower() == "none"):
        if optional:
            return None
        raise bad("given")
    if hint is bool:
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if typing.get_origin(hint) is tuple and typing.get_args(hint) == (str, ...):
        items = name_list(value) if isinstance(value, str) else value
        if not isinstance(items, list | tuple) or not all(isinstance(v, str) for v in items):
            raise bad("a list of names")
        return o.check(tuple(items))
    if typing.get_origin(hint) is tuple:
        try:
            pair = size_hw(value) if isinstance(value, str) else tuple(int(v) for v in value)
        except (argparse.ArgumentTypeError, TypeError, ValueError):
            raise bad("HEIGHTxWIDTH (e.g. 480x640) or [height, width]") from None
        if len(pair) != 2:
            raise bad("HEIGHTxWIDTH")
        return pair
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        try:
            return hint(value)
        except ValueError:
            raise bad("one of " + ", ".join(e.value for e in hint)) from None
    if hint is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if hint is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if hint in (str, Path) and isinstance(value, str):
        return hint(value)
    raise bad({int: "an integer", float: "a number", str: "text", Path: "a path"}.get(hint, str(hint)))


def given(args: argparse.Namespace, opts: list[Option], prefix: str = "") -> dict[tuple[str, ...], Any]:
    """The options given on the command line, by field path (lists as tuples; effect names checked)."""
    out = {}
    for o in opts:
        if hasattr(args, o.key(prefix)):
            value = getattr(args, o.key(prefix))
            out[o.path] = o.check(tuple(value) if isinstance(value, list) else value)
    return out


def with_values(config: Any, values: dict[tuple[str, ...], Any]) -> Any:
    """``config`` with nested fields replaced: {("measure", "n_points"): 800, ("plots",): False}."""
    direct = {path[0]: v for path, v in values.items() if len(path) == 1}
    nested: dict[str, dict] = {}
    for path, v in values.items():
        if len(path) > 1:
            nested.setdefault(path[0], {})[path[1:]] = v
    for name, inner in nested.items():
        direct[name] = with_values(getattr(config, name), inner)
    return dataclasses.replace(config, **direct)


def build(cls: type, values: dict[tuple[str, ...], Any], **fixed: Any) -> Any:
    """An instance of ``cls`` from the given values and ``fixed`` fields (the rest: its defaults)."""
    top = {path[0]: v for path, v in values.items() if len(path) == 1}
    base = cls(**{**top, **fixed})
    return with_values(base, {p: v for p, v in values.items() if len(p) > 1})


def config_from_args(cls: type, args: argparse.Namespace, exclude: tuple[str, ...] = (), **fixed: Any) -> Any:
    """``cls`` from the options :func:`add_config` added (plus ``fixed`` fields)."""
    return build(cls, given(args, options(cls, exclude)), **fixed)


def add_config(parser: argparse.ArgumentParser, cls: type, exclude: tuple[str, ...] = ()) -> list[argparse.Action]:
    """Every option of the configuration dataclass ``cls`` (but ``exclude``) on ``parser``; returns their actions."""
    return add_options(parser, options(cls, exclude))
