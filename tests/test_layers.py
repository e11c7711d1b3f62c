"""The import layers: watergan (physics, nets, data I/O) <- eval (measuring) <- pipeline (stages, CLI).
Nothing imports upward, at module level or inside a function."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Each package and the packages of ours it must not import.
FORBIDDEN = {"watergan": ("eval", "pipeline"), "eval": ("pipeline",)}


def imported_packages(source: str, own: str) -> set[tuple[str, int]]:
    """(top-level package, line) of every import in a module of package ``own``, relative imports
    resolved to ``own``."""
    tree = ast.parse(source)
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {(alias.name.split(".")[0], node.lineno) for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            found.add((own if node.level else (node.module or "").split(".")[0], node.lineno))
    return found


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_no_module_imports_a_higher_layer(package):
    bad = [f"{path.relative_to(ROOT)}:{line} imports {name}"
           for path in sorted((ROOT / package).rglob("*.py"))
           for name, line in sorted(imported_packages(path.read_text(), package)) if name in FORBIDDEN[package]]
    assert bad == [], "\n".join(bad)


def test_the_check_sees_upward_imports_anywhere_in_a_module():
    source = ("import numpy\nfrom . import x\n\ndef f():\n"
              "    from pipeline.workspace import Workspace\n    import eval.tables\n")
    assert imported_packages(source, "watergan") == {("numpy", 1), ("watergan", 2), ("pipeline", 5), ("eval", 6)}
