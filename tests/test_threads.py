"""The threads a run takes: --threads N, or with 0 the cores no other job keeps busy."""

import os

import pytest


def test_free_cores_count_a_job_running_now_and_not_one_that_just_ended(monkeypatch):
    from watergan import threads

    cores = len(os.sched_getaffinity(0))
    monkeypatch.setattr(os, "cpu_count", lambda: cores)
    monkeypatch.setattr(os, "getloadavg", lambda: (1.0, 1.0, 1.0))
    monkeypatch.setattr(threads, "runnable_now", lambda: 1)  # this process alone: the minute's job has ended
    assert threads.free_cores() == cores
    monkeypatch.setattr(threads, "runnable_now", lambda: 2)  # another job running now
    assert threads.free_cores() == max(1, cores - 1)
    monkeypatch.setattr(threads, "runnable_now", lambda: None)  # no /proc: the minute's load alone
    assert threads.free_cores() == max(1, cores - 1)
    monkeypatch.setattr(os, "getloadavg", lambda: (10.0 * cores, 0.0, 0.0))
    monkeypatch.setattr(threads, "runnable_now", lambda: 10 * cores)
    assert threads.free_cores() == 1


def test_runnable_now_counts_this_process():
    from watergan.threads import runnable_now

    running = runnable_now()
    if os.path.exists("/proc/loadavg"):  # Linux: read, and this process is running while it reads
        assert running is not None and running >= 1
    else:
        assert running is None


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
