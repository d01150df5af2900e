"""Fast path for regular grid cloth: a stencil over the (3, n, m) position array.

A regular n x m vertex grid with the 12-neighbour spring pattern of the standard
cloth-drop benchmark (structural (1,0),(0,1); shear (1,1),(1,-1); bending "two apart"
(2,0),(0,2)) needs no index tables: every spring is a shifted slice of the grid, so
a substep's forces are one fused element-wise XLA loop and many substeps run inside one
jitted ``lax.scan``.

Layout: positions and velocities are stored component-major, ``(3, n, m)`` [m], [m/s],
so the grid axes are the contiguous, vectorised ones. :func:`to_vertices` and
:func:`from_vertices` convert to and from the ``(n*m, 3)`` vertex layout used by
:mod:`dax_physics.cloth` (row-major, vertex ``i*m + j``).

Physics (semi-implicit Euler, SI units, z up)::

    f_i = sum_springs (k (|d| - L) + c (v_j - v_i).d_hat) d_hat      d = x_j - x_i
    v  <- v + dt (f / m + g)
    x  <- x + dt v
    ground clamp: where x_z < z_ground: x_z = z_ground and v_z = max(v_z, 0)

This is exactly the benchmark scene's model (a frictionless ground clamp, no
self-collision); the general mesh solver in :mod:`dax_physics.cloth.sim` adds friction,
colliders, self-collision and grasping.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from dax_physics import _fusion, pytree_dataclass

#: The six unique neighbour directions (di, dj) and their spring family.
GRID_DIRECTIONS = ((1, 0, "struct"), (0, 1, "struct"), (1, 1, "shear"), (1, -1, "shear"),
                   (2, 0, "bend"), (0, 2, "bend"))


@dataclasses.dataclass(frozen=True)
class GridClothConfig:
    """Static configuration of a grid cloth (hashable; a jit static argument).

    n, m: vertices along the two grid axes.
    dt: substep [s].
    mass: mass of one vertex [kg].
    k_struct, k_shear, k_bend: spring stiffness [N/m] of the three families.
    damping: dashpot coefficient along each spring [N s/m].
    gravity: acceleration (gx, gy, gz) [m/s^2].
    ground: height of the ground clamp [m]; ``None`` disables it.
    """

    n: int
    m: int
    dt: float = 1e-4
    mass: float = 1.0 / 4096
    k_struct: float = 1000.0
    k_shear: float = 1000.0
    k_bend: float = 200.0
    damping: float = 0.02
    gravity: tuple = (0.0, 0.0, -9.8)
    ground: float | None = 0.0

    def stiffness(self, family: str) -> float:
        return {"struct": self.k_struct, "shear": self.k_shear, "bend": self.k_bend}[family]

    def max_stable_dt(self) -> float:
        """Largest stable substep [s] (Gershgorin bound, see :func:`stable_dt`)."""
        ksum = 4 * self.k_struct + 4 * self.k_shear + 4 * self.k_bend
        return stable_dt(ksum, 12 * self.damping, self.mass)

    def check_stable(self):
        """Raise ``ValueError`` naming the largest stable dt if ``dt`` exceeds it."""
        dtmax = self.max_stable_dt()
        if not self.dt <= dtmax:
            raise ValueError(f"grid cloth substep dt={self.dt:g} s is unstable: the largest "
                             f"stable dt for these springs and masses is {dtmax:.4g} s")


def stable_dt(k_sum, c_sum, mass, safety: float = 0.9) -> float:
    """Largest stable semi-implicit Euler substep [s] for a vertex of ``mass`` [kg] whose
    springs sum to ``k_sum`` [N/m] and dashpots to ``c_sum`` [N s/m].

    Uses the Gershgorin bounds omega^2 <= 2 k_sum / m and gamma <= 2 c_sum / m on the
    highest mode and the stability condition of semi-implicit Euler for a damped
    oscillator, omega^2 dt^2 + 2 gamma dt < 4, times a ``safety`` factor.
    """
    w2 = 2.0 * float(k_sum) / float(mass)
    g = 2.0 * float(c_sum) / float(mass)
    if w2 <= 0:
        return float("inf") if g <= 0 else safety * 2.0 / g
    return safety * (-g + np.sqrt(g * g + 4.0 * w2)) / w2


@pytree_dataclass
class GridCloth:
    """Rest lengths [m] of the six spring directions (arrays of the overlap shapes)."""

    rest: tuple  # six arrays, shapes (n - di, m - |dj|)


@pytree_dataclass
class GridState:
    x: jnp.ndarray  # (3, n, m) positions [m]
    v: jnp.ndarray  # (3, n, m) velocities [m/s]


def to_vertices(a):
    """(3, n, m) -> (n*m, 3)."""
    return jnp.moveaxis(a, 0, -1).reshape(-1, 3)


def from_vertices(a, n, m):
    """(n*m, 3) -> (3, n, m)."""
    return jnp.moveaxis(jnp.asarray(a).reshape(n, m, 3), -1, 0)


def _pair_slices(n, m, di, dj):
    """Slices (a, b) of the grid so that b = a shifted by (di, dj), both in range."""
    a0 = (slice(0, n - di), slice(max(0, -dj), m - max(0, dj)))
    b0 = (slice(di, n), slice(max(0, dj), m - max(0, -dj)))
    return a0, b0


def grid_rest_lengths(x0_vertices, n, m):
    """Rest lengths of the six directions from a (n*m, 3) rest configuration (numpy,
    computed in the array's own precision so they match table-based implementations)."""
    x0 = np.asarray(x0_vertices).reshape(n, m, 3)
    out = []
    for di, dj, _ in GRID_DIRECTIONS:
        a, b = _pair_slices(n, m, di, dj)
        out.append(np.linalg.norm(x0[b] - x0[a], axis=-1).astype(x0.dtype))
    return GridCloth(tuple(jnp.asarray(r) for r in out))


def _neighbours(cfg: GridClothConfig, cloth: GridCloth, dtype):
    """The 12 springs seen from a vertex: ``(k, (oi, oj), L, has)`` per neighbour offset,
    with the rest length and a 0/1 "this vertex has that spring" mask on the vertex grid
    (both ends of each direction: +o from its a end, -o from its b end)."""
    out = []
    for (di, dj, fam), rest in zip(GRID_DIRECTIONS, cloth.rest, strict=True):
        for sign, pad in ((1, ((0, di), (max(0, -dj), max(0, dj)))),
                          (-1, ((di, 0), (max(0, dj), max(0, -dj))))):
            oi, oj = sign * di, sign * dj
            i = jax.lax.broadcasted_iota(jnp.int32, (cfg.n, cfg.m), 0) + oi
            j = jax.lax.broadcasted_iota(jnp.int32, (cfg.n, cfg.m), 1) + oj
            has = ((i >= 0) & (i < cfg.n) & (j >= 0) & (j < cfg.m)).astype(dtype)
            out.append((cfg.stiffness(fam), (oi, oj), jnp.pad(rest, pad), has))
    return out


_PAD = 2  # the longest spring spans two vertices


def _shifted(ap, o, n, m):
    """``a[:, i + oi, j + oj]`` for every vertex, from ``ap`` padded by :data:`_PAD`."""
    return ap[:, _PAD + o[0]:_PAD + o[0] + n, _PAD + o[1]:_PAD + o[1] + m]


def _padded(a):
    return jnp.pad(a, ((0, 0), (_PAD, _PAD), (_PAD, _PAD)))


def _spring(cfg, k, L, has, d, dv):
    """Unit vector u, length ln, 1/ln and the signed spring + dashpot force s along u."""
    ln = jnp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    inv = 1.0 / jnp.maximum(ln, 1e-12)
    du = (dv[0] * d[0] + dv[1] * d[1] + dv[2] * d[2]) * inv
    s = has * (k * (ln - L) + cfg.damping * du)
    return ln, inv, du, s


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _forces(cfg, cloth, x, v):
    n, m = cfg.n, cfg.m
    xp, vp = _padded(x), _padded(v)
    f = [0.0, 0.0, 0.0]
    for k, o, L, has in _neighbours(cfg, cloth, x.dtype):
        xs, vs = _shifted(xp, o, n, m), _shifted(vp, o, n, m)
        d = [xs[q] - x[q] for q in range(3)]
        _, inv, _, s = _spring(cfg, k, L, has, d, [vs[q] - v[q] for q in range(3)])
        f = [f[q] + (s * inv) * d[q] for q in range(3)]
    return jnp.stack(f)


def _forces_fwd(cfg, cloth, x, v):
    return _forces(cfg, cloth, x, v), (cloth, x, v)


def _forces_bwd(cfg, res, g):
    """Reverse mode by hand, gather-free like the forward. A spring (i, j = i + o) adds
    F = s u to f_i and -F to f_j, so it sees the cotangent G = g_i - g_j through F alone:

        dF/dd^T G  = (s / ln) (G - (G.u) u) + (G.u) ds/dd,  ds/dd = k u + c (dv - (dv.u) u) / ln
        dF/ddv^T G = (G.u) c u,                             dF/dL^T G = -k (G.u)

    (times the spring's mask), and d = x_j - x_i gives x_j +=, x_i -= the first. Seen from j
    (offset -o) every term changes sign, so each vertex sums ``-dF/dd^T G`` over its own 12
    springs, as the forward does. Autodiff of the forward transposed its 72 shifted slices
    into padded cotangents: 7x slower than the forward.

    The six outputs (dx and dv, three components each) are computed in three fused loops,
    one per component q, each returning (dx_q, dv_q) as one complex array, so that the two
    share their springs' work. Each loop reads its own ``optimization_barrier`` view of the
    inputs (no copy is made): with shared inputs, XLA would not duplicate the 12 views'
    square roots and divisions into three loops and gave each its own loop instead. Six
    separate outputs sharing those loops took 1.6x as long (64 x 64 cloth, 1000 substeps:
    a gradient of 415 ms against 255 ms, for a forward of 88 ms)."""
    cloth, x, v = res
    n, m = cfg.n, cfg.m
    nbrs = _neighbours(cfg, cloth, x.dtype)

    def component(q, x, v, g):
        xp, vp, gp = _padded(x), _padded(v), _padded(g)
        dx, dv, dL = 0.0, 0.0, []
        for idx, (k, o, L, has) in enumerate(nbrs):
            xs, vs, gs = (_shifted(a, o, n, m) for a in (xp, vp, gp))
            d = [xs[c] - x[c] for c in range(3)]
            _, inv, du, s = _spring(cfg, k, L, has, d, [vs[c] - v[c] for c in range(3)])
            u = [d[c] * inv for c in range(3)]
            G = [g[c] - gs[c] for c in range(3)]
            Gu = G[0] * u[0] + G[1] * u[1] + G[2] * u[2]
            ds_dd = has * (k * u[q] + cfg.damping * ((vs[q] - v[q]) - du * u[q]) * inv)
            dx = dx - (s * inv * (G[q] - Gu * u[q]) + Gu * ds_dd)
            dv = dv - Gu * has * cfg.damping * u[q]
            if idx % 2 == 0:  # the +o view of a direction: its rest lengths, on the a ends
                a, _ = _pair_slices(n, m, *o)
                dL.append((-k * has * Gu)[a])
        return jax.lax.complex(dx, dv), dL

    # the barrier's q operand keeps XLA from merging the three barriers into one
    out = [component(q, *jax.lax.optimization_barrier((x, v, g, jnp.int32(q)))[:3])
           for q in range(3)]
    dL = out[0][1]  # only computed where a rest length's cotangent is used
    pairs = _fusion.materialise(tuple(p for p, _ in out))
    return (GridCloth(tuple(dL)), jnp.stack([p.real for p in pairs]),
            jnp.stack([p.imag for p in pairs]))


_forces.defvjp(_forces_fwd, _forces_bwd)


def grid_forces(cfg: GridClothConfig, cloth: GridCloth, x, v):
    """Spring + dashpot forces [N] on every vertex, (3, n, m).

    Each vertex sums its own (up to) 12 springs from shifted slices of the positions and
    velocities padded by two: every spring is evaluated once from each end (the two
    forces are exact negatives of each other, as ``d`` and ``d_hat`` change sign), and
    the whole sum is one fused loop over the vertices. Evaluating each spring once and
    padding its force back to both ends took 12 loops plus two sums: 2x slower. The
    reverse mode is written the same way (:func:`_forces_bwd`)."""
    return _forces(cfg, cloth, x, v)


def grid_step(cfg: GridClothConfig, cloth: GridCloth, state: GridState) -> GridState:
    """One semi-implicit Euler substep of the grid cloth."""
    x, v = state.x, state.v
    f = grid_forces(cfg, cloth, x, v)
    g = jnp.asarray(cfg.gravity, x.dtype).reshape(3, 1, 1)
    v = v + cfg.dt * (f * (1.0 / cfg.mass) + g)
    x = x + cfg.dt * v
    if cfg.ground is not None:
        below = x[2] < cfg.ground
        # Written so that reverse mode keeps two masks per substep and no float array: the
        # clamped values are linear in x and v (a - a is +0), so no zero tangent array is
        # made and saved, as it was for jnp.where with a constant.
        z = jax.lax.select(below, x[2] - x[2] + cfg.ground, x[2])
        vz = jax.lax.select(below & (v[2] < 0.0), v[2] - v[2], v[2])
        x = jnp.stack([x[0], x[1], z])
        v = jnp.stack([v[0], v[1], vz])
    return GridState(x, v)


def grid_rollout(cfg: GridClothConfig, cloth: GridCloth, state: GridState, n_steps: int,
                  unroll: int = 1) -> GridState:
    """Run ``n_steps`` substeps as one ``lax.scan`` (``unroll`` substeps per loop body)."""
    def body(s, _):
        return grid_step(cfg, cloth, s), None
    state, _ = jax.lax.scan(body, state, None, length=n_steps, unroll=unroll)
    return state


def cloth_drop_scene(n: int = 64, dt: float = 1e-4, dtype=jnp.float32):
    """The standard cloth-drop scene of the Taichi and Warp reference implementations with
    the peers' y-up mapped to z-up: returns ``(cfg, cloth, state)``.

    A 1 m x 1 m sheet of n x n vertices and 1 kg, k_struct = k_shear = 1000 N/m,
    k_bend = 200 N/m (two apart), dashpot 0.02 N s/m, gravity 9.8 m/s^2, ground clamp at
    0; the sheet starts at rest, tilted from 0.02 m to 0.08 m above the ground along its
    first axis. Rest lengths are those of the tilted initial state.
    """
    npdt = np.dtype(jnp.dtype(dtype).name)
    u = np.linspace(0.0, 1.0, n, dtype=np.float32)
    ii, jj = np.meshgrid(u, u, indexing="ij")
    # peers: (x, y_up, z) = (ii, 0.02 + 0.06 ii, jj); here (x, y, z_up) = (ii, jj, height)
    x0 = np.stack([ii, jj, (np.float32(0.02) + np.float32(0.06) * ii)], -1).astype(np.float32)
    x0 = x0.reshape(n * n, 3)
    cloth = grid_rest_lengths(x0, n, n)
    cloth = GridCloth(tuple(r.astype(dtype) for r in cloth.rest))
    cfg = GridClothConfig(n=n, m=n, dt=dt, mass=1.0 / (n * n))
    cfg.check_stable()
    x = from_vertices(x0.astype(npdt), n, n)
    state = GridState(x, jnp.zeros_like(x))
    return cfg, cloth, state
