"""The threads a run takes: --threads N, or with 0 the cores no other job keeps busy."""

import os

import pytest


def test_free_cores_are_the_cores_less_the_load_and_at_least_one():
    from watergan.threads import free_cores

    cores = len(os.sched_getaffinity(0))
    expected = max(1, min(cores, os.cpu_count() - round(os.getloadavg()[0] + 1e-9)))
    assert 1 <= free_cores() <= cores
    assert abs(free_cores() - expected) <= 1  # the load average moves between the two readings


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
