"""One MLS-MPM substep as a sequence of named stages, and rollouts of many.

:func:`step` runs, in this order (each stage a pure function under a ``jax.named_scope``
of its name, so a profile attributes its time):

1. :func:`stencil`: the active window's origin, each particle's 3x3x3 block of nodes and
   its quadratic B-spline weights;
2. :func:`p2g`: Kirchhoff stress (scope ``p2g/stress``), affine momentum, one scatter of
   momentum and mass onto the grid;
3. :func:`grid_update`: node momentum -> node velocity, with the light-node guard;
4. :func:`boundaries`: the kinematic drive, the walls, the colliders;
5. :func:`g2p`: gather of each particle's block, new velocity, APIC matrix C, position;
6. :func:`deformation`: the fluids' volume ratio J and the deformation H, with the
   plastic return map (:func:`plasticity`, scope ``deformation/plasticity``);
7. :func:`held`: colliders advance, and the particles they hold move with them;
8. :func:`project`: free particles inside a collider whose spec sets ``project`` go back
   onto its surface (nothing is compiled when none does);
9. :func:`stability`: the ``finite`` flag (positions finite, no particle outrunning dt).

Arrays: N particles, a window of M = Wx Wy Wz nodes, C = 4 grid channels (momentum
[kg m/s] and mass [kg]; 5 with a drive, the driven mass). Matrices per particle are
component lists (:mod:`dax_physics.mpm.algebra`).

Where XLA:CPU would fuse a cheap value into each of many readers and recompute it there,
the stages write it once (:func:`dax_physics._fusion.materialise`); a cotangent that many
adjoints read is materialised likewise (``materialise_cotangent``). The reverse pass keeps
the values named in :data:`REVERSE_SAVED` and recomputes the rest.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from .. import _transfer
from .. import colliders as col
from .._checks import step_count
from .._fusion import materialise
from ..materials import MaterialParams
from ..precision import HIGHEST
from ..scan import checkpointed_scan
from . import algebra as alg
from .config import MPMConfig, max_stable_speed
from .constitutive import KIND_CODE, kirchhoff_stress, particle_kinds, return_map
from .state import MPMState, window_origin

#: Driven-mass fraction above which a grid node moves with the driven particles
#: (:func:`step`'s ``drive``); below it the drive fades out smoothly to zero driven mass.
DRIVE_FRACTION = 1e-3

#: The intermediates of a substep that its reverse pass keeps: the P2G grid (the grid
#: update's adjoint divides by its masses), the G2P moments (the new velocity, C and J are
#: affine in them) and the polar rotation of elastic particles (an iteration). Everything
#: else is recomputed from the substep's input state, all of it elementwise: weights,
#: stresses, the grid update.
REVERSE_SAVED = ("mpm_grid", "mpm_moments", "mpm_polar")
_REMAT_POLICY = jax.checkpoint_policies.save_only_these_names(*REVERSE_SAVED)


class Stencil(NamedTuple):
    """Where the particles meet the grid: ``origin`` (3,) int32, the window's origin
    [cells]; ``base`` (N, 3) int32, each block's corner in window cells (clamped into the
    window); ``fx`` (N, 3), the position relative to the corner [cells], in [0.5, 1.5);
    ``w`` (N, 3 offsets, 3 axes), the B-spline weights; ``escaped`` (), a block was
    clamped."""

    origin: jnp.ndarray
    base: jnp.ndarray
    fx: jnp.ndarray
    w: jnp.ndarray
    escaped: jnp.ndarray


class Nodes(NamedTuple):
    """The grid after the momentum-to-velocity update: ``v`` (M, 4) velocity [m/s] in the
    first three channels (the fourth is m / m, never read); ``mass`` (M,) [kg]; ``heavy``
    (M,), nodes that pass gradients; ``has_mass`` (M,)."""

    v: jnp.ndarray
    mass: jnp.ndarray
    heavy: jnp.ndarray
    has_mass: jnp.ndarray


@jax.named_scope("stencil")
def stencil(cfg: MPMConfig, x) -> Stencil:
    """The window origin, block corners and B-spline weights of the positions ``x`` (N, 3)
    [m] (:class:`Stencil`)."""
    origin = window_origin(cfg, x)
    Xp = x * (1.0 / cfg.dx)
    base_f = jnp.floor(Xp - 0.5)
    fx = Xp - base_f
    base = base_f.astype(jnp.int32) - origin
    hi = jnp.asarray(cfg.window, jnp.int32) - 3
    escaped = jnp.any((base < 0) | (base > hi))
    if not cfg.full_grid:
        dom_base = base + origin
        escaped = escaped | jnp.any(
            (dom_base < 0) | (dom_base > jnp.asarray(cfg.domain, jnp.int32) - 3))
    # materialised: fused, both would be recomputed inside every gathered or scattered row
    base = materialise(jnp.clip(base, 0, hi))
    w = materialise(jnp.stack(
        [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2],
        axis=1))  # (N, offset, axis)
    return Stencil(origin, base, fx, w, escaped)


@jax.named_scope("p2g")
def p2g(cfg: MPMConfig, params: MaterialParams, state: MPMState, drive, st: Stencil):
    """``(grid (M, C), Hm, m (N,) [kg])``: the particles' momentum (after stress and gravity
    impulses) and mass scattered onto the window, with the components ``Hm`` of ``state.H``
    and the particle masses that later stages read."""
    dt, inv_dx = cfg.dt, 1.0 / cfg.dx
    Cm = alg.mat3(state.C)
    Hm = alg.mat3(state.H)
    m = state.vol * params.density[state.mat]
    tau = kirchhoff_stress(cfg, params, state, Hm, Cm)
    k_stress = -dt * state.vol * 4.0 * inv_dx * inv_dx
    A = [[k_stress * tau[i][j] + m * Cm[i][j] for j in range(3)] for i in range(3)]
    R = _affine_rows(cfg, state.v, st.fx, m, A, None if drive is None else drive[0])
    grid = _transfer.spread(cfg.window, st.base, st.w, R)
    return checkpoint_name(grid.reshape(-1, R.shape[-1]), "mpm_grid"), Hm, m


def _affine_rows(cfg: MPMConfig, v, fx, m, A, weight):
    """The rows R (N, 4, C) of each particle's affine node values (see
    :mod:`dax_physics._transfer`): the momentum at offset o is w_o (b + dx A o) with
    b = m v - dx A fx, so row 0 is b and the masses, rows 1-3 dx times the columns of A
    (zero in the mass channels), from the velocities ``v`` (N, 3) [m/s], the masses
    ``m`` (N,) [kg] and ``A`` (components, [kg/s]); ``weight`` (N,): the drive's weight,
    whose mass ``weight m`` is a fifth channel, or None.

    Gravity's impulse enters as momentum m g dt per particle, not as g dt added to the grid
    velocity after the division: that add would contract into a fused multiply-add only in
    the vectorised part of the grid loop, and a node's rounding would depend on where it
    sits in the window."""
    dt, dx = cfg.dt, cfg.dx
    vg = [v[:, i] + dt * cfg.gravity[i] if cfg.gravity[i] else v[:, i] for i in range(3)]
    b = [m * vg[i] - dx * (A[i][0] * fx[:, 0] + A[i][1] * fx[:, 1] + A[i][2] * fx[:, 2])
         for i in range(3)]
    masses = [m] if weight is None else [m, m * jnp.asarray(weight, fx.dtype)]
    # The distinct entries (13, 14 with a drive) are materialised: fused, XLA would put the
    # stress computation into the 27-fold scatter input and redo it for every stencil node.
    entries = list(materialise(tuple(
        b + [dx * A[c][a] for a in range(3) for c in range(3)] + masses)))
    b, dxA, masses = entries[:3], entries[3:12], entries[12:]
    zeros = [jnp.zeros_like(m)] * len(masses)
    return materialise(jnp.stack(
        [jnp.stack(b + masses, axis=-1)]
        + [jnp.stack(dxA[3 * a:3 * a + 3] + zeros, axis=-1) for a in range(3)], axis=1))


@jax.named_scope("grid_update")
def grid_update(grid, m) -> Nodes:
    """Node velocities [m/s] from the P2G ``grid`` (M, C) of momentum and mass, given the
    particle masses ``m`` (N,) [kg] (:class:`Nodes`).

    All four channels are divided (the G2P gather reads aligned 4-channel rows; a pad of a
    3-channel velocity would become the root of this loop's fusion). A node touched only by
    the far tail of the weights can hold a vanishing mass: its velocity is exact forward,
    but the reverse-mode derivative -p / m^2 would overflow float32, so below a millionth
    of the lightest particle's mass it keeps its forward value and passes no gradient (such
    a node moves nothing)."""
    gm = grid[:, 3]
    has_mass = gm > 0.0
    gv_exact = _per_mass(grid[:, :4], jnp.where(has_mass, gm, 1.0))
    heavy = gm > 1e-6 * jax.lax.stop_gradient(jnp.min(m))
    gv_heavy = _per_mass(grid[:, :4], jnp.where(heavy, gm, 1.0))
    gv = jnp.where(heavy[:, None], gv_heavy,
                   jnp.where(has_mass[:, None], jax.lax.stop_gradient(gv_exact), 0.0))
    return Nodes(gv, gm, heavy, has_mass)


@jax.custom_vjp
def _per_mass(p, mass):
    """The node velocities ``p / mass[:, None]`` of the (M, C) node momenta. Its reverse
    mode writes the mass cotangent ``-sum_c dv_c v_c / mass`` as a C-term sum: autodiff's
    sum over the broadcast channel axis would be a library reduction call on XLA:CPU, and
    a channel-by-channel division five padded grid adds."""
    return p / mass[:, None]


def _per_mass_fwd(p, mass):
    v = p / mass[:, None]
    return v, (v, mass)


def _per_mass_bwd(res, dv):
    v, mass = res
    dmass = -sum(dv[:, c] * v[:, c] for c in range(v.shape[1])) / mass
    return dv / mass[:, None], dmass


_per_mass.defvjp(_per_mass_fwd, _per_mass_bwd)


@jax.named_scope("boundaries")
def boundaries(cfg: MPMConfig, params: MaterialParams, state: MPMState, drive, origin,
               grid, nodes: Nodes):
    """Node velocities (M, 4) [m/s] after, in this order, the drive, the walls and the
    colliders (the drive and the colliders act on the three velocity channels); nodes
    without mass get zero."""
    gv = nodes.v
    if drive is not None:
        gv = jnp.concatenate([_drive_grid(gv[:, :3], grid[:, 4], nodes.mass,
                                          jnp.asarray(drive[1], state.x.dtype),
                                          nodes.heavy), gv[:, 3:]], axis=1)
    if cfg.walls != "none":
        gv = _walls(cfg, origin, gv)
    if cfg.colliders:
        # materialised: each node's velocity component then carries only its own chain
        # (the drive and the walls act per component); fused into the colliders' loops,
        # which mix the three components, every chain would be redone in each of them
        v = materialise(gv[:, :3])
        gv = jnp.concatenate([col.apply_colliders_grid(
            cfg.colliders, state.colliders, v, cfg.dx, cfg.window, origin,
            params.friction), gv[:, 3:]], axis=1)
    return jnp.where(nodes.has_mass[:, None], gv, 0.0)


def _drive_grid(gv, driven_mass, gm, velocity, heavy):
    """Grid velocities ``gv`` (M, 3) with every node that carries more than
    :data:`DRIVE_FRACTION` driven mass set to ``velocity`` (3,) [m/s]: the infinite-mass
    limit of a rigid grip. A grip that only reset its particles after the substep would let
    the pulled material's stress slow the nodes it shares with them: the gap that opens
    between grip and free particles would enter no particle's F, and no force would close
    it.

    Below :data:`DRIVE_FRACTION` a node blends the drive in with a C1 ramp (smoothstep) of
    its driven fraction: a hard switch would make the node's velocity, and the rollout,
    jump in the drive's velocity, a jump autodiff cannot see. On the nearly empty nodes
    (``heavy`` false, as in :func:`grid_update`) the fraction keeps its forward value and
    passes no gradient: its derivative -d / m^2 would overflow float32."""
    frac_heavy = driven_mass / (DRIVE_FRACTION * jnp.where(heavy, gm, 1.0))
    frac_light = jax.lax.stop_gradient(
        driven_mass / (DRIVE_FRACTION * jnp.where(gm > 0.0, gm, 1.0)))
    t = jnp.clip(jnp.where(heavy, frac_heavy, frac_light), 0.0, 1.0)
    alpha = (t * t * (3.0 - 2.0 * t))[:, None]
    return gv + alpha * (velocity - gv)


def _walls(cfg: MPMConfig, origin, gv):
    """``gv`` (M, 4) with the walls' condition on the nodes on or beyond the wall surfaces
    (global index ``<= wall_cells`` or ``>= domain - wall_cells``); the mass channel's
    column is never a wall."""
    node = jnp.asarray(np.indices(cfg.window).reshape(3, -1).T, jnp.int32) + origin
    lo_wall = jnp.pad(node <= cfg.wall_cells, ((0, 0), (0, 1)))
    hi_wall = jnp.pad(node >= jnp.asarray(cfg.domain, jnp.int32) - cfg.wall_cells,
                      ((0, 0), (0, 1)))
    if cfg.walls == "sticky":
        return jnp.where(jnp.any(lo_wall | hi_wall, axis=1, keepdims=True), 0.0, gv)
    return jnp.where((lo_wall & (gv < 0)) | (hi_wall & (gv > 0)), 0.0, gv)


@jax.named_scope("g2p")
def g2p(cfg: MPMConfig, state: MPMState, st: Stencil, gv):
    """``(x (N, 3) [m], v (N, 3) [m/s], C)``: each particle's new velocity and APIC matrix
    C [1/s] (components) gathered from the node velocities ``gv`` (M, 4), and its position
    advanced by ``dt v``."""
    inv_dx = 1.0 / cfg.dx
    # materialised: fused, the whole grid update (division, walls, colliders) would be
    # redone for every one of the 27 reads per particle
    gv4 = materialise(gv.reshape(*cfg.window, 4))
    S = checkpoint_name(_transfer.collect(gv4, st.base, st.w), "mpm_moments")
    new_v = [S[:, 0, c] for c in range(3)]
    new_C = [[4.0 * inv_dx * (S[:, 1 + j, i] - new_v[i] * st.fx[:, j]) for j in range(3)]
             for i in range(3)]
    v = jnp.stack(new_v, axis=-1)
    return state.x + cfg.dt * v, v, new_C


@jax.named_scope("deformation")
def deformation(cfg: MPMConfig, params: MaterialParams, state: MPMState, C, Hm):
    """``(J (N,), H (N, 3, 3))`` after the substep, from the new APIC matrix ``C`` and the
    old ``Hm`` (components): the fluids' volume ratio, capped at 1 unless
    ``cfg.fluid_tension``, and ``F <- (I + dt C) F`` as ``H <- H + (D + D H)``, D = dt C
    (the increment is added to the small H, not to O(1) entries of F), with the plastic
    return map; fluid particles keep H = 0 (an unused F is never polar-decomposed)."""
    kinds = cfg.kinds
    J = state.J
    if "fluid" in kinds:
        J = state.J * (1.0 + cfg.dt * (C[0][0] + C[1][1] + C[2][2]))
        if not cfg.fluid_tension:  # a liquid pushes but does not pull
            J = jnp.minimum(J, 1.0)
    if kinds == {"fluid"}:
        return J, state.H
    # D's cotangent is materialised: it gathers the adjoints of the H update (and of the
    # return map), and every component of the next adjoint reads all of them
    D = alg.cotangent_materialised([[cfg.dt * c for c in row] for row in C])
    DH = alg.mul(D, Hm)
    Hn = [[Hm[i][j] + (D[i][j] + DH[i][j]) for j in range(3)] for i in range(3)]
    if "plastic" in kinds:
        Hn = plasticity(cfg, params, state, Hn, D)
    if "fluid" in kinds:
        is_fl = particle_kinds(cfg, state.mat) == KIND_CODE["fluid"]
        Hn = [[jnp.where(is_fl, 0.0, Hn[i][j]) for j in range(3)] for i in range(3)]
    return J, alg.stack3(Hn)


@jax.named_scope("plasticity")
def plasticity(cfg: MPMConfig, params: MaterialParams, state: MPMState, Hn, D):
    """The plastic particles' ``b_e - I`` (components) after the radial return map of the
    trial ``b_e = (I + D) b (I + D)^T``; ``Hn`` = (I + D) b - I for them, other particles'
    entries pass through."""
    is_pl = particle_kinds(cfg, state.mat) == KIND_CODE["plastic"]
    # b_trial - I = Hn + D^T + Hn D^T; its cotangent is materialised like D's
    HnDt = alg.mul(Hn, alg.transpose(D))
    B_trial = [[Hn[i][j] + (D[j][i] + HnDt[i][j]) for j in range(3)] for i in range(3)]
    B_trial = alg.cotangent_materialised(B_trial)
    B_new = return_map(params, state.mat, B_trial)
    return [[jnp.where(is_pl, B_new[i][j], Hn[i][j]) for j in range(3)] for i in range(3)]


@jax.named_scope("held")
def held(cfg: MPMConfig, state: MPMState, x, v, C):
    """``(x, v, C, colliders)``: the colliders advanced by ``dt``, and every held particle
    moved rigidly with its collider (position [m], velocity [m/s], C = 0)."""
    cstate = col.advance(state.colliders, cfg.dt)
    if not cfg.colliders:
        return x, v, C, cstate
    k = jnp.maximum(state.held, 0)
    Rk = jax.vmap(col.quat_to_matrix)(cstate.quat)[k]
    hx = cstate.pos[k] + jnp.einsum("nij,nj->ni", Rk, state.held_offset, precision=HIGHEST)
    hv = cstate.lin_vel[k] + jnp.cross(cstate.ang_vel[k], hx - cstate.pos[k])
    is_held = (state.held >= 0)[:, None]
    return (jnp.where(is_held, hx, x), jnp.where(is_held, hv, v),
            jnp.where(is_held[:, :, None], 0.0, C), cstate)


@jax.named_scope("project")
def project(cfg: MPMConfig, state: MPMState, x, v, colliders):
    """``(x, v)`` with the free particles (``state.held < 0``) that ended the substep inside
    a collider flagged ``project`` moved onto its surface at its new pose ``colliders``
    (:func:`dax_physics.colliders.project_particles`)."""
    if not any(c.project for c in cfg.colliders):
        return x, v
    return col.project_particles(cfg.colliders, colliders, x, v, state.held < 0)


@jax.named_scope("stability")
def stability(cfg: MPMConfig, params: MaterialParams, state: MPMState, x, v):
    """The new ``finite`` flag (): still finite, every position finite, and no particle
    above the speed :func:`~dax_physics.mpm.max_stable_speed` (it breaks the CFL condition
    outright; the run may still be finite). Explicit sums and ``any`` of a comparison: a
    float max or sum over an axis would be a library reduction call on XLA:CPU."""
    speed_limit = max_stable_speed(cfg, params)
    speed2 = sum(v[:, i] * v[:, i] for i in range(3))
    outran = jnp.any(speed2 > speed_limit * jnp.abs(speed_limit))
    return state.finite & jnp.all(jnp.isfinite(x)) & ~outran


def _step(cfg: MPMConfig, params: MaterialParams, state: MPMState, drive) -> MPMState:
    """One substep: the stages in order (module docstring); :func:`step` checkpoints it."""
    st = stencil(cfg, state.x)
    grid, Hm, m = p2g(cfg, params, state, drive, st)
    nodes = grid_update(grid, m)
    gv = boundaries(cfg, params, state, drive, st.origin, grid, nodes)
    x, v, C = g2p(cfg, state, st, gv)
    J, H = deformation(cfg, params, state, C, Hm)
    x, v, C, colliders = held(cfg, state, x, v, alg.stack3(C))
    x, v = project(cfg, state, x, v, colliders)
    finite = stability(cfg, params, state, x, v)
    return state.replace(x=x, v=v, C=C, H=H, J=J, colliders=colliders, origin=st.origin,
                         finite=finite, escaped=state.escaped | st.escaped,
                         time=state.time + cfg.dt)


_remat_step = jax.checkpoint(_step, static_argnums=(0,), prevent_cse=False,
                             policy=_REMAT_POLICY)


def step(cfg: MPMConfig, params: MaterialParams, state: MPMState, drive=None) -> MPMState:
    """Advance the scene by one substep of ``cfg.dt`` seconds (pure; jit with ``cfg``
    static). The colliders' friction is ``params.friction`` when set.

    drive: ``None`` or ``(weight, velocity)``: particles moved kinematically at the
        velocity ``velocity`` (3,) [m/s] (a held part of the object; ``weight`` (N,) is 1
        for them, 0 for the free ones). The grid carries the constraint: the nodes that
        carry driven mass move at ``velocity`` (:func:`_drive_grid`), so the velocity
        field that the free particles and every particle's F see moves with the driven
        part. The caller still sets the driven particles' positions after the substep.
        It adds a fifth scatter channel; ``None`` compiles the substep without it.

    Reverse mode keeps only the substep's input state and :data:`REVERSE_SAVED` (the P2G
    grid, the G2P moments and the elastic rotation) and recomputes the rest, all of it
    elementwise, in the backward pass."""
    return _remat_step(cfg, params, state, drive)


def rollout(cfg: MPMConfig, params: MaterialParams, state: MPMState, n_substeps: int, *,
            segment: int | None = None, unroll: int = 1) -> MPMState:
    """Run ``n_substeps`` substeps of :func:`step` as one scan (pure, not jitted: jit it
    with ``cfg``, ``n_substeps`` and ``segment`` static, e.g. ``jax.jit(rollout,
    static_argnums=(0, 3), static_argnames=("segment",))``).

    segment: substeps per checkpointed segment (:func:`dax_physics.checkpointed_scan`,
        whose remainder rule applies); reverse-mode memory then grows with the number of
        segments, not substeps, at the cost of recomputing each segment once in the
        backward pass. ``None``: no checkpointing. Forward values are the same either way.
    unroll: passed to the scan.
    A negative or non-integer ``n_substeps`` raises ``ValueError`` (0 returns ``state``).
    """
    n_substeps = step_count(n_substeps, "n_substeps")

    def body(s, _):
        return step(cfg, params, s), None

    return checkpointed_scan(body, state, length=n_substeps, segment=segment,
                             unroll=unroll)[0]
