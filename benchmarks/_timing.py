"""Timing helpers for benchmark scripts: medians of repeated calls, peak memory, and one
JSON line per record. Speed is measured with these and printed, never asserted in tests."""

from __future__ import annotations

import contextlib
import fcntl
import json
import resource
import time

import jax
import numpy as np


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far [MiB]."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def median_time(fn, reps: int, min_time: float = 0.0, max_reps: int = 50,
                clock=time.perf_counter):
    """Median time [s] of ``fn()`` (its result waited for with ``jax.block_until_ready``)
    over at least ``reps`` calls and ``min_time`` seconds, at most ``max_reps`` calls;
    returns ``(median, all times)``. ``clock``: wall time by default; ``time.process_time``
    counts the CPU time of every thread of the process (steadier on a shared machine, and
    equal to the wall time of a process pinned to one core that nothing else preempts)."""
    times = []
    start = time.perf_counter()
    while len(times) < reps or time.perf_counter() - start < min_time:
        t0 = clock()
        jax.block_until_ready(fn())
        times.append(clock() - t0)
        if len(times) >= max_reps:
            break
    return float(np.median(times)), times


@contextlib.contextmanager
def timing_lock(path):
    """Hold an exclusive lock on the file ``path`` (created if missing) for the block, so
    that processes sharing one accelerator time their calls one at a time while they
    compile in parallel; ``path=None`` holds nothing."""
    if path is None:
        yield
        return
    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def timed_compile(fn, *args):
    """``(compiled, seconds)``: ``fn`` (a ``jax.jit`` function) lowered and compiled ahead
    of time for ``args``."""
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    return compiled, time.perf_counter() - t0


def grad_vs_forward(loss, arg, reps: int) -> tuple[dict, object]:
    """Time ``jax.grad(loss)(arg)`` against ``loss(arg)``, both compiled ahead of time and
    called alternately ``reps`` times so that their ratio sees one machine state. Returns
    ``(record, gradient)``; the record holds the medians ``grad_s`` and ``forward_s`` [s],
    ``grad_over_forward``, the gradient's ``compile_s`` and its XLA temporaries
    ``xla_temp_mb`` [MiB]."""
    grad, compile_s = timed_compile(jax.jit(jax.grad(loss)), arg)
    mem = grad.memory_analysis()
    g = jax.block_until_ready(grad(arg))
    fwd, _ = timed_compile(jax.jit(loss), arg)
    jax.block_until_ready(fwd(arg))
    grad_times, fwd_times = [], []
    for _ in range(max(reps, 1)):
        fwd_times.append(median_time(lambda: fwd(arg), 1)[0])
        grad_times.append(median_time(lambda: grad(arg), 1)[0])
    med, fwd_med = float(np.median(grad_times)), float(np.median(fwd_times))
    return dict(grad_s=med, forward_s=fwd_med, grad_over_forward=med / fwd_med,
                compile_s=compile_s,
                xla_temp_mb=None if mem is None else mem.temp_size_in_bytes / 2 ** 20), g


def emit(record: dict, as_json: bool) -> None:
    """Print ``record`` as one JSON line (``as_json``) or as aligned ``key: value`` lines."""
    if as_json:
        print(json.dumps(record), flush=True)
    else:
        for k, v in record.items():
            print(f"{k:>24}: {v}")
