"""What a running stage is doing: a progress bar for training loops, and a heartbeat for everything else.

:class:`TrainingBar`: a bar for loops that stop at an iteration count, at the end of a time budget, or at
whichever comes first. A bar that counts iterations towards a count the budget will never reach
(``--gan-budget-min 4`` with the default 100000 iterations) shows an ETA of hours for a run that ends in
minutes. With a budget the bar counts the budget's seconds instead (elapsed of the budget; its ETA is the
budget left), and the iterations go into its postfix.

:func:`activity` and :func:`say`: the rule that a stage never runs a minute without a word. ``with
activity("[4/11] water", enabled):`` around a stage starts a daemon thread that prints
``[4/11] water: still running, 2m30s: <what>`` every ``interval_s`` (30 s) unless a progress bar (tqdm)
printed within that time; ``say("fitting the stack")`` from any code, in any thread, sets ``<what>``
(cheap: one assignment under a lock, no output by itself; outside an activity it is kept for none).
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Iterator
from typing import TextIO

from tqdm import tqdm

#: Seconds between two heartbeat lines of a stage that prints nothing else.
HEARTBEAT_S = 30.0

_lock = threading.Lock()
_what = ""


def say(what: str) -> None:
    """Set what the running stage is doing now (shown by the next heartbeat line; no output by itself)."""
    global _what
    with _lock:
        _what = what


def _said() -> str:
    with _lock:
        return _what


def duration(seconds: float) -> str:
    """``45s``, ``2m30s``, ``1h02m``."""
    s = int(seconds)
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


def _bar_printed_since(t: float) -> bool:
    """Whether a live, shown tqdm bar printed after the time ``t`` (``time.time()``)."""
    with tqdm.get_lock():
        bars = list(getattr(tqdm, "_instances", ()))
    return any(not bar.disable and getattr(bar, "last_print_t", 0.0) > t for bar in bars)


@contextlib.contextmanager
def activity(label: str, enabled: bool = True, interval_s: float = HEARTBEAT_S,
             file: TextIO | None = None) -> Iterator[None]:
    """Within the block, print ``LABEL: still running, ELAPSED[: WHAT]`` every ``interval_s`` seconds (to
    ``file``, default the current stdout) unless a progress bar printed since the last line; ``WHAT`` is
    the last :func:`say` in the block. ``enabled`` False: nothing is printed (a run without progress)."""
    say("")
    if not enabled:
        yield
        return
    started, stop = time.monotonic(), threading.Event()

    def beat() -> None:
        last = time.time()
        while not stop.wait(interval_s):
            if _bar_printed_since(last):
                last = time.time()
                continue
            what = _said()
            line = f"{label}: still running, {duration(time.monotonic() - started)}" + (f": {what}" if what else "")
            tqdm.write(line, file=file or sys.stdout)
            (file or sys.stdout).flush()
            last = time.time()

    thread = threading.Thread(target=beat, name=f"heartbeat {label}", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        say("")


class TrainingBar:
    """``update(step, elapsed_s, **postfix)`` once per iteration, ``close()`` at the end.

    desc:      the bar's label.
    target:    the iteration the loop stops at (None: the budget alone).
    start:     the iteration it starts from (a resumed run).
    budget_s:  the time at which the loop stops, seconds since its start (None: no budget).
    elapsed_s: the time already spent when the bar starts (a second stage inside the same budget).
    """

    def __init__(self, desc: str, target: int | None, start: int, budget_s: float | None, enabled: bool,
                 elapsed_s: float = 0.0, file: TextIO | None = None) -> None:
        self.target, self.budget_s = target, budget_s
        if budget_s is None:
            self.bar = tqdm(total=target, initial=start, disable=not enabled, desc=desc, unit="it", file=file)
        else:
            self.bar = tqdm(total=round(budget_s, 1), initial=round(min(elapsed_s, budget_s), 1),
                            disable=not enabled, desc=desc, unit="s", file=file,
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s of the budget "
                                       "[{elapsed}<{remaining}{postfix}]")

    def update(self, step: int, elapsed_s: float, **postfix: str) -> None:
        """After iteration ``step``, ``elapsed_s`` seconds after the loop's start."""
        if self.budget_s is None:
            self.bar.update(1)
        else:
            self.bar.n = round(min(elapsed_s, self.budget_s), 1)
            postfix = {"it": f"{step}" if self.target is None else f"{step}/{self.target}", **postfix}
        self.bar.set_postfix(postfix)

    def close(self) -> None:
        self.bar.close()
