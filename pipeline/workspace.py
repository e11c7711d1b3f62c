"""The on-disk run folder: one sub-folder per stage, each with its config and result, skip-if-done.

```
WORKSPACE/
  <stage folder>/        one per stage of the stage table (pipeline/stages.py), numbered in run order:
                         00_survey/ 01_sfm/ 02_dense/ 03_range/ ... 11_report/
  <stage>/config.json    the stage's configuration (a frozen dataclass, as JSON), its upstream and hash
  <stage>/result.json    the stage's result: workspace-relative paths and summary numbers
```

Every file a stage writes is in its folder and named in its result. A workspace holding a stage
folder with a ``result.json`` that the table does not name (``04_sfm/``, ``06_water/``: an older
version numbered its folders otherwise) is refused with an error saying to run into a new workspace,
never read under the new names.

A stage's hash covers its configuration and the hashes of the result records of the stages it
reads (``reads`` in the stage table), so a standalone stage command (``watergan sfm``) and
``watergan run`` recognise each other's results, and a rerun upstream reruns the stages after it.
A stage whose ``result.json`` records the same hash, and whose files are all there as it wrote
them (the record lists each file of the stage's folder with its size), is finished and is skipped
unless forced; a stage whose files were deleted or cut short reruns, saying which. Paths inside the
workspace enter a configuration's hash relative to it, so a moved or renamed workspace is still
finished (results store workspace-relative paths).
Every file is written atomically (a temporary file renamed into place), so an interrupted run
never leaves a half-written output that looks finished.

One process at a time writes a workspace: the first stage a process runs takes the lock
``WORKSPACE/.lock`` (held until the process ends); another process is refused with an error naming
the first's process id and command.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from watergan.errors import UserInputError
from watergan.io import atomic_write_json, from_jsonable, to_jsonable

if TYPE_CHECKING:
    from .stages import Stage

def config_hash(config: Any, root: Path | None = None) -> str:
    """SHA-256 (first 16 hex digits) of the configuration's canonical JSON (fields marked
    ``metadata={"hash": False}`` left out); with a workspace ``root``, paths inside it count relative to it."""
    text = json.dumps(to_jsonable(config, for_hash=True), sort_keys=True, separators=(",", ":"))
    if root is not None:
        for prefix in dict.fromkeys((str(root.resolve()), str(root.absolute()))):
            text = text.replace(json.dumps(prefix)[1:-1] + "/", "<workspace>/")
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


#: The workspaces this process holds the lock of: the lock file's (device, inode) -> the open lock file (by inode:
#: a workspace moved while this process holds it is still held).
_LOCKS: dict[tuple[int, int], Any] = {}


def lock_workspace(root: Path) -> None:
    """Take the workspace's lock for this process (kept until it ends; taking it again is a no-op). Raises
    :class:`UserInputError` naming the process that holds it."""
    root = root.resolve()
    try:
        handle = open(root / ".lock", "a+")  # noqa: SIM115  held open: the lock lives as long as the file is open
    except OSError as exc:
        raise UserInputError(f"cannot write workspace {root} (its lock file {root / '.lock'}: {exc.strerror}): run "
                             f"into a folder you can write to, or make this one writable") from None
    stat = os.fstat(handle.fileno())
    key = (stat.st_dev, stat.st_ino)
    if key in _LOCKS:
        handle.close()
        return
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "another process"
        handle.close()
        raise UserInputError(f"workspace {root} is in use by {holder}: wait for it to finish, or run into another "
                             f"workspace") from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"process {os.getpid()} ({' '.join(sys.argv)[:200]})\n")
    handle.flush()
    _LOCKS[key] = handle


def check_outside_survey(root: Path, survey_dir: str | Path) -> None:
    """A workspace is never inside the survey folder it runs on (nor that folder itself): the survey is never
    written to. A UserInputError saying where to put it otherwise."""
    survey, inside = Path(survey_dir).resolve(), Path(root).resolve()
    if inside == survey or survey in inside.parents:
        raise UserInputError(f"workspace {root} is inside the survey folder {survey}, which is never written to: give "
                             f"a workspace outside it (e.g. --workspace {survey.parent / (survey.name + '_ws')})")


def release_workspaces() -> None:
    """Give up every workspace lock this process holds (a long-lived process, a test session, between runs)."""
    while _LOCKS:
        _LOCKS.popitem()[1].close()


class Workspace:
    """A run folder. ``Workspace(path)`` creates it when missing. ``stages`` is the stage table
    (default: :data:`pipeline.stages.STAGES`; a test may give its own)."""

    def __init__(self, root: str | Path, stages: Mapping[str, Stage] | None = None) -> None:
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise UserInputError(f"workspace {self.root} exists and is not a folder: choose another path")
        self._created = not self.root.exists()
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserInputError(f"cannot create workspace {self.root}: {exc.strerror}; "
                                 f"choose a folder you can write to") from exc
        if stages is None:
            from .stages import STAGES as stages
        self.stages = stages
        known = {s.folder for s in stages.values()}
        older = sorted(p.name for p in self.root.iterdir() if p.name not in known and (p / "result.json").is_file())
        if older:
            raise UserInputError(f"workspace {self.root} was made by an older version of watergan (its stage folders "
                                 f"{', '.join(older)} are not this version's: "
                                 f"{', '.join(s.folder for s in stages.values())}); rerun into a new workspace "
                                 f"(`watergan run SURVEY --workspace NEW`)")

    def stage(self, name: str) -> Stage:
        if name not in self.stages:
            raise KeyError(f"unknown stage '{name}'; stages: {', '.join(self.stages)}")
        return self.stages[name]

    def folder(self, stage: str) -> Path:
        """The stage's folder (not created: for reading)."""
        return self.root / self.stage(stage).folder

    def stage_dir(self, stage: str) -> Path:
        """The stage's folder, created when missing (for writing)."""
        path = self.folder(stage)
        path.mkdir(parents=True, exist_ok=True)
        return path

    def path(self, relative: str | Path) -> Path:
        """An absolute path from a workspace-relative one (as results store them)."""
        return self.root / relative

    def relative(self, path: str | Path) -> str:
        """The workspace-relative form of a path inside the workspace."""
        return str(Path(path).resolve().relative_to(self.root.resolve()))

    def record(self, stage: str) -> dict | None:
        """The stage's ``result.json`` as saved (stage, config_hash, upstream, result), None before it ran."""
        path = self.folder(stage) / "result.json"
        if not path.is_file():
            return None
        return json.loads(path.read_text())

    def result(self, stage: str) -> Any:
        """The stage's result as its typed dataclass (the stage table's ``result``), None before it ran; a
        record another version of watergan wrote (other fields) is an error saying to rerun the stage."""
        record = self.record(stage)
        if record is None:
            return None
        try:
            return from_jsonable(self.stage(stage).result_type, record["result"])
        except (KeyError, TypeError, ValueError) as exc:
            raise UserInputError(f"{self.folder(stage) / 'result.json'} was written by another "
                                 f"version of watergan ({exc}): rerun the stage with --force {stage}") from None

    def require(self, stage: str, what: str) -> Any:
        """The result of ``stage``, or a clear error saying that ``what`` needs it run first."""
        result = self.result(stage)
        if result is None:
            raise UserInputError(f"{what} needs the {stage} stage in {self.root}: run "
                                 f"{self.stage(stage).how_to_run()} first")
        return result

    def upstream(self, stage: str) -> dict[str, str]:
        """Per stage that ``stage`` reads: the hash of its whole result record, which changes whenever it
        reran (its timings differ), so a rerun upstream reruns the stages that read it."""
        return {s: config_hash(self.record(s) or {}) for s in self.stage(stage).reads}

    def stage_hash(self, stage: str, config: Any) -> str:
        """The hash a finished ``stage`` records: its configuration (paths inside the workspace relative to it,
        so that a moved workspace is still done) and the results it read (records, as saved)."""
        return config_hash({"config": config, "upstream": self.upstream(stage)}, self.root)

    def outputs(self, stage: str) -> dict[str, int]:
        """{workspace-relative path: size in bytes} of every file in the stage's folder but its config and result
        (what :meth:`save` records; a linked file counts by its target, a linked folder is not walked: the survey
        stage's links to the user's survey)."""
        folder = self.folder(stage)
        found = {}
        for path in sorted(folder.rglob("*")) if folder.is_dir() else ():
            record = path.parent == folder and path.name in ("config.json", "result.json")
            if path.is_file() and not record and not path.name.startswith("."):
                found[str(path.relative_to(self.root))] = path.stat().st_size
        return found

    def missing(self, stage: str) -> list[str]:
        """The files the stage's record lists that are gone or changed size (deleted, cut short); empty for a
        stage that has not run or whose record lists none."""
        listed = (self.record(stage) or {}).get("outputs", {})
        return [p for p, size in listed.items()
                if not (self.root / p).is_file() or (self.root / p).stat().st_size != size]

    def is_done(self, stage: str, config: Any) -> bool:
        """True when the stage finished with this very configuration on the same upstream results, its files
        are there as it wrote them (:meth:`missing`) and its record reads back (one from another version of
        watergan is not done)."""
        record = self.record(stage)
        if record is None or record.get("config_hash") != self.stage_hash(stage, config) or self.missing(stage):
            return False
        try:
            self.result(stage)
        except UserInputError:
            return False
        return True

    def save(self, stage: str, config: Any, result: Any) -> dict:
        """Record a finished stage: config.json, then result.json (written last: it marks completion) with the
        stage's files and their sizes (:meth:`outputs`)."""
        folder = self.stage_dir(stage)
        upstream = self.upstream(stage)
        digest = self.stage_hash(stage, config)
        atomic_write_json(folder / "config.json", {"config": config, "config_hash": digest, "upstream": upstream})
        record = {"stage": stage, "config_hash": digest, "upstream": upstream, "result": to_jsonable(result),
                  "outputs": self.outputs(stage)}
        atomic_write_json(folder / "result.json", record)
        return record

    def run(self, stage: str, config: Any, force: bool = False) -> Any:
        """Run the stage's function ``fn(ws, config)`` unless it is already done with this configuration
        on the same upstream results; returns its typed result. The first stage a process runs takes the
        workspace's lock (:func:`lock_workspace`); a stage whose files are gone reruns, saying which. A stage run
        on a survey folder (its configuration's ``survey_dir``) that holds this workspace is refused before anything
        is written (:func:`check_outside_survey`; the empty folder this object made is removed)."""
        if getattr(config, "survey_dir", ""):
            try:
                check_outside_survey(self.root, config.survey_dir)
            except UserInputError:
                if self._created and self.root.is_dir() and not any(self.root.iterdir()):
                    self.root.rmdir()
                raise
        if force or not self.is_done(stage, config):
            lock_workspace(self.root)
            gone = self.missing(stage)
            if gone and not force:
                print(f"{stage}: {len(gone)} of its files are gone or cut short since it ran (e.g. {gone[0]}): "
                      f"running it again", file=sys.stderr)
            (self.folder(stage) / "result.json").unlink(missing_ok=True)  # a rerun is unfinished until it saves again
            self.save(stage, config, self.stage(stage).fn(self, config))
        return self.result(stage)
