"""The training progress bar: a budgeted run shows the budget's seconds, not an iteration ETA."""

import io

from watergan.progress import TrainingBar


def _final_line(out: io.StringIO) -> str:
    return out.getvalue().replace("\r", "\n").strip().splitlines()[-1]


def test_a_budgeted_bar_counts_the_budget_and_shows_the_iterations():
    out = io.StringIO()
    bar = TrainingBar("train-gan", 100000, 0, 240.0, True, file=out)
    for step, seconds in ((1, 0.5), (2, 1.0), (3, 12.0)):
        bar.update(step, seconds, d="0.500")
    bar.close()
    line = _final_line(out)
    assert "12/240 s of the budget" in line and "it=3/100000" in line and "d=0.500" in line, line
    assert "100000it" not in line and "/100000 [" not in line


def test_a_second_stage_starts_at_the_time_already_spent():
    out = io.StringIO()
    bar = TrainingBar("restorer stage 2", 500, 0, 150.0, True, elapsed_s=75.0, file=out)
    bar.update(1, 76.0)
    bar.close()
    assert "76/150 s of the budget" in _final_line(out)


def test_without_a_budget_the_bar_counts_iterations():
    out = io.StringIO()
    bar = TrainingBar("train-gan", 50, 10, None, True, file=out)
    for step in range(11, 21):
        bar.update(step, 0.1 * step, g="1.0")
    bar.close()
    assert "20/50" in _final_line(out) and " s of the budget" not in out.getvalue()
