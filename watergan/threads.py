"""How many threads this process's numerical work takes (torch's and OpenCV's pools), chosen for the machine's load.

``with use_threads(n):`` around a run (``watergan run --threads N``, a stage command's ``--threads N``) sets
both pools to ``n`` threads, or with 0 to the cores no other job keeps busy (:func:`free_cores`): on a machine
shared with another job, a pool with a thread per core has one thread waiting for a busy core at every
parallel step, and every other thread waits for it.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Iterator
from pathlib import Path

from watergan.errors import UserInputError


def free_cores() -> int:
    """The cores this process may use that no other job keeps busy: its cores (its CPU affinity) less the jobs
    running now, at least 1. A job is counted when both the load over the last minute (os.getloadavg, rounded to
    the nearest whole job) and the tasks of other processes runnable at this instant (:func:`runnable_elsewhere`)
    show it: the minute's average alone still counts a job that ended seconds ago."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        busy = math.floor(os.getloadavg()[0] + 0.5)
    except OSError:  # no load average on this system
        busy = 0
    running = runnable_elsewhere()
    if running is not None:
        busy = min(busy, running)
    return max(1, min(cores, (os.cpu_count() or cores) - busy))


def runnable_elsewhere() -> int | None:
    """Tasks runnable at this instant outside this process: /proc/loadavg's runnable count less this process's own
    runnable threads (:func:`runnable_here`; a pool's workers still spinning after a parallel step are this
    process's, not another job); None where unreadable."""
    try:
        total = int(Path("/proc/loadavg").read_text().split()[3].split("/")[0])
    except (OSError, IndexError, ValueError):
        return None
    return max(0, total - runnable_here())


def runnable_here() -> int:
    """This process's threads runnable at this instant (state R in /proc/self/task/*/stat), at least 1: the one
    reading."""
    count = 0
    for task in Path("/proc/self/task").glob("*/stat"):
        try:
            count += task.read_text().rsplit(")", 1)[1].split()[0] == "R"
        except (OSError, IndexError):  # a thread that ended while being read
            continue
    return max(1, count)


@contextlib.contextmanager
def use_threads(threads: int = 0) -> Iterator[int]:
    """Within the block, torch's and OpenCV's threads set to ``threads`` (0: :func:`free_cores`), the count
    yielded; their earlier counts are set back after it. A negative count is a UserInputError."""
    if threads < 0:
        raise UserInputError(f"--threads must be 0 (auto: the cores not busy) or a positive count, got {threads}")
    import cv2
    import torch

    count = threads or free_cores()
    before = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(count)
    cv2.setNumThreads(count)
    try:
        yield count
    finally:
        torch.set_num_threads(before[0])
        cv2.setNumThreads(before[1])


def threads_line(count: int, given: int) -> str:
    """The line a run prints about its threads."""
    cores = os.cpu_count() or 1
    how = "--threads" if given else "the cores not busy; --threads N to choose"
    return f"threads: {count} of {cores} cores ({how})"
