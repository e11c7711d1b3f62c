"""The on-disk run folder: one sub-folder per stage, each with its config and result, skip-if-done.

```
WORKSPACE/
  00_survey/  01_gan/  02_restorer/  03_correct/  04_sfm/  05_dense/  06_eval/  07_mesh/  08_diagnose/  report/
  <stage>/config.json    the stage's configuration (a frozen dataclass, as JSON) and its hash
  <stage>/result.json    the stage's result: workspace-relative paths and summary numbers
```

A stage whose ``result.json`` records the hash of the same configuration is finished and is
skipped unless forced. Every file is written atomically (a temporary file renamed into place), so
an interrupted run never leaves a half-written output that looks finished.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from watergan.errors import UserInputError

STAGE_DIRS: dict[str, str] = {
    "survey": "00_survey",
    "gan": "01_gan",
    "restorer": "02_restorer",
    "correct": "03_correct",
    "sfm": "04_sfm",
    "dense": "05_dense",
    "eval": "06_eval",
    "mesh": "07_mesh",
    "diagnose": "08_diagnose",
    "report": "report",
}


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def _jsonable(value: Any, for_hash: bool = False) -> Any:
    """Dataclasses as dicts, paths as strings; ``for_hash`` leaves out dataclass fields marked
    ``metadata={"hash": False}`` (where work runs, progress bars: not what a stage computes)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _jsonable(getattr(value, f.name), for_hash) for f in dataclasses.fields(value)
                if not (for_hash and f.metadata.get("hash") is False)}
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {str(k): _jsonable(v, for_hash) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v, for_hash) for v in value]
    return value


def atomic_write_json(path: Path, value: Any) -> None:
    """JSON (dataclasses and paths converted) with sorted keys: the same value gives the same bytes."""
    atomic_write_text(path, json.dumps(_jsonable(value), indent=2, sort_keys=True) + "\n")


def config_hash(config: Any) -> str:
    """SHA-256 (first 16 hex digits) of the configuration's canonical JSON (fields marked
    ``metadata={"hash": False}`` left out)."""
    text = json.dumps(_jsonable(config, for_hash=True), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


class Workspace:
    """A run folder. ``Workspace(path)`` creates it when missing."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise UserInputError(f"workspace {self.root} exists and is not a folder: choose another path")
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserInputError(f"cannot create workspace {self.root}: {exc.strerror}; "
                                 f"choose a folder you can write to") from exc

    def stage_dir(self, stage: str) -> Path:
        if stage not in STAGE_DIRS:
            raise KeyError(f"unknown stage '{stage}'; stages: {', '.join(STAGE_DIRS)}")
        path = self.root / STAGE_DIRS[stage]
        path.mkdir(parents=True, exist_ok=True)
        return path

    def path(self, relative: str | Path) -> Path:
        """An absolute path from a workspace-relative one (as results store them)."""
        return self.root / relative

    def relative(self, path: str | Path) -> str:
        """The workspace-relative form of a path inside the workspace."""
        return str(Path(path).resolve().relative_to(self.root.resolve()))

    def load_result(self, stage: str) -> dict | None:
        path = self.root / STAGE_DIRS[stage] / "result.json"
        if not path.is_file():
            return None
        return json.loads(path.read_text())

    def is_done(self, stage: str, config: Any) -> bool:
        """True when the stage finished with this very configuration."""
        result = self.load_result(stage)
        return result is not None and result.get("config_hash") == config_hash(config)

    def save(self, stage: str, config: Any, result: Any) -> dict:
        """Record a finished stage: config.json, then result.json (written last: it marks completion)."""
        folder = self.stage_dir(stage)
        digest = config_hash(config)
        atomic_write_json(folder / "config.json", {"config": config, "config_hash": digest})
        record = {"stage": stage, "config_hash": digest, "result": _jsonable(result)}
        atomic_write_json(folder / "result.json", record)
        return record

    def run(self, stage: str, config: Any, fn: Callable[[Workspace, Any], Any], force: bool = False) -> dict:
        """Run ``fn(ws, config)`` unless the stage is already done with this configuration."""
        if not force and self.is_done(stage, config):
            return self.load_result(stage)
        result_path = self.root / STAGE_DIRS[stage] / "result.json"
        result_path.unlink(missing_ok=True)  # a rerun is unfinished until it saves again
        return self.save(stage, config, fn(self, config))
