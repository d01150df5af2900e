"""Benchmark of the reinforcement-learning methods' training speed and memory (JSON).

Per task and method, with the method's full-budget config (``--set`` overrides fields):
training throughput in environment steps per second, the time of one training update,
and memory: XLA's own accounting of the compiled one-update program (``xla_temp_mb``,
its scratch memory, the part that grows with the backpropagation horizon) and the
process's peak resident memory so far. The time per update is measured as ``(t(3
updates) - t(1 update)) / 2`` of the whole jitted ``train`` (so initialisation, reset and
evaluation cancel), each the median of ``--reps`` calls after compilation.

    python -m benchmarks.rl_speed --json --tasks fold_cloth1,whip_rope --methods ppo
    python -m benchmarks.rl_speed --json --tasks whip_rope --methods apg,shac

Speed is measured here, never asserted in tests.
"""

from __future__ import annotations

import argparse
import ast
import sys

import jax

import dax_tasks
from benchmarks._timing import emit, median_time, peak_rss_mb, timed_compile
from dax_algos import registry

#: the methods this command measures (:mod:`benchmarks.il_speed` measures ILD's updates
#: with its demonstrations, through :func:`measure`)
RL_METHODS = ("ppo", "apg", "shac")


def _steps_per_update(method: str, config, env) -> int:
    if method == "ppo":
        return config.num_envs * config.unroll_length
    if method == "ild":  # one episode per env and update, in windows
        return config.num_envs * env.horizon
    return config.num_envs * config.window_for(env)


def config_for_updates(method: str, task: str, env, updates: int, overrides=None, **fields):
    """``(config, steps per update)``: ``method``'s full-budget config on ``task`` (with
    ``overrides``) whose ``total_env_steps`` is ``updates`` updates' worth, ``fields`` set
    on top (what :func:`measure` and :mod:`benchmarks.profile_fusions` train)."""
    m = registry.get(method)
    overrides = overrides or {}
    per = _steps_per_update(method, m.config("full", task, **overrides), env)
    config = m.config("full", task, **{**overrides, "total_env_steps": per * updates, **fields})
    return config, per


def measure(task: str, method: str, reps: int = 3, overrides: dict | None = None,
            task_overrides: dict | None = None, data=()) -> dict:
    """One record (see the module docstring); ``data``: what the method's ``train`` takes
    after ``(key, params)`` (ILD's demonstration)."""
    env = dax_tasks.make(task, **(task_overrides or {}))
    m = registry.get(method)
    base = m.config("full", task, **(overrides or {}))
    per = _steps_per_update(method, base, env)
    params = env.default_params
    record = {"task": task, "method": method, "steps_per_update": per}
    times = {}
    for updates in (1, 3):
        cfg, _ = config_for_updates(method, task, env, updates, overrides)
        train = m.learner.make_train(env, cfg)
        fn = jax.jit(train)
        compiled, compile_s = timed_compile(fn, jax.random.PRNGKey(0), params, *data)
        times[updates], _ = median_time(
            lambda c=compiled: jax.block_until_ready(c(jax.random.PRNGKey(0), params, *data)),
            reps)
        record[f"compile_s_{updates}"] = round(compile_s, 3)
        if updates == 1:
            mem = compiled.memory_analysis()
            if mem is not None:
                record["xla_temp_mb"] = round(mem.temp_size_in_bytes / 2**20, 1)
                record["xla_argument_output_mb"] = round(
                    (mem.argument_size_in_bytes + mem.output_size_in_bytes) / 2**20, 1)
    per_update = max((times[3] - times[1]) / 2, 1e-9)
    record.update(update_s=round(per_update, 4), env_steps_per_s=round(per / per_update, 1),
                  config={k: (list(v) if isinstance(v, tuple) else v)
                          for k, v in vars(base).items()},
                  peak_rss_mb=round(peak_rss_mb(), 1), device=str(jax.devices()[0]))
    return record


def parse_sets(items) -> dict:
    """Config overrides from ``--set FIELD=VALUE`` items (VALUE a Python literal)."""
    overrides = {}
    for item in items:
        name, _, value = item.partition("=")
        overrides[name] = ast.literal_eval(value)
    return overrides


def _s(x: float) -> str:
    """Seconds with three significant figures."""
    return f"{x:#.3g}".rstrip(".")


def update_label(r: dict) -> str:
    """What one update of record ``r`` is: its envs times the env steps each takes, and
    the backpropagation window where the config has one shorter than that."""
    envs = r["config"].get("num_envs") or 1
    steps = r["steps_per_update"] // envs
    window = r["config"].get("window")
    w = f", window {window}" if window and window < steps else ""
    return f"{envs} envs × {steps} steps{w}"


def render_table(path) -> str:
    """The Markdown table of a file of :func:`main`'s JSON lines: per task and method, the
    env steps of one training update, its time, the env steps per second, XLA's scratch
    memory of the one-update program and its compile time; the device, the process's
    peak memory and the file's date under the table."""
    from benchmarks._report import file_date, read_result

    path, recs = read_result(path)
    out = ["| task | method (one update) | env steps per update | time per update [s] | "
           "env steps/s | XLA scratch [MiB] | compile [s] |", "|---|---|---|---|---|---|---|"]
    for r in recs:
        out.append(f"| {r['task']} | {r['method']} ({update_label(r)}) | "
                   f"{r['steps_per_update']} | {_s(r['update_s'])} | "
                   f"{_s(r['env_steps_per_s'])} | {r.get('xla_temp_mb', '-')} | "
                   f"{_s(r['compile_s_1'])} |")
    devices = sorted({r.get("device", "?") for r in recs})
    rss = [r["peak_rss_mb"] for r in recs if r.get("peak_rss_mb")]
    out += ["", "Time per update = (t(3 updates) − t(1 update)) / 2 of the jitted `train`, "
            "each the median of the run's calls after compilation (initialisation, reset "
            "and evaluation cancel), with each method's full-budget config; XLA scratch: "
            "the compiled one-update program's temporaries. "
            f"{', '.join(devices)}, process peak RSS up to {max(rss, default=0):.0f} MB; "
            f"the file does not record the machine's load. `{path.as_posix()}` "
            f"({file_date(path) or 'date not recorded'})."]
    return "\n".join(out) + "\n"


def _mean_range(times) -> str:
    """``"mean (min–max)"`` of ``times`` [s], or the one time."""
    mean = sum(times) / len(times)
    return f"{_s(mean)} ({_s(min(times))}–{_s(max(times))})" if len(times) > 1 else _s(mean)


def render_before_after(path) -> str:
    """The Markdown table of a before/after comparison: JSON lines of :func:`measure`
    records (RL and ILD alike) each tagged with ``code`` ("before" or "after"), its
    ``commit``, the ``arm`` it ran in (arms interleaved, e.g. before, after, after, before,
    so that a drift in the machine's speed falls on both) and the 1-minute load when the
    arm started. Per task and method: the mean time per update of each code over its arms
    with the range, the factor before ÷ after, and XLA's scratch memory of the one-update
    program before → after."""
    from benchmarks._report import file_date, read_result
    from benchmarks.before_after import arm_order

    path, recs = read_result(path)
    pairs: dict = {}
    for r in recs:
        if "update_s" in r:  # the file may hold other benchmarks' records too
            pairs.setdefault((r["task"], r["method"]), {}).setdefault(r["code"], []).append(r)
    out = ["| task | method (one update) | before: time per update [s] | after [s] | "
           "before ÷ after | XLA scratch before → after [MiB] |",
           "|---|---|---|---|---|---|"]
    for (task, method), by in pairs.items():
        if set(by) != {"before", "after"}:
            continue
        t = {c: [r["update_s"] for r in by[c]] for c in by}
        mean = {c: sum(v) / len(v) for c, v in t.items()}
        mem = " → ".join(str(by[c][0].get("xla_temp_mb", "-")) for c in ("before", "after"))
        out.append(f"| {task} | {method} ({update_label(by['after'][0])}) | "
                   f"{_mean_range(t['before'])} | {_mean_range(t['after'])} | "
                   f"{mean['before'] / mean['after']:.2f} | {mem} |")
    order = arm_order(recs)
    devices = sorted({r.get("device", "?") for r in recs if "update_s" in r})
    out += ["", "Time per update as in the table above, the mean over each code's arms "
            f"(range in brackets); arms in the order run: {order}. {', '.join(devices)}. "
            f"`{path.as_posix()}` ({file_date(path) or 'date not recorded'})."]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.rl_speed",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="fold_cloth1,whip_rope")
    p.add_argument("--methods", default="ppo,apg,shac")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="config override (Python literal), e.g. --set num_envs=64")
    p.add_argument("--json", action="store_true", help="one JSON line per measurement")
    args = p.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]
    other = [m for m in methods if m not in RL_METHODS]
    if other:
        p.error(f"--methods {','.join(other)}: not a reinforcement-learning method (valid: "
                f"{', '.join(RL_METHODS)}); ILD and Transporter train on demonstrations, "
                f"measured by python -m benchmarks.il_speed")
    overrides = parse_sets(args.set)
    for task in args.tasks.split(","):
        for method in methods:
            print(f"{task} / {method} ...", file=sys.stderr)
            emit(measure(task, method, args.reps, overrides), args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
