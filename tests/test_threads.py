"""The threads a run takes: --threads N, or with 0 the cores no other job keeps busy."""

import os

import pytest


def test_free_cores_count_a_job_running_now_and_not_one_that_just_ended(monkeypatch):
    from watergan import threads

    cores = len(os.sched_getaffinity(0))
    monkeypatch.setattr(os, "cpu_count", lambda: cores)
    monkeypatch.setattr(os, "getloadavg", lambda: (1.0, 1.0, 1.0))
    monkeypatch.setattr(threads, "runnable_elsewhere", lambda: 0)  # this process alone: the minute's job has ended
    assert threads.free_cores() == cores
    monkeypatch.setattr(threads, "runnable_elsewhere", lambda: 1)  # another job running now
    assert threads.free_cores() == max(1, cores - 1)
    monkeypatch.setattr(threads, "runnable_elsewhere", lambda: None)  # no /proc: the minute's load alone
    assert threads.free_cores() == max(1, cores - 1)
    monkeypatch.setattr(os, "getloadavg", lambda: (10.0 * cores, 0.0, 0.0))
    monkeypatch.setattr(threads, "runnable_elsewhere", lambda: 10 * cores)
    assert threads.free_cores() == 1


@pytest.mark.skipif(not os.path.exists("/proc/self/task"), reason="Linux's /proc")
def test_this_processs_own_busy_threads_are_not_another_job():
    """Two threads of this process kept busy (numpy's matrix products release the GIL) are counted as this
    process's runnable threads (runnable_here), which runnable_elsewhere takes off /proc/loadavg's count."""
    import threading
    import time

    import numpy as np

    from watergan.threads import runnable_here

    stop = threading.Event()
    a = np.random.default_rng(0).random((300, 300))

    def spin():
        while not stop.is_set():
            a @ a

    workers = [threading.Thread(target=spin) for _ in range(2)]
    for w in workers:
        w.start()
    try:
        seen, deadline = 1, time.monotonic() + 5.0
        while seen < 2 and time.monotonic() < deadline:
            seen = max(seen, runnable_here())
        assert seen >= 2
    finally:
        stop.set()
        for w in workers:
            w.join()


def test_use_threads_sets_torch_and_opencv_and_puts_them_back():
    import cv2
    import torch

    from watergan.errors import UserInputError
    from watergan.threads import use_threads

    before = torch.get_num_threads(), cv2.getNumThreads()
    with use_threads(3) as count:
        assert count == 3 and torch.get_num_threads() == 3 and cv2.getNumThreads() == 3
    assert (torch.get_num_threads(), cv2.getNumThreads()) == before
    with use_threads(0) as count:
        assert count >= 1 and torch.get_num_threads() == count
    with pytest.raises(UserInputError, match="--threads"), use_threads(-1):
        pass
