"""The training progress bar (a budgeted run shows the budget's seconds, not an iteration ETA) and the heartbeat of a
stage that prints nothing else."""

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


def test_a_silent_stage_says_every_interval_that_it_is_still_running_and_what_it_does(capsys):
    import time

    from watergan.progress import activity, say

    with activity("[4/11] water", True, interval_s=0.1):
        say("measuring the frames")
        time.sleep(0.35)  # a stage that prints nothing for three and a half intervals
    lines = capsys.readouterr().out.splitlines()
    assert 2 <= len(lines) <= 3 and all(line == "[4/11] water: still running, 0s: measuring the frames"
                                        for line in lines), lines


def test_no_heartbeat_while_a_bar_moves_or_when_disabled(capsys):
    import time

    from tqdm import tqdm

    from watergan.progress import activity, say

    with activity("[2/11] sfm", True, interval_s=0.1):
        with tqdm(total=20, file=io.StringIO(), mininterval=0) as bar:
            for _ in range(20):
                time.sleep(0.015)
                bar.update(1)
    with activity("[3/11] dense", False, interval_s=0.05):
        say("fusing")
        time.sleep(0.15)
    say("outside a stage: kept for none")
    assert capsys.readouterr().out == ""


def test_durations_read_as_minutes_and_hours():
    from watergan.progress import duration

    assert [duration(s) for s in (45.9, 150, 3725)] == ["45s", "2m30s", "1h02m"]
