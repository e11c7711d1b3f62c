"""Run a stage's per-image work here or on a Dask cluster, with the same results; and the threads that run it here.

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

Here, the corrections (the restorer's and the physics inverse) run frames side by side in thread lanes
(:func:`cpu_lanes` on a CPU, :func:`cuda_lanes` on a GPU), with :func:`io_threads` readers reading the next
frames ahead of them (:func:`read_ahead`) and the allocator told to keep what they free (:func:`keep_freed_memory`).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from tqdm import tqdm

from watergan.errors import UserInputError

if TYPE_CHECKING:
    import torch

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


IO_THREADS = 2
"""Threads that read the next images while the nets run on a CPU (OpenCV's PNG codecs and file I/O release the GIL,
so they overlap the nets)."""


def io_threads(dev: torch.device) -> int:
    """Threads that read the next images: ``IO_THREADS`` on a CPU, where the lanes take the cores; on CUDA, where
    the nets leave the cores to decoding and encoding, :func:`cuda_lanes` of them."""
    return IO_THREADS if dev.type == "cpu" else cuda_lanes()


def cpu_lanes() -> int:
    """Batches the nets correct at once on a CPU: one per intra-op thread torch would use, each lane running its
    batch on one thread. The restorer's convolutions are narrow (3-16 channels at full resolution) and split poorly
    across threads; whole batches side by side keep every core busy, and a lane whose core is taken by another job
    waits alone instead of stalling the other thread at every layer."""
    import torch

    return max(1, torch.get_num_threads())


CUDA_LANES = 4
"""The fewest batches in flight on a GPU (:func:`cuda_lanes`)."""


def cuda_lanes() -> int:
    """Batches in flight on a GPU: one on the GPU while the others' outputs are encoded and written (PNG encoding,
    not the nets, bounds a GPU's frames per second), half the machine's cores and at least ``CUDA_LANES``
    (benchmarks/bench_gpu.py sweeps the lanes and readers)."""
    return max(CUDA_LANES, (os.cpu_count() or 1) // 2)


def keep_freed_memory() -> bool:
    """glibc's allocator told to serve blocks of up to 32 MiB from its heap and to keep what is freed (mallopt
    M_MMAP_THRESHOLD and M_TRIM_THRESHOLD), for the rest of the process. By default each frame's full-resolution
    tensors are mapped afresh and unmapped when freed, and every page of every one is faulted in again, which costs
    the correction's element-wise steps more than their arithmetic; the heap then holds what one batch needs
    (benchmarks/RESULTS/restorer.md). False where the C library is not glibc."""
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    return bool(mallopt(m_mmap_threshold, 32 * 2**20)) and bool(mallopt(m_trim_threshold, 2**30))


def read_ahead(pool: ThreadPoolExecutor, read: Callable[[int, T], R], items: Iterable[T], ahead: int
               ) -> Iterator[tuple[int, T, Future[R]]]:
    """(index, item, the future of ``read(index, item)``) of each item in order, with up to ``ahead`` reads
    submitted to ``pool`` before the one yielded."""
    reads: deque[tuple[int, T, Future[R]]] = deque()
    for k, item in enumerate(items):
        reads.append((k, item, pool.submit(read, k, item)))
        if len(reads) > ahead:
            yield reads.popleft()
    yield from reads
