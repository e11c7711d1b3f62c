"""The README's code examples run as written."""

import re
import subprocess
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


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
    assert "15 registered effects" in out
