"""Benchmark of the imitation-learning methods (JSON): Transporter networks' training time
per epoch and inference time per action, ILD's time and memory per update.

* ``transporter`` / ``transporter_rgb``: an epoch is one pass over the demonstrated steps
  (``ceil(M / batch_size)`` Adam steps, M = 10 demonstrations x the horizon); its time is
  ``(t(3 epochs) - t(1 epoch)) / 2`` of the jitted training (initialisation cancels), the
  median of ``--reps`` calls after compilation. Inference: one jitted ``act`` on one
  picture (both networks, the pick's argmax, the transport's correlations), the median of
  at least 20 calls and 1 s.
* ``ild``: as :mod:`benchmarks.rl_speed` (time per update, one episode per env;
  XLA's scratch memory of the one-update program, the process's peak resident memory).

The demonstrations come from the standard sets (made or reused in ``--demos``).

    python -m benchmarks.il_speed --json --tasks fold_cloth1 --methods transporter,ild
"""

from __future__ import annotations

import argparse
import math
import sys

import jax

import dax_tasks
from benchmarks._timing import emit, median_time, peak_rss_mb, timed_compile
from benchmarks.rl_speed import measure as measure_updates
from benchmarks.rl_speed import parse_sets
from dax_algos import learner, registry
from dax_algos.il import demos, transporter


def _data(env, method, config, demo_dir):
    runnable = registry.get(method).build(env, config)
    path = demos.locate(env, runnable.demos, demo_dir)
    return runnable.demos.load(env, path)


def measure_transporter(task: str, method: str, reps: int = 3, overrides=None,
                        demo_dir=None) -> dict:
    env = dax_tasks.make(task)
    m = registry.get(method)
    base = m.config("full", task, **(overrides or {}))
    data = _data(env, method, base, demo_dir)
    samples = int(data.obs.shape[0])
    per_epoch = math.ceil(samples / base.batch_size)
    record = {"task": task, "method": method, "samples": samples,
              "adam_steps_per_epoch": per_epoch}
    times = {}
    for epochs in (1, 3):
        cfg = m.config("full", task, **{**(overrides or {}), "train_steps": per_epoch * epochs})
        fit = jax.jit(lambda k, d, cfg=cfg: transporter.fit(k, d, cfg))
        compiled, compile_s = timed_compile(fit, jax.random.PRNGKey(0), data)
        times[epochs], _ = median_time(
            lambda c=compiled: jax.block_until_ready(c(jax.random.PRNGKey(0), data)), reps)
        record[f"compile_s_{epochs}"] = round(compile_s, 3)
        if epochs == 3:
            params = compiled(jax.random.PRNGKey(0), data)[0]
    epoch_s = max((times[3] - times[1]) / 2, 1e-9)
    act = jax.jit(transporter.make_act(env, base))
    policy = learner.Policy(params, None)
    obs = data.obs[0]
    act_compiled, act_compile_s = timed_compile(act, policy, obs)
    act_s, _ = median_time(lambda: act_compiled(policy, obs), 20, min_time=1.0)
    record.update(epoch_s=round(epoch_s, 4), adam_step_ms=round(1e3 * epoch_s / per_epoch, 2),
                  inference_ms_per_action=round(1e3 * act_s, 3),
                  inference_compile_s=round(act_compile_s, 3),
                  config={k: (list(v) if isinstance(v, tuple) else v)
                          for k, v in vars(base).items()},
                  peak_rss_mb=round(peak_rss_mb(), 1), device=str(jax.devices()[0]))
    return record


def render_table(path) -> str:
    """The Markdown table of a file of :func:`main`'s JSON lines: per method and task, the
    training cost (Transporter: seconds per epoch over the demonstrated steps and per Adam
    step; ILD: seconds per update, as :func:`benchmarks.rl_speed.render_table`), the
    inference time per action (Transporter), the compile time and the process's peak
    resident memory so far; the device and the file's date under the table."""
    from benchmarks._report import file_date, read_result
    from benchmarks.rl_speed import _s, update_label

    path, recs = read_result(path)
    out = ["| method | task | training | per action | compile [s] | process peak RSS so "
           "far |", "|---|---|---|---|---|---|"]
    for r in recs:
        if "epoch_s" in r:
            train = (f"{_s(r['epoch_s'])} s per epoch ({r['samples']} samples, "
                     f"{r['adam_steps_per_epoch']} Adam steps of "
                     f"{r['config'].get('batch_size')}: {r['adam_step_ms']:.0f} ms each)")
            act = f"{r['inference_ms_per_action']:.1f} ms"
        else:
            train = (f"{_s(r['update_s'])} s per update ({update_label(r)}), XLA scratch "
                     f"{r.get('xla_temp_mb', '-')} MiB")
            act = "-"
        out.append(f"| {r['method']} | {r['task']} | {train} | {act} | "
                   f"{_s(r['compile_s_1'])} | {r['peak_rss_mb'] / 1e3:.2f} GB |")
    devices = sorted({r.get("device", "?") for r in recs})
    out += ["", "Epoch and update times: (t(3) − t(1)) / 2 of the jitted training, each the "
            "median of the run's calls after compilation; per action: one jitted `act` on "
            "one picture, the median of at least 20 calls and 1 s. "
            f"{', '.join(devices)}; the file does not record the machine's load. "
            f"`{path.as_posix()}` ({file_date(path) or 'date not recorded'})."]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.il_speed",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="fold_cloth1")
    p.add_argument("--methods", default="transporter,transporter_rgb,ild")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--demos", default=None, help="demonstration directory (default: the "
                                                 "cache, $DAX_CACHE_DIR/demos)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="config override (Python literal), e.g. --set train_steps=500")
    p.add_argument("--json", action="store_true", help="one JSON line per measurement")
    args = p.parse_args(argv)
    overrides = parse_sets(args.set)
    for task in args.tasks.split(","):
        for method in args.methods.split(","):
            print(f"{task} / {method} ...", file=sys.stderr)
            if method.startswith("transporter"):
                record = measure_transporter(task, method, args.reps, overrides, args.demos)
            else:
                env = dax_tasks.make(task)
                config = registry.get(method).config("full", task, **overrides)
                data = _data(env, method, config, args.demos)
                record = measure_updates(task, method, args.reps, overrides, data=(data,))
            emit(record, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
