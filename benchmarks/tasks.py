"""Benchmark of the tasks: per task and batch size, reset time, forward step time,
step-plus-gradient time (gradient of the summed reward with respect to the actions) and
the compile time of each, with the resolution the task runs at. One JSON line per task on
stdout (``--json``); progress on stderr. Speed is measured here, never asserted in tests.

    python -m benchmarks.tasks --json                         # all tasks, batch 1 and 8
    python -m benchmarks.tasks --json --tasks fold_cloth1 --batch 1 --reps 5
    python -m benchmarks.tasks --json --resolution default,reference --batch 1
    python -m benchmarks.tasks resolution --task fold_cloth1 --out DIR
    python -m benchmarks.tasks throughput --out benchmarks/results/DATE-throughput.json

The ``resolution`` subcommand is the speed-versus-accuracy study of one task
(:mod:`benchmarks.resolution`): the expert's episode on a ladder of resolutions,
each compared with a fine reference, one chart and one JSON per task.

The ``throughput`` subcommand (:func:`throughput_main`) is the tracked batched figure:
env steps per second at batch 1, 16 and 64 for every task, forward and with the action
gradient, compile time apart, the load average and the resolution recorded, one JSON
document; a batch too heavy for the machine is recorded as not measured, with the reason.
:func:`render_throughput_table` prints the README's table from that file
(``python -m benchmarks.tables throughput FILE``).

``--resolution reference`` builds each task at the original DaXBench benchmark's particle
or vertex count and substeps per step (``dax_tasks.make(name, resolution="reference")``),
so its time compares with the original's at equal work; every record carries the
original's figures (:data:`DAXBENCH`) beside the measured ones.

Times are medians over at least ``--reps`` calls and ``--min-time`` seconds (at most 50
calls) after the compiled function's first call; compile
times come from lowering and compiling ahead of time (set ``JAX_COMPILATION_CACHE_DIR``
unset to see cold compiles). ``per_env_step_s`` = step time / batch size. The actions
timed are the task's scripted expert's (so the gripper touches the object), else the
middle of the action box. ``grad_finite`` says whether that gradient was finite
(``grad_norm`` is null when it was not, so the output stays strict JSON).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._timing import emit, median_time, peak_rss_mb, timed_compile, timing_lock
from dax_tasks import RESOLUTIONS, TASKS, VmapWrapper, available, make

#: The original DaXBench benchmark, measured on the 2-core CPU class the README's tables
#: use (jax 0.4.13, batch 1, steady env step; noise +-15-20 %): what it simulates per env
#: step and how long a step takes [s] (``grad_s``: step plus gradient, where measured).
#: Cloth: mass-spring; the square cloths are a 16 x 32 mask on an 80 x 80 lattice, 40
#: sub-actions x 50 substeps. MPM: ``grid`` is the grid resolution, ``active`` the cells
#: it simulates.
DAXBENCH = {
    "fold_cloth1": {"model": "mass-spring", "object_points": 512, "substeps": 2000,
                    "dt": 2e-3, "step_s": 0.070, "grad_s": 0.85},
    "fold_cloth3": {"model": "mass-spring", "object_points": 512, "substeps": 2000,
                    "dt": 2e-3, "step_s": 0.070, "grad_s": 0.85},
    "unfold_cloth1": {"model": "mass-spring", "object_points": 512, "substeps": 2000,
                      "dt": 2e-3, "step_s": 0.070, "grad_s": 0.85},
    "unfold_cloth3": {"model": "mass-spring", "object_points": 512, "substeps": 2000,
                      "dt": 2e-3, "step_s": 0.070, "grad_s": 0.85},
    "fold_tshirt": {"model": "mass-spring", "object_points": 3573, "substeps": 2000,
                    "dt": 5e-4, "step_s": 0.664, "grad_s": 5.06},
    "push_rope": {"model": "MPM rope", "object_points": 582, "substeps": 3990, "dt": 5e-5,
                  "grid": 128, "active": [64, 6, 64], "step_s": 19.0},
    "whip_rope": {"model": "MPM", "object_points": 67, "substeps": 70, "dt": 1e-4,
                  "grid": 64, "active": [32, 32, 32], "step_s": 0.085},
    "pour_water": {"model": "MPM liquid", "object_points": 702, "substeps": 23, "dt": 3e-4,
                   "grid": 80, "active": [26, 20, 26], "step_s": 0.130},
    "pour_soup": {"model": "MPM", "object_points": 7631, "substeps": 25, "dt": 4e-4,
                  "grid": 128, "active": [128, 64, 128], "step_s": 6.81},
}

#: Scene fields reported as the task's resolution when the scene has them.
RESOLUTION_FIELDS = ("dx", "dt", "domain", "window", "ppc", "n", "size", "spacing", "shape")


def resolution(env) -> dict:
    """What a task models: object points, substeps per env step and the scene's grid."""
    out = {"object_points": int(env.n_object_points), "substeps": env.spec.substeps,
           "horizon": env.horizon, "action_kind": env.spec.action_kind,
           "sim_time_per_step_s": round(env.dt, 6)}
    scene = env.spec.scene
    if dataclasses.is_dataclass(scene):
        for f in RESOLUTION_FIELDS:
            if hasattr(scene, f):
                v = getattr(scene, f)
                out[f"scene_{f}"] = list(v) if isinstance(v, tuple) else v
    return out


def probe_act(env, batch: int | None):
    """``act(state, params) -> action``: the action a benchmark steps ``env`` with (already
    wrapped to ``batch`` members, ``None``: unbatched): the task's scripted expert's, else
    the middle of the action box, float32, ``(action_dim,)`` or ``(batch, action_dim)``."""
    if env.has_expert:
        return env.expert_action
    mid = jnp.asarray(0.5 * (np.asarray(env.spec.action_low)
                             + np.asarray(env.spec.action_high)), jnp.float32)
    shape = (env.spec.action_dim,) if batch is None else (batch, env.spec.action_dim)

    def act(state, params):
        return jnp.broadcast_to(mid, shape)
    return act


def prepare_batch(env, batch: int | None, grad: bool = True) -> dict:
    """The compiled programs of one env (``batch=None``) or a :class:`VmapWrapper` batch,
    ready to time (:func:`time_batch`): its reset, its step and (``grad``) the step plus
    the gradient of the summed reward with respect to the actions, each compiled ahead of
    time (``compile_*_s`` [s]) and called once, so that no timed call is a first call. The
    params are an argument of every program (data, as a learner passes them). The actions
    are the task's scripted expert's, else the middle of the action box. The gradient's
    call gives ``grad_finite``, ``grad_norm`` (null when not finite) and its XLA
    temporaries ``grad_temp_mb`` [MiB]."""
    if batch is not None:
        env = VmapWrapper(env, batch_size=batch)
    params = env.default_params
    key = jax.random.PRNGKey(0)
    reset, c_reset = timed_compile(jax.jit(env.reset), key, params)
    _, state = reset(key, params)
    action = jax.jit(probe_act(env, batch))(state, params)
    step, c_step = timed_compile(jax.jit(env.step), state, action, params)
    jax.block_until_ready(step(state, action, params))
    prep = {"batch": 1 if batch is None else batch, "reset": (reset, (key, params)),
            "step": (step, (state, action, params)), "grad": None,
            "compile_reset_s": c_reset, "compile_step_s": c_step, "compile_grad_s": None,
            "grad_finite": None, "grad_norm": None, "grad_temp_mb": None}
    if not grad:
        return prep

    def total_reward(a, s, p):
        return jnp.sum(env.step(s, a, p)[2])

    grad_c, c_grad = timed_compile(jax.jit(jax.value_and_grad(total_reward)), action, state,
                                   params)
    g = np.asarray(grad_c(action, state, params)[1])
    finite = bool(np.all(np.isfinite(g)))  # a NaN gradient is reported (null norm), not hidden
    mem = grad_c.memory_analysis()
    prep.update(grad=(grad_c, (action, state, params)), compile_grad_s=c_grad,
                grad_finite=finite, grad_norm=float(np.linalg.norm(g)) if finite else None,
                grad_temp_mb=None if mem is None else mem.temp_size_in_bytes / 2 ** 20)
    return prep


def time_batch(prep: dict, reps: int, min_time: float = 0.0, clock=time.perf_counter,
               lock=None) -> dict:
    """Median call times [s] of a :func:`prepare_batch` result's programs: ``reset_s``,
    ``step_s``, ``per_env_step_s`` and ``step_grad_s`` (null without the gradient), with
    its compile times and gradient checks. ``clock`` times the calls
    (:func:`benchmarks._timing.median_time`); ``lock``: a file whose exclusive lock is held
    while timing (:func:`benchmarks._timing.timing_lock`), None for none."""
    def med(entry):
        fn, args = entry
        return median_time(lambda: fn(*args), reps, min_time, clock=clock)[0]

    with timing_lock(lock):
        t_reset, t_step = med(prep["reset"]), med(prep["step"])
        t_grad = None if prep["grad"] is None else med(prep["grad"])
    b = prep["batch"]
    out = {"batch": b, "reset_s": t_reset, "step_s": t_step, "per_env_step_s": t_step / b,
           "step_grad_s": t_grad}
    out.update({k: prep[k] for k in ("compile_reset_s", "compile_step_s", "compile_grad_s",
                                     "grad_finite", "grad_norm", "grad_temp_mb")})
    return out


def bench_batch(env, batch: int | None, reps: int, min_time: float = 0.0,
                grad: bool = True, clock=time.perf_counter, lock=None) -> dict:
    """Times of one env (``batch=None``) or a :class:`VmapWrapper` batch:
    :func:`time_batch` of :func:`prepare_batch` (``grad=False`` skips the
    step-plus-gradient; its figures are then null)."""
    return time_batch(prepare_batch(env, batch, grad), reps, min_time, clock, lock)


def bench_task(name: str, batches, reps: int, overrides: dict | None = None,
               min_time: float = 0.0, resolution_name: str = "default",
               grad: bool = True, clock=time.perf_counter) -> dict:
    env = make(name, resolution=resolution_name, **(overrides or {}))
    record = {"bench": "task", "task": name, "resolution": resolution_name,
              **resolution(env), "daxbench": DAXBENCH.get(name), "batches": []}
    for b in batches:
        print(f"[benchmarks.tasks] {name} ({resolution_name}) batch {b}",
              file=sys.stderr, flush=True)
        record["batches"].append(bench_batch(env, None if b == 1 else b, reps, min_time,
                                             grad, clock))
    record["clock"] = "process" if clock is time.process_time else "wall"
    record["peak_rss_mb"] = peak_rss_mb()
    record["device"] = str(jax.devices()[0])
    return record


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.tasks", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", default="all",
                   help="comma-separated task names or 'all' (the implemented ones)")
    p.add_argument("--batch", default="1,8", help="comma-separated batch sizes")
    p.add_argument("--reps", type=int, default=3, help="timed calls per measurement (at least)")
    p.add_argument("--min-time", type=float, default=1.0,
                   help="time each measurement for at least this many seconds (at most 50 "
                        "calls); run-to-run noise on 2 shared cores is about 10 %%")
    p.add_argument("--resolution", default="default",
                   help="comma-separated resolutions: 'default' (the task's own) and/or "
                        "'reference' (the original benchmark's points and substeps)")
    p.add_argument("--no-grad", action="store_true",
                   help="skip the step-plus-gradient timing (null in the output)")
    p.add_argument("--clock", choices=("wall", "process"), default="wall",
                   help="wall time (default) or the process's CPU time (steadier on a shared "
                        "machine; pin the process to one core with taskset to compare)")
    p.add_argument("--json", action="store_true", help="one JSON line per task")
    return p


def parse_tasks(text: str) -> list:
    if text == "all":
        return list(available())
    names = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in names if t not in TASKS]
    if bad:
        raise ValueError(f"unknown task(s) {bad}; valid names: {', '.join(TASKS)}")
    return names


def main(argv=None, overrides: dict | None = None) -> list:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["resolution"]:  # the speed-versus-accuracy study of one task
        from benchmarks.resolution import main as resolution_main

        return resolution_main(argv[1:])
    if argv[:1] == ["throughput"]:
        return throughput_main(argv[1:], overrides)
    args = build_parser().parse_args(argv)
    try:
        names = parse_tasks(args.tasks)
        batches = [int(b) for b in args.batch.split(",")]
        resolutions = [r.strip() for r in args.resolution.split(",") if r.strip()]
        bad = [r for r in resolutions if r not in RESOLUTIONS]
        if bad or not resolutions:
            raise ValueError(f"unknown resolution(s) {bad}; valid: {', '.join(RESOLUTIONS)}")
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    if any(b < 1 for b in batches) or args.reps < 1:
        print("error: batch sizes and --reps must be >= 1", file=sys.stderr)
        raise SystemExit(2)
    clock = time.process_time if args.clock == "process" else time.perf_counter
    records = []
    for res in resolutions:
        for name in names:
            rec = bench_task(name, batches, args.reps, overrides, args.min_time, res,
                             not args.no_grad, clock)
            emit(rec, args.json)
            records.append(rec)
    return records


# ------------------------------------------------------------------ batched throughput

#: The batch sizes of the tracked throughput figure.
THROUGHPUT_BATCHES = (1, 16, 64)


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _skip_reason(prev: dict | None, batch: int, limit_s: float, grad: bool,
                 linear: bool = True) -> str | None:
    """Why ``batch`` is not measured, from the last measured row ``prev``, or None. With
    ``linear`` (a CPU, whose call times grow about linearly with the batch) the last call
    time is scaled by the batch ratio, else (an accelerator) taken as it is."""
    if prev is None or not prev.get("measured"):
        return None
    key = "grad_s" if grad and prev.get("grad_s") else "step_s"
    est = prev[key] * (batch / prev["batch"] if linear else 1.0)
    if est > limit_s:
        what = "step-plus-gradient" if key == "grad_s" else "step"
        how = "scaled linearly" if linear else "unscaled"
        return (f"too heavy for this machine: one {what} call would take about {est:.2g} s "
                f"(batch {prev['batch']}'s {prev[key]:.2f} s {how}), over the "
                f"{limit_s:g} s limit per call (--max-call-s)")
    return None


def throughput_row(prep: dict, reps: int, min_time: float, clock=time.perf_counter,
                   lock=None) -> dict:
    """One row of the throughput figure from a :func:`prepare_batch` result (batch 1: the
    env itself, else a :class:`VmapWrapper`): the median call times ``step_s`` /
    ``grad_s`` [s] of the step and of the step plus the gradient of the summed reward with
    respect to the actions; ``steps_per_s`` / ``grad_steps_per_s`` = batch / median; the
    compile times, the gradient's XLA temporaries [MiB]; the 1-minute load average before
    and after; ``lock`` as in :func:`time_batch`."""
    load0 = _load()
    rec = time_batch(prep, reps, min_time, clock, lock)
    batch = rec["batch"]
    return {"batch": batch, "measured": True, "step_s": rec["step_s"],
            "steps_per_s": batch / rec["step_s"], "grad_s": rec["step_grad_s"],
            "grad_steps_per_s": None if rec["step_grad_s"] is None
            else batch / rec["step_grad_s"],
            "compile_step_s": rec["compile_step_s"], "compile_grad_s": rec["compile_grad_s"],
            "grad_temp_mb": rec["grad_temp_mb"], "grad_finite": rec["grad_finite"],
            "peak_rss_mb": peak_rss_mb(), "load_1min": [load0, _load()]}


def _failed(batch: int, err: Exception) -> dict:
    return {"batch": batch, "measured": False,
            "reason": f"failed: {type(err).__name__}: {str(err)[:300]}"}


def throughput(names, batches=THROUGHPUT_BATCHES, reps: int = 3, min_time: float = 0.0,
               resolution_name: str = "default", grad: bool = True, max_call_s: float = 30.0,
               overrides: dict | None = None, clock=time.perf_counter,
               lock=None, barrier=None) -> dict:
    """The throughput document (see :func:`throughput_main`): per task its resolution
    (:func:`resolution`) and one :func:`throughput_row` per batch size, in increasing
    order. On a CPU a batch whose call, scaled linearly from the last measured batch,
    would exceed ``max_call_s`` seconds is recorded ``measured: false`` with the reason
    (on an accelerator, which runs a batch in parallel, the last call time is taken
    unscaled); so is one whose compile or run fails (the error). ``lock``: see
    :func:`time_batch`. ``barrier``: ``(ready, go)`` file paths: every program is compiled
    first, then ``ready`` is created and the timing waits until ``go`` exists (so that
    processes compiling in parallel time on a quiet machine)."""
    device = jax.devices()[0]
    doc = {"bench": "throughput", "date": datetime.date.today().isoformat(),
           "resolution": resolution_name, "batches": sorted(batches), "reps": reps,
           "min_time_s": min_time, "max_call_s": max_call_s,
           "clock": "process" if clock is time.process_time else "wall",
           "device": str(device), "device_kind": device.device_kind,
           "cpu_count": os.cpu_count(),
           "machine": platform.machine(), "jax": jax.__version__,
           # compile times with a persistent cache that holds the program are its load time
           "compilation_cache": bool(jax.config.jax_compilation_cache_dir),
           "load_1min_start": _load(), "tasks": []}
    linear = device.platform == "cpu"
    envs = {name: make(name, resolution=resolution_name, **(overrides or {}))
            for name in names}

    def prepare(name, b):
        print(f"[benchmarks.tasks throughput] {name} ({resolution_name}) batch {b}",
              file=sys.stderr, flush=True)
        try:
            return prepare_batch(envs[name], None if b == 1 else b, grad)
        except Exception as err:  # noqa: BLE001 - recorded, the run goes on
            return err

    preps = {}
    if barrier is not None:
        preps = {(n, b): prepare(n, b) for n in names for b in sorted(batches)}
        ready, go = barrier
        Path(ready).touch()
        while not os.path.exists(go):
            time.sleep(0.5)
    for name in names:
        task = {"task": name, **resolution(envs[name]), "rows": []}
        prev = None
        for b in sorted(batches):
            reason = _skip_reason(prev, b, max_call_s, grad, linear)
            if reason is not None:
                row = {"batch": b, "measured": False, "reason": reason}
            else:
                prep = preps.pop((name, b), None) or prepare(name, b)
                if isinstance(prep, Exception):
                    row = _failed(b, prep)
                else:
                    try:
                        row = throughput_row(prep, reps, min_time, clock, lock)
                    except Exception as err:  # noqa: BLE001 - recorded, the run goes on
                        row = _failed(b, err)
            task["rows"].append(row)
            if row["measured"]:
                prev = row
        doc["tasks"].append(task)
    doc["load_1min_end"] = _load()
    return doc


def throughput_main(argv=None, overrides: dict | None = None) -> dict:
    """``python -m benchmarks.tasks throughput``: prints the throughput document (and
    writes it to ``--out``)."""
    from benchmarks._report import write_report

    p = argparse.ArgumentParser(prog="python -m benchmarks.tasks throughput",
                                description="Env steps per second of every task at batch "
                                            "1, 16 and 64, forward and with the action "
                                            "gradient (one JSON document).")
    p.add_argument("--tasks", default="all")
    p.add_argument("--batch", default=",".join(map(str, THROUGHPUT_BATCHES)))
    p.add_argument("--resolution", default="default", choices=list(RESOLUTIONS))
    p.add_argument("--reps", type=int, default=3, help="timed calls per figure (median)")
    p.add_argument("--min-time", type=float, default=0.0,
                   help="time each figure for at least this many seconds (at most 50 calls)")
    p.add_argument("--max-call-s", type=float, default=30.0,
                   help="do not measure a batch whose call, scaled linearly from the last "
                        "measured batch, would take longer than this [s]")
    p.add_argument("--no-grad", action="store_true")
    p.add_argument("--clock", choices=("wall", "process"), default="wall")
    p.add_argument("--jobs", type=int, default=1,
                   help="compile in this many processes at once (one per task), each "
                        "timing only while it holds a shared lock, so the timed calls "
                        "never overlap: for a machine with many cores and one accelerator")
    p.add_argument("--time-lock", default=None, help=argparse.SUPPRESS)  # set by --jobs
    p.add_argument("--barrier", default=None, help=argparse.SUPPRESS)  # READY,GO: by --jobs
    p.add_argument("--out", default=None, help="write the JSON document here too")
    argv = sys.argv[2:] if argv is None else list(argv)
    args = p.parse_args(argv)
    try:
        names = parse_tasks(args.tasks)
        batches = [int(b) for b in args.batch.split(",")]
    except ValueError as err:
        p.error(str(err))
    if any(b < 1 for b in batches) or args.reps < 1 or args.jobs < 1:
        p.error("batch sizes, --reps and --jobs must be >= 1")
    clock = time.process_time if args.clock == "process" else time.perf_counter
    if args.jobs > 1 and len(names) > 1:
        doc = _throughput_jobs(names, sorted(batches), argv, args.jobs, args.out)
    else:
        doc = throughput(names, batches, args.reps, args.min_time, args.resolution,
                         not args.no_grad, args.max_call_s, overrides, clock,
                         args.time_lock,
                         None if args.barrier is None else args.barrier.split(","))
    doc["command"] = "python -m benchmarks.tasks throughput " + " ".join(argv)
    write_report(doc, args.out)
    return doc


def _without_option(argv: list, name: str) -> list:
    """``argv`` less the option ``name`` and its value (``--name V`` or ``--name=V``)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == name:
            skip = True
        elif not a.startswith(name + "="):
            out.append(a)
    return out


def _throughput_jobs(names: list, batches: list, argv: list, jobs: int,
                     out: str | None = None) -> dict:
    """The throughput document of ``names``, one child process per task
    (``python -m benchmarks.tasks throughput --tasks NAME``, the other options of ``argv``
    passed on), at most ``jobs`` at once. The children compile all their programs in
    parallel; once every running child has (or has exited), they time, one at a time (a
    lock file), so no timed call overlaps another's call or compile when ``jobs`` is at
    least the number of tasks. The children's tasks are merged in the order of ``names``;
    a child that fails leaves its task's rows ``measured: false`` with its exit status.
    ``jobs`` is recorded and the loads span all children. Children do not preallocate
    accelerator memory. With ``out``, the document so far is written there (atomically)
    as each child ends, so a run cut short keeps its finished tasks."""
    import subprocess
    import tempfile

    from dax_tasks.io import atomic_write

    base = argv
    for opt in ("--tasks", "--jobs", "--out", "--time-lock", "--barrier"):
        base = _without_option(base, opt)
    env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    docs = {}

    def merged() -> dict:
        done = [docs[n] for n in names if n in docs and "bench" in docs[n]]
        doc = {k: v for k, v in (done[0] if done else {}).items()
               if k not in ("tasks", "command")}
        doc.update(bench="throughput", batches=batches, jobs=jobs)
        if done:
            doc["load_1min_start"] = min(d["load_1min_start"] for d in done)
            doc["load_1min_end"] = max(d["load_1min_end"] for d in done)
        doc["tasks"] = [t for n in names if n in docs for t in docs[n]["tasks"]]
        return doc

    with tempfile.TemporaryDirectory(prefix="dax-throughput-") as tmp:
        lock = os.path.join(tmp, "timing.lock")
        procs, pending, wave = {}, list(names), 0
        while pending or procs:
            if not procs:  # a new wave of at most `jobs` children, one barrier each
                wave += 1
                go = os.path.join(tmp, f"go.{wave}")
                while pending and len(procs) < jobs:
                    name = pending.pop(0)
                    part = os.path.join(tmp, f"{name}.json")
                    ready = os.path.join(tmp, f"ready.{name}")
                    cmd = [sys.executable, "-m", "benchmarks.tasks", "throughput", *base,
                           "--tasks", name, "--time-lock", lock, "--out", part,
                           "--barrier", f"{ready},{go}"]
                    procs[name] = (subprocess.Popen(cmd, env=env,
                                                    stdout=subprocess.DEVNULL), part, ready)
            time.sleep(1.0)
            if all(os.path.exists(r) or pr.poll() is not None
                   for pr, _, r in procs.values()):
                Path(go).touch()
            for name, (proc, part, _) in list(procs.items()):
                if proc.poll() is None:
                    continue
                del procs[name]
                if proc.returncode == 0 and os.path.exists(part):
                    docs[name] = json.loads(Path(part).read_text())
                else:
                    reason = (f"failed: the child process exited with status "
                              f"{proc.returncode} (its stderr is in the run's log)")
                    docs[name] = {"tasks": [{"task": name, "rows": [
                        {"batch": b, "measured": False, "reason": reason}
                        for b in batches]}]}
                if out:
                    atomic_write(out, json.dumps(merged(), indent=1) + "\n")
    return merged()


def _device_words(doc: dict) -> str:
    """The device of a throughput document in words: its kind where recorded (an
    accelerator's model name), and how the compiles ran when they ran in parallel."""
    kind = doc.get("device_kind")
    words = doc["device"] if not kind or kind == "cpu" else f"{kind} ({doc['device']})"
    if doc.get("jobs", 1) > 1:
        words += (f", compiled in {doc['jobs']} processes at once whose timed calls "
                  "took turns")
    return words


def _rate(x: float | None) -> str:
    """Env steps per second with two or three significant figures."""
    if x is None:
        return "-"
    return f"{x:.0f}" if x >= 100 else f"{x:.3g}"


def render_throughput_table(path) -> str:
    """The Markdown table of a throughput document (:func:`throughput_main`'s JSON file at
    ``path``): one row per task, per batch size its env steps per second forward and, in
    parentheses, with the action gradient; a batch not measured is marked and its reason
    given under the table, with the date, device, load and command of the run."""
    path = Path(path)
    root = Path(__file__).resolve().parent.parent  # a relative path: from the repository
    doc = json.loads((path if path.is_absolute() or path.exists() else root / path)
                     .read_text())
    if doc.get("bench") != "throughput":
        raise ValueError(f"{path}: not a throughput document (bench {doc.get('bench')!r})")
    batches = doc["batches"]
    head = ["task", f"{doc['resolution']}: points, substeps × dt"] + [
        f"batch {b}: env steps/s (with grad)" for b in batches]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    notes = []
    for t in doc["tasks"]:
        res = f"{t['object_points']}, {t['substeps']} × {t['scene_dt'] * 1e3:.3g} ms" \
            if "scene_dt" in t else f"{t['object_points']}, {t['substeps']}"
        cells = [t["task"], res]
        rows = {r["batch"]: r for r in t["rows"]}
        for b in batches:
            r = rows.get(b)
            if r is None:
                cells.append("")
            elif r["measured"]:
                cells.append(f"{_rate(r['steps_per_s'])} ({_rate(r['grad_steps_per_s'])})")
            else:
                notes.append(f"{t['task']} at batch {b}: {r['reason']}.")
                cells.append(f"not measured [{len(notes)}]")
        lines.append("| " + " | ".join(cells) + " |")
    loads = [x for t in doc["tasks"] for r in t["rows"] if r.get("measured")
             for x in r["load_1min"]]
    load = f"{min(loads):.1f}-{max(loads):.1f}" if loads else "-"
    lines += ["", f"Env steps per second = batch / median call time ({doc['reps']} calls "
              f"after an ahead-of-time compile, {doc['clock']} clock); with grad: the step "
              f"plus the gradient of the summed reward with respect to the actions. "
              f"{doc['date']}, {_device_words(doc)} ({doc['cpu_count']} cores, jax "
              f"{doc['jax']}), 1-minute load average {load} during the runs; "
              f"`{path.as_posix()}` (`{doc.get('command', 'benchmarks.tasks throughput')}`)."]
    for i, n in enumerate(notes, 1):
        lines += ["", f"[{i}] {n}"]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()


def _sec(x: float | None) -> str:
    """Seconds with two significant figures (trailing zeros kept), ``-`` when not
    measured."""
    return "-" if x is None else f"{x:#.2g}".rstrip(".")


def _points(r: dict) -> str:
    dt = f" × {r['scene_dt'] * 1e3:.3g} ms" if r.get("scene_dt") else ""
    return f"{r['object_points']}, {r['substeps']}{dt}"


def render_speed_table(path) -> str:
    """The Markdown table of a speed document: ``main``'s JSON records (``records``: one
    per task and resolution; ``pinned``: optional records timed with ``--clock process``
    on one pinned core) gathered in one JSON file with its ``commands``, ``description``
    and the ``uptime`` before each run. One row per task: its default resolution's step,
    step-plus-gradient and batched step times [s, medians], its reference resolution's,
    and DaXBench's own figures (:data:`DAXBENCH`, carried by each record) with DaXBench's
    step time over the reference step's (above 1: this package is faster at equal
    work)."""
    from benchmarks._report import file_date, load_range, read_result

    path, doc = read_result(path)
    recs = doc["records"]
    by = {(r["task"], r["resolution"]): r for r in recs}
    tasks = list(dict.fromkeys(r["task"] for r in recs))
    batches = sorted({b["batch"] for r in recs if r["resolution"] == "default"
                      for b in r["batches"] if b["batch"] != 1})
    head = (["task", "default: points, substeps × dt", "step [s]", "step + grad [s]"]
            + [f"batch {b} step [s]" for b in batches]
            + ["reference: points, substeps × dt", "step [s]", "step + grad [s]",
               "DaXBench: points, substeps", "DaXBench step (grad) [s]",
               "DaXBench / reference step"])
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]

    def one(r, batch=1, key="step_s"):
        row = next((b for b in (r or {}).get("batches", []) if b["batch"] == batch), None)
        return None if row is None else row.get(key)

    for t in tasks:
        d, ref = by.get((t, "default")), by.get((t, "reference"))
        dax = (d or ref or {}).get("daxbench") or {}
        cells = [t, _points(d) if d else "-", _sec(one(d)), _sec(one(d, key="step_grad_s"))]
        cells += [_sec(one(d, b)) for b in batches]
        cells += [_points(ref) if ref else "-", _sec(one(ref)),
                  _sec(one(ref, key="step_grad_s"))]
        if dax:
            grad = f" ({dax['grad_s']})" if dax.get("grad_s") else ""
            ratio = f"{_sec(dax['step_s'] / one(ref))}×" if one(ref) else "-"
            cells += [f"{dax['object_points']}, {dax['substeps']}",
                      f"{dax['step_s']}{grad}", ratio]
        else:
            cells += ["-", "-", "-"]
        lines.append("| " + " | ".join(cells) + " |")
    loads = [float(m) for u in doc.get("uptime_before_each_run", {}).values()
             for m in [u.split("load average:")[1].split(",")[0]] if "load average:" in u]
    clock = {r.get("clock") or "wall" for r in recs}
    device = {r.get("device") for r in recs} - {None}
    lines += ["", f"Medians after an ahead-of-time compile, {'/'.join(sorted(clock))} clock, "
              f"{', '.join(sorted(device)) or 'device not recorded'}; a batched step is "
              f"the whole batch's call. 1-minute load average before the runs: "
              f"{load_range(loads)}. {doc.get('description', '')} "
              f"`{path.as_posix()}` ({file_date(path) or 'date not recorded'}): "
              + "; ".join(f"`{c}`" for c in doc.get("commands", [])) + "."]
    pinned = doc.get("pinned") or []
    if pinned:
        lines += ["", "| pinned to one core, CPU time | resolution: points, substeps × dt | "
                      "step [s] | step + grad [s] |", "| --- | --- | --- | --- |"]
        for r in pinned:
            lines.append(f"| {r['task']} | {r['resolution']}: {_points(r)} | "
                         f"{_sec(one(r))} | {_sec(one(r, key='step_grad_s'))} |")
    return "\n".join(lines) + "\n"
