"""The dynamic state of an MPM scene, its construction and checks, and what acts on it
between substeps (grasping, collider commands).

:func:`init_state` and :func:`check_state` look at values (host side, outside ``jit``);
:func:`grasp`, :func:`release` and :func:`set_collider_velocity` are pure. SI units.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .. import colliders as col
from .._pytree import pytree_dataclass
from ..materials import MaterialParams
from ..precision import mm
from .config import MPMConfig, max_stable_speed


@pytree_dataclass
class MPMState:
    """Dynamic state of an MPM scene with N particles and K colliders.

    x: positions [m] (N, 3).  v: velocities [m/s] (N, 3).
    C: APIC affine velocity matrix [1/s] (N, 3, 3).
    H: displacement gradient ``F - I`` (N, 3, 3); for ``plastic`` particles ``b_e - I``
       with b_e the elastic left Cauchy-Green tensor (stored relative to the identity so
       float32 keeps the increments; see :mod:`dax_physics.mpm`).  :attr:`F` is ``I + H``.
    J: volume ratio (N,), tracked for fluids (capped at 1: no tension).
    vol: rest volume [m^3] (N,).  mat: material id (N,) int32.
    held: index of the collider holding the particle, -1 if free (N,) int32.
    held_offset: the held particle's position in its collider's frame [m] (N, 3).
    colliders: :class:`~dax_physics.colliders.ColliderState`.
    origin: the active window's origin in cells (3,) int32.
    finite: all positions stayed finite and no particle outran the time step (a speed above
    :func:`~dax_physics.mpm.max_stable_speed`: the run is unstable) so far ().
    escaped: some particle's stencil left the window or domain and was clamped ().
    time: simulated time [s] ().
    """

    x: jnp.ndarray
    v: jnp.ndarray
    C: jnp.ndarray
    H: jnp.ndarray
    J: jnp.ndarray
    vol: jnp.ndarray
    mat: jnp.ndarray
    held: jnp.ndarray
    held_offset: jnp.ndarray
    colliders: col.ColliderState
    origin: jnp.ndarray
    finite: jnp.ndarray
    escaped: jnp.ndarray
    time: jnp.ndarray

    @property
    def n_particles(self) -> int:
        """N, the number of particles."""
        return self.x.shape[-2]

    @property
    def F(self):
        """The deformation gradient ``I + H`` (N, 3, 3) (``b_e`` for plastic particles);
        read-only: build a state with ``replace(H=F - I)``."""
        return self.H + jnp.eye(3, dtype=self.H.dtype)


def window_origin(cfg: MPMConfig, x):
    """Integer origin (3,) int32 [cells] of the active window, centred on the bounding box
    of the positions ``x`` (N, 3) [m] and clamped into the domain."""
    if cfg.full_grid:
        return jnp.zeros((3,), jnp.int32)
    lo = jnp.floor(jnp.min(x, axis=0) / cfg.dx)
    hi = jnp.floor(jnp.max(x, axis=0) / cfg.dx)
    half = jnp.asarray(cfg.window, x.dtype) // 2
    origin = jnp.floor(0.5 * (lo + hi)) - half + 1
    upper = jnp.asarray(cfg.domain, x.dtype) - jnp.asarray(cfg.window, x.dtype)
    return jnp.clip(origin, 0, upper).astype(jnp.int32)


def init_state(cfg: MPMConfig, x, v=None, mat=None, vol=None, colliders=None,
               dtype=jnp.float32) -> MPMState:
    """Build a validated initial state (``ValueError`` naming the problem otherwise).

    x: positions (N, 3) [m] inside the domain: between the wall surfaces (``wall_cells *
        dx`` to ``(domain - wall_cells) * dx`` per axis) or, without walls, where every
        particle's stencil fits the grid (1 cell to ``domain - 2`` cells).
    v: velocities (N, 3) [m/s], default zero.
    mat: material ids (N,), default 0.
    vol: rest volume per particle [m^3], scalar or (N,); default ``dx^3 / 8`` (8 particles
        per cell).
    colliders: a :class:`ColliderState` with one row per ``cfg.colliders`` entry; default
        poses at the origin.
    """
    x, v = _positions_velocities(x, v)
    n = x.shape[0]
    mat = _material_ids(cfg, n, mat)
    vol = np.full(n, cfg.dx ** 3 / 8) if vol is None else np.asarray(vol)
    if not _broadcasts_to(vol.shape, (n,)):
        raise ValueError(f"particle volumes must be a scalar or have shape ({n},), "
                         f"got {vol.shape}")
    vol = np.broadcast_to(vol, (n,))
    if not np.all(vol > 0):
        raise ValueError("particle volumes must be > 0 m^3")
    _check_inside(cfg, x)
    if colliders is None:
        k = len(cfg.colliders)
        colliders = col.ColliderState.create(jnp.zeros((k, 3), dtype), dtype=dtype)
    if colliders.pos.shape[0] != len(cfg.colliders):
        raise ValueError(f"collider state has {colliders.pos.shape[0]} rows but the config "
                         f"declares {len(cfg.colliders)} colliders")
    state = MPMState(
        x=jnp.asarray(x, dtype), v=jnp.asarray(v, dtype),
        C=jnp.zeros((n, 3, 3), dtype), H=jnp.zeros((n, 3, 3), dtype), J=jnp.ones((n,), dtype),
        vol=jnp.asarray(vol, dtype), mat=jnp.asarray(mat, jnp.int32),
        held=jnp.full((n,), -1, jnp.int32), held_offset=jnp.zeros((n, 3), dtype),
        colliders=colliders, origin=jnp.zeros((3,), jnp.int32),
        finite=jnp.asarray(True), escaped=jnp.asarray(False), time=jnp.zeros((), dtype))
    return state.replace(origin=window_origin(cfg, state.x))


def _positions_velocities(x, v):
    """Checked positions (N, 3) and velocities broadcast to them, as NumPy arrays."""
    x = np.asarray(x)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"particle positions must have shape (N, 3), got {x.shape}")
    if x.shape[0] == 0:
        raise ValueError("an MPM state needs at least one particle, got 0")
    if not np.all(np.isfinite(x)):
        bad = int(np.argwhere(~np.isfinite(x).all(1))[0, 0])
        raise ValueError(f"particle positions contain NaN or inf (first at particle {bad})")
    v = np.zeros_like(x) if v is None else np.asarray(v)
    # checked before broadcasting: np.broadcast_to's own error does not say what is wrong
    if not _broadcasts_to(v.shape, x.shape):
        raise ValueError(f"velocities must have shape {x.shape} (or broadcast to it), "
                         f"got {v.shape}")
    v = np.broadcast_to(v, x.shape)
    if not np.all(np.isfinite(v)):
        raise ValueError("particle velocities contain NaN or inf")
    return x, v


def _material_ids(cfg: MPMConfig, n: int, mat):
    """Checked material ids (N,): integers indexing ``cfg.materials``; the error names an
    offending id."""
    mat = np.zeros(n, np.int32) if mat is None else np.asarray(mat)
    if mat.shape != (n,):
        raise ValueError(f"material ids must have shape ({n},), got {mat.shape}")
    if not np.issubdtype(mat.dtype, np.integer):
        raise ValueError(f"material ids must be integers, got dtype {mat.dtype}")
    bad_ids = mat[(mat < 0) | (mat >= len(cfg.materials))]
    if bad_ids.size:
        raise ValueError(f"unknown material id {int(bad_ids[0])}: the table has "
                         f"{len(cfg.materials)} materials (ids 0..{len(cfg.materials) - 1})")
    return mat


def _check_inside(cfg: MPMConfig, x):
    """Refuse positions outside the domain less its walls. Grid nodes sit at 0 .. n - 1
    cells, so a particle's B-spline stencil fits in the grid only for 0.5 <= x / dx < n -
    1.5: particles stay at least half a cell inside that, and between the wall surfaces
    (``wall_cells`` and ``domain - wall_cells`` cells, where the walls' constrained nodes
    start)."""
    walls = cfg.wall_cells if cfg.walls != "none" else 0
    lo = max(walls, 1) * cfg.dx
    hi = np.asarray(cfg.domain) * cfg.dx - max(walls, 2) * cfg.dx
    outside = np.any((x < lo) | (x > hi), axis=1)
    if outside.any():
        i = int(np.argmax(outside))
        raise ValueError(f"{int(outside.sum())} particles lie outside the simulation domain "
                         f"[{lo:.4g}, {hi.tolist()}) m (minus walls); first: particle {i} at "
                         f"{x[i].tolist()}")


def _broadcasts_to(shape, target) -> bool:
    """Whether an array of ``shape`` broadcasts to exactly ``target``."""
    try:
        return np.broadcast_shapes(tuple(shape), tuple(target)) == tuple(target)
    except ValueError:
        return False


def check_state(state: MPMState, cfg: MPMConfig | None = None,
                params: MaterialParams | None = None) -> None:
    """Raise if a rollout went non-finite or unstable (a particle outran the time step,
    :func:`~dax_physics.mpm.max_stable_speed`: ``FloatingPointError``) or lost particles
    out of the window/domain (``RuntimeError``). An unstable run is reported as such even
    when its particles also left the window (they did because of it); with ``cfg`` (and
    ``params``, default ``cfg.params``) the message gives the speed limit. (This syncs with
    the host: call it after a rollout, not inside one.)"""
    if not np.asarray(state.finite).all():
        _raise_non_finite(state, cfg, params)
    if np.asarray(state.escaped).any():
        raise RuntimeError("particles left the active window or the domain and were clamped; "
                           "enlarge MPMConfig.window/domain")


def _raise_non_finite(state: MPMState, cfg: MPMConfig | None, params):
    """The ``FloatingPointError`` of a state whose ``finite`` flag is down."""
    x, v = np.asarray(state.x), np.asarray(state.v)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
        raise FloatingPointError("the MPM state became non-finite (NaN/inf): the time step "
                                 "is probably unstable for the velocities reached")
    speed = float(np.max(np.linalg.norm(v, axis=-1)))
    if cfg is not None:
        limit = float(max_stable_speed(cfg, cfg.params if params is None else params))
        if speed > limit:
            raise FloatingPointError(
                f"the MPM run became unstable: a particle moved at {speed:.3g} m/s, "
                f"faster than the {limit:.3g} m/s the time step dt = {cfg.dt:.3g} s "
                f"can carry (dx / dt minus the fastest wave speed); lower dt or "
                f"raise MPMConfig.max_speed to what the scene reaches")
    raise FloatingPointError(
        f"the MPM run became unstable or non-finite: a particle outran the time step "
        f"(dax_physics.mpm.max_stable_speed; the fastest moves at {speed:.3g} m/s "
        f"now) or a value went NaN/inf; lower dt or raise MPMConfig.max_speed")


def grasp(cfg: MPMConfig, state: MPMState, index: int, radius: float) -> MPMState:
    """Attach to collider ``index`` every free particle within ``radius`` [m] of its
    surface; attached particles then move rigidly with the collider."""
    spec = cfg.colliders[index]
    cs = state.colliders
    phi, _ = col.sdf(spec, cs.pos[index], cs.quat[index], state.x)
    take = (phi < radius) & (state.held < 0)
    R = col.quat_to_matrix(cs.quat[index])
    local = mm(state.x - cs.pos[index], R)
    return state.replace(held=jnp.where(take, index, state.held),
                         held_offset=jnp.where(take[:, None], local, state.held_offset))


def release(state: MPMState, index: int) -> MPMState:
    """Detach every particle held by collider ``index``."""
    return state.replace(held=jnp.where(state.held == index, -1, state.held))


def set_collider_velocity(state: MPMState, index: int, lin_vel=None, ang_vel=None) -> MPMState:
    """Set the velocity command of collider ``index`` [m/s, rad/s, world frame]."""
    return state.replace(colliders=state.colliders.with_velocity(index, lin_vel, ang_vel))
