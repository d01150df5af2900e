"""The runner's progress line (issue 37): it says what is under way and for how long,
redraws itself while a run compiles or trains (no run needs to finish for the clock to
move), and estimates the time left from a group's first run and its later seeds
separately, so one expensive compilation does not swing it."""

import io
import threading

from dax_algos.bench import progress
from dax_algos.bench.progress import Clock, clock_text


class FakeTime:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_clock_text():
    assert [clock_text(s) for s in (0, 59.9, 61, 3600, 3725)] == [
        "0:00", "0:59", "1:01", "1:00:00", "1:02:05"]


def test_the_line_says_what_is_under_way_and_for_how_long():
    now = FakeTime()
    clock = Clock(6, groups=2, enabled=False, now=now)
    assert clock.line() == "dax-bench 0:00 | 0/6 runs | starting 0:00 | ETA after the first run"
    clock.start("fold_cloth1", "ppo")
    clock.phase("compiling")
    now.t += 75
    assert clock.line() == ("dax-bench 1:15 | 0/6 runs | fold_cloth1 / ppo: compiling 1:15 | "
                            "ETA after the first run")


def test_the_estimate_separates_first_runs_from_later_seeds():
    now = FakeTime()
    clock = Clock(6, groups=2, enabled=False, now=now)  # 2 groups of 3 seeds
    clock.start("t", "a")
    now.t += 60  # compile + seed 0
    clock.finished({"status": "ok"})
    now.t += 2  # seed 1
    clock.finished({"status": "failed"})
    # left: group b's first run (60 s) and 3 more seeds (2 s each)
    assert clock.eta() == 60 + 3 * 2
    assert "2/6 runs, 1 failed" in clock.line()


def test_the_line_is_redrawn_while_a_run_is_under_way(monkeypatch):
    monkeypatch.setattr(progress, "LOG_EVERY", 0.0)
    stream = io.StringIO()
    clock = Clock(2, groups=1, stream=stream, interval=0.01)
    clock.start("fold_cloth1", "cem_mpc")
    clock.phase("compiling")
    ticked = threading.Event()
    for _ in range(500):  # until the thread has drawn three lines, with no run finished
        if stream.getvalue().count("compiling") >= 3:
            ticked.set()
            break
        ticked.wait(0.01)
    clock.close()
    assert ticked.is_set(), stream.getvalue()
    assert clock.done == 0


def test_a_disabled_clock_writes_nothing():
    stream = io.StringIO()
    clock = Clock(3, stream=stream, enabled=False)
    clock.finished({"status": "ok"})
    clock.close()
    assert stream.getvalue() == ""
