"""Solid checks on MLS-MPM: an elastic cantilever against beam theory (and its mean
deflection over ten periods: no creep), the bar wave speed, lateral contraction against
Poisson's ratio, elasto-plastic uniaxial compression (yield and permanent set), and a
stiff rope swinging as a compound pendulum. float32, 8 particles per cell."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from dax_physics import colliders, mpm, sampling
from dax_physics.materials import Material, MaterialParams

from . import Point, Result, on_front_note, register
from ._run import masked_mean, trace, zero_crossings

G = 9.81
WALL = 3


def _dt_config(dx, domain, materials, dt_fraction=1.0, **kw):
    """An MPMConfig whose dt is ``dt_fraction`` of the largest stable substep."""
    probe = mpm.MPMConfig(materials=materials, dx=dx, dt=1e-12, domain=domain, **kw)
    return mpm.MPMConfig(materials=materials, dx=dx, dt=dt_fraction * mpm.max_stable_dt(probe),
                         domain=domain, **kw)


# --------------------------------------------------------------------------- cantilever

#: The cantilever: thickness = width = 2 cm, free length 6 thicknesses, rho 1000 kg/m^3,
#: E = 10 MPa, nu = 0.3 (static tip deflection 0.78 mm, 4 % of the thickness).
BEAM = dict(h=0.02, length_ratio=6.0, rho=1000.0, E=1.0e7, nu=0.3)


def beam_theory(h, L, rho, E, nu):
    """Static tip deflection of a cantilever of square section h x h under its own weight:
    Euler-Bernoulli q L^4 / (8 E I) plus Timoshenko's shear term q L^2 / (2 kappa G A)
    (kappa = 10 (1 + nu) / (12 + 11 nu) for a rectangle, Cowper 1966), and the first
    bending period 2 pi / 1.8751^2 L^2 sqrt(rho A / (E I)) [m, s]."""
    A, inertia = h * h, h ** 4 / 12.0
    q = rho * G * A
    kappa = 10.0 * (1.0 + nu) / (12.0 + 11.0 * nu)
    shear = E / (2.0 * (1.0 + nu))
    deflection = q * L ** 4 / (8.0 * E * inertia) + q * L ** 2 / (2.0 * kappa * shear * A)
    period = 2.0 * math.pi / 1.875104 ** 2 * L ** 2 * math.sqrt(rho * A / (E * inertia))
    return deflection, period


def cantilever(cells: int, periods: int = 2, dt_fraction: float = 1.0, dtype=jnp.float32,
               ppc: int = 8):
    """A cantilever ``cells`` cells thick, clamped over 4 cells by a sticky box collider
    whose face is the root (a lattice plane), released from straight under gravity: it
    oscillates about its static deflection. Returns the mean tip deflection over each
    measured period (between upward crossings of the overall mean), the period, and the
    beam-theory values."""
    b = BEAM
    h = b["h"]
    L = b["length_ratio"] * h
    dx = h / cells
    clamp = 4 * dx
    mat = Material("elastic", b["rho"], youngs_modulus=b["E"], poisson_ratio=b["nu"])
    x0 = (WALL + 2) * dx + clamp  # the clamp's face
    nx = round((x0 + L) / dx) + WALL + 3
    ny = cells + 2 * WALL + 4
    z0 = (WALL + 6) * dx  # room below for the deflection
    nz = round((z0 + h) / dx) + WALL + 3
    box = colliders.ColliderSpec("box", (0.5 * clamp + dx, 0.5 * ny * dx, 0.5 * nz * dx),
                                 mode="sticky")
    cfg = _dt_config(dx, (nx, ny, nz), (mat,), dt_fraction, colliders=(box,),
                     wall_cells=WALL, max_speed=0.5)
    y0 = (WALL + 2) * dx
    x, vol = sampling.box((x0 - clamp, y0, z0), (x0 + L, y0 + h, z0 + h), dx, ppc=ppc,
                          jitter=0.0)
    cs = colliders.ColliderState.create([[x0 - 0.5 * clamp - dx, 0.5 * ny * dx,
                                          0.5 * nz * dx]], dtype=dtype)
    state = mpm.init_state(cfg, x, vol=vol, colliders=cs, dtype=dtype)
    params = MaterialParams.from_materials(cfg.materials, dtype=dtype)
    deflection, period = beam_theory(h, L, b["rho"], b["E"], b["nu"])
    tip = jnp.asarray(x[:, 0] > x0 + L - dx)
    z_tip0 = float(x[x[:, 0] > x0 + L - dx, 2].mean())
    every = 10
    n_chunks = math.ceil((periods + 0.3) * period / (every * cfg.dt))

    def probe(s):
        return jnp.stack([s.time, masked_mean(tip, s.x[:, 2])])

    final, tr, wall_s = trace(cfg, params, state, n_chunks, every, probe)
    mpm.check_state(final)
    t, d = tr[:, 0], z_tip0 - tr[:, 1]
    mid = d.mean()
    up = np.nonzero((d[:-1] < mid) & (d[1:] >= mid))[0]
    tc = t[up] + (mid - d[up]) / (d[up + 1] - d[up]) * (t[up + 1] - t[up])
    means = []
    for k in range(len(tc) - 1):
        m = (t >= tc[k]) & (t < tc[k + 1])
        means.append(float(np.trapezoid(d[m], t[m]) / (t[m][-1] - t[m][0])))
    return dict(cells=cells, dx=dx, dt=cfg.dt, wall_s=wall_s, particles=len(x),
                substeps=n_chunks * every, means=means, reference=deflection,
                period=float(np.mean(np.diff(tc))) if len(tc) > 1 else float("nan"),
                period_theory=period)


@register
def check_cantilever(level="default"):
    """Tip deflection of a clamped cantilever under its own weight against Euler-Bernoulli
    beam theory with Timoshenko's shear correction (Timoshenko & Gere, Mechanics of
    Materials; shear coefficient of Cowper 1966): the mean over the first period of the
    oscillation that follows the release. Expected first order (the clamp face and the
    free end are resolved to O(dx))."""
    sweep = (2, 4) if level == "quick" else (2, 3, 4)
    points = []
    for cells in sweep:
        r = cantilever(cells, periods=2)
        points.append(Point(cells, r["dx"], r["means"][0] / r["reference"] - 1.0, r["wall_s"],
                            measured=r["means"][0], expected=r["reference"], extra=dict(
                                period_error_vs_euler_bernoulli=r["period"] / r["period_theory"]
                                - 1.0, particles=r["particles"], substeps=r["substeps"])))
    return Result(
        name="cantilever", solver="MPM elastic",
        reference="Euler-Bernoulli + Timoshenko shear, q L^4/(8EI) + q L^2/(2 kappa G A)",
        quantity="mean tip deflection / beam theory - 1", resolution_label="cells through "
        "the thickness", default=4, points=points, tolerance=0.03, expected_order=1.0,
        pareto_note=on_front_note(points, 2, "Push-Rope's and Whip-Rope's 2 cm ropes are 2 "
                                  "cells thick"),
        notes="period vs Euler-Bernoulli's first mode (no rotary inertia or shear): " +
        ", ".join(f"{p.resolution:g} cells {p.extra['period_error_vs_euler_bernoulli']:+.1%}"
                  for p in points))


@register
def check_cantilever_creep(level="default"):
    """An elastic solid at rest under load must not creep: the cantilever (4 cells thick)
    in float32, its mean tip deflection over each of ten periods against the first
    period's, at the largest stable dt and at half of it (the drift of a float32 round-off
    bias grows as dt shrinks; float64 is the reference that does not drift). Error: the
    largest |mean_k / mean_1 - 1| over both time steps; tolerance 0.5 %."""
    periods = 3 if level == "quick" else 10
    points, extra = [], {}
    for frac in (1.0, 0.5):
        r = cantilever(4, periods=periods, dt_fraction=frac)
        m = np.asarray(r["means"])
        drift = m / m[0] - 1.0
        worst = float(drift[np.argmax(np.abs(drift))])
        points.append(Point(frac, r["dt"], worst, r["wall_s"], extra=dict(
            per_period_mean_over_theory=[float(v) for v in m / r["reference"]],
            periods_measured=len(m), substeps=r["substeps"])))
    res = Result(
        name="cantilever_creep", solver="MPM elastic",
        reference="elasticity: no creep (mean deflection constant, float64 as control)",
        quantity="max |mean_k / mean_1 - 1| over 10 periods", resolution_label="dt / dt_max",
        default=1.0, points=points, tolerance=0.005, expected_order=None, extra=extra,
        pareto_note="time-step study: both dt pass; the tasks run at 0.9-1.0 dt_max",
        error_label="drift")
    worst = max(abs(p.error) for p in points)
    res.conditions["both time steps within 0.5 %"] = worst <= 0.005
    return res


# --------------------------------------------------------------------------- bar waves

def bar_mode(cells_per_length: int, ppc: int = 8, dt_fraction: float = 0.5, length=0.2,
             youngs=1.0e5, density=1000.0, v0=0.05):
    """A free-free elastic bar (nu = 0, so the 1-D wave speed sqrt(E/rho) is exact) started
    in its first longitudinal mode v(x) = v0 cos(pi x / L); the end's velocity reverses
    after a quarter period L / (2 c). Returns the measured and exact wave speeds."""
    dx = length / cells_per_length
    width = max(2 * dx, length / 8)
    margin = 6 * dx
    lo = np.array([margin, margin, margin])
    x, vol = sampling.box(lo, lo + [length, width, width], dx, ppc=ppc, seed=0, jitter=0.0)
    mat = Material("elastic", density, youngs_modulus=youngs, poisson_ratio=0.0)
    dom = math.ceil((length + 2 * margin) / dx) + 1
    domw = math.ceil((width + 2 * margin) / dx) + 1
    cfg = _dt_config(dx, (dom, domw, domw), (mat,), dt_fraction, gravity=(0.0, 0.0, 0.0),
                     walls="none", max_speed=v0)
    v = np.zeros_like(x)
    v[:, 0] = v0 * np.cos(np.pi * (x[:, 0] - margin) / length)
    state = mpm.init_state(cfg, x, v, vol=vol)
    end = jnp.asarray(x[:, 0] < margin + 0.1 * length)
    c = math.sqrt(youngs / density)
    n = math.ceil(1.6 * (length / (2 * c)) / cfg.dt)

    def probe(s):
        return jnp.stack([s.time, masked_mean(end, s.v[:, 0])])

    final, tr, wall_s = trace(cfg, cfg.params, state, n, 1, probe)
    mpm.check_state(final)
    zc = zero_crossings(np.concatenate([[0.0], tr[:, 0]]), np.concatenate([[v0], tr[:, 1]]))
    c_meas = length / (2.0 * zc[0]) if len(zc) else float("nan")
    return dict(cells=cells_per_length, dx=dx, dt=cfg.dt, particles=len(x), substeps=n,
                wall_s=wall_s, wave_speed=c_meas, wave_speed_exact=c)


@register
def check_bar_wave_speed(level="default"):
    """Longitudinal wave speed of a free-free bar, c = sqrt(E / rho) (nu = 0: the 1-D bar
    speed is exact; Graff, Wave Motion in Elastic Solids, ch. 2): the quarter period of
    the first mode. Expected second order (a smooth mode)."""
    sweep = (8, 16) if level == "quick" else (8, 16, 32)
    points = []
    for cells in sweep:
        r = bar_mode(cells)
        points.append(Point(cells, r["dx"], r["wave_speed"] / r["wave_speed_exact"] - 1.0,
                            r["wall_s"], measured=r["wave_speed"],
                            expected=r["wave_speed_exact"]))
    return Result(
        name="bar_wave_speed", solver="MPM elastic", reference="c = sqrt(E/rho) (1-D bar)",
        quantity="c_sim / c - 1", resolution_label="cells along the bar", default=16,
        points=points, tolerance=0.03, expected_order=2.0,
        pareto_note=on_front_note(points, 16, "Push-Rope's 24 cm rope is 24 cells long "
                                  "(nearest: 16)"))


# --------------------------------------------------------------------------- uniaxial tests

def _stress(cfg, params, s):
    """Cauchy stress sigma = tau / J per particle, (N, 3, 3)."""
    Hm = mpm.algebra.mat3(s.H)
    tau = mpm.constitutive.kirchhoff_stress(cfg, params, s, Hm, mpm.algebra.mat3(s.C))
    if cfg.kinds == {"plastic"}:
        J = jnp.sqrt(jnp.maximum(1.0 + mpm.algebra.det_minus_one(Hm), 1e-12))
    else:
        J = 1.0 + mpm.algebra.det_minus_one(Hm)
    return jnp.stack([jnp.stack(row, -1) for row in tau], -2) / J[:, None, None]


def compression(cells: int, material: Material, strain: float, unload: bool,
                ppc: int = 8, side: float = 0.08, speed_fraction: float = 0.01,
                stress: bool = True):
    """A cube of ``side`` m, ``cells`` cells, on the frictionless floor (a slip wall),
    compressed by a frictionless plate (a box collider in ``separate`` mode) moving down at
    ``speed_fraction`` of the P-wave speed to the engineering ``strain``; then either held
    (``unload`` False) or moved back up at the same speed to where it started and left
    there while the cube settles. No gravity. Returns the traces of each phase: time, the
    logarithmic axial and lateral strains (from the spread of the particles) and the mean
    axial and lateral Cauchy stresses (zeros without ``stress``: for the fixed-corotated
    model XLA fused the probe's polar decomposition into the substep and ran 70x slower)."""
    dx = side / cells
    dom = cells + 2 * WALL + 8
    plate_h = 2 * dx
    plate = colliders.ColliderSpec("box", (0.5 * dom * dx, 0.5 * dom * dx, plate_h),
                                   mode="separate", friction=0.0)
    speed = speed_fraction * material.wave_speed
    cfg = _dt_config(dx, (dom, dom, dom), (material,), 1.0, colliders=(plate,),
                     gravity=(0.0, 0.0, 0.0), wall_cells=WALL, max_speed=10 * speed)
    w = WALL * dx
    lo = np.array([w + 4 * dx, w + 4 * dx, w])
    x, vol = sampling.box(lo, lo + side, dx, ppc=ppc, jitter=0.0)
    top = w + side
    cs = colliders.ColliderState.create([[0.5 * dom * dx, 0.5 * dom * dx, top + plate_h]],
                                        lin_vel=[[0.0, 0.0, -speed]])
    state = mpm.init_state(cfg, x, vol=vol, colliders=cs)
    params = cfg.params
    x0 = jnp.asarray(x)
    sd0 = jnp.std(x0, axis=0)
    t_load = strain * side / speed
    hold = 4.0 * side / material.wave_speed * 10
    n_load = math.ceil(t_load / cfg.dt)
    n_hold = math.ceil(hold / cfg.dt)
    every = max(1, (n_load + n_hold) // 400)

    def probe(s):
        sd = jnp.std(s.x, axis=0)
        sig = jnp.mean(_stress(cfg, params, s), axis=0) if stress else jnp.zeros((3, 3))
        return jnp.stack([s.time, jnp.log(sd[2] / sd0[2]),
                          0.5 * (jnp.log(sd[0] / sd0[0]) + jnp.log(sd[1] / sd0[1])),
                          sig[2, 2], 0.5 * (sig[0, 0] + sig[1, 1])])

    phases = [(n_load, -speed)]
    if unload:
        # back to the start, then 3 cells further at 10x the speed: a collider holds
        # material within a cell of its surface through the grid, so a plate left at the
        # start would still press on the cube
        phases += [(n_load, speed), (math.ceil(3 * dx / (10 * speed) / cfg.dt), 10 * speed),
                   (n_hold, 0.0)]
    else:
        phases += [(n_hold, 0.0)]
    traces, wall_s = [], 0.0
    for n, vz in phases:
        state = mpm.set_collider_velocity(state, 0, [0.0, 0.0, vz])
        state, tr, w_s = trace(cfg, params, state, math.ceil(n / every), every, probe)
        traces.append(tr)
        wall_s += w_s
    mpm.check_state(state)
    return dict(cells=cells, dx=dx, wall_s=wall_s, phases=traces, particles=len(x))


#: The elastic material of the Poisson check and the dough of the plasticity check.
POISSON_SOLID = Material("elastic", 1000.0, youngs_modulus=1.0e5, poisson_ratio=0.3)
DOUGH = Material("plastic", 1000.0, youngs_modulus=1.0e5, poisson_ratio=0.3,
                 yield_stress=500.0)


@register
def check_poisson(level="default"):
    """Lateral contraction of a cube compressed 1 % between frictionless plates (uniaxial
    stress): -eps_lateral / eps_axial = nu (Hooke's law; logarithmic strains of the
    particles' spread, time-averaged over the hold). Homogeneous, so any resolution
    should get it: no convergence order expected."""
    sweep = (4, 8) if level == "quick" else (4, 6, 8)
    points = []
    nu = POISSON_SOLID.poisson_ratio
    for cells in sweep:
        r = compression(cells, POISSON_SOLID, 0.01, unload=False, stress=False)
        hold = r["phases"][1]
        hold = hold[len(hold) // 4:]
        ratio = float(-hold[:, 2].mean() / hold[:, 1].mean())
        points.append(Point(cells, r["dx"], ratio / nu - 1.0, r["wall_s"], measured=ratio,
                            expected=nu, extra=dict(axial_strain=float(hold[:, 1].mean()))))
    return Result(
        name="poisson", solver="MPM elastic", reference="Hooke: eps_lat = -nu eps_ax",
        quantity="nu_sim / nu - 1", resolution_label="cells along the cube", default=8,
        points=points, tolerance=0.03, expected_order=None,
        pareto_note=on_front_note(points, 4, "Pour-Soup's 1.5 cm chunks are 1.5 cells "
                                  "(nearest: 4)"))


@register
def check_plastic_yield(level="default"):
    """Elasto-plastic (von Mises, perfectly plastic) uniaxial compression to 5x the yield
    strain between frictionless plates: the axial Cauchy stress plateaus at the yield
    stress sigma_y (the von Mises criterion in uniaxial stress, Simo & Hughes 1998, ch. 2),
    and after unloading the cube keeps the permanent set eps_max - sigma_y / E (logarithmic
    strains). Error: |plateau / sigma_y - 1|; the permanent set's error is a condition
    (within 10 % of the expected set)."""
    sweep = (4, 8) if level == "quick" else (4, 6, 8)
    mat = DOUGH
    eps_y = mat.yield_stress / mat.youngs_modulus
    points = []
    for cells in sweep:
        r = compression(cells, mat, 5 * eps_y, unload=True, speed_fraction=0.003)
        load, _, _, rest = r["phases"]
        flowing = load[:, 1] < -2.0 * eps_y
        plateau = float(-load[flowing, 3].mean())
        eps_max = float(load[-1, 1])
        eps_set = float(rest[len(rest) // 2:, 1].mean())
        expected_set = eps_max + mat.yield_stress / mat.youngs_modulus
        points.append(Point(cells, r["dx"], plateau / mat.yield_stress - 1.0, r["wall_s"],
                            measured=plateau, expected=mat.yield_stress, extra=dict(
                                max_strain=eps_max, permanent_set=eps_set,
                                expected_set=expected_set,
                                set_error=eps_set / expected_set - 1.0,
                                residual_stress=float(rest[len(rest) // 2:, 3].mean()))))
    res = Result(
        name="plastic_yield", solver="MPM plastic",
        reference="von Mises uniaxial: sigma = sigma_y; set = eps_max - sigma_y/E",
        quantity="plateau stress / sigma_y - 1", resolution_label="cells along the cube",
        default=8, points=points, tolerance=0.03, expected_order=None,
        pareto_note=on_front_note(points, 4, "dough in the demo scene: 4-6 cells"),
        notes="permanent set vs expected: " + ", ".join(
            f"{p.resolution:g} cells {p.extra['set_error']:+.1%}" for p in points))
    res.conditions["permanent set within 10 %"] = all(
        abs(p.extra["set_error"]) <= 0.10 for p in points)
    return res


# --------------------------------------------------------------------------- rope pendulum

#: The rope of the pendulum check: 16 cm long, 2 cm square, rho 1100 kg/m^3 (a rope), stiff
#: enough (E = 1 MPa) that its first bending mode is 11x faster than the swing.
ROPE = Material("elastic", 1100.0, youngs_modulus=1.0e6, poisson_ratio=0.3)


def rope_pendulum(cells: int, theta0: float = 0.1, ppc: int = 8, length=0.16, width=0.02):
    """A straight rope ``length`` m long, ``cells`` cells along it, hanging from a pivot: one
    grid node held still by a sticky sphere collider of half a cell on the rope's axis one
    cell below its top. Started at rest tilted by ``theta0`` about the pivot. Returns the
    measured half periods and the compound-pendulum period of the sampled particles,
    T = 2 pi sqrt(I_p / (m g d)) (1 + theta0^2 / 16)."""
    dx = length / cells
    pivot_node = np.array([WALL + 12, WALL + 8, WALL + 3 + cells + 2])
    dom = (2 * pivot_node[0], 2 * pivot_node[1], pivot_node[2] + WALL + 4)
    sphere = colliders.ColliderSpec("sphere", (0.5 * dx,), mode="sticky")
    cfg = _dt_config(dx, dom, (ROPE,), 1.0, colliders=(sphere,), wall_cells=WALL,
                     max_speed=0.5)
    p = pivot_node * dx
    top = p[2] + dx
    x, vol = sampling.box((p[0] - width / 2, p[1] - width / 2, top - length),
                          (p[0] + width / 2, p[1] + width / 2, top), dx, ppc=ppc, jitter=0.0)
    r = x - p
    c, s = math.cos(theta0), math.sin(theta0)
    x = (p + r @ np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]).T).astype(np.float32)
    cs = colliders.ColliderState.create([p])
    state = mpm.init_state(cfg, x, vol=vol, colliders=cs)
    rr = np.asarray(x, np.float64) - p
    d = float(np.linalg.norm(rr.mean(0)))
    Ip = float(np.mean(rr[:, 0] ** 2 + rr[:, 2] ** 2))  # per unit mass, about the y axis
    period = 2 * math.pi * math.sqrt(Ip / (G * d)) * (1.0 + theta0 ** 2 / 16.0)
    n = math.ceil(1.3 * period / cfg.dt)
    every = 5
    pj = jnp.asarray(p, jnp.float32)

    def probe(s):
        com = jnp.mean(s.x, axis=0) - pj
        return jnp.stack([s.time, jnp.arctan2(com[0], -com[2])])

    final, tr, wall_s = trace(cfg, cfg.params, state, math.ceil(n / every), every, probe)
    mpm.check_state(final)
    zc = zero_crossings(tr[:, 0], tr[:, 1])
    measured = 2.0 * float(np.mean(np.diff(zc))) if len(zc) >= 2 else float("nan")
    if len(zc) == 1:
        measured = 4.0 * float(zc[0])
    return dict(cells=cells, dx=dx, wall_s=wall_s, particles=len(x), period=measured,
                period_exact=period)


@register
def check_rope_pendulum(level="default"):
    """A stiff rope swinging from a pivot as a compound pendulum: T = 2 pi sqrt(I_p / (m g
    d)) with I_p and d of the sampled particles about the pivot, plus the finite-amplitude
    term theta0^2 / 16 (Landau & Lifshitz, Mechanics, sec. 11). Expected first order (the
    pivot is one grid node: its position is known to O(dx))."""
    sweep = (8, 16) if level == "quick" else (8, 12, 16)
    points = []
    for cells in sweep:
        r = rope_pendulum(cells)
        points.append(Point(cells, r["dx"], r["period"] / r["period_exact"] - 1.0, r["wall_s"],
                            measured=r["period"], expected=r["period_exact"]))
    return Result(
        name="rope_pendulum", solver="MPM elastic (rope)",
        reference="compound pendulum T = 2 pi sqrt(I_p/(m g d))",
        quantity="T_sim / T - 1", resolution_label="cells along the rope", default=16,
        points=points, tolerance=0.03, expected_order=1.0,
        pareto_note=on_front_note(points, 16, "Whip-Rope's rope is 1 cm cells (nearest: 16)"))
