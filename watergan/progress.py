"""A progress bar for training loops that stop at an iteration count, at the end of a time budget, or
at whichever comes first.

A bar that counts iterations towards a count the budget will never reach (``--gan-budget-min 4`` with
the default 100000 iterations) shows an ETA of hours for a run that ends in minutes. With a budget the
bar counts the budget's seconds instead (elapsed of the budget; its ETA is the budget left), and the
iterations go into its postfix.
"""

from __future__ import annotations

from typing import TextIO

from tqdm import tqdm


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
