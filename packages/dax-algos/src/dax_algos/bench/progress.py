"""The runner's progress display: one status line on stderr that a thread redraws every
second, so the clock ticks while a run compiles or trains.

The line gives the time since the start, the runs finished (and failed) of those to do,
what is under way and for how long (``fold_cloth1 / ppo: compiling 0:14``) and an estimate
of the time left (:meth:`Clock.eta`). On a terminal the line is redrawn in place; written to
a file or a pipe, a line is printed at each finished run and every :data:`LOG_EVERY`
seconds in between.
"""

from __future__ import annotations

import sys
import threading
import time

#: seconds between two status lines when stderr is not a terminal
LOG_EVERY = 30.0


def clock_text(seconds: float) -> str:
    """``m:ss``, or ``h:mm:ss`` from an hour on."""
    s = int(max(seconds, 0.0))
    h, m, s = s // 3600, s // 60 % 60, s % 60
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class Clock:
    """The status line of a grid of ``total`` runs in ``groups`` (task, method) groups (each
    compiled once; ``0``: runs are independent, as on Ray).

    The estimate of the time left separates a group's first run (which includes building
    the method and compiling it) from its later seeds: each is the mean of those measured
    so far, times what is left of each kind; until a run has finished there is none."""

    def __init__(self, total: int, groups: int = 0, enabled: bool = True, stream=None,
                 interval: float = 1.0, now=time.monotonic):
        self.total, self.groups = total, groups
        self.enabled = enabled and total > 0
        self.stream = stream if stream is not None else sys.stderr
        self.interval, self.now = interval, now
        self.t0 = now()
        self.done = self.failed = self.started = 0
        self.what, self.since = "starting", self.t0
        self._group = ""
        self.group_t0 = None
        self.first_costs: list = []
        self.seed_costs: list = []
        self._last_result = None
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._logged = self.t0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = None
        if self.enabled:
            self._thread = threading.Thread(target=self._tick, name="dax-bench-clock",
                                            daemon=True)
            self._thread.start()

    # what the runner tells it ---------------------------------------------------------

    def building(self, task: str) -> None:
        """A task is being built."""
        self._group = task
        self._set(task, "building the task")

    def start(self, task: str, method: str) -> None:
        """A (task, method) group starts."""
        self.group_t0 = self._last_result = self.now()
        self.started += 1
        self._group = f"{task} / {method}"
        self._set(self._group, "")

    def phase(self, text: str) -> None:
        """What the current group is doing now (``"compiling"``, ``"seed 2"``)."""
        self._set(self._group, text)

    def finished(self, row) -> None:
        """A run finished (its results row)."""
        t = self.now()
        if self._last_result is not None:
            first = self._last_result == self.group_t0
            (self.first_costs if first else self.seed_costs).append(t - self._last_result)
        self._last_result = t
        self.done += 1
        self.failed += row.get("status") == "failed"
        if self.enabled and not self._tty:
            self._draw(force=True)

    def close(self) -> None:
        """Stop the clock (the last line stays, followed by a newline on a terminal)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            if self._tty:
                self._draw(force=True)
                self._write("\n")

    # the line -------------------------------------------------------------------------

    def _set(self, group: str, text: str) -> None:
        self.what = f"{group}: {text}" if text else group
        self.since = self.now()

    def eta(self) -> float | None:
        """Estimated seconds left (``None`` until a run has finished): the first runs
        left (of the groups not started, and the current group's if it has none yet) at
        the mean first-run time, the other runs at the mean later-seed time, less what
        the run under way has taken (at most four fifths of its kind's mean)."""
        left = self.total - self.done
        if not self.done:
            return None
        if not left:
            return 0.0
        under_way = self.now() - (self._last_result or self.now())
        if not self.groups or not self.first_costs:
            per = (self.now() - self.t0 - under_way) / self.done
            return max(left * per - min(under_way, per), 0.0)
        first = sum(self.first_costs) / len(self.first_costs)
        seed = (sum(self.seed_costs) / len(self.seed_costs)) if self.seed_costs else first
        in_first = self._last_result == self.group_t0  # the current group's first run
        firsts = min(max(self.groups - self.started, 0) + in_first, left)
        now_cost = first if in_first else seed
        # the run under way: its mean less what it has taken, but a run past its mean is
        # not about to end (a fifth of its mean still counted)
        done_part = min(under_way, 0.8 * now_cost)
        return firsts * first + (left - firsts) * seed - done_part

    def line(self) -> str:
        """The status line now."""
        eta = self.eta()
        parts = [f"dax-bench {clock_text(self.now() - self.t0)}",
                 f"{self.done}/{self.total} runs" + (f", {self.failed} failed"
                                                     if self.failed else ""),
                 f"{self.what} {clock_text(self.now() - self.since)}",
                 "ETA " + ("after the first run" if eta is None else clock_text(eta))]
        return " | ".join(parts)

    def _draw(self, force: bool = False) -> None:
        if not self.enabled:
            return
        if self._tty:
            self._write("\r" + self.line()[:160] + "\x1b[K")
        elif force or self.now() - self._logged >= LOG_EVERY:
            self._logged = self.now()
            self._write(self.line() + "\n")

    def _write(self, text: str) -> None:
        with self._lock:
            self.stream.write(text)
            self.stream.flush()

    def _tick(self) -> None:
        while not self._stop.wait(self.interval):
            self._draw()
