"""The validation suite: every solver against a known answer, with convergence charts.

``python -m benchmarks.validate --out DIR`` runs every check, writes ``validation.json``,
``validation.md`` (check, reference, default resolution, error, tolerance, pass, expected
and measured convergence order, a Pareto note) and one chart per check (error against cell
size and against wall time), and exits non-zero when a check fails. Agreement with the
Taichi and Warp references says the code does what the model says; these checks say
whether the model is right: analytic solutions (hydrostatics, sound and bar waves, beam
theory, Poisson contraction, yield, catenary, pendulums) and published laboratory
measurements (Martin & Moyce's collapsing water column).

Each check is a function ``check(level) -> Result`` registered with :func:`register`;
``level`` is ``"default"`` (the validation run) or ``"quick"`` (the smallest sweep that still
measures something, for a fast look); the package's tests call the scenes behind the
checks directly on tiny grids. Each check's docstring names its reference.

The task-level rows (one env step's action gradient per task family) are in
:mod:`.tasks`; they need dax-tasks installed.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

LEVELS = ("default", "quick")

_REGISTRY: dict[str, object] = {}


@dataclasses.dataclass
class Point:
    """One point of a check's resolution sweep.

    resolution: the swept number (cells across the feature, vertices, ...).
    cell_size: the grid cell or mesh edge [m] (or the finite-difference step for gradient
        checks). error: the signed relative error of the measured quantity. wall_s: wall
    time of the run [s] (compile excluded). measured, expected: the values compared.
    """

    resolution: float
    cell_size: float
    error: float
    wall_s: float
    measured: float | None = None
    expected: float | None = None
    extra: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class Result:
    """What one check found. ``error`` is the absolute relative error at the default
    resolution (``default``, a value of ``Point.resolution``); the check passes when it is
    at most ``tolerance`` and every extra condition in ``conditions`` holds."""

    name: str
    solver: str
    reference: str
    quantity: str
    resolution_label: str
    default: float
    points: list
    tolerance: float
    expected_order: float | None = None
    pareto_note: str = ""
    conditions: dict = dataclasses.field(default_factory=dict)
    notes: str = ""
    extra: dict = dataclasses.field(default_factory=dict)
    error_label: str = "relative error"
    #: fit the convergence order only on points with at least this cell size (gradient
    #: checks: the steps where truncation, not round-off, dominates)
    order_min_cell_size: float | None = None

    @property
    def default_point(self) -> Point:
        return min(self.points, key=lambda p: abs(p.resolution - self.default))

    @property
    def error(self) -> float:
        return abs(self.default_point.error)

    @property
    def measured_order(self) -> float | None:
        lo = self.order_min_cell_size
        return convergence_order([p for p in self.points if lo is None or p.cell_size >= lo])

    @property
    def passed(self) -> bool:
        return bool(self.error <= self.tolerance and all(self.conditions.values()))

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.update(error=self.error, measured_order=self.measured_order, passed=self.passed,
                 conditions={k: bool(v) for k, v in self.conditions.items()})
        return _finite(d)


def _finite(obj):
    """Strict JSON: non-finite floats become strings."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else str(f)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def convergence_order(points) -> float | None:
    """Least-squares slope of log |error| against log cell size over the sweep (None with
    fewer than two points of distinct cell size or a zero error)."""
    pts = [(p.cell_size, abs(p.error)) for p in points if p.error and p.cell_size > 0]
    if len({h for h, _ in pts}) < 2:
        return None
    h, e = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(h, e, 1)[0])


def pareto_front(points) -> list:
    """The sweep points no other point beats in both |error| and wall time."""
    return [p for p in points
            if not any(q is not p and abs(q.error) <= abs(p.error) and q.wall_s <= p.wall_s
                       and (abs(q.error) < abs(p.error) or q.wall_s < p.wall_s)
                       for q in points)]


def on_front_note(points, default, task: str) -> str:
    """A sentence saying whether the point at ``default`` resolution is on the sweep's
    Pareto front (error against wall time) and what it costs and gives."""
    p = min(points, key=lambda q: abs(q.resolution - default))
    front = pareto_front(points)
    where = "on" if p in front else "not on"
    return (f"{task}: the {p.resolution:g} point is {where} the Pareto front "
            f"(|error| {abs(p.error):.2%}, {p.wall_s:.2g} s)")


def register(fn):
    """Add a check function to the suite (a decorator); its name is the function's name
    without a ``check_`` prefix."""
    name = fn.__name__.removeprefix("check_")
    _REGISTRY[name] = fn
    return fn


def timed(fn, *args):
    """``(result, seconds)`` of ``fn(*args)`` with the result's arrays waited for."""
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def checks(tasks: bool = True) -> dict:
    """Name -> check function: the solver checks and, with ``tasks``, the task-level rows of
    :mod:`.tasks` (which import dax-tasks)."""
    from . import cloth, fluid, gradients, solid  # noqa: F401  (they register themselves)

    found = dict(_REGISTRY)
    if tasks:
        from . import tasks as task_rows

        for fn in task_rows.checks():
            found[fn.__name__.removeprefix("check_")] = fn
    return found


__all__ = ["LEVELS", "Point", "Result", "checks", "convergence_order",
           "on_front_note", "pareto_front", "register", "timed"]
