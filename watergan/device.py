"""Which torch device a run uses: the one place that turns a ``device`` option into a device."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from enum import StrEnum

import torch

from .errors import UserInputError


class Device(StrEnum):
    """The values of every ``device`` option: auto (CUDA when available, else CPU), cpu or cuda."""

    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


DEVICE_NAMES = tuple(Device)


def pick_device(name: str) -> torch.device:
    """"auto": CUDA when available, else CPU; "cpu" or "cuda" as asked."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise UserInputError("device 'cuda' requested but CUDA is not available")
    if name not in DEVICE_NAMES:
        raise UserInputError(f"device must be auto, cpu or cuda, got {name!r}")
    return torch.device(name)


@contextmanager
def single_torch_thread() -> Iterator[None]:
    """Run torch on one thread inside the block (restored after). The stack's element-wise work on
    one frame is short on one thread, while torch's thread pool can take far longer when the ray caster
    and PNG writers (or other processes) hold the cores."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
