"""What changes on an accelerator: run-to-run determinism, agreement with the CPU, and the
price of deterministic scatters, on the solvers' benchmark scenes and one task gradient.

Workloads (each one jitted program, compiled ahead of time):

=============  ==========================================================================
mpm_fluid      the peers' MPM block drop, fluid, 8192 particles, 32^3, 500 substeps:
               final positions (the side-by-side agreement run)
mpm_elastic    the same scene, fixed-corotated elastic
cloth          the peers' 64x64 cloth drop, 1000 substeps (stencil path, no scatter)
mpm_grad       d(mean height after 100 substeps)/d(initial velocities), fluid scene
cloth_grad     d(mean height after 1000 substeps)/d(initial velocities), cloth scene
task_grad      Whip-Rope, 8 rollouts x 10 env steps: the summed reward's gradient wrt the
               actions (``dax_tasks.core.distributed.rollout_gradient_fn``)
=============  ==========================================================================

Each configuration runs in its own process: ``cpu`` (``JAX_PLATFORMS=cpu``), and for the
accelerator ``gpu`` (XLA's defaults) and ``gpu-det``
(``XLA_FLAGS=--xla_gpu_deterministic_ops=true``). A process runs every workload
``--repeats`` times and records per workload: the median call time, whether all repeats
gave the same bits (and the largest difference between them), and the results, saved to a
temporary ``.npz``. The parent then compares every configuration with ``cpu``: the largest
absolute difference of the result arrays, the mean position's difference (the quantity the
side-by-side agreement reads, in metres) and, for gradients, the relative difference.

    python -m benchmarks.accelerator --configs cpu,gpu,gpu-det --out RESULT.json

On a machine without an accelerator, ``--configs cpu`` checks CPU determinism alone.
One JSON document to stdout and to ``--out``; progress to stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

from benchmarks._report import write_report
from dax_physics.precision import DETERMINISTIC_FLAG

WORKLOADS = ("mpm_fluid", "mpm_elastic", "cloth", "mpm_grad", "cloth_grad", "task_grad")
CONFIGS = {
    "cpu": {"JAX_PLATFORMS": "cpu"},
    "gpu": {"JAX_PLATFORMS": "cuda"},
    "gpu-det": {"JAX_PLATFORMS": "cuda", "XLA_FLAGS": DETERMINISTIC_FLAG},
}


def build(name):
    """``(jitted fn, args)`` of one workload; the fn returns a dict of arrays."""
    import jax
    import jax.numpy as jnp

    if name in ("mpm_fluid", "mpm_elastic", "mpm_grad"):
        from benchmarks.physics import block_drop_scene
        from dax_physics import mpm

        cfg, state = block_drop_scene("elastic" if name == "mpm_elastic" else "fluid",
                                      32, 8192)
        if name == "mpm_grad":
            def loss(v0):
                return jnp.mean(mpm.rollout(cfg, cfg.params, state.replace(v=v0), 100).x[:, 2])

            return jax.jit(lambda v0: {"grad": jax.grad(loss)(v0)}), (state.v,)
        return jax.jit(lambda s: {"x": mpm.rollout(cfg, cfg.params, s, 500).x}), (state,)
    if name in ("cloth", "cloth_grad"):
        from benchmarks import cloth_grid as c

        cfg, cloth, state = c.cloth_drop_scene(64)
        if name == "cloth_grad":
            def loss(v0):
                return jnp.mean(c.grid_rollout(cfg, cloth, c.GridState(state.x, v0), 1000).x[2])

            return jax.jit(lambda v0: {"grad": jax.grad(loss)(v0)}), (state.v,)
        return jax.jit(lambda s: {"x": c.grid_rollout(cfg, cloth, s, 1000).x}), (state,)
    if name == "task_grad":
        import dax_tasks
        from dax_tasks.core.distributed import rollout_gradient_fn

        fn = rollout_gradient_fn(dax_tasks.make("whip_rope"), 8, 10)
        return fn, (jax.random.PRNGKey(0),)
    raise ValueError(f"unknown workload {name!r}; valid: {', '.join(WORKLOADS)}")


def child(names, repeats, npz_path) -> dict:
    import jax
    import numpy as np

    from benchmarks._timing import timed_compile

    records, arrays = {}, {}
    for name in names:
        fn, args = build(name)
        compiled, compile_s = timed_compile(fn, *args)
        outs, times = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = jax.block_until_ready(compiled(*args))
            times.append(time.perf_counter() - t0)
            outs.append({k: np.asarray(v) for k, v in out.items()})
        first = outs[0]
        diffs = [max(float(np.max(np.abs(o[k].astype(np.float64) - first[k])))
                     for k in first) for o in outs[1:]]
        records[name] = {
            "compile_s": round(compile_s, 3),
            "first_call_s": round(times[0], 4),
            "median_s": round(float(np.median(times[1:] or times)), 4),
            "repeats_bitwise_equal": all(
                np.array_equal(o[k], first[k]) for o in outs[1:] for k in first),
            "repeats_max_abs_diff": max(diffs, default=0.0),
            "finite": all(bool(np.all(np.isfinite(a))) for a in first.values()),
        }
        for k, a in first.items():
            arrays[f"{name}.{k}"] = a
        print(f"  {name}: {json.dumps(records[name])}", file=sys.stderr, flush=True)
    np.savez(npz_path, **arrays)
    dev = jax.devices()[0]
    return {"backend": jax.default_backend(), "device_kind": dev.device_kind,
            "jax": jax.__version__, "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "workloads": records}


def _mean_position(x):
    """Mean of positions stored (N, 3) (particles) or (3, n, m) (the grid cloth)."""
    return (x.reshape(3, -1).T if x.ndim == 3 else x.reshape(-1, 3)).mean(0)


def compare(ref, other) -> dict:
    """Differences of ``other``'s results from ``ref``'s (both npz mappings)."""
    import numpy as np

    out = {}
    for key in ref.files:
        if key not in other.files:
            continue
        a, b = ref[key].astype(np.float64), other[key].astype(np.float64)
        rec = {"max_abs_diff": float(np.max(np.abs(a - b)))}
        if key.endswith(".x"):
            rec["mean_position_diff_m"] = float(np.max(np.abs(
                _mean_position(a) - _mean_position(b))))
        else:
            rec["relative_diff"] = float(np.linalg.norm(a - b) / max(np.linalg.norm(a), 1e-30))
        out[key] = rec
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--configs", default="cpu,gpu,gpu-det",
                   help=f"comma-separated subset of {','.join(CONFIGS)}; the first is the "
                        "reference the others are compared with")
    p.add_argument("--workloads", default=",".join(WORKLOADS))
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--timeout", type=float, default=1800, help="seconds per configuration")
    p.add_argument("--out", default=None)
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    names = [w for w in args.workloads.split(",") if w]
    for w in names:
        if w not in WORKLOADS:
            p.error(f"unknown workload {w!r}; valid: {', '.join(WORKLOADS)}")
    if args.repeats < 2:
        p.error(f"--repeats must be >= 2 to compare repeats, got {args.repeats}")
    if args.child:
        print(json.dumps(child(names, args.repeats, args.child)), flush=True)
        return 0
    configs = [c for c in args.configs.split(",") if c]
    for c in configs:
        if c not in CONFIGS:
            p.error(f"unknown config {c!r}; valid: {', '.join(CONFIGS)}")
    import numpy as np

    doc = {"benchmark": "accelerator", "workloads": names, "repeats": args.repeats,
           "command": "python -m benchmarks.accelerator " + " ".join(
               argv if argv is not None else sys.argv[1:]),
           "configs": {}, "versus_" + configs[0]: {}}
    with tempfile.TemporaryDirectory() as tmp:
        for c in configs:
            print(f"{c}:", file=sys.stderr, flush=True)
            env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS",)}
            env.update(CONFIGS[c])
            npz = os.path.join(tmp, f"{c}.npz")
            cmd = [sys.executable, __file__, "--child", npz, "--workloads", ",".join(names),
                   "--repeats", str(args.repeats)]
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True,
                                  timeout=args.timeout)
            sys.stderr.write(proc.stderr[-4000:])
            if proc.returncode != 0:
                doc["configs"][c] = {"error": f"exit {proc.returncode}",
                                     "stderr_tail": proc.stderr[-2000:]}
                continue
            doc["configs"][c] = json.loads(proc.stdout.strip().splitlines()[-1])
        ref_path = os.path.join(tmp, f"{configs[0]}.npz")
        if os.path.exists(ref_path):
            with np.load(ref_path) as ref:
                for c in configs[1:]:
                    path = os.path.join(tmp, f"{c}.npz")
                    if os.path.exists(path):
                        with np.load(path) as other:
                            doc["versus_" + configs[0]][c] = compare(ref, other)
    write_report(doc, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
