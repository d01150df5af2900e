"""Resolution as a measured choice: a speed-versus-accuracy study of one task.

    python -m benchmarks.tasks resolution --task fold_cloth1 --out DIR [--seed 0] [--steps N]

For one task this builds a small, explicit ladder of resolutions (:func:`ladder`: from
coarser than the default to a *fine* rung at least twice as fine as the default in grid
and particle spacing, or in mesh spacing), runs the task's scripted expert closed loop
(every expert reads the state: the cloth experts pick the vertex farthest from its goal,
the push expert the particle farthest from the line, the pour expert and the whip expert
track a path with feedback) for the same seed on every rung, and compares each rung's
trajectory with the fine rung's. It writes ``DIR/resolution-<task>.json`` (every number)
and, where matplotlib is installed (it is not a dependency), ``DIR/resolution-<task>.png``:
the episode's object-point error against CPU time per env step, the Pareto front and the
default marked.

``--mode replay`` replays the default rung's expert actions on every rung instead (the
physics' resolution error alone, without the experts' own choices; see :func:`study`).
``--scale-contact`` (cloth) scales the self-collision's per-pair constants with the mesh
(see :func:`ladder`): the contact is per vertex pair, so with fixed constants a finer mesh
presses its layers apart harder and the rungs differ in their contact law, not only in
their discretisation.

**How trajectories of different resolutions are compared.** The particle or vertex counts
differ between rungs, so the comparison is at resolution-independent points:

* cloth (``probe = "mesh"``): fixed *material* points, the rest positions of the default
  mesh's vertices, located on each rung's rest mesh (the triangle that contains the point,
  barycentric weights; a point outside a mesh's outline, as on a T-shirt's jagged edge,
  goes to the nearest triangle with its weights clamped to it) and followed through the
  episode by the same weights on the deformed mesh. Exact for any affine motion of the
  cloth (a rigid shift gives an error equal to the shift, at any resolution).
* ropes (``probe = "centreline"``): 25 material points along the rope's centre line, at
  arc lengths ``s_k`` = 0, 1, ..., 24 cm (Push-Rope) or 0.25 m / 24 apart (Whip-Rope), each
  the mean position of the particles whose rest arc length lies within ``ROPE_KERNEL``
  (2 cm) of ``s_k``, weighted by a hat kernel (the whole cross-section averaged). At t = 0
  the rungs differ only by the particle sampling: that is the error floor reported as
  ``error_t0``.
* liquids (``probe = "cloud"``, the pour tasks): water has no material points that last
  (it mixes), so the particle clouds are compared as sets: the symmetric Chamfer distance
  ``(mean_i min_j |a_i - b_j| + mean_j min_i |a_i - b_j|) / 2`` [m], with heights measured
  from each rung's table (its floor is ``3 dx`` high, so a finer grid lowers the table by
  1.5 cm; the bowls stand on it, and the ladder lowers the wrist's start, workspace and
  pour point with it, so every rung is the same scene relative to the table). The task's
  own ``D`` (mean distance to the target cavity, resolution-independent but for its
  ``dx/2`` wall tolerance) is compared too: ``distance_diff_mean``. Two samplings of the
  same liquid are not at Chamfer 0: its value at t = 0 (``error_t0``) is that floor.

Per env step t = 1..T the error ``e_t`` is the mean distance [m] between a rung's points
and the fine rung's (Chamfer for the liquids); the JSON has ``e_t`` for every step, its
mean (``error_mean``, the figure on the chart and in the README) and maximum
(``error_max``; for material points also ``error_z_mean``, the mean of the vertical
component alone), the final ``r_gt`` of each rung and its difference to the fine rung's
(``score_diff``: the task's own score, each rung against the goal its own resolution
makes), the mean over the steps of ``|D - D_fine|`` (``distance_diff_mean`` [m]), and
the CPU time (``step_cpu_s``, the process's time, steadier on a shared machine) and wall
time (``step_wall_s``) per env step: medians over the episode's steps after an
ahead-of-time compile. A rung is on the Pareto front when no other rung is at
once no slower and no less accurate, and better in one of the two. Rungs whose physics
fails are left off the front (:func:`valid`): a cloth rung whose layers pass through each
other at the end (its thickness below its mesh spacing lets a vertex slip through the
other layer's triangles) is listed under ``invalid`` in the JSON and crossed on the chart.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._timing import timed_compile
from dax_tasks import TASKS, env_class, get_spec, make
from dax_tasks.io import atomic_write

#: Half-width [m] of the hat kernel (in rest arc length) of a rope's centre-line points.
ROPE_KERNEL = 0.02
#: Centre-line points of a rope.
ROPE_POINTS = 25
#: The chaos floor's start perturbation [m] (see :func:`study`).
FLOOR_SHIFT = 1e-5
#: A cloth rung with more than this share of its overlapping vertices within 1 mm of
#: another layer at the end has layers passing through each other (:func:`valid`).
LAYER_FAIL_SHARE = 0.05
#: How the rungs are driven (see :func:`study`).
STUDY_MODES = ("closed", "replay")
#: Fraction of the largest stable substep (the bound each task checks itself; the cloth's
#: already holds a safety factor of 0.9, the MPM's a CFL number of 0.5) a rung may use.
DT_SAFETY = 1.0


# ----------------------------------------------------------------------------- the probes

def barycentric_weights(rest_xy, faces, points_xy):
    """``(tri (K,), w (K, 3))``: for each of ``points_xy`` (K, 2) the triangle of the mesh
    (rest positions ``rest_xy`` (V, 2), ``faces`` (F, 3)) that contains it, or the one
    nearest to containing it (largest smallest barycentric coordinate), and its barycentric
    weights, clamped to be >= 0 and summing to 1 (NumPy, float64)."""
    rest_xy = np.asarray(rest_xy, np.float64)
    faces = np.asarray(faces)
    p = np.asarray(points_xy, np.float64)
    a, b, c = (rest_xy[faces[:, k]] for k in range(3))
    v0, v1 = b - a, c - a  # (F, 2)
    det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    keep = np.abs(det) > 0
    if not np.any(keep):
        raise ValueError("the mesh has no triangle of non-zero area")
    det = np.where(keep, det, 1.0)
    d = p[:, None, :] - a[None]  # (K, F, 2)
    l1 = (d[..., 0] * v1[:, 1] - d[..., 1] * v1[:, 0]) / det
    l2 = (v0[:, 0] * d[..., 1] - v0[:, 1] * d[..., 0]) / det
    lam = np.stack([1.0 - l1 - l2, l1, l2], -1)  # (K, F, 3)
    score = np.where(keep, lam.min(-1), -np.inf)
    tri = np.argmax(score, axis=1)
    w = np.clip(lam[np.arange(len(p)), tri], 0.0, None)
    w /= w.sum(1, keepdims=True)
    return tri, w


@dataclasses.dataclass(frozen=True)
class MeshProbe:
    """Material points of a cloth mesh (see the module docstring): ``faces`` (F, 3), and
    for each point its triangle ``tri`` (K,) and barycentric weights ``w`` (K, 3)."""

    faces: np.ndarray
    tri: np.ndarray
    w: np.ndarray

    @staticmethod
    def build(rest, faces, points) -> MeshProbe:
        """The probe of the rest mesh ``rest`` (V, 2 or 3) at material points ``points``
        (K, 2 or 3; only x and y are used: the rest mesh is flat)."""
        tri, w = barycentric_weights(np.asarray(rest)[:, :2], faces, np.asarray(points)[:, :2])
        return MeshProbe(np.asarray(faces), tri, w)

    def __call__(self, x) -> np.ndarray:
        """The material points' positions (K, 3) on the deformed mesh ``x`` (V, 3)."""
        x = np.asarray(x, np.float64)
        corners = x[self.faces[self.tri]]  # (K, 3, 3)
        return np.einsum("kj,kjd->kd", self.w, corners)


@dataclasses.dataclass(frozen=True)
class CentrelineProbe:
    """Centre-line points of a rope: hat-kernel weights (K, N) over the particles' rest arc
    lengths (see the module docstring)."""

    weights: np.ndarray

    @staticmethod
    def build(rest_s, stations, kernel: float = ROPE_KERNEL) -> CentrelineProbe:
        """Weights of particles at rest arc lengths ``rest_s`` (N,) for the centre-line
        points at arc lengths ``stations`` (K,) [m]."""
        s = np.asarray(rest_s, np.float64)
        w = np.clip(1.0 - np.abs(s[None, :] - np.asarray(stations)[:, None]) / kernel, 0, None)
        total = w.sum(1, keepdims=True)
        if np.any(total <= 0):
            raise ValueError(f"a centre-line point has no particle within {kernel} m of it")
        return CentrelineProbe(w / total)

    def __call__(self, x) -> np.ndarray:
        return self.weights @ np.asarray(x, np.float64)


@dataclasses.dataclass(frozen=True)
class CloudProbe:
    """A liquid's particle cloud, heights measured from the table at ``floor_z`` [m]."""

    floor_z: float

    def __call__(self, x) -> np.ndarray:
        x = np.array(x, np.float64)
        x[:, 2] -= self.floor_z
        return x


def chamfer(a, b, chunk: int = 2048) -> float:
    """Symmetric Chamfer distance [m] of point sets ``a`` (N, 3) and ``b`` (M, 3): the mean
    of ``mean_i min_j |a_i - b_j|`` and ``mean_j min_i |a_i - b_j|`` (NumPy). The nearest
    neighbours are found with a matrix product and their distances then computed directly,
    so identical sets are at exactly 0."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    centre = a.mean(0)
    a, b = a - centre, b - centre
    bb = np.sum(b * b, 1)
    near_ab = np.empty(len(a), np.int64)
    best_ba = np.full(len(b), np.inf)
    near_ba = np.zeros(len(b), np.int64)
    for i in range(0, len(a), chunk):
        blk = a[i:i + chunk]
        d2 = np.sum(blk * blk, 1)[:, None] + bb[None] - 2.0 * blk @ b.T
        near_ab[i:i + chunk] = d2.argmin(1)
        j = d2.argmin(0)
        better = d2[j, np.arange(len(b))] < best_ba
        best_ba = np.where(better, d2[j, np.arange(len(b))], best_ba)
        near_ba = np.where(better, i + j, near_ba)
    d_ab = np.linalg.norm(a - b[near_ab], axis=1)
    d_ba = np.linalg.norm(b - a[near_ba], axis=1)
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def point_error(kind: str, a, b) -> float:
    """The error [m] between two probes' outputs: mean distance of corresponding material
    points (``mesh``, ``centreline``) or the Chamfer distance of two clouds (``cloud``)."""
    if kind == "cloud":
        return chamfer(a, b)
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"material points of shapes {a.shape} and {b.shape} do not "
                         f"correspond")
    return float(np.mean(np.linalg.norm(a - b, axis=-1)))


PROBE_KINDS = {"pour_water": "cloud", "pour_soup": "cloud", "push_rope": "centreline",
               "whip_rope": "centreline", "fold_cloth1": "mesh", "fold_cloth3": "mesh",
               "fold_tshirt": "mesh", "unfold_cloth1": "mesh", "unfold_cloth3": "mesh"}


def make_probe(env):
    """The resolution-independent probe of ``env`` (see the module docstring)."""
    name = env.spec.name
    kind = PROBE_KINDS[name]
    scene = env.spec.scene
    if kind == "mesh":
        from dax_tasks.tasks._cloth import rest_vertices

        rest, faces = rest_vertices(scene)
        points, _ = rest_vertices(get_spec(name).scene)  # the default mesh's vertices
        return MeshProbe.build(rest, faces, points)
    if kind == "centreline":
        stations = np.linspace(0.0, scene.rope_length, ROPE_POINTS)
        return CentrelineProbe.build(np.asarray(env._rest)[:, 0], stations)
    return CloudProbe(float(scene.floor_z))


# ----------------------------------------------------------------------------- the ladders

@dataclasses.dataclass(frozen=True)
class Rung:
    """One resolution of a task: ``label``, ``spacing`` (grid cell or mesh spacing [m]),
    the :func:`dax_tasks.make` ``overrides`` (TaskSpec fields, a new scene) and what it
    changes (``note``)."""

    label: str
    spacing: float
    overrides: dict
    note: str = ""
    is_default: bool = False
    is_fine: bool = False


def _stable_substeps(step_time: float, dtmax: float, at_least: int = 1) -> int:
    return max(at_least, math.ceil(step_time / (DT_SAFETY * dtmax) * (1 + 1e-9)))


def _mpm_rung(name, label, note, dx=None, ppc=None, window=None, domain=None,
              substeps=None, fine=False):
    """An MPM rung: the default scene with a new cell size (domain and window scaled to
    keep their extent), particles per cell and substeps (default: the default's scaled by
    the cell size, at least what the stability bound needs)."""
    from dax_physics import max_stable_dt

    spec = get_spec(name)
    scene = spec.scene
    dx = scene.dx if dx is None else dx
    r = scene.dx / dx
    changes = {"dx": dx, "ppc": scene.ppc if ppc is None else ppc}
    if domain is None:
        domain = tuple(round(c * r) for c in scene.domain)
        if not all(abs(c * dx - c0 * scene.dx) < 1e-9 for c, c0 in zip(domain, scene.domain,
                                                                       strict=True)):
            raise ValueError(f"{name}: dx {dx} does not divide the domain "
                             f"{[c * scene.dx for c in scene.domain]} m")
    changes["domain"] = domain
    if hasattr(scene, "window"):
        changes["window"] = window or tuple(math.ceil(c * r) for c in scene.window)
    step_time = spec.substeps * scene.dt
    if substeps is None:
        substeps = spec.substeps if dx == scene.dx else math.ceil(spec.substeps * r)
        # the bound at this cell size, from a configuration at a substep surely stable
        cfg = env_class(name).mpm_config(dataclasses.replace(scene, **changes, dt=1e-7))
        dtmax = max_stable_dt(cfg)
        substeps = _stable_substeps(step_time, dtmax, substeps)
    changes["dt"] = step_time / substeps
    if hasattr(scene, "lift_substeps"):  # Push-Rope: the lift keeps its share of the step
        changes["lift_substeps"] = round(scene.lift_substeps * substeps / spec.substeps)
    new = dataclasses.replace(scene, **changes)
    if hasattr(scene, "floor_z") and new.floor_z != scene.floor_z:
        # The pour tasks' table is the floor wall's surface, 3 cells high: on a finer grid
        # it is lower. Everything placed in absolute heights (the wrist's start, its
        # workspace, the expert's pour point) moves with it, so the scene is the same
        # relative to the table (the bowls stand on it already).
        dz = new.floor_z - scene.floor_z

        def lower(v, k=2):
            return tuple(c + dz if i == k else c for i, c in enumerate(v))

        new = dataclasses.replace(new, source_wrist=lower(scene.source_wrist),
                                  wrist_low=lower(scene.wrist_low),
                                  wrist_high=lower(scene.wrist_high),
                                  pour_offset=lower(scene.pour_offset))
    return Rung(label, dx, {"substeps": substeps, "scene": new}, note,
                is_default=new == scene and substeps == spec.substeps, is_fine=fine)


def _cloth_rung(name, label, note, fine=False, scale_contact=False, **scene_changes):
    """A cloth rung: the default scene with a new mesh (``n`` or ``spacing``), the substep at
    most ``DT_SAFETY`` of its stable bound and enough substeps for the default's simulated
    time per env step (the settling keeping its share), and the self-collision's hash
    slots scaled with the vertices per hash cell (at least the default's). The cloth's
    material and thickness are the default's; its per-pair contact constants too, or with
    ``scale_contact`` scaled by the mesh spacing to the fourth power (see below)."""
    import dax_physics.cloth as dc
    from dax_tasks.tasks import _cloth

    spec = get_spec(name)
    scene = spec.scene
    trial = dataclasses.replace(scene, **scene_changes)
    if trial == scene:
        return Rung(label, scene.mesh_spacing, {}, note, is_default=True, is_fine=fine)
    ratio = scene.mesh_spacing / trial.mesh_spacing
    # Self-collision is per vertex pair: a vertex of area s^2 meets ~pi h^2 / s^2 vertices of
    # the layer under it, so the pressure between layers goes as k h^3 / s^4. Scaling the
    # per-pair stiffness, damping and friction by s^4 keeps the layers' pressure-gap law
    # (their rest gap under gravity, their shear resistance) the same on every mesh.
    contact = ratio ** -4 if scale_contact else 1.0
    trial = dataclasses.replace(
        trial, self_candidates=max(scene.self_candidates,
                                   math.ceil(scene.self_candidates * ratio ** 2)),
        self_stiffness=scene.self_stiffness * contact,
        self_damping=scene.self_damping * contact,
        self_friction=scene.self_friction * contact)
    step_time = spec.substeps * scene.dt
    dtmax = dc.max_stable_dt(_cloth.cloth_config(trial), _cloth.make_cloth(trial))
    substeps = _stable_substeps(step_time, dtmax)
    settle = round(substeps * scene.settle_substeps / spec.substeps)
    new = dataclasses.replace(trial, dt=step_time / substeps, settle_substeps=settle)
    return Rung(label, new.mesh_spacing, {"substeps": substeps, "scene": new}, note,
                is_fine=fine)


def _mpm_ladder(name: str, between: str) -> list:
    """An MPM task's four rungs around its default (``dx``, ``ppc``): half the particles
    per cell; the default; ``between`` = ``"particles"`` (twice the particles per cell) or
    ``"grid"`` (grid and particle spacing x 0.8); the fine rung (the cell halved, the
    particles per cell kept). Labels are read off the scenes, so they follow the default."""
    scene = get_spec(name).scene
    dx, ppc = scene.dx, scene.ppc

    def label(d, p, tag=""):
        return f"dx {1e3 * d:g} mm, ppc {p}{tag}"

    if between == "particles":
        middle = _mpm_rung(name, label(dx, 2 * ppc), "twice the particles", ppc=2 * ppc)
    else:
        d = round(0.8 * dx, 9)
        middle = _mpm_rung(name, label(d, ppc), "grid and particle spacing x 0.8", dx=d)
    return [
        _mpm_rung(name, label(dx, ppc // 2), "half the default's particles", ppc=ppc // 2),
        _mpm_rung(name, label(dx, ppc, " (default)"), "the default"),
        middle,
        _mpm_rung(name, label(dx / 2, ppc, " (fine)"), "grid and particle spacing halved",
                  dx=dx / 2, fine=True),
    ]


def ladder(name: str, scale_contact: bool = False) -> list:
    """The rungs of task ``name``, coarse to fine; the last is the fine reference (twice
    as fine as the default in spacing: grid and particles, or mesh). ``scale_contact``
    (cloth): the self-collision's per-pair stiffness, damping and friction scaled by the
    mesh spacing to the fourth power, so the pressure between layers is the same law on
    every mesh (off: the same per-pair constants, a contact that stiffens as the mesh
    refines)."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; valid names: {', '.join(TASKS)}")
    if name in ("pour_water", "pour_soup"):  # the middle rung: twice the particles
        rungs = _mpm_ladder(name, between="particles")
    elif name in ("push_rope", "whip_rope"):  # the middle rung: a finer grid
        rungs = _mpm_ladder(name, between="grid")
    elif name == "fold_tshirt":
        cloth = functools.partial(_cloth_rung, name, scale_contact=scale_contact)
        rungs = [
            cloth("3.5 cm mesh", "coarser mesh", spacing=0.035),
            cloth("2.5 cm mesh (default)", "the default"),
            cloth("1.875 cm mesh", "mesh spacing x 0.75", spacing=0.01875),
            cloth("1.25 cm mesh (fine)", "mesh spacing halved", fine=True, spacing=0.0125),
        ]
    else:  # the square cloths
        cloth = functools.partial(_cloth_rung, name, scale_contact=scale_contact)
        rungs = [
            cloth("9 x 9 (3.75 cm)", "coarser mesh", n=9),
            cloth("11 x 11 (3 cm, default)", "the default"),
            cloth("16 x 16 (2 cm)", "mesh spacing x 2/3", n=16),
            cloth("21 x 21 (1.5 cm, fine)", "mesh spacing halved", fine=True, n=21),
        ]
    return rungs


# ----------------------------------------------------------------------------- running

def run_rung(name: str, rung: Rung, seed: int = 0, steps: int | None = None,
             log=None, perturb: float = 0.0, actions=None) -> dict:
    """The expert's closed-loop episode of ``name`` at ``rung`` from ``PRNGKey(seed)``, or,
    with ``actions`` (a sequence of at least ``steps`` actions), those actions replayed
    open loop: the probe's points at t = 0..T, ``r_gt`` and ``D`` per step, the actions
    taken, CPU and wall time per env step (medians over the steps, after an ahead-of-time
    compile). ``perturb`` [m] moves the object's particles or vertices (not the tools) by
    that much along x at the start (the chaos floor, see :func:`study`)."""
    t_build = time.perf_counter()
    env = make(name, **rung.overrides)
    build_s = time.perf_counter() - t_build
    params = env.default_params
    probe = make_probe(env)
    steps = env.horizon if steps is None else min(int(steps), env.horizon)
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    _, state = jax.jit(env.reset)(jax.random.PRNGKey(seed), params)
    if perturb:
        x = state.physics.x
        state = state.replace(physics=state.physics.replace(
            x=x + jnp.asarray([perturb, 0.0, 0.0], x.dtype)))
    if actions is None:
        expert, c_expert = timed_compile(jax.jit(env.expert_action), state, params)
        action = expert(state, params)
    else:
        if len(actions) < steps:
            raise ValueError(f"{len(actions)} actions to replay, {steps} steps asked")
        c_expert, action = 0.0, jnp.asarray(actions[0])
    step, c_step = timed_compile(jax.jit(env.step), state, action, params)
    points = [probe(env.object_points(state.physics))]
    r_gt, dist, cpu, wall, taken = [], [], [], [], []
    for t in range(steps):
        if actions is None:
            action = jax.block_until_ready(expert(state, params))
        else:
            action = jnp.asarray(actions[t])
        taken.append(np.asarray(action))
        c0, w0 = time.process_time(), time.perf_counter()
        _, state, _, _, info = jax.block_until_ready(step(state, action, params))
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
        points.append(probe(env.object_points(state.physics)))
        r_gt.append(float(info["r_gt"]))
        dist.append(float(info["distance"]))
        if log:
            log(f"  {rung.label}: step {t + 1}/{steps} r_gt {r_gt[-1]:.4f} "
                f"({cpu[-1]:.3f} s CPU, {wall[-1]:.3f} s wall)")
    spec = env.spec
    scene = spec.scene
    return {
        **_layer_record(name, env, state),
        "label": rung.label, "note": rung.note, "is_default": rung.is_default,
        "is_fine": rung.is_fine, "spacing_m": rung.spacing,
        "object_points": int(env.n_object_points), "substeps": spec.substeps,
        "dt_s": float(scene.dt), "scene": _scene_summary(scene),
        "steps": steps, "r_gt": r_gt, "distance": dist, "final_r_gt": r_gt[-1],
        "step_cpu_s": float(np.median(cpu)), "step_wall_s": float(np.median(wall)),
        "compile_step_s": c_step, "compile_expert_s": c_expert, "build_s": build_s,
        "finite": bool(np.all(np.isfinite(np.asarray(points[-1])))),
        "_points": points, "_actions": taken,
    }


def _layer_record(name: str, env, state) -> dict:
    """Cloth: whether the final state's layers lie apart (``_cloth.layer_gaps``: the
    vertical gap of every vertex to each triangle of another layer above or below it)
    as ``layer_overlaps`` (how many such vertex-triangle pairs), ``layer_gap_min_m`` and
    ``layer_gap_under_1mm`` (the share of them closer than 1 mm: layers passing through
    each other, as when the thickness is below the mesh spacing). Empty for the others."""
    if PROBE_KINDS[name] != "mesh":
        return {}
    from dax_tasks.tasks import _cloth

    scene = env.spec.scene
    gaps = _cloth.layer_gaps(np.asarray(env.object_points(state.physics)),
                             np.asarray(env.base_cloth.faces), _cloth.flat_vertices(scene),
                             3.01 * scene.mesh_spacing)
    return {"layer_overlaps": int(len(gaps)),
            "layer_gap_min_m": float(gaps.min()) if len(gaps) else None,
            "layer_gap_under_1mm": float(np.mean(gaps < 1e-3)) if len(gaps) else 0.0}


def _scene_summary(scene) -> dict:
    keys = ("dx", "ppc", "domain", "window", "n", "spacing", "settle_substeps",
            "self_candidates", "lift_substeps")
    out = {}
    for k in keys:
        if hasattr(scene, k):
            v = getattr(scene, k)
            out[k] = list(v) if isinstance(v, tuple) else v
    if getattr(scene, "shape", None) == "square":
        out.pop("spacing", None)
    elif getattr(scene, "shape", None) == "tshirt":
        out.pop("n", None)
    return out


def compare(name: str, records: list) -> list:
    """Each record's error against the fine record's (``is_fine``; the last if none is),
    per step and summarised (see the module docstring); returns the records with
    ``error`` (t = 1..T), ``error_t0``, ``error_mean``, ``error_max``, ``score_diff``
    added and their points dropped."""
    kind = PROBE_KINDS[name]
    fine = next((r for r in records if r.get("is_fine")), records[-1])
    ref = fine["_points"]
    out = []
    for rec in records:
        pts = rec["_points"]
        n = min(len(pts), len(ref))
        err = [point_error(kind, pts[t], ref[t]) for t in range(n)]
        rec = {k: v for k, v in rec.items() if k not in ("_points", "_actions")}
        rec.update(error_t0=err[0], error=err[1:], error_mean=float(np.mean(err[1:])),
                   error_max=float(np.max(err[1:])),
                   score_diff=rec["final_r_gt"] - fine["final_r_gt"],
                   distance_diff_mean=float(np.mean(np.abs(
                       np.asarray(rec["distance"][:n - 1]) - fine["distance"][:n - 1]))))
        if kind != "cloud":  # the vertical part: how much of it is the layers' heights
            rec["error_z_mean"] = float(np.mean([np.mean(np.abs(
                np.asarray(pts[t])[:, 2] - np.asarray(ref[t])[:, 2])) for t in range(1, n)]))
        out.append(rec)
    return out


def valid(record: dict) -> bool:
    """Whether a rung's physics holds: a cloth rung whose layers pass through each other
    (more than :data:`LAYER_FAIL_SHARE` of its overlapping vertices within 1 mm of another
    layer at the end) is not a point of the speed-accuracy trade-off, however near the fine
    rung it lies. Other rungs are valid."""
    return record.get("layer_gap_under_1mm", 0.0) <= LAYER_FAIL_SHARE


def pareto(records: list, time_key: str = "step_cpu_s", error_key: str = "error_mean"):
    """Indices of the valid records (:func:`valid`) on the Pareto front of (time, error),
    both lower-better: no other valid record is at once no slower and no less accurate
    and better in one of them."""
    front = []
    for i, a in enumerate(records):
        if not valid(a):
            continue
        dominated = any(
            b[time_key] <= a[time_key] and b[error_key] <= a[error_key]
            and (b[time_key] < a[time_key] or b[error_key] < a[error_key])
            for j, b in enumerate(records) if j != i and valid(b))
        if not dominated:
            front.append(i)
    return front


def verdict(records: list, time_key: str = "step_cpu_s") -> dict:
    """Whether the default is on the front; if not, the rung that dominates it most (by
    time) with the ratios of time and error."""
    front = pareto(records, time_key)
    i = next((k for k, r in enumerate(records) if r["is_default"]), None)
    if i is None:
        return {"default_on_front": None}
    d = records[i]
    out = {"default_on_front": i in front, "default_label": d["label"],
           "default_error_mean_m": d["error_mean"], "default_error_max_m": d["error_max"],
           "default_score_diff": d["score_diff"], "front": [records[k]["label"] for k in front],
           "invalid": [r["label"] for r in records if not valid(r)]}
    if i not in front and valid(d):
        dom = [r for k, r in enumerate(records) if k != i and valid(r)
               and r[time_key] <= d[time_key] and r["error_mean"] <= d["error_mean"]]
        best = min(dom, key=lambda r: r[time_key])
        out["dominated_by"] = {
            "label": best["label"], "time_ratio": best[time_key] / d[time_key],
            "error_ratio": (best["error_mean"] / d["error_mean"]) if d["error_mean"] else None}
    return out


def study(name: str, rungs: list | None = None, seed: int = 0, steps: int | None = None,
          log=None, floor: float = FLOOR_SHIFT, mode: str = "closed") -> dict:
    """Run every rung (default :func:`ladder`) and compare them (see the module docstring);
    the JSON-able result.

    ``mode``: ``"closed"``, each rung's expert acts on its own state (the score a rung
    gets, but a rung whose expert picks another vertex or push point diverges from the
    fine rung for a reason that is not the physics); ``"replay"``, the default rung's
    closed-loop actions are replayed open loop on every rung (the same control inputs:
    the error is the physics' resolution error alone, the errors of a converging solver
    shrink toward the fine rung; the scores are those of the replayed actions).

    ``floor`` [m] (0: skipped): the default rung (else the first) is run a second time
    with its object moved by ``floor`` along x at the start, and compared with its own
    unmoved run (``chaos_floor``: error and score difference). A perturbation of 10 µm
    is physics that is the same up to rounding; what it grows into over the episode is the
    part of a rung's error that no resolution removes (the folds of stacked cloth layers
    and the splashes of a pour are chaotic), so differences between rungs below it say
    nothing about the resolution."""
    if mode not in STUDY_MODES:
        raise ValueError(f"unknown study mode {mode!r}; valid: {', '.join(STUDY_MODES)}")
    rungs = ladder(name) if rungs is None else list(rungs)
    if not rungs:
        raise ValueError("a study needs at least one rung")
    k = next((i for i, r in enumerate(rungs) if r.is_default), 0)
    replay = None
    if mode == "replay":  # the default first: its actions drive every other rung
        if log:
            log(f"[resolution] {name}: {rungs[k].label} (its actions are replayed)")
        first = run_rung(name, rungs[k], seed, steps, log)
        replay = first["_actions"]
    records = []
    for i, rung in enumerate(rungs):
        if replay is not None and i == k:
            records.append(first)
            continue
        if log:
            log(f"[resolution] {name}: {rung.label}")
        records.append(run_rung(name, rung, seed, steps, log, actions=replay))
    chaos = None
    if floor:
        base = dataclasses.replace(rungs[k], label=rungs[k].label + f" moved {floor:g} m",
                                   is_default=False, is_fine=True)
        if log:
            log(f"[resolution] {name}: {base.label} (chaos floor)")
        moved = run_rung(name, base, seed, steps, log, perturb=floor, actions=replay)
        pair = compare(name, [{**records[k], "is_fine": False}, moved])
        chaos = {"rung": rungs[k].label, "shift_m": floor,
                 **{key: pair[0][key] for key in ("error", "error_t0", "error_mean",
                                                  "error_max", "score_diff")}}
    records = compare(name, records)
    return {"bench": "resolution", "task": name, "seed": seed, "steps": records[0]["steps"],
            "mode": mode, "probe": PROBE_KINDS[name], "error_unit": "m",
            "time_key": "step_cpu_s", "rungs": records, **verdict(records),
            "chaos_floor": chaos,
            "device": str(jax.devices()[0]), "load_average": list(os.getloadavg())}


def chart(result: dict, path: str) -> bool:
    """Error against CPU time per env step, the front and the default marked; False
    without matplotlib (not a dependency)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import matplotlib.ticker
    except ImportError:
        return False
    recs = result["rungs"]
    t = [r["step_cpu_s"] for r in recs]
    e = [1e3 * r["error_mean"] for r in recs]
    emax = [1e3 * r["error_max"] for r in recs]
    front = pareto(recs)
    fig, ax = plt.subplots(figsize=(5.6, 3.8))
    ax.scatter(t, e, c="tab:blue", zorder=3, label="episode mean error")
    ax.scatter(t, emax, c="tab:blue", marker="_", s=120, zorder=3, label="episode max error")
    for x, lo, hi in zip(t, e, emax, strict=True):
        ax.plot([x, x], [lo, hi], c="tab:blue", lw=0.6, alpha=0.5)
    ft = sorted(front, key=lambda k: t[k])
    ax.plot([t[k] for k in ft], [e[k] for k in ft], "k--", lw=0.9, label="Pareto front")
    for k, r in enumerate(recs):
        ax.annotate(r["label"], (t[k], e[k]), fontsize=7,  # staggered: rungs may be close
                    xytext=(4, (-10, 4, -22, 16)[k % 4]), textcoords="offset points")
        if not valid(r):
            ax.scatter([t[k]], [e[k]], s=90, marker="x", c="tab:gray", zorder=4,
                       label="layers pass through each other")
        if r["is_default"]:
            ax.scatter([t[k]], [e[k]], s=160, facecolors="none", edgecolors="tab:red",
                       zorder=4, label="default")
    chaos = result.get("chaos_floor")
    if chaos:
        ax.axhline(1e3 * chaos["error_mean"], color="tab:gray", ls=":", lw=0.9,
                   label=f"chaos floor (default, start moved {1e6 * chaos['shift_m']:g} µm)")
    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    lo, hi = min(t), max(t)
    ax.set_xlim(lo / 1.5, hi * 4.0)  # room for the labels on the right
    ax.set_xlabel("CPU time per env step [s]")
    what = {"cloud": "Chamfer", "centreline": "centre-line point",
            "mesh": "material point"}[result["probe"]]
    ax.set_ylabel(f"{what} error vs fine [mm]")
    how = {"closed": "expert (closed loop)", "replay": "default's expert actions replayed"}
    ax.set_title(f"{result['task']}: {how[result.get('mode', 'closed')]}, seed "
                 f"{result['seed']}, {result['steps']} steps", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=80))
    plt.close(fig)
    return True


def _mm(x) -> str:
    """A distance [m] in mm: one decimal, two significant figures below 1 mm."""
    v = 1e3 * x
    return f"{v:.1f}" if abs(v) >= 1 else f"{v:#.2g}".rstrip(".")


def render_table(*paths) -> str:
    """The Markdown table of studies (:func:`study`'s JSON files, one per task): per task
    its rungs (the default in bold, the fine rung last, a rung whose physics fails crossed),
    the default's error against the fine rung (mean / max over the env steps [mm]), the
    chaos floor's mean error [mm], the final r_gt of the default and the fine rung, the CPU
    time per env step of both [s] and whether the default is on the Pareto front (if not,
    the rung that dominates it with its time and error ratios); the seed, mode, device,
    load and dates under the table."""
    from benchmarks._report import file_date, load_range, read_result

    out = ["| task | rungs (default in bold, fine last, ✗ not valid) | default's error vs "
           "fine: mean / max [mm] | chaos floor [mm] | final r_gt: default / fine | CPU per "
           "step: default / fine [s] | default on the Pareto front |",
           "| --- | --- | --- | --- | --- | --- | --- |"]
    loads, seeds, modes, dates, devices, files = [], set(), set(), set(), set(), []
    for path in paths:
        path, doc = read_result(path)
        files.append(f"`{path.as_posix()}`")
        rungs = doc["rungs"]
        d = next(r for r in rungs if r["is_default"])
        f = next(r for r in rungs if r["is_fine"])
        invalid = set(doc.get("invalid", []))
        names = []
        for r in rungs:
            label = r["label"].replace(" (default)", "").replace(", default)", ")")
            label = label.replace(" (fine)", "").replace(", fine)", ")")
            label = f"**{label}**" if r["is_default"] else label
            names.append(label + (" ✗" if r["label"] in invalid else ""))
        if doc.get("default_on_front"):
            front = "yes, among the valid rungs" if invalid else "yes"
        elif doc.get("dominated_by"):
            dom = doc["dominated_by"]
            front = (f"no ({dom['label']} is {1 / dom['time_ratio']:.1f}x as fast with "
                     f"{dom['error_ratio']:.2f}x the error)")
        else:
            front = "no"
        chaos = doc.get("chaos_floor") or {}
        out.append(f"| {doc['task']} | {'; '.join(names)} | {_mm(d['error_mean'])} / "
                   f"{_mm(d['error_max'])} | "
                   f"{_mm(chaos['error_mean']) if chaos else '-'} | "
                   f"{d['final_r_gt']:.3f} / {f['final_r_gt']:.3f} | "
                   f"{d['step_cpu_s']:#.2g}".rstrip(".") + f" / {f['step_cpu_s']:#.3g}".rstrip(".")
                   + f" | {front} |")
        loads += doc.get("load_average", [])[:1]
        seeds.add(doc["seed"])
        modes.add(doc.get("mode", "closed"))
        dates.add(file_date(path) or "date not recorded")
        devices.add(doc.get("device", "?"))
    out += ["", f"Seed {', '.join(map(str, sorted(seeds)))}, {' and '.join(sorted(modes))} "
            "loop (closed: each rung's own expert; replay: the default's actions). Error: "
            "the mean distance between a rung's probe points and the fine rung's, per env "
            "step, its mean and maximum over the episode; chaos floor: the default against "
            "itself with its start moved "
            f"{FLOOR_SHIFT * 1e6:g} µm; CPU per step: the process's CPU time per env step, "
            "median over the episode after an ahead-of-time compile. ✗: layers that pass "
            "through each other at the end (`benchmarks.resolution.valid`), left off the "
            "front. "
            f"{', '.join(sorted(devices))}, 1-minute load {load_range(loads)} at the start "
            f"of the runs; {', '.join(sorted(dates))}; `python -m benchmarks.tasks "
            f"resolution --task TASK --out DIR` (files: "
            + ", ".join(files) + ")."]
    return "\n".join(out) + "\n"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m benchmarks.tasks resolution",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", required=True, help=f"one of {', '.join(TASKS)}")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=None,
                   help="env steps per episode (default: the task's horizon)")
    p.add_argument("--floor", type=float, default=FLOOR_SHIFT,
                   help="start perturbation [m] of the chaos-floor run of the default "
                        "(0: no such run)")
    p.add_argument("--mode", choices=STUDY_MODES, default="closed",
                   help="closed: each rung's expert acts on its own state; replay: the "
                        "default rung's expert actions replayed on every rung (the physics' "
                        "resolution error alone)")
    p.add_argument("--scale-contact", action="store_true",
                   help="cloth: scale the self-collision's per-pair constants by the mesh "
                        "spacing^4 on every rung (the same pressure between layers)")
    p.add_argument("--prefix", default="resolution-",
                   help="file name prefix: DIR/<prefix><task>.json and .png")
    args = p.parse_args(argv)
    if args.task not in TASKS:
        print(f"error: unknown task {args.task!r}; valid names: {', '.join(TASKS)}",
              file=sys.stderr)
        raise SystemExit(2)
    if args.steps is not None and args.steps < 1:
        print("error: --steps must be >= 1", file=sys.stderr)
        raise SystemExit(2)
    os.makedirs(args.out, exist_ok=True)
    result = study(args.task, ladder(args.task, args.scale_contact), seed=args.seed,
                   steps=args.steps,
                   log=lambda m: print(m, file=sys.stderr, flush=True), floor=args.floor,
                   mode=args.mode)
    base = os.path.join(args.out, f"{args.prefix}{args.task}")
    atomic_write(base + ".json", json.dumps(result, indent=1).encode())
    result["png"] = chart(result, base + ".png")
    summary = {k: result[k] for k in ("task", "mode", "default_on_front", "default_error_mean_m",
                                      "default_error_max_m", "default_score_diff")
               if k in result}
    if result.get("chaos_floor"):
        summary["chaos_floor_error_mean"] = result["chaos_floor"]["error_mean"]
    summary["rungs"] = [{k: r[k] for k in ("label", "step_cpu_s", "error_mean", "error_max",
                                            "final_r_gt", "score_diff", "layer_gap_under_1mm")
                         if k in r} for r in result["rungs"]]
    print(json.dumps(summary), flush=True)
    return result


if __name__ == "__main__":
    main()
