"""Benchmarks of dax-physics. Each subcommand prints one JSON line (speed is measured here,
never asserted in tests).

    python -m benchmarks.physics mpm-block --material fluid --grid 32 --particles 8192 \\
        --substeps 100 --json
    python -m benchmarks.physics mpm-grad --substeps 100 --checkpoint-segments 10 --json
    python -m benchmarks.physics active-region --json
    python -m benchmarks.physics mpm-study --out bench_out --json
    python -m benchmarks.physics cloth-drop --n 64 --substeps 1000 --json
    python -m benchmarks.physics cloth-fold --json
    python -m benchmarks.physics cloth-sag-study --out bench_out --json

Throughputs are medians over repetitions after a warm-up run; compile time is measured by
lowering and compiling ahead of time. Set ``JAX_COMPILATION_CACHE_DIR`` off (the default)
to see cold compile times.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._timing import emit, grad_vs_forward, median_time, peak_rss_mb
from dax_physics import mpm, sampling
from dax_physics.materials import Material

# --------------------------------------------------------------------------- block drop

def block_drop_scene(material: str, grid: int, particles: int, dtype=jnp.float32):
    """The MPM block-drop scene of the Taichi and Warp reference implementations, z up.

    Domain [0, 1]^3 on grid^3 cells, N uniformly random particles from
    ``numpy.random.default_rng(0).random((N, 3), float32)`` in the cube of side 0.4 at
    (0.30, 0.15, 0.30) in the reference's (x, up, z) order, mapped to (x, z_ref, up) here;
    initial velocity 2 m/s down; dt 1e-4 s; rho 1; particle volume 0.4^3 / N; gravity
    9.8 m/s^2. Fluid: tau = K J (J - 1) I with K = 400 Pa, tension allowed (J > 1) as in
    the references; elastic: fixed-corotated with E = 5e3 Pa, nu = 0.2. The references'
    slip walls constrain the nodes with index < 3 and > grid - 3, which is ``wall_cells =
    2`` here (walls 2 cells from each side: see :mod:`dax_physics.mpm`), so the scene is
    the same at every grid: at grid 16 the cube's lowest particles (0.15 m) sit above the
    wall (0.125 m). The scene needs a grid of at least 14 cells (0.15 m >= 2 / grid).
    """
    if grid < 14:
        raise ValueError(f"the block-drop scene needs a grid of at least 14 cells (its cube "
                         f"starts 0.15 m above the floor, the wall is 2 cells thick), got "
                         f"{grid}")
    rng = np.random.default_rng(0)
    lo = np.array([0.30, 0.15, 0.30], np.float32)
    x_ref = (lo + np.float32(0.4) * rng.random((particles, 3), dtype=np.float32)).astype(
        np.float32)
    x = x_ref[:, [0, 2, 1]]  # (x, up, z) -> (x, y, z) with z up
    v = np.tile(np.array([0.0, 0.0, -2.0], np.float32), (particles, 1))
    if material == "fluid":
        mat = Material("fluid", 1.0, bulk_modulus=400.0)
    elif material == "elastic":
        mat = Material("elastic", 1.0, youngs_modulus=5.0e3, poisson_ratio=0.2)
    else:
        raise ValueError(f"unknown block material {material!r}; valid: fluid, elastic")
    cfg = mpm.MPMConfig(materials=(mat,), dx=1.0 / grid, dt=1e-4, domain=(grid,) * 3,
                        gravity=(0.0, 0.0, -9.8), walls="slip", wall_cells=2, max_speed=2.0,
                        fluid_tension=True)
    state = mpm.init_state(cfg, x, v, vol=0.4 ** 3 / particles, dtype=dtype)
    return cfg, state


def cmd_mpm_block(args):
    cfg, state = block_drop_scene(args.material, args.grid, args.particles)
    params = cfg.params
    n = args.substeps
    run = mpm.rollout
    if args.batch:
        state = jax.tree.map(lambda a: jnp.broadcast_to(a, (args.batch,) + a.shape), state)
        run = jax.jit(jax.vmap(lambda p, s: mpm.rollout(cfg, p, s, n), in_axes=(None, 0)))
        t0 = time.perf_counter()
        compiled = run.lower(params, state).compile()
    else:
        t0 = time.perf_counter()
        compiled = jax.jit(lambda p, s: mpm.rollout(cfg, p, s, n)).lower(params, state).compile()
    compile_s = time.perf_counter() - t0
    out = compiled(params, state)
    jax.block_until_ready(out)

    def go():
        jax.block_until_ready(compiled(params, state))

    med, times = median_time(go, args.reps, args.min_time)
    x = np.asarray(out.x)
    scenes = max(args.batch, 1)
    record = dict(
        bench="mpm-block", material=args.material, grid=args.grid, particles=args.particles,
        substeps=n, batch=args.batch, substeps_per_s=n / med,
        scene_substeps_per_s=scenes * n / med,
        particle_substeps_per_s=scenes * n * args.particles / med,
        compile_s=compile_s, reps=len(times),
        mean_position=x.reshape(-1, 3).astype(np.float64).mean(0).tolist(),
        finite=bool(np.isfinite(x).all()), escaped=bool(np.asarray(out.escaped).any()),
        backend=jax.default_backend(), jax=jax.__version__)
    emit(record, args.json)


# --------------------------------------------------------------------------- gradient memory

def cmd_mpm_grad(args):
    cfg, state = block_drop_scene(args.material, args.grid, args.particles)
    params = cfg.params
    n = args.substeps
    seg = None if args.checkpoint_segments <= 1 else n // args.checkpoint_segments
    if seg is not None and n % args.checkpoint_segments:
        raise SystemExit(f"--substeps {n} must be a multiple of --checkpoint-segments")

    def loss(v0):
        out = mpm.rollout(cfg, params, state.replace(v=v0), n, segment=seg)
        return jnp.mean(out.x[:, 2])

    rss0 = peak_rss_mb()
    timing, g = grad_vs_forward(loss, state.v, args.reps)
    record = dict(
        bench="mpm-grad", material=args.material, grid=args.grid, particles=args.particles,
        substeps=n, checkpoint_segments=args.checkpoint_segments, segment_length=seg,
        **timing, peak_rss_mb=peak_rss_mb(), peak_rss_before_mb=rss0,
        grad_norm=float(jnp.linalg.norm(g)), finite=bool(jnp.all(jnp.isfinite(g))))
    emit(record, args.json)


# --------------------------------------------------------------------------- active region

def rope_scene(window, substeps_dt=1e-4, domain=128, with_colliders=True):
    """An elastic rope lying on a table in a 1 m room of ``domain``^3 cells, spanning about
    32 x 26 x 3 cells, with a capsule pusher moving into it (a Push-Rope scene);
    ``window`` None for the full grid."""
    from dax_physics.colliders import ColliderSpec, ColliderState

    dx = 1.0 / domain
    table_z = 4.0 * dx
    s = np.linspace(0.0, 1.0, 24)
    pts = np.stack([0.40 + 0.22 * s,
                    0.50 + 0.09 * np.sin(2 * np.pi * s),
                    np.full_like(s, table_z + 0.0115)], axis=1)
    x, vol = sampling.capsule_chain(pts, 0.011, dx, ppc=8, seed=0)
    rope = Material("elastic", 1100.0, youngs_modulus=2.0e5, poisson_ratio=0.3)
    specs, cstate = (), None
    if with_colliders:
        specs = (ColliderSpec("plane", (), mode="separate", friction=0.5),
                 ColliderSpec("capsule", (0.01, 0.02), mode="separate", friction=0.3))
        cstate = ColliderState.create(
            [[0.0, 0.0, table_z], [0.51, 0.37, table_z + 0.035]],
            lin_vel=[[0.0, 0.0, 0.0], [0.0, 0.3, 0.0]])
    cfg = mpm.MPMConfig(materials=(rope,), dx=dx, dt=substeps_dt, domain=(domain,) * 3,
                        window=window, gravity=(0.0, 0.0, -9.81), walls="slip",
                        colliders=specs, max_speed=1.0)
    return cfg, mpm.init_state(cfg, x, vol=vol, colliders=cstate)


def cmd_active_region(args):
    results = {}
    finals = {}
    extent = None
    for name, window in (("window", tuple(args.window)), ("full", None)):
        cfg, state = rope_scene(window, with_colliders=not args.no_colliders)
        if extent is None:
            ext = np.ptp(np.asarray(state.x), axis=0) / cfg.dx
            extent = [round(float(e), 1) for e in ext]
        params = cfg.params
        t0 = time.perf_counter()
        compiled = jax.jit(
            lambda p, s, cfg=cfg: mpm.rollout(cfg, p, s, args.substeps)).lower(
                params, state).compile()
        compile_s = time.perf_counter() - t0
        out = compiled(params, state)
        jax.block_until_ready(out)
        med, times = median_time(
            lambda c=compiled, p=params, s=state: jax.block_until_ready(c(p, s)), args.reps, 0.0)
        finals[name] = np.asarray(out.x)
        results[name] = dict(
            grid_cells=list(cfg.window), substeps_per_s=args.substeps / med,
            compile_s=compile_s, escaped=bool(out.escaped), finite=bool(out.finite))
    record = dict(
        bench="active-region", domain_cells=[128] * 3, colliders=not args.no_colliders,
        rope_extent_cells=extent,
        particles=int(finals["full"].shape[0]), substeps=args.substeps, **results,
        speedup=results["window"]["substeps_per_s"] / results["full"]["substeps_per_s"],
        max_abs_position_diff_m=float(np.max(np.abs(finals["window"] - finals["full"]))))
    emit(record, args.json)


# --------------------------------------------------------------------------- speed vs accuracy

def measure_bar(cells: int, ppc: int, dt_fraction: float):
    """The validation suite's free-free bar (:func:`benchmarks.validate.solid.bar_mode`):
    its first longitudinal mode's quarter period against the exact wave speed."""
    from benchmarks.validate.solid import bar_mode

    r = bar_mode(cells, ppc=ppc, dt_fraction=dt_fraction)
    c, exact = r["wave_speed"], r["wave_speed_exact"]
    ok = bool(np.isfinite(c))
    return dict(cells=cells, ppc=ppc, dt=r["dt"], dt_fraction=dt_fraction,
                particles=r["particles"], substeps=r["substeps"], wall_s=r["wall_s"],
                wave_speed=float(c) if ok else None, wave_speed_exact=exact,
                error=float(abs(c - exact) / exact) if ok else None)


def cmd_mpm_study(args):
    rows = []
    for cells in args.cells:
        for ppc in args.ppc:
            for frac in args.dt_fraction:
                rows.append(measure_bar(cells, ppc, frac))
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    ok = [r for r in rows if r.get("error") is not None]
    record = dict(bench="mpm-study", scene="free-free bar, first longitudinal mode, nu=0",
                  known_answer="c = sqrt(E/rho) (quarter period L/(2c))", rows=rows)
    if ok:
        # cheapest configuration within 2 % of the exact wave speed
        good = [r for r in ok if r["error"] <= 0.02]
        if good:
            best = min(good, key=lambda r: r["wall_s"])
            record["cheapest_within_2pct"] = best
    if args.out:
        import pathlib
        out = pathlib.Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "mpm_study.json").write_text(json.dumps(record, indent=1))
        try:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            record["chart"] = "matplotlib not installed (pip install dax-physics[plot])"
        else:
            fig, ax = plt.subplots(figsize=(6, 4))
            for ppc in args.ppc:
                for frac, marker in zip(args.dt_fraction, "os^v", strict=False):
                    pts = [(r["wall_s"], r["error"], r["cells"]) for r in ok
                           if r["ppc"] == ppc and r["dt_fraction"] == frac]
                    if pts:
                        w_, e_, c_ = zip(*pts, strict=True)
                        ax.plot(w_, e_, marker=marker, label=f"ppc {ppc}, dt {frac:g} x max")
                        for wi, ei, ci in pts:
                            ax.annotate(f"{ci}", (wi, ei), fontsize=7)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("wall time of the run [s]")
            ax.set_ylabel("relative error of the wave speed")
            ax.set_title("MPM speed vs accuracy (labels: cells per bar length)")
            ax.legend(fontsize=7)
            fig.tight_layout()
            fig.savefig(out / "mpm_study.png", dpi=120)
            record["chart"] = str(out / "mpm_study.png")
    emit(record, args.json)


# --------------------------------------------------------------------------- CLI

def render_gpu_cpu_table(*paths) -> str:
    """The Markdown table of the solver benchmarks on an accelerator beside a CPU, from
    result files recognised by their content: the accelerator's JSON lines of this
    module's (or ``dax_physics.tools.bench``'s) ``--json`` records after an ``about`` line
    with its ``commands``; on the CPU, a ``benchmarks.side_by_side`` document (DaX's
    median substeps per second per scene) and a ``benchmarks.grad_over_forward`` document
    (the median gradient ÷ forward ratio of the ``current`` side). One row per benchmark;
    a cell with no figure is empty; the runs' machines, loads and dates under the
    table."""
    from benchmarks._report import file_date, load_range, read_result

    gpu, about, sbs, gof, notes = [], {}, None, None, []
    for path in paths:
        path, doc = read_result(path)
        where = f"`{path.as_posix()}` ({file_date(path) or 'date not recorded'})"
        if isinstance(doc, list):
            about = next((r for r in doc if "about" in r), {})
            gpu = [r for r in doc if "bench" in r]
            notes.append(f"accelerator: {about.get('about', '')}; {where}: "
                         + "; ".join(f"`{c}`" for c in about.get("commands", [])))
        elif "scenes" in doc:
            sbs, meta = doc, doc["meta"]
            load = load_range([meta["loadavg_start"][0], meta["loadavg_end"][0]])
            notes.append(f"CPU substeps/s: `{meta['tool']}`, DaX's median of {meta['reps']} "
                         f"runs, {meta['cpu_count']} cores, started {meta['started_utc']}, "
                         f"1-minute load {load}; {where}")
        elif doc.get("bench") == "grad-over-forward":
            gof = doc
            loads = [r.get("load_1min") for r in doc["runs"] if r.get("side") == "current"]
            notes.append(f"CPU gradient ÷ forward: `benchmarks.grad_over_forward`, median of "
                         f"{doc['rounds']} rounds of {doc['reps']} alternating calls, "
                         f"{doc['cpus']} cores, 1-minute load {load_range(loads)}; {where}")
        else:
            raise ValueError(f"{path}: neither accelerator JSON lines, a side-by-side nor a "
                             "grad-over-forward document")

    def g(**match):
        return next((r for r in gpu if all(r.get(k) == v for k, v in match.items())), None)

    def rate(r, key="substeps_per_s"):
        return "" if r is None else f"{r[key]:.0f}"

    def cpu_rate(scene):
        s = (sbs or {}).get("scenes", {}).get(scene, {})
        v = s.get("substeps_per_s_median", {}).get("dax")
        return "" if v is None else f"{v:.0f}"

    def ratio(*rs):
        return "" if any(r is None for r in rs) else " / ".join(
            f"{r['grad_over_forward']:.2f}" for r in rs)

    def cpu_ratio(*names):
        s = (gof or {}).get("summary", {})
        vals = [s.get(f"{n}/current", {}).get("grad_over_forward_median") for n in names]
        return "" if None in vals else " / ".join(f"{v:.2f}" for v in vals)

    m = re.search(r"on one (.+?) \(", about.get("about", ""))
    head_gpu = m[1] if m else "accelerator"
    cpus = (sbs or {}).get("meta", {}).get("cpu_count") or (gof or {}).get("cpus")
    rows = [
        ("`mpm-block` fluid, 8192 particles, 32³ [substeps/s]",
         rate(g(bench="mpm-block", material="fluid", grid=32, batch=0)), cpu_rate("fluid32")),
        ("`mpm-block` elastic [substeps/s]",
         rate(g(bench="mpm-block", material="elastic", grid=32, batch=0)),
         cpu_rate("elastic32")),
        ("`mpm-block` fluid, 32 768 particles, 64³ [substeps/s]",
         rate(g(bench="mpm-block", material="fluid", grid=64, batch=0)), cpu_rate("fluid64")),
        ("`mpm-block --batch 64` fluid 32³ [scene-substeps/s]",
         rate(g(bench="mpm-block", material="fluid", grid=32, batch=64),
              "scene_substeps_per_s"), ""),
        ("`cloth-drop` 64×64 [substeps/s]", rate(g(bench="cloth-drop", n=64)),
         cpu_rate("cloth")),
        ("`mpm-grad` fluid / elastic, no segments: gradient ÷ forward",
         ratio(g(bench="mpm-grad", material="fluid", checkpoint_segments=1),
               g(bench="mpm-grad", material="elastic", checkpoint_segments=1)),
         cpu_ratio("fluid-s1", "elastic-s1")),
        ("`mpm-grad` fluid, 10 segments: gradient ÷ forward",
         ratio(g(bench="mpm-grad", material="fluid", checkpoint_segments=10)),
         cpu_ratio("fluid-s10")),
        ("`cloth-grad` 64×64: gradient ÷ forward", ratio(g(bench="cloth-grad", n=64)),
         cpu_ratio("cloth")),
    ]
    out = [f"| benchmark | {head_gpu} | {cpus or '?'}-core CPU |", "| --- | --- | --- |"]
    out += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    out += ["", "Medians after a warm-up or ahead-of-time compile. " + ". ".join(notes) + "."]
    return "\n".join(out) + "\n"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.physics", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)

    b = sub.add_parser("mpm-block", help="the peers' MPM block-drop scene: throughput")
    b.add_argument("--material", choices=("fluid", "elastic"), default="fluid")
    b.add_argument("--grid", type=int, default=32)
    b.add_argument("--particles", type=int, default=8192)
    b.add_argument("--substeps", type=int, default=100)
    b.add_argument("--batch", type=int, default=0, help="vmap over this many copies")
    b.add_argument("--reps", type=int, default=5)
    b.add_argument("--min-time", type=float, default=2.0)
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_mpm_block)

    g = sub.add_parser("mpm-grad", help="gradient time and memory, with/without checkpointing")
    g.add_argument("--material", choices=("fluid", "elastic"), default="fluid")
    g.add_argument("--grid", type=int, default=32)
    g.add_argument("--particles", type=int, default=8192)
    g.add_argument("--substeps", type=int, default=100)
    g.add_argument("--checkpoint-segments", type=int, default=10,
                   help="number of jax.checkpoint segments (<= 1: no checkpointing)")
    g.add_argument("--reps", type=int, default=3)
    g.add_argument("--json", action="store_true")
    g.set_defaults(func=cmd_mpm_grad)

    a = sub.add_parser("active-region", help="windowed vs full 128^3 grid on a rope scene")
    a.add_argument("--window", type=int, nargs=3, default=(44, 40, 16))
    a.add_argument("--no-colliders", action="store_true",
                   help="rope alone (no table collider and pusher)")
    a.add_argument("--substeps", type=int, default=50)
    a.add_argument("--reps", type=int, default=3)
    a.add_argument("--json", action="store_true")
    a.set_defaults(func=cmd_active_region)

    s = sub.add_parser("mpm-study", help="speed vs accuracy sweep (grid, ppc, dt)")
    s.add_argument("--cells", type=int, nargs="+", default=(8, 16, 32))
    s.add_argument("--ppc", type=int, nargs="+", default=(1, 8))
    s.add_argument("--dt-fraction", type=float, nargs="+", default=(0.2, 0.8))
    s.add_argument("--out", default="bench_out")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_mpm_study)

    from benchmarks import physics_cloth  # cloth-drop, cloth-fold, cloth-sag-study

    physics_cloth.add_subparsers(sub)
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
