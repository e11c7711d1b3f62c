"""Run a stage's per-image work here or on a Dask cluster, with the same results.

``map_tasks(fn, items, scheduler)`` is the one executor of the per-image stages (correction, dense
depth, baselines, colour sampling):

- ``scheduler`` empty or None: a plain loop in this process with a progress bar (``distributed`` is
  not imported);
- ``scheduler`` an address (``tcp://HOST:8786``, from ``dask scheduler``): the items go to the
  cluster's workers through ``distributed.Client.map``; results come back in the input order;
- ``scheduler`` a ``distributed.Client`` (e.g. of a ``LocalCluster``): used as it is, not closed.

What is shipped must pickle: ``fn`` a top-level function of an importable module, the items plain
values (paths, arrays, frozen dataclasses). Workers read and write the shared file system, so the
paths must mean the same on every machine (give absolute paths; :func:`shared_path` makes them
so) and every output is written atomically (a temporary file renamed into place) by the task that
made it. A task's exception stops the run: the remaining tasks are cancelled and it is raised here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from tqdm import tqdm

from watergan.errors import UserInputError

T = TypeVar("T")
R = TypeVar("R")

CONNECT_TIMEOUT_S = 20.0
"""How long to try to reach a scheduler before saying it cannot be reached."""


def is_distributed(scheduler: Any) -> bool:
    """True when ``scheduler`` names a cluster (an address or a Client), False for local runs."""
    return scheduler is not None and scheduler != ""


def chunks(items: Sequence[T], size: int) -> list[list[T]]:
    """``items`` in consecutive lists of at most ``size`` (at least 1)."""
    size = max(int(size), 1)
    return [list(items[i:i + size]) for i in range(0, len(items), size)]


def rows_by_label(labels: np.ndarray, keys: Iterable[int]) -> list[np.ndarray]:
    """For each key, the indices of ``labels`` equal to it, ascending (``np.flatnonzero(labels == key)``
    for every key at the cost of one sort: per-image observations of a large survey)."""
    labels = np.asarray(labels)
    order = np.argsort(labels, kind="stable")
    ordered = labels[order]
    keys = np.asarray(list(keys))
    lo, hi = np.searchsorted(ordered, keys, "left"), np.searchsorted(ordered, keys, "right")
    return [order[a:b] for a, b in zip(lo, hi, strict=True)]


def shared_path(path: str | Path) -> Path:
    """The absolute form of ``path``, so that workers started elsewhere find the same file."""
    return Path(path).resolve()


def connect(scheduler: str, timeout_s: float = CONNECT_TIMEOUT_S):
    """A ``distributed.Client`` of the scheduler at ``scheduler``; a UserInputError naming the address
    when it cannot be reached within ``timeout_s`` seconds (or is not an address)."""
    try:
        from distributed import Client
        from distributed.comm import get_address_host_port
    except ImportError as exc:  # pragma: no cover - a dependency of the project
        raise UserInputError("running on a scheduler needs dask's distributed package: "
                             "pip install 'dask[distributed]'") from exc
    try:
        get_address_host_port(scheduler)  # a malformed address fails here, before a Client half exists
    except ValueError as exc:
        raise UserInputError(f"'{scheduler}' is not a Dask scheduler address ({exc}): give one like "
                             f"tcp://HOST:8786") from exc
    try:
        return Client(scheduler, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise UserInputError(f"cannot reach the Dask scheduler at '{scheduler}' within {timeout_s:g} s "
                             f"({type(exc).__name__}: {exc}); start one with `dask scheduler` and workers with "
                             f"`dask worker {scheduler}`, or leave --scheduler out to run here") from exc


def map_tasks(fn: Callable[[T], R], items: Iterable[T], scheduler: Any = None, desc: str = "",
              progress: bool = True, unit: str = "task", timeout_s: float = CONNECT_TIMEOUT_S) -> list[R]:
    """``[fn(item) for item in items]``, locally or on a Dask cluster (see the module docstring)."""
    items = list(items)
    if not is_distributed(scheduler):
        return [fn(item) for item in tqdm(items, desc=desc, unit=unit, disable=not progress)]
    if not items:
        return []
    from distributed import as_completed

    own = isinstance(scheduler, str)
    client = connect(scheduler, timeout_s) if own else scheduler
    futures = []
    try:
        futures = client.map(fn, items, pure=False)
        position = {future.key: i for i, future in enumerate(futures)}
        results: list[Any] = [None] * len(items)
        with tqdm(total=len(items), desc=desc, unit=unit, disable=not progress) as bar:
            for future in as_completed(futures, loop=client.loop):
                results[position[future.key]] = future.result()  # a task's exception is raised here
                future.release()
                bar.update(1)
        return results
    finally:
        if futures:
            client.cancel([f for f in futures if not f.done()])
        if own:
            client.close()
