"""What both trainers (:mod:`watergan.train`, :mod:`watergan.train_restorer`) do around their steps.

- the checkpoint, ``checkpoint.pt``: a dict of tensors and plain values written with ``torch.save``
  through :func:`watergan.io.atomic_write_bytes` (a reader sees the old or the new one, never a torn
  one) and read with ``weights_only`` on the CPU (:func:`save_torch`, :func:`load_torch`); a run with
  ``resume`` goes on from it when there is one (:func:`read_resume_checkpoint`);
- the training log, ``train_log.jsonl``: one JSON object per iteration, appended; a resumed run first
  cuts it back to the rows up to its checkpoint, a fresh one empties it (:class:`TrainingLog`);
- the wall-clock budget of a run (:class:`Clock`);
- the result, ``result.json``: the run's result dataclass as indented JSON (:class:`TrainingResult`).
"""

from __future__ import annotations

import io
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from .errors import UserInputError
from .io import atomic_write_bytes, atomic_write_text, to_jsonable

CHECKPOINT = "checkpoint.pt"
TRAIN_LOG = "train_log.jsonl"
RESULT_JSON = "result.json"


# ----------------------------------------------------------------------------------------- checkpoint
def save_torch(path: str | Path, payload: dict) -> None:
    """``payload`` (tensors, plain values and dicts of them) as a ``torch.save`` file, atomically (the folder
    is created)."""
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    atomic_write_bytes(Path(path), buffer.getvalue())


def load_torch(path: str | Path, missing: str) -> dict:
    """A file written by :func:`save_torch`, tensors on the CPU (``weights_only``). A missing file is a
    :class:`UserInputError` of ``missing`` (what to do); a torn or foreign one, one naming the file."""
    path = Path(path)
    if not path.is_file():
        raise UserInputError(missing)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a torn or foreign file: say which
        raise UserInputError(f"checkpoint {path} cannot be read ({type(exc).__name__}: {exc})") from exc


def read_resume_checkpoint(out: Path, resume: bool, command: str, fresh: str) -> dict | None:
    """The checkpoint to resume from: ``out/checkpoint.pt`` when ``resume`` and it exists; else None (said
    on stderr, "``command``: no checkpoint in ``out``, ``fresh``", when a resume was asked for)."""
    path = out / CHECKPOINT
    if resume and path.is_file():
        return load_torch(path, f"no checkpoint at {path}")
    if resume:
        print(f"{command}: no checkpoint in {out}, {fresh}", file=sys.stderr)
    return None


# ------------------------------------------------------------------------------------------------ log
class TrainingLog:
    """``train_log.jsonl``: one JSON object per iteration. Opening it (:meth:`start`) rewrites the file
    with the rows whose ``key`` values (compared as a tuple) are at most ``upto``, those a resumed run's
    checkpoint holds, or empties it (``upto`` None: a fresh start); rows are then appended
    (:meth:`write`) while it is open as a context manager."""

    def __init__(self, path: Path, key: Sequence[str]):
        self.path, self.key = Path(path), tuple(key)
        self._file = None

    @classmethod
    def start(cls, out: Path, key: Sequence[str], upto: Sequence[int] | None) -> TrainingLog:
        """The log of the run in ``out``, cut back to ``upto`` (None: emptied)."""
        log = cls(Path(out) / TRAIN_LOG, key)
        atomic_write_text(log.path, "" if upto is None else log.lines_up_to(upto))
        return log

    def lines_up_to(self, upto: Sequence[int]) -> str:
        """The file's lines whose key is at most ``upto`` ("" without a file)."""
        if not self.path.is_file():
            return ""
        rows = [line for line in self.path.read_text().splitlines() if line.strip()]
        keep = [line for line in rows if self._key(json.loads(line)) <= tuple(upto)]
        return "".join(line + "\n" for line in keep)

    def _key(self, row: dict) -> tuple:
        return tuple(row[name] for name in self.key)

    def __enter__(self) -> TrainingLog:
        self._file = self.path.open("a")
        return self

    def __exit__(self, *exc) -> None:
        self._file.close()
        self._file = None

    def write(self, row: dict) -> None:
        """Append one row (an iteration)."""
        self._file.write(json.dumps(row) + "\n")

    def flush(self) -> None:
        """Push the rows written so far to the file (before a checkpoint, so the two agree)."""
        self._file.flush()

    def rows(self) -> list[dict]:
        """Every row of the file."""
        return [json.loads(line) for line in self.path.read_text().splitlines() if line.strip()]


# --------------------------------------------------------------------------------------------- budget
@dataclass
class Clock:
    """A run's wall-clock time since it began (``time.perf_counter``) and its budget."""

    budget_s: float | None
    """Seconds the run may take (None: no limit)."""
    began: float = field(default_factory=time.perf_counter)

    @classmethod
    def minutes(cls, budget_min: float | None) -> Clock:
        """A clock started now with a budget of ``budget_min`` minutes (None: none)."""
        return cls(None if budget_min is None else 60.0 * budget_min)

    def elapsed(self) -> float:
        """Seconds since the run began."""
        return time.perf_counter() - self.began

    def stamp(self) -> float:
        """:meth:`elapsed` rounded to milliseconds, as the log's ``seconds``."""
        return round(self.elapsed(), 3)

    def reached(self, end_s: float | None, reserve_s: float = 0.0) -> bool:
        """Whether the time since the run began, plus ``reserve_s`` kept for later work, is at least
        ``end_s`` (None: never)."""
        return end_s is not None and self.elapsed() + reserve_s >= end_s


# --------------------------------------------------------------------------------------------- result
class TrainingResult:
    """Base of the trainers' result dataclasses: their JSON form and ``result.json``."""

    def to_json(self) -> dict[str, Any]:
        """The fields as JSON values (paths as strings, tuples as lists)."""
        return to_jsonable(self)

    def write(self, out: Path) -> None:
        """``out/result.json``: :meth:`to_json`, indented, fields in their order, atomically."""
        atomic_write_text(Path(out) / RESULT_JSON, json.dumps(self.to_json(), indent=2) + "\n")
