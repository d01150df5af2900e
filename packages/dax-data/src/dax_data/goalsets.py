"""Goal sets: each task's goal particle set written in dax-tasks' goal-file format.

``write_goals(["fold_cloth1"], out_dir)`` computes each goal with the task's own canonical
motion (:func:`dax_tasks.core.goals.compute_goal`: the env's ``canonical_goal()``, the code the
task itself falls back to, not a second copy) and writes it with
:func:`dax_tasks.core.goals.save_goal` (atomic) under the name
:func:`dax_tasks.core.goals.goal_file` gives, so a task reads it with
``dax_tasks.make(name, goal_path=file)``, or from the cache when ``out_dir`` is
``$DAX_CACHE_DIR/goals``.
"""

from __future__ import annotations

import time
from pathlib import Path

from . import __version__


def task_names(task: str) -> list:
    """``[task]``, or every registered task (:func:`dax_tasks.available`: the nine benchmark
    tasks and any registered in this process) for ``"all"``; ``ValueError`` listing them
    for a name that is not registered."""
    import dax_tasks

    registered = dax_tasks.available()
    if task == "all":
        return list(registered)
    if task not in registered:
        raise ValueError(f"unknown task {task!r}; valid: all, {', '.join(registered)}")
    return [task]


def write_goal(name: str, out_dir, spec=None) -> dict:
    """Compute and write the goal of task ``name`` (default spec unless ``spec``) into
    ``out_dir``; returns ``{"task", "path", "points", "seconds"}``."""
    import dax_tasks
    from dax_tasks.core import goals

    spec = dax_tasks.get_spec(name) if spec is None else spec
    env = dax_tasks.env_class(name)(spec)
    t0 = time.perf_counter()
    pts = goals.compute_goal(env)
    prov = goals.provenance(spec, f"canonical_goal() of dax_tasks {type(env).__name__} "
                            f"({name}), written by dax-data goals", dax_data=__version__)
    path = goals.save_goal(goals.goal_file(spec, Path(out_dir)), pts, prov)
    return {"task": name, "path": str(path), "points": int(pts.shape[0]),
            "seconds": time.perf_counter() - t0}


def write_goals(names, out_dir) -> list:
    return [write_goal(n, out_dir) for n in names]
