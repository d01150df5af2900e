"""Cloth checks (mass-spring cloth, float32): a strip hanging between two pins against the
catenary, the pinned curtain's static sag (self-convergence), and a hanging sheet swinging
in the fundamental mode of a hanging chain."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from dax_physics import cloth as C

from . import Point, Result, on_front_note, register
from ._run import zero_crossings

G = 9.81


def _strip(n: int, m: int, length: float, width: float, **material):
    """A flat strip of n x m vertices in the x-y plane (x along its length) and its grid
    indices (vertex ``i*m + j``)."""
    v, f = C.square_mesh(n, m, size=(length, width))
    return C.make_cloth(v, f, **material), v


def _run(cfg, cloth, state, n_steps, every, probe):
    """Probe the cloth after every ``every`` of ``n_steps`` substeps; wall time excludes
    compilation."""
    import time

    def run(s):
        def body(s, _):
            s = C.rollout(cfg, cloth, s, every)
            return s, probe(s)

        return jax.lax.scan(body, s, None, length=n_steps // every)

    compiled = jax.jit(run).lower(state).compile()
    t0 = time.perf_counter()
    final, tr = jax.block_until_ready(compiled(state))
    return final, np.asarray(tr, np.float64), time.perf_counter() - t0


# --------------------------------------------------------------------------- catenary

def catenary_sag(span: float, length: float) -> float:
    """Sag [m] of an inextensible uniform chain of ``length`` hung between two points
    ``span`` apart at equal height: y = a cosh(x / a) with length = 2 a sinh(span / (2 a))
    (solved by bisection), sag = a (cosh(span / (2 a)) - 1)."""
    lo, hi = 1e-6 * span, 1e6 * span  # length(a) decreases from inf to span as a grows
    for _ in range(200):
        a = math.sqrt(lo * hi)
        if 2 * a * math.sinh(span / (2 * a)) > length:
            lo = a
        else:
            hi = a
    return a * (math.cosh(span / (2 * a)) - 1.0)


def catenary(n: int, length=0.3, width=0.02, span_ratio=0.8, stretch=2000.0, t_end=3.0):
    """A strip ``length`` m long, ``n`` vertices along it and 3 across, pinned along both
    short edges (two grippers) ``span_ratio * length`` apart at equal height, released from
    a V shape of the same length and damped by air drag until static. Returns the sag of the
    centre line's midpoint, the inextensible catenary's sag and the largest strain."""
    cl, v = _strip(n, 3, length, width, density=0.2, stretch=stretch, bend=0.0,
                   damping=0.05)
    span = span_ratio * length
    s = v[:, 0] - 0.5 * length  # arc length from the middle
    # the V of the same length: two straight halves from the pins down to the middle
    drop = math.sqrt((0.5 * length) ** 2 - (0.5 * span) ** 2)
    x0 = np.stack([s * span / length, v[:, 1], -drop * (1.0 - np.abs(s) / (0.5 * length))], 1)
    base = C.ClothConfig(air_drag=2.0, table_height=None)
    cfg = dataclasses.replace(base, dt=0.9 * C.max_stable_dt(base, cl))
    st = C.ClothState.create(cl, x=x0, n_grippers=2)
    ends = (np.isclose(v[:, 0], 0.0), np.isclose(v[:, 0], length))
    for g, sel in enumerate(ends):
        st = st.replace(grip=st.grip.at[g].set(jnp.asarray(sel, st.x.dtype)))
    mid = jnp.asarray(np.isclose(np.abs(s), np.abs(s).min()))
    pairs, rest = cl.pairs, cl.rest_length
    n_steps = math.ceil(t_end / cfg.dt)
    every = max(1, n_steps // 100)

    def probe(state):
        d = jnp.linalg.norm(state.x[pairs[:, 1]] - state.x[pairs[:, 0]], axis=1)
        z = jnp.sum(jnp.where(mid, state.x[:, 2], 0.0)) / jnp.sum(mid)
        return jnp.stack([-z, jnp.max(jnp.where(cl.kind == 0, d / rest - 1.0, 0.0))])

    _, tr, wall_s = _run(cfg, cl, st, n_steps, every, probe)
    return dict(n=n, edge=length / (n - 1), wall_s=wall_s, sag=float(tr[-1, 0]),
                sag_change_last_10pct=float(abs(tr[-1, 0] - tr[-10, 0]) / tr[-1, 0]),
                max_strain=float(tr[-1, 1]), reference=catenary_sag(span, length))


@register
def check_cloth_catenary(level="default"):
    """A cloth strip hanging between two pinned edges against the catenary y = a cosh(x/a)
    (Bernoulli 1691; the inextensible uniform chain: the springs are stiff enough that the
    strip stretches by about 0.1 %, reported). Expected second order in the edge length (a
    chain of lumped masses approximates the catenary to O(h^2))."""
    sweep = (9, 17) if level == "quick" else (9, 17, 33)
    points = []
    for n in sweep:
        r = catenary(n)
        points.append(Point(n, r["edge"], r["sag"] / r["reference"] - 1.0, r["wall_s"],
                            measured=r["sag"], expected=r["reference"], extra=dict(
                                max_strain=r["max_strain"],
                                still_moving=r["sag_change_last_10pct"])))
    return Result(
        name="cloth_catenary", solver="cloth", reference="catenary y = a cosh(x/a)",
        quantity="sag / catenary sag - 1", resolution_label="vertices along the strip",
        default=17, points=points, tolerance=0.01, expected_order=2.0,
        pareto_note=on_front_note(points, 17, "the cloth tasks use 1 cm edges on 20-30 cm "
                                  "cloths: 21-31 vertices (nearest: 17)"),
        notes="strain of the springs (the catenary assumes none): " + ", ".join(
            f"{p.resolution:g}: {p.extra['max_strain']:.2%}" for p in points))


# --------------------------------------------------------------------------- static sag

def curtain_sag(n: int, dt_fraction: float = 0.5, size=0.3, t_end=2.0):
    """The pinned curtain of the cloth-sag study: a vertical ``size`` square sheet held at
    its two top corners (every vertex within 5 cm of them), settled under air drag; the sag
    of the top edge's midpoint after ``t_end`` s."""
    v, f = C.square_mesh(n, size=(size, size))
    v = np.stack([v[:, 0], np.zeros(len(v)), v[:, 1]], 1)
    cl = C.make_cloth(v, f, density=0.2, stretch=20.0, bend=0.5)
    base = C.ClothConfig(air_drag=2.0, table_height=None)
    cfg = dataclasses.replace(base, dt=dt_fraction * C.max_stable_dt(base, cl))
    st = C.ClothState.create(cl, n_grippers=2)
    top = np.flatnonzero(np.isclose(v[:, 2], size))
    st = C.grasp(st, 0, v[top[0]], 0.0501)
    st = C.grasp(st, 1, v[top[-1]], 0.0501)
    steps = round(t_end / cfg.dt)
    centre = int(top[len(top) // 2])
    _, tr, wall_s = _run(cfg, cl, st, steps, steps, lambda s: s.x[centre, 2])
    return dict(n=n, edge=size / (n - 1), wall_s=wall_s, sag=float(size - tr[-1]))


@register
def check_cloth_static_sag(level="default"):
    """The pinned curtain's static sag (the existing cloth-sag study) against the finest
    resolution (n = 49) as the reference: a self-convergence check, no analytic answer
    exists for a sheet held at two corners. Expected order about 1 (the corner grasps hold
    every vertex within 5 cm, a region that changes with the mesh)."""
    sweep = (7, 13) if level == "quick" else (7, 13, 25)
    ref = curtain_sag(49)
    points = [Point(n, r["edge"], r["sag"] / ref["sag"] - 1.0, r["wall_s"], measured=r["sag"],
                    expected=ref["sag"]) for n in sweep for r in [curtain_sag(n)]]
    return Result(
        name="cloth_static_sag", solver="cloth",
        reference=f"self-convergence: n = 49 sag {ref['sag'] * 1e3:.3f} mm",
        quantity="sag / sag(n=49) - 1", resolution_label="vertices along an edge",
        default=25, points=points, tolerance=0.05, expected_order=1.0,
        pareto_note=on_front_note(points, 25, "Fold-Cloth-1 uses 21 x 21 vertices "
                                  "(nearest: 25)"))


# --------------------------------------------------------------------------- pendulum

def _bessel_j0(x):
    """J0(x) by its power series (enough terms for x <= 3)."""
    x = np.asarray(x, np.float64)
    term, total = np.ones_like(x), np.ones_like(x)
    for k in range(1, 30):
        term = term * -(x * x / 4.0) / (k * k)
        total = total + term
    return total


J0_FIRST_ZERO = 2.404825557695773


def hanging_sheet(n: int, length=0.3, width=0.06, amplitude=0.01, periods=2.2):
    """A sheet ``length`` m long hanging from its pinned top edge, ``n`` vertices along it,
    started at rest in the fundamental mode of a hanging chain, u(s) = A J0(j01 sqrt(s /
    L)) out of its plane (s measured up from the free end). Returns the measured period and
    the hanging chain's T = 4 pi sqrt(L / g) / j01."""
    m = max(3, round(width / (length / (n - 1))) + 1)
    cl, v = _strip(n, m, length, width, density=0.2, stretch=500.0, bend=0.0)
    # hang: x along the length -> down the z axis; the sheet in the x-z plane
    s = v[:, 0]  # distance from the free end after the flip below
    x0 = np.stack([v[:, 1], np.zeros(len(v)), s], 1)  # top edge at z = length
    shape = _bessel_j0(J0_FIRST_ZERO * np.sqrt(np.clip(s, 0.0, None) / length))
    x0[:, 1] = amplitude * shape
    cl = cl.replace(rest_pos=jnp.asarray(x0, cl.rest_pos.dtype))
    base = C.ClothConfig(table_height=None)
    cfg = dataclasses.replace(base, dt=0.9 * C.max_stable_dt(base, cl))
    st = C.ClothState.create(cl, x=x0, n_grippers=1)
    st = st.replace(grip=st.grip.at[0].set(jnp.asarray(np.isclose(s, length), st.x.dtype)))
    period = 4.0 * math.pi * math.sqrt(length / G) / J0_FIRST_ZERO
    n_steps = math.ceil(periods * period / cfg.dt)
    every = 4
    sh = jnp.asarray(shape, st.x.dtype)
    _, tr, wall_s = _run(cfg, cl, st, n_steps, every,
                         lambda state: jnp.sum(sh * state.x[:, 1]) / jnp.sum(sh * sh))
    t = cfg.dt * every * np.arange(1, len(tr) + 1)
    zc = zero_crossings(t, tr)
    measured = 2.0 * float(np.mean(np.diff(zc))) if len(zc) >= 2 else float("nan")
    return dict(n=n, edge=length / (n - 1), wall_s=wall_s, period=measured,
                period_exact=period)


@register
def check_cloth_pendulum(level="default"):
    """A hanging sheet swinging out of its plane in the fundamental mode of a hanging chain
    (D. Bernoulli 1733): u(s) = J0(2 omega sqrt(s / g)), period T = 4 pi sqrt(L / g) / j01,
    j01 = 2.4048 the first zero of J0. Expected second order in the edge length."""
    sweep = (9, 17) if level == "quick" else (9, 17, 33)
    points = []
    for n in sweep:
        r = hanging_sheet(n)
        points.append(Point(n, r["edge"], r["period"] / r["period_exact"] - 1.0, r["wall_s"],
                            measured=r["period"], expected=r["period_exact"]))
    return Result(
        name="cloth_pendulum", solver="cloth",
        reference="hanging chain T = 4 pi sqrt(L/g) / j01", quantity="T_sim / T - 1",
        resolution_label="vertices along the sheet", default=17, points=points,
        tolerance=0.01, expected_order=2.0,
        pareto_note=on_front_note(points, 17, "cloth tasks: 21-31 vertices along a cloth "
                                  "(nearest: 17)"))
