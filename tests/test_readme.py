"""The README's and docs/'s code examples run as written, and the README's Status agrees with its results table.

Which blocks run: every block fenced ```python in README.md and docs/*.md. A block whose first line names a file
(``# name.py`` or ``# name.py: what it is``) is a plugin: it is written to that file and loaded through the CLI
(``watergan --plugin name.py effects``), which must list the effect it registers; any other block runs as a script
in a fresh interpreter. A Python block that is not meant to run is fenced ```python skip (highlighted the same by
markdown viewers); shell commands are fenced ```sh and outputs ```text, neither of which runs.

Links: every markdown link of the README, docs/, benchmarks/RESULTS.md and its topic files must name a file of the
repository (and a heading of it for ``#anchor``) or a web address.

The Status section states what the Results table shows: the claims it makes (each correction's board error as a
multiple of the oracle's, whether its consistency is lower than raw's and every baseline's in each channel) are
computed from the table's numbers (``benchmarks/readme_table.py``, which writes them) and must appear in it word for
word, and every other number in it must be a number of the table. The table and the claims are what
``benchmarks/readme_table.py`` writes from the results JSON it reads (``--check``, without running a benchmark).
"""

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PLUGIN_FILE = re.compile(r"#\s*(\w+\.py)\b")
_spec = importlib.util.spec_from_file_location("readme_table", ROOT / "benchmarks" / "readme_table.py")
readme_table = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(readme_table)


def python_blocks(path: Path = README) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def run_python(code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_stack_example_runs_and_round_trips(capsys):
    stack_example = next(b for b in python_blocks() if "Stack.from_config" in b)
    exec(compile(stack_example, "README-stack", "exec"), {})
    printed = capsys.readouterr().out
    assert '"name": "attenuation"' in printed and '"k": [1.4]' in printed


def test_plugin_example_registers_through_the_cli(tmp_path):
    plugin = next(b for b in python_blocks() if "@register" in b)
    path = tmp_path / "green_tint.py"
    path.write_text(plugin)
    out = subprocess.run([sys.executable, "-m", "pipeline.cli", "--plugin", str(path), "effects"],
                         capture_output=True, text=True, check=True).stdout
    assert "green_tint: a uniform green cast" in out
    assert "21 registered effects" in out


DOC_BLOCKS = [pytest.param(block, id=f"{doc.name}-{i}") for doc in DOCS for i, block in enumerate(python_blocks(doc))]


def test_the_docs_hold_both_plugin_examples():
    names = {m.group(1) for doc in DOCS for b in python_blocks(doc) if (m := PLUGIN_FILE.match(b))}
    assert {"my_effect.py", "frame_exposure.py"} <= names


@pytest.mark.parametrize("block", DOC_BLOCKS)
def test_docs_example_runs(block, tmp_path):
    plugin = PLUGIN_FILE.match(block)
    if plugin is None:
        done = run_python(block, tmp_path)
        assert done.returncode == 0, done.stderr
        return
    path = tmp_path / plugin.group(1)
    path.write_text(block)
    name = re.search(r'^\s+name = "(\w+)"', block, flags=re.M).group(1)
    done = subprocess.run([sys.executable, "-m", "pipeline.cli", "--plugin", str(path), "effects"], cwd=ROOT,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert re.search(rf"^{name}: ", done.stdout, flags=re.M), done.stdout


# The Status and the Results table.

def section(text: str, title: str) -> str:
    """The body of the README's ``## title`` section."""
    match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", text, flags=re.S | re.M)
    assert match, f"README has no '## {title}' section"
    return match.group(1)


def headline_table(text: str) -> tuple[dict[str, dict[str, float]], set[str]]:
    """The Results section's table as {row: {column: value}}, and every number written in it."""
    lines = [line for line in section(text, "Results").splitlines() if line.startswith("|")]
    cells = [[c.strip() for c in line.strip("|").split("|")] for line in lines]
    header, rows = cells[0], cells[2:]
    table = {row[0]: {col: float(value) for col, value in zip(header[1:], row[1:], strict=True)} for row in rows}
    return table, {value for row in rows for value in row[1:]}


def test_status_agrees_with_the_results_table():
    text = README.read_text()
    table, numbers = headline_table(text)
    status = " ".join(section(text, "Status").split())
    claims, ratios = readme_table.status_claims(table)
    for claim in claims:
        assert claim in status, f"the Status should say {claim!r} (computed from the Results table)"
    for number in re.findall(r"(?<![\w.-])\d+(?:\.\d+)?x?(?![\w.])", re.sub(r"\]\([^)]*\)", "]", status)):
        if number.endswith("x"):
            assert number in ratios, f"the Status quotes {number}, not a ratio of the Results table"
        else:
            assert number in numbers, f"the Status quotes {number}, which is not in the Results table"


def test_status_claims_follow_the_numbers():
    """The claims are computed, not copied: a table where monocular mode loses to raw in every channel gives
    other phrases than the README's."""
    table, _ = headline_table(README.read_text())
    for c in "RGB":
        table[f"consistency {c}"]["ours, monocular"] = 100.0
    claims, _ = readme_table.status_claims(table)
    assert "consistency lower than raw's in no channel" in claims


def test_the_table_and_claims_are_what_the_results_json_gives():
    """The Results table, the commit it names and the Status's claims are those ``benchmarks/readme_table.py`` writes
    from ``benchmarks/results/product_fast.json`` (its ``--check``; no benchmark runs)."""
    diff = readme_table.differences(README, readme_table.RESULT)
    assert not diff, "README.md differs from what benchmarks/readme_table.py writes:\n" + "\n".join(diff)


def test_the_table_check_sees_a_changed_figure(tmp_path):
    """A README whose table or claims differ from the JSON's figures fails the check, and writing it repairs both."""
    readme = tmp_path / "README.md"
    text = README.read_text()
    table, _ = headline_table(text)
    oracle = f"{table['board, CIEDE2000']['oracle']:g}"
    readme.write_text(text.replace(f"| {oracle} |", "| 9.99 |", 1))
    assert readme_table.differences(readme, readme_table.RESULT)
    fixed = readme_table.render(readme.read_text(), json.loads(readme_table.RESULT.read_text()))
    assert fixed == text


def test_links_stay_inside_the_repository():
    """Every markdown link of the README, docs/, RESULTS.md and its topic files names a file of the repository (and a
    heading of it, for ``#anchor``), or a public web address (papers); none points at a local path outside the
    checkout."""
    for doc in [README, ROOT / "benchmarks" / "RESULTS.md", *sorted((ROOT / "benchmarks" / "RESULTS").glob("*.md")),
                *DOCS]:
        for target in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
            if target.startswith(("https://", "http://")):
                continue
            path, _, anchor = target.partition("#")
            resolved = (doc.parent / path).resolve() if path else doc
            assert resolved.is_relative_to(ROOT) and resolved.exists(), \
                f"{doc.name}: link {target} is not a file of the repository"
            if anchor:
                headings = {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
                            for h in re.findall(r"^#+ (.*)$", resolved.read_text(), flags=re.M)}
                assert anchor in headings, f"{doc.name}: link {target} names no heading of {resolved.name}"
