"""Scaling over devices: a batch of rollouts forward and backward on 1, 2 and 4 devices.

The workload is the literature's headline one: ``--rollouts`` (128) rollouts of
``--steps`` (80) env steps with uniform random actions, and the gradient of the summed
reward wrt every action (:func:`dax_tasks.core.distributed.rollout_gradient_fn`: one jitted
program, the batch split over the devices by :mod:`dax_tasks.core.sharding`). The task is
Whip-Rope at its default resolution (an MPM rope of 288 particles, velocity actions; the
JSON files of 2026-11-24 were measured on the Whip-Rope before dax-tasks 0.2.0, 16 substeps
per env step, today's has 29): its per-step action gradient is the quantity the
literature times, and its step is cheap enough for long rollouts (a cloth task needs 700
substeps per pick-and-place step and has a horizon of 3 to 10). Steps past the horizon are
simulated like the others.

Each device count runs in its own process (the count is fixed when JAX starts:
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` on CPU; on a machine with N GPUs
pass ``--platform gpu``, and the devices are real). Per count: the compile time (lowering
and compiling, apart), the median of ``--reps`` timed calls, the process's peak resident
memory, the accelerator's peak allocated memory per device (GPU only), and XLA's planned
memory per device (arguments, outputs, temporaries), and the
summed reward and gradient norm (the same on every count, a check that the runs did the
same work), and the machine's 1-minute load average before and after (other jobs on the
cores slow the timings). One JSON document to stdout and to ``--out``.

Forced host devices share the machine's cores: on CPU this measures what splitting costs
and gains on the same cores, not the speed-up of more hardware.

    python -m benchmarks.scaling --devices 1,2,4 --rollouts 128 --steps 80 --reps 3 \\
        --out benchmarks/results/DATE-scaling.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time

from benchmarks._report import write_report


def child(args) -> dict:
    import jax
    import numpy as np

    import dax_tasks
    from benchmarks._timing import median_time, peak_rss_mb, timed_compile
    from dax_tasks.core.distributed import rollout_gradient_fn

    load_before = os.getloadavg()[0]
    env = dax_tasks.make(args.task)
    fn = rollout_gradient_fn(env, args.rollouts, args.steps)
    key = jax.random.PRNGKey(args.seed)
    compiled, compile_s = timed_compile(fn, key)
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(key))
    first_s = time.perf_counter() - t0
    run_s, times = median_time(lambda: compiled(key), reps=args.reps)
    mem = compiled.memory_analysis()
    grad = np.asarray(out["grad"])
    return {
        "devices": jax.device_count(), "platform": jax.devices()[0].platform,
        "device_kind": jax.devices()[0].device_kind,
        "batch_sharded": str(out["grad"].sharding.spec) if hasattr(
            out["grad"].sharding, "spec") else type(out["grad"].sharding).__name__,
        "compile_s": round(compile_s, 3), "first_call_s": round(first_s, 3),
        "run_s_median": round(run_s, 3), "run_s_all": [round(t, 3) for t in times],
        "env_steps_per_s": round(args.rollouts * args.steps / run_s, 1),
        "peak_rss_mib": round(peak_rss_mb(), 1),
        "device_peak_mib": device_peak_mib(),
        "xla_bytes_per_device": None if mem is None else {
            "arguments": mem.argument_size_in_bytes, "outputs": mem.output_size_in_bytes,
            "temporaries": mem.temp_size_in_bytes},
        "load_avg_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "return": float(out["return"]), "grad_norm": float(np.linalg.norm(grad)),
        "grad_finite": bool(np.all(np.isfinite(grad))),
    }


def device_peak_mib():
    """The accelerator's peak allocated memory per device [MiB] (``memory_stats``; GPUs
    report it, the CPU backend reports nothing: then None, and ``peak_rss_mib`` counts)."""
    import jax

    stats = [d.memory_stats() for d in jax.local_devices()]
    if not all(s and "peak_bytes_in_use" in s for s in stats):
        return None
    return [round(s["peak_bytes_in_use"] / 2 ** 20, 1) for s in stats]


def run_child(args, devices: int) -> dict:
    env = dict(os.environ)
    if args.platform == "cpu":
        flags = re.sub(r"--xla_force_host_platform_device_count=\S+", "",
                       env.get("XLA_FLAGS", ""))
        env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={devices}"
        env["JAX_PLATFORMS"] = "cpu"
    else:
        env["CUDA_VISIBLE_DEVICES"] = ",".join(str(i) for i in range(devices))
    cmd = [sys.executable, __file__, "--child", "--task", args.task, "--rollouts",
           str(args.rollouts), "--steps", str(args.steps), "--reps", str(args.reps),
           "--seed", str(args.seed)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True,
                          timeout=args.timeout)
    if proc.returncode != 0:
        raise SystemExit(f"error: the {devices}-device run exited {proc.returncode}:\n"
                         f"{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _bytes(n: float) -> str:
    """A byte count in MB or GB (decimal), two or three significant figures."""
    return (f"{n / 1e9:#.2g}".rstrip(".") + " GB" if n >= 1e9
            else f"{n / 1e6:#.3g}".rstrip(".") + " MB")


def _sig(x: float, n: int = 3) -> str:
    """``x`` with ``n`` significant figures, trailing zeros kept; whole numbers from 100."""
    return f"{x:.0f}" if abs(x) >= 10 ** (n - 1) else f"{x:#.{n}g}".rstrip(".")


def render_table(*paths) -> str:
    """The Markdown table of :func:`main`'s JSON documents at ``paths``: one row per device
    count of each, with where it ran, the batch, the compile time, the timed calls' median
    (range, count), env steps per second, XLA's temporaries per device, the peak memory
    (the accelerator's per device where measured, else the process's resident memory),
    the 1-minute load before and after, and the summed reward and gradient norm (equal
    work on every count); the task, commands and dates under the table."""
    from benchmarks._report import file_date, load_range, read_result

    out = ["| where | devices | rollouts × steps | compile [s] | run [s] | env steps/s | "
           "XLA temporaries per device | peak memory | 1-min load | summed reward, "
           "gradient norm |", "|---|---|---|---|---|---|---|---|---|---|"]
    sources, tasks = [], set()
    for path in paths:
        path, doc = read_result(path)
        tasks.add(doc["task"])
        cpus = doc.get("machine", {}).get("cpus")
        for r in doc["results"]:
            kind = r.get("device_kind", r.get("platform", "?"))
            where = (f"{cpus}-core CPU, jax {doc['jax']}" if kind == "cpu"
                     else f"{kind}, jax {doc['jax']}")
            runs = r.get("run_s_all") or [r["run_s_median"]]
            spread = f"{_sig(min(runs))}-{_sig(max(runs))}, " if len(runs) > 1 else ""
            peak = (f"{max(r['device_peak_mib']) / 1024:.2g} GiB on the device"
                    if r.get("device_peak_mib") else f"RSS {r['peak_rss_mib'] / 1024:.2g} GiB")
            out.append(f"| {where} | {r['devices']} | {doc['rollouts']} × {doc['steps']} | "
                       f"{_sig(r['compile_s'])} | {_sig(r['run_s_median'])} ({spread}"
                       f"{len(runs)} run{'s' if len(runs) > 1 else ''}) | "
                       f"{_sig(r['env_steps_per_s'])} | "
                       f"{_bytes(r['xla_bytes_per_device']['temporaries'])} | {peak} | "
                       f"{load_range(r.get('load_avg_1min') or [])} | "
                       f"{r['return']:.6g}, {r['grad_norm']:.6g} |")
        sources.append(f"`{path.as_posix()}` ({file_date(path) or 'date not recorded'}: "
                       f"`{doc['command']}`)")
    out += ["", f"{', '.join(sorted(tasks))} at its default resolution of the day, uniform "
            "random actions, the summed reward and its gradient with respect to every "
            "action in one jitted program, the batch split over the devices (forced host "
            "devices on a CPU share its cores); run: the median of the timed calls after "
            "the compile. " + "; ".join(sources) + "."]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--devices", default="1,2,4", help="comma-separated device counts")
    p.add_argument("--task", default="whip_rope")
    p.add_argument("--rollouts", type=int, default=128)
    p.add_argument("--steps", type=int, default=80)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--platform", choices=("cpu", "gpu"), default="cpu")
    p.add_argument("--timeout", type=float, default=3600, help="seconds per device count")
    p.add_argument("--out", help="also write the JSON here")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    for name in ("rollouts", "steps", "reps"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.child:
        print(json.dumps(child(args)), flush=True)
        return 0
    try:
        counts = [int(c) for c in args.devices.split(",")]
    except ValueError:
        p.error(f"--devices takes comma-separated ints, got {args.devices!r}")
    if any(c < 1 for c in counts):
        p.error(f"--devices must be positive, got {args.devices!r}")
    for c in counts:
        if args.rollouts % c:
            p.error(f"--rollouts {args.rollouts} is not a multiple of {c} devices "
                    "(it would run unsplit)")
    results = []
    for c in counts:
        results.append(run_child(args, c))
        print(json.dumps(results[-1]), file=sys.stderr, flush=True)
    import jax

    doc = {"benchmark": "scaling", "task": args.task, "rollouts": args.rollouts,
           "steps": args.steps, "reps": args.reps, "seed": args.seed,
           "platform": args.platform, "jax": jax.__version__,
           "machine": {"cpus": os.cpu_count(), "processor": platform.processor() or
                       platform.machine()},
           "command": "python -m benchmarks.scaling " + " ".join(
               a for a in (argv if argv is not None else sys.argv[1:])),
           "results": results}
    write_report(doc, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
