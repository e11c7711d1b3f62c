"""The built-in effects, one per file. Importing this package imports every module in its folder,
whose ``@register`` decorators register the built-ins: a new built-in is one new file here."""

import importlib
import pkgutil

#: The modules of the built-in effects (every module in this folder), imported.
MODULES = tuple(importlib.import_module(f"{__name__}.{info.name}") for info in pkgutil.iter_modules(__path__))
