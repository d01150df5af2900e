"""Does the Whip-Rope rope tear when the gripper pulls it suddenly? (issue 16)

The straight canonical rope, at rest, is pulled by its held end at a constant velocity
(along the rope, away from it: -x; and sideways: +y) for ``--steps`` env steps; the speed
cap is lifted. Reports, per speed, the largest over time of

* gap: distance from the held block to the nearest free particle [cm] (at rest ~0.3 cm),
* nbr: the largest nearest-neighbour distance of a free particle [cm] (a particle or a
  piece that came off; at rest ~0.6 cm),
* strain: the largest stretch of the rope's centre line between consecutive 1-cm slices
  (rest length 1 cm) minus 1,

all speeds in one vmapped rollout. Usage:
    python -m benchmarks.whip_tear [--drive grid|none] [--E PA] [--substeps N] \
        [--scene dt=...,max_speed=...] [--steps 12] [--speeds 0.5,1,2,3]

`--drive none --E 4e4 --substeps 16 --scene dt=6.25e-4,max_speed=2.5` is the rope and
grip before dax-tasks 0.2.0; the numbers are in the whip_rope docstring.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

import dax_tasks
from dax_tasks.tasks import whip_rope as wr


def metrics(x, held, s_rest, slice_len=0.01):
    """(gap, nbr, strain) of positions ``x`` (N, 3); ``held`` (N,) bool, ``s_rest`` (N,)."""
    free = ~held
    d = jnp.linalg.norm(x[:, None, :] - x[None, :, :], axis=-1)
    gap = jnp.min(jnp.where(free[:, None] & held[None, :], d, jnp.inf))
    dn = jnp.where(jnp.eye(x.shape[0], dtype=bool), jnp.inf, d)
    nbr = jnp.max(jnp.where(free, jnp.min(dn, axis=1), 0.0))
    nb = int(np.ceil(s_rest.max() / slice_len))
    idx = np.minimum((s_rest / slice_len).astype(int), nb - 1)
    onehot = jnp.asarray(np.eye(nb)[idx].T, x.dtype)           # (nb, N)
    cen = onehot @ x / onehot.sum(1, keepdims=True)
    rest = np.bincount(idx, s_rest, nb) / np.bincount(idx, None, nb)
    seg = jnp.linalg.norm(jnp.diff(cen, axis=0), axis=1) / np.diff(rest)
    return gap, nbr, jnp.max(seg) - 1.0


def run(env, velocities, steps):
    held = jnp.asarray(wr.held_mask(env.spec.scene))
    rest, _ = wr.rest_particles(env.spec.scene)
    s_rest = np.asarray(rest[:, 0])
    params = env.default_params
    state0 = env._template

    def one(v):
        def body(s, _):
            s = env.apply_action(s, v, params)
            return s, metrics(s.x, held, s_rest)
        s, m = jax.lax.scan(body, state0, None, length=steps)
        return jnp.stack([jnp.max(mm) for mm in m]), s.finite

    return jax.jit(jax.vmap(one))(velocities)


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--steps", type=int, default=12)
    p.add_argument("--speeds", default="0.5,1,2,3")
    p.add_argument("--substeps", type=int, default=None)
    p.add_argument("--scene", default="", help="k=v,... WhipRopeScene overrides")
    p.add_argument("--E", type=float, default=None, help="the rope's Young's modulus [Pa]")
    p.add_argument("--drive", default="grid", help="grid | none (the grip before 0.2.0)")
    a = p.parse_args(argv)
    if a.E:
        wr.ROPE = dataclasses.replace(wr.ROPE, youngs_modulus=a.E)
    over = {}
    for kv in filter(None, a.scene.split(",")):
        k, v = kv.split("=")
        t = type(getattr(wr.WHIP_ROPE.scene, k))
        over[k] = v.lower() in ("1", "true") if t is bool else t(v)
    speeds = [float(s) for s in a.speeds.split(",")]
    over.setdefault("grid_grip", a.drive == "grid")
    scene = dataclasses.replace(wr.WHIP_ROPE.scene, grip_speed=max(speeds) + 1, **over)
    kw = dict(scene=scene, action_low=(-10.0,) * 3, action_high=(10.0,) * 3,
              cache_goal=False)
    if a.substeps:
        kw["substeps"] = a.substeps
    env = dax_tasks.make("whip_rope", **kw)
    print(f"grip on the grid: {scene.grid_grip}; E {wr.ROPE.youngs_modulus:.3g} Pa, dx "
          f"{scene.dx} m, dt {scene.dt:.4g} s x {env.spec.substeps} substeps, "
          f"{wr.held_mask(scene).size} particles ({int(wr.held_mask(scene).sum())} held)")
    vel = []
    for sp in speeds:
        vel += [[-sp, 0.0, 0.0], [0.0, sp, 0.0]]
    t0 = time.time()
    m, fin = run(env, jnp.asarray(vel, jnp.float32), a.steps)
    m = np.asarray(m)
    print(f"({time.time() - t0:.1f} s) over {a.steps} steps of {env.dt * 1e3:.0f} ms")
    print(f"{'speed':>6} {'dir':>5} {'gap cm':>7} {'nbr cm':>7} {'strain':>7} finite")
    for i in range(len(vel)):
        sp, d = speeds[i // 2], ("along" if i % 2 == 0 else "side")
        print(f"{sp:6.2f} {d:>5} {100 * m[i, 0]:7.2f} {100 * m[i, 1]:7.2f} "
              f"{m[i, 2]:7.3f} {bool(fin[i])}")


if __name__ == "__main__":
    main()
