"""The registry of effects: built-ins, entry points and user plugin files.

- ``@register`` adds an :class:`Effect` subclass under its ``name``.
- Third-party packages declare effects in the entry-point group ``watergan.effects``; each entry
  point names a module or an Effect class, importing which registers the effects.
- ``load_plugin("my_effect.py")`` imports a user's file, whose ``@register`` decorators do the rest.
"""

from __future__ import annotations

import difflib
import importlib.util
import sys
from importlib.metadata import entry_points
from pathlib import Path

from ..errors import UserInputError
from .effect import Effect

ENTRY_POINT_GROUP = "watergan.effects"

_REGISTRY: dict[str, type[Effect]] = {}
_entry_points_loaded = False


class UnknownEffectError(KeyError):
    """An effect name that nothing registered."""

    def __str__(self) -> str:  # KeyError quotes its message; show it plainly
        return self.args[0]


class PluginError(UserInputError):
    """A plugin file or entry point that could not be loaded."""


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator: register an effect under ``cls.name``."""
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise TypeError(f"@register expects an Effect subclass, got {cls!r}")
    if not cls.name or not cls.name.isidentifier():
        raise ValueError(f"effect class {cls.__name__} needs a snake_case `name`, got {cls.name!r}")
    if cls.axis not in Effect.AXES:
        raise ValueError(f"effect {cls.name}: axis {cls.axis!r} is not one of {Effect.AXES}")
    existing = _REGISTRY.get(cls.name)
    if existing is not None and existing.__qualname__ != cls.__qualname__:
        raise ValueError(f"effect name '{cls.name}' is already registered by {existing.__module__}")
    _REGISTRY[cls.name] = cls
    return cls


def _load_builtins() -> None:
    from . import effects  # noqa: F401  (importing registers the built-ins)


def _load_entry_points() -> None:
    global _entry_points_loaded
    if _entry_points_loaded:
        return
    _entry_points_loaded = True
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
        except Exception as exc:  # a broken third-party package must not hide the cause
            raise PluginError(f"entry point '{ep.name}' ({ep.value}) in group {ENTRY_POINT_GROUP} "
                              f"failed to load: {type(exc).__name__}: {exc}") from exc
        if isinstance(obj, type) and issubclass(obj, Effect) and obj.name not in _REGISTRY:
            register(obj)


def available() -> dict[str, type[Effect]]:
    """Every registered effect by name (built-ins, entry points and loaded plugins), sorted."""
    _load_builtins()
    _load_entry_points()
    return dict(sorted(_REGISTRY.items()))


def builtin_effects() -> dict[str, type[Effect]]:
    """The built-in effects (one per module of :mod:`watergan.formation.effects`) by name, sorted."""
    from . import effects

    modules = {module.__name__ for module in effects.MODULES}
    return {name: cls for name, cls in sorted(_REGISTRY.items()) if cls.__module__ in modules}


def get(name: str) -> type[Effect]:
    """The effect class registered as ``name``, or an error listing the close matches."""
    effects = available()
    if name not in effects:
        close = difflib.get_close_matches(name, effects, n=3)
        hint = f" Did you mean: {', '.join(close)}?" if close else ""
        raise UnknownEffectError(
            f"unknown effect '{name}'.{hint} Registered effects: {', '.join(effects)}. "
            f"Add your own with --plugin FILE.py (see `watergan effects`)."
        )
    return effects[name]


def load_plugin(path: str | Path) -> list[str]:
    """Import a user's Python file; return the names of the effects it registered."""
    path = Path(path)
    if not path.is_file():
        raise PluginError(f"plugin file {path} does not exist or is not a file")
    before = set(available())
    module_name = f"watergan_plugin_{path.stem}"
    spec = importlib.util.spec_from_file_location(module_name, path)
    if spec is None or spec.loader is None:
        raise PluginError(f"plugin file {path} is not an importable Python file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as exc:
        sys.modules.pop(module_name, None)
        raise PluginError(f"plugin file {path} failed to import: {type(exc).__name__}: {exc}") from exc
    added = sorted(set(_REGISTRY) - before)
    if not added:
        raise PluginError(f"plugin file {path} registered no effect: decorate an Effect subclass "
                          f"with @watergan.formation.register")
    return added
