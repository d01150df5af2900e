"""Cloth benchmarks (JSON on stdout): ``cloth-drop``, ``cloth-grad``, ``cloth-fold``,
``cloth-sag-study``, ``cloth-mesh``.

``benchmarks.physics`` registers these with :func:`add_subparsers`; standalone use:
``python -m benchmarks.physics_cloth cloth-drop --n 64 --substeps 1000 --json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import cloth_grid as grid
from benchmarks._timing import emit, grad_vs_forward, median_time, peak_rss_mb
from dax_physics import cloth as c

# ----------------------------------------------------------------------------- cloth-drop

#: The peers' spring directions (di, dj) on the vertex grid, their family (Cloth.kind: 0
#: structural, 1 shear, 2 bending) and stiffness [N/m].
DROP_SPRINGS = ((1, 0, 0, 1000.0), (0, 1, 0, 1000.0), (1, 1, 1, 1000.0), (1, -1, 1, 1000.0),
                (2, 0, 2, 200.0), (0, 2, 2, 200.0))


def cloth_drop_scene(n: int = 64, dt: float = 1e-4, dtype=jnp.float32):
    """The Taichi and Warp references' cloth-drop scene on the tasks' solver
    (:mod:`dax_physics.cloth`, its mesh path), the peers' y-up mapped to z-up: returns
    ``(cfg, cloth, state)``.

    A 1 m x 1 m sheet of n x n vertices (vertex ``i n + j``) and 1 kg; the peers' 12
    springs per vertex: structural (1,0), (0,1) and shear (1,1), (1,-1) at 1000 N/m,
    bending two apart (2,0), (0,2) at 200 N/m, dashpot 0.02 N s/m along each; gravity 9.8
    m/s^2; a frictionless table at z = 0 (the peers' ground clamp). The sheet starts at
    rest, tilted from 0.02 m to 0.08 m above the table along its first axis; rest lengths
    are those of that state. Every spring falls in a stencil class
    (:func:`dax_physics.cloth.spring_layout`: offsets 1, 2, n - 1, n, n + 1, 2 n).
    """
    u = np.linspace(0.0, 1.0, n, dtype=np.float32)
    ii, jj = np.meshgrid(u, u, indexing="ij")
    x0 = np.stack([ii, jj, np.float32(0.02) + np.float32(0.06) * ii], -1).reshape(-1, 3)
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    pairs, kind, k = [], [], []
    for di, dj, fam, stiff in DROP_SPRINGS:
        ok = (a + di < n) & (b + dj >= 0) & (b + dj < n)
        pairs.append(np.stack([(a * n + b)[ok], ((a + di) * n + b + dj)[ok]], 1))
        kind.append(np.full(ok.sum(), fam, np.int8))
        k.append(np.full(ok.sum(), stiff))
    pairs = np.concatenate(pairs)
    rest = np.linalg.norm(x0[pairs[:, 1]] - x0[pairs[:, 0]], axis=1)  # in float32
    V = n * n
    offsets, table, residual = c.spring_layout(pairs, V)
    cloth = c.Cloth(rest_pos=jnp.asarray(x0, dtype), mass=jnp.full((V,), 1.0 / V, dtype),
                    area=jnp.full((V,), 1.0 / V, dtype), pairs=jnp.asarray(pairs, jnp.int32),
                    kind=jnp.asarray(np.concatenate(kind)),
                    rest_length=jnp.asarray(rest, dtype),
                    stiffness=jnp.asarray(np.concatenate(k), dtype),
                    damping=jnp.full((len(pairs),), 0.02, dtype),
                    faces=jnp.asarray(c.square_mesh(n)[1]), offsets=offsets,
                    stencil_edge=jnp.asarray(table, jnp.int32),
                    residual=jnp.asarray(residual, jnp.int32))
    cfg = c.ClothConfig(dt=dt, gravity=(0.0, 0.0, -9.8), table_height=0.0)
    c.check_params(cfg, cloth)
    return cfg, cloth, c.ClothState.create(cloth, n_grippers=0)


def _drop_sim(args):
    """``(jitted rollout, state, implementation name)`` of ``--path``."""
    steps = args.substeps
    if args.path == "grid":
        cfg, cloth, state = grid.cloth_drop_scene(args.n, dt=args.dt)
        return (jax.jit(lambda s: grid.grid_rollout(cfg, cloth, s, steps, unroll=args.unroll)),
                state, "dax-jax-grid-stencil")
    cfg, cloth, state = cloth_drop_scene(args.n, dt=args.dt)
    return (jax.jit(lambda s: c.rollout(cfg, cloth, s, steps, unroll=args.unroll)), state,
            "dax-cloth-mesh")


def run_cloth_drop(args):
    """The peers' cloth drop on ``--path mesh`` (default: :func:`dax_physics.cloth.rollout`,
    the solver the cloth tasks run) or ``--path grid`` (``benchmarks.cloth_grid``, the
    regular-grid stencil no task uses, for comparison)."""
    sim, state, impl = _drop_sim(args)
    steps = args.substeps
    t0 = time.perf_counter()
    out = jax.block_until_ready(sim(state))
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(sim(state))  # warm-up
    med, ts = median_time(lambda: sim(state), args.reps)
    z = np.asarray(out.x[2] if args.path == "grid" else out.x[:, 2])
    rec = dict(bench="cloth-drop", impl=impl, path=args.path, n=args.n, substeps=steps,
               dt=args.dt, reps=args.reps, substeps_per_s=steps / med,
               us_per_substep=1e6 * med / steps,
               substeps_per_s_runs=[steps / t for t in ts], compile_s=compile_s,
               mean_height=float(z.mean()), min_height=float(z.min()),
               reference_mean_height=0.008108, finite=bool(np.isfinite(z).all()),
               load_1min=round(os.getloadavg()[0], 2),
               backend=jax.default_backend(), jax=jax.__version__, threads=os.cpu_count())
    emit(rec, args.json)
    return rec


# ----------------------------------------------------------------------------- cloth-fold

def run_cloth_grad(args):
    """The cloth-drop scene's gradient: d(mean height after ``substeps``)/d(initial
    velocities), timed against the forward rollout of the same loss."""
    cfg, cloth, state = grid.cloth_drop_scene(args.n, dt=args.dt)
    steps = args.substeps

    def loss(v0):
        out = grid.grid_rollout(cfg, cloth, grid.GridState(state.x, v0), steps)
        return jnp.mean(out.x[2])

    timing, g = grad_vs_forward(loss, state.v, args.reps)
    rec = dict(bench="cloth-grad", impl="dax-jax-stencil", n=args.n, substeps=steps,
               dt=cfg.dt, reps=args.reps, **timing, peak_rss_mb=peak_rss_mb(),
               grad_norm=float(jnp.linalg.norm(g)), finite=bool(jnp.all(jnp.isfinite(g))),
               backend=jax.default_backend(), jax=jax.__version__, threads=os.cpu_count())
    emit(rec, args.json)


def fold_scene(n: int = 32, size: float = 0.3, dtype=jnp.float32):
    """A cloth on a table folded corner onto (near) the opposite corner with
    self-collision; returns ``(cfg, cloth, state, schedule, pick, place)``."""
    sp = size / (n - 1)
    cl = c.square_cloth(n, size=(size, size), density=0.2, stretch=50.0, bend=0.2,
                        damping=0.02, dtype=dtype)
    cfg = c.ClothConfig(dt=1.0, friction_static=1.0, friction_dynamic=0.8, thickness=sp,
                        self_stiffness=50.0, self_damping=0.01, self_friction=0.005,
                        air_drag=0.5, strain_limit=0.05)
    import dataclasses
    cfg = dataclasses.replace(cfg, dt=float(np.floor(c.max_stable_dt(cfg, cl) * 1e6) / 1e6))
    t_scale = 1.0  # seconds of motion per phase unit
    n_of = lambda t: int(round(t / cfg.dt))  # noqa: E731
    sc = c.PickPlace(approach_steps=n_of(0.02 * t_scale), lift_steps=n_of(0.15 * t_scale),
                     move_steps=n_of(0.375 * t_scale), lower_steps=n_of(0.15 * t_scale),
                     settle_steps=n_of(0.375 * t_scale), lift_height=0.08, radius=0.5 * sp,
                     segment=100)
    pick = jnp.zeros(3, dtype)
    place = jnp.asarray([0.9 * size, 0.9 * size, sp], dtype)
    return cfg, cl, c.ClothState.create(cl), sc, pick, place


def run_cloth_fold(args):
    cfg, cl, st, sc, pick, place = fold_scene(args.n)
    goal = cl.rest_pos

    def loss(q):
        out = c.pick_and_place(cfg, cl, st, pick, q, sc)
        return jnp.mean(jnp.sum((out.x - goal) ** 2, -1))
    fwd = jax.jit(loss)
    bwd = jax.jit(jax.value_and_grad(loss))
    t0 = time.perf_counter()
    jax.block_until_ready(fwd(place))
    c_fwd = time.perf_counter() - t0
    t0 = time.perf_counter()
    val, grad = jax.block_until_ready(bwd(place))
    c_bwd = time.perf_counter() - t0
    t_fwd, _ = median_time(lambda: fwd(place), args.reps)
    t_bwd, _ = median_time(lambda: bwd(place), args.reps)
    rec = dict(bench="cloth-fold", n=args.n, vertices=cl.n_vertices, substeps=sc.n_steps,
               dt=cfg.dt, self_collision=True, segment=sc.segment,
               forward_s=t_fwd, forward_backward_s=t_bwd,
               substeps_per_s_forward=sc.n_steps / t_fwd, compile_forward_s=c_fwd,
               compile_forward_backward_s=c_bwd, loss=float(val),
               grad_place=np.asarray(grad).tolist(),
               finite=bool(np.isfinite(np.asarray(grad)).all()),
               peak_rss_mb=peak_rss_mb(), reps=args.reps)
    emit(rec, args.json)
    return rec


# ----------------------------------------------------------------------------- sag study

def _curtain_sag(n, dt_frac, size=0.3, t_end=2.0):
    """Hanging-cloth sag [m]: a vertical size x size sheet held over 0.05 m at both top
    corners, sag of the top edge's midpoint after ``t_end`` s (static by then)."""
    v, f = c.square_mesh(n, size=(size, size))
    v = np.stack([v[:, 0], np.zeros(len(v)), v[:, 1]], 1)
    cl = c.make_cloth(v, f, density=0.2, stretch=20.0, bend=0.5)
    base = c.ClothConfig(air_drag=2.0, table_height=None)
    dtmax = c.max_stable_dt(base, cl)
    import dataclasses
    cfg = dataclasses.replace(base, dt=dt_frac * dtmax)
    st = c.ClothState.create(cl, n_grippers=2)
    top = np.flatnonzero(np.isclose(v[:, 2], size))
    st = c.grasp(st, 0, v[top[0]], 0.0501)
    st = c.grasp(st, 1, v[top[-1]], 0.0501)
    steps = int(round(t_end / cfg.dt))
    t0 = time.perf_counter()
    out = jax.block_until_ready(jax.jit(lambda s: c.rollout(cfg, cl, s, steps))(st))
    wall = time.perf_counter() - t0
    return dict(n=n, dt=cfg.dt, dt_fraction=dt_frac, substeps=steps,
                sag=float(size - out.x[top[len(top) // 2], 2]), wall_s=wall)


def run_sag_study(args):
    ns = [int(s) for s in args.ns.split(",")]
    fracs = [float(s) for s in args.dt_fractions.split(",")]
    load0 = round(os.getloadavg()[0], 2)
    ref = _curtain_sag(args.n_ref, min(fracs))
    rows = []
    for n in ns:
        for fr in fracs:
            r = _curtain_sag(n, fr)
            r["abs_error"] = abs(r["sag"] - ref["sag"])
            r["rel_error"] = r["abs_error"] / ref["sag"]
            rows.append(r)
    rec = dict(bench="cloth-sag-study", reference=ref, rows=rows, n_ref=args.n_ref,
               dt_fractions=fracs, date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
               cpus=os.cpu_count(), jax=jax.__version__, device=str(jax.devices()[0]),
               load_1min=[load0, round(os.getloadavg()[0], 2)])
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "cloth_sag_study.json"), "w") as fh:
        json.dump(rec, fh, indent=1)
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        for fr in fracs:
            rs = [r for r in rows if r["dt_fraction"] == fr]
            ax[0].loglog([r["n"] for r in rs], [max(r["rel_error"], 1e-6) for r in rs], "o-",
                         label=f"dt = {fr} x dt_max")
            ax[1].loglog([r["wall_s"] for r in rs], [max(r["rel_error"], 1e-6) for r in rs],
                         "o-", label=f"dt = {fr} x dt_max")
        ax[0].set_xlabel("vertices per side")
        ax[0].set_ylabel(f"relative sag error vs n = {args.n_ref}")
        ax[1].set_xlabel("wall time for 2 s simulated (incl. compile) [s]")
        for a in ax:
            a.legend()
            a.grid(True, which="both", alpha=0.3)
        fig.suptitle("hanging-cloth sag: resolution and substep vs error")
        fig.tight_layout()
        fig.savefig(os.path.join(args.out, "cloth_sag_study.png"), dpi=100)
        rec["chart"] = os.path.join(args.out, "cloth_sag_study.png")
    except ImportError:
        rec["chart"] = None
    emit(rec, args.json)
    return rec


# ----------------------------------------------------------------------------- CLI

# ----------------------------------------------------------------------------- cloth-mesh

def mesh_scene(n: int, dt: float = 2.5e-4):
    """The cloth tasks' square cloth on the mesh path: 0.3 m, n x n vertices, 0.2 kg/m^2,
    stretch = shear 10 N/m, bend 0.5 N/m, dashpot 0.01, table friction 1.0 / 0.8, one
    vertex held by a gripper moving at (0.1, 0, 0.05) m/s. Returns ``(cfg, cloth, state)``."""
    cloth = c.square_cloth(n, size=(0.3, 0.3), origin=(-0.15, -0.15), density=0.2,
                           stretch=10.0, shear=10.0, bend=0.5, damping=0.01)
    cloth = cloth.replace(table_friction=jnp.asarray([1.0, 0.8], jnp.float32))
    cfg = c.ClothConfig(dt=dt, table_height=0.0)
    state = c.ClothState.create(cloth, n_grippers=1)
    state = state.replace(grip=state.grip.at[0, 0].set(1.0),
                          gripper_vel=jnp.asarray([[0.1, 0.0, 0.05]], jnp.float32))
    return cfg, cloth, state


def run_cloth_mesh(args):
    """Forward and forward-plus-gradient time of ``--substeps`` mesh-path substeps with the
    stencil spring sum and with the scatter sum (the same cloth without its layout), the
    two interleaved; process time by default (``--wall`` for wall time), which on a
    shared machine with the process pinned to one core (``taskset -c 1``) is the steadier
    figure."""
    clock = time.perf_counter if args.wall else time.process_time
    for n in [int(v) for v in args.ns.split(",")]:
        emit(_mesh_record(n, args.substeps, args.reps, clock, args.wall), args.json)


def _mesh_record(n: int, S: int, reps: int, clock, wall: bool) -> dict:
    cfg, cloth, state = mesh_scene(n)
    # the substep shrinks with the spacing: 2.5e-4 s is stable up to about 26 x 26 vertices
    # (60 x 60 blew up to NaN), so finer cloths run at their largest stable substep
    cfg = dataclasses.replace(cfg, dt=min(cfg.dt, c.max_stable_dt(cfg, cloth)))
    variants = {"stencil": cloth,
                "scatter": cloth.replace(offsets=(), stencil_edge=None, residual=None)}
    fwd = jax.jit(lambda cl, s: jax.lax.scan(lambda s, _: (c.step(cfg, cl, s), None), s,
                                             None, length=S)[0].x)

    def loss(gv, cl, s):
        s = s.replace(gripper_vel=gv)
        out = jax.lax.scan(lambda s, _: (c.step(cfg, cl, s), None), s, None, length=S)[0]
        return jnp.sum(out.x[:, 2] ** 2) + jnp.sum(out.x[:, 0])
    grad = jax.jit(jax.grad(loss))
    times = {k: {"forward": [], "grad": []} for k in variants}
    for cl in variants.values():  # compile and warm up
        jax.block_until_ready((fwd(cl, state), grad(state.gripper_vel, cl, state)))
    for rep in range(reps):
        for k, cl in variants.items():
            t0 = clock()
            jax.block_until_ready(fwd(cl, state))
            times[k]["forward"].append(clock() - t0)
            if rep < max(reps // 2, 1):
                t0 = clock()
                jax.block_until_ready(grad(state.gripper_vel, cl, state))
                times[k]["grad"].append(clock() - t0)
    V = cloth.n_vertices
    x = {k: np.asarray(fwd(cl, state)) for k, cl in variants.items()}
    rec = {"bench": "cloth-mesh", "n": n, "vertices": V, "springs": int(cloth.pairs.shape[0]),
           "substeps": S, "dt": cfg.dt,
           "finite": bool(all(np.isfinite(v).all() for v in x.values())),
           "clock": "wall" if wall else "process",
           "max_abs_dx_stencil_vs_scatter_m": float(np.abs(x["stencil"] - x["scatter"]).max())}
    for k in variants:
        t_f = float(np.median(times[k]["forward"]))
        rec[k] = {"forward_s": t_f, "us_per_substep": 1e6 * t_f / S,
                  "vertex_substeps_per_s": V * S / t_f,
                  "forward_grad_s": float(np.median(times[k]["grad"]))}
    return rec


def render_mesh_table(path) -> str:
    """The Markdown table of a file of ``cloth-mesh`` records (:func:`run_cloth_mesh`'s
    JSON lines, one per cloth size): per size the forward time per substep with the
    scatter and with the stencil spring sum [µs], the vertex-substeps per second of both
    and the forward-plus-gradient time of both [s]; the clock, the positions' agreement
    and the file under the table."""
    from benchmarks._report import file_date, read_result

    path, recs = read_result(path)
    recs = recs if isinstance(recs, list) else [recs]
    substeps = sorted({r["substeps"] for r in recs})
    out = ["| mesh path, " + "/".join(map(str, substeps)) + " substeps | "
           + " | ".join(f"{r['vertices']} vertices" for r in recs) + " |",
           "|---|" + "---|" * len(recs)]
    rows = [("forward, scatter sum [µs/substep]",
             lambda r: f"{r['scatter']['us_per_substep']:.1f}"),
            ("forward, stencil sum [µs/substep]",
             lambda r: f"{r['stencil']['us_per_substep']:.1f}"),
            ("M vertex-substeps/s, scatter → stencil",
             lambda r: f"{r['scatter']['vertex_substeps_per_s'] / 1e6:.1f} → "
                       f"{r['stencil']['vertex_substeps_per_s'] / 1e6:.1f}"),
            ("forward + gradient [s], scatter → stencil",
             lambda r: f"{r['scatter']['forward_grad_s']:.3f} → "
                       f"{r['stencil']['forward_grad_s']:.3f}")]
    out += [f"| {name} | " + " | ".join(cell(r) for r in recs) + " |" for name, cell in rows]
    clocks = sorted({r.get("clock", "wall") for r in recs})
    agree = max(r["max_abs_dx_stencil_vs_scatter_m"] for r in recs)
    out += ["", f"Medians, {'/'.join(clocks)} clock; positions after the last substep agree "
            f"to {agree:.1g} m between the two sums. The file records neither the machine "
            f"nor its load; `{path.as_posix()}` ({file_date(path) or 'date not recorded'})."]
    return "\n".join(out) + "\n"


def render_sag_table(path) -> str:
    """The Markdown table of a ``cloth-sag-study`` document (:func:`run_sag_study`'s
    JSON): per cloth size and substep its sag [mm], its error against the fine reference
    and its wall time for the 2 s simulated, compile included [s]; the reference, the
    largest change the substep makes at one size, and the run's date, machine and load
    under the table."""
    from benchmarks._report import file_date, load_range, read_result

    path, doc = read_result(path)
    ref = doc["reference"]
    out = ["| vertices per side | dt / dt_max | substeps | sag [mm] | error vs n = "
           f"{ref['n']} | wall, compile included [s] |", "|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        out.append(f"| {r['n']} | {r['dt_fraction']:g} | {r['substeps']} | "
                   f"{1e3 * r['sag']:.3f} | {100 * r['rel_error']:.1f} % | "
                   f"{r['wall_s']:.2f} |")
    by_n = {}
    for r in doc["rows"]:
        by_n.setdefault(r["n"], []).append(r["sag"])
    dt_change = max((max(s) - min(s)) / ref["sag"] for s in by_n.values())
    when = doc.get("date") or file_date(path) or "date not recorded"
    machine = (f"{doc['device']}, {doc['cpus']} cores, jax {doc['jax']}, 1-minute load "
               f"{load_range(doc['load_1min'])}" if "cpus" in doc
               else "machine and load not recorded")
    out += ["", f"A vertical 0.3 m curtain held at its two top corners, sag of its top "
            f"edge's midpoint after 2 s; reference: n = {ref['n']} at dt_max × "
            f"{ref['dt_fraction']:g}, sag {1e3 * ref['sag']:.3f} mm. The substep changes "
            f"the sag by at most {100 * dt_change:.2g} % of it at one size. {when}, "
            f"{machine}; `{path.as_posix()}`."]
    return "\n".join(out) + "\n"


def add_subparsers(subparsers):
    """Register ``cloth-drop``, ``cloth-grad``, ``cloth-fold``, ``cloth-mesh`` and
    ``cloth-sag-study`` on an argparse
    subparsers object; each sets ``func`` so the caller runs ``args.func(args)``."""
    p = subparsers.add_parser("cloth-drop", help="peers' 64x64 cloth-drop scene (tasks' solver)")
    p.add_argument("--path", choices=["mesh", "grid"], default="mesh",
                   help="mesh: dax_physics.cloth (what the tasks run); grid: cloth_grid.py")
    p.add_argument("--n", type=int, default=64)
    p.add_argument("--substeps", type=int, default=1000)
    p.add_argument("--dt", type=float, default=1e-4)
    p.add_argument("--reps", type=int, default=7)
    p.add_argument("--unroll", type=int, default=1)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run_cloth_drop)

    p = subparsers.add_parser("cloth-grad", help="cloth-drop gradient time against forward")
    p.add_argument("--n", type=int, default=64)
    p.add_argument("--substeps", type=int, default=1000)
    p.add_argument("--dt", type=float, default=1e-4)
    p.add_argument("--reps", type=int, default=7)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run_cloth_grad)

    p = subparsers.add_parser("cloth-fold", help="pick-and-place fold with self-collision")
    p.add_argument("--n", type=int, default=32)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run_cloth_fold)

    p = subparsers.add_parser("cloth-mesh", help="mesh path: stencil vs scatter spring sum")
    p.add_argument("--ns", default="11,16,23", help="square cloth sizes (n x n vertices)")
    p.add_argument("--substeps", type=int, default=2000)
    p.add_argument("--reps", type=int, default=6)
    p.add_argument("--wall", action="store_true", help="wall time instead of process time")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run_cloth_mesh)

    p = subparsers.add_parser("cloth-sag-study", help="resolution/substep vs sag error")
    p.add_argument("--ns", default="7,13,25")
    p.add_argument("--n-ref", type=int, default=49)
    p.add_argument("--dt-fractions", default="0.25,1.0")
    p.add_argument("--out", default="bench_out")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run_sag_study)


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m benchmarks.physics_cloth")
    add_subparsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
