"""3D MLS-MPM (APIC transfers, quadratic B-splines) as pure JAX functions.

The split follows the rest of dax-physics:

* :class:`MPMConfig` is static and hashable (grid, time step, material kinds, colliders,
  walls). It is a ``static_argnums`` argument; changing it recompiles.
* :class:`MaterialParams` (see :mod:`dax_physics.materials`) holds the differentiable
  material numbers.
* :class:`MPMState` is the dynamic pytree: particles, collider poses and bookkeeping.

All functions work under ``jax.jit``, ``jax.vmap`` (a batch of scenes) and ``jax.grad``.
Units are SI, z is up.

**Active region.** The simulation domain is ``domain`` cells of size ``dx`` starting at the
world origin. The grid that is actually allocated is a *window* of static shape ``window``
cells whose integer origin is recentred on the particles' bounding box at every substep, so
a rope on a large table is simulated on a grid the size of the rope. With
``window == domain`` (the default) the window is the whole domain. A particle whose
B-spline stencil does not fit in the window (or in the domain) is never dropped silently:
its stencil is clamped into the window and the state's ``escaped`` flag is raised, which
:func:`check_state` turns into an error. Results of a windowed run equal the full-grid run
whenever the flag stays down.

**Walls.** The domain boundary carries walls ``wall_cells`` thick: their surfaces are the
planes ``wall_cells * dx`` and ``(domain - wall_cells) * dx`` of each axis, and the grid
nodes on or beyond a surface (global index ``<= wall_cells`` or ``>= domain -
wall_cells``) are constrained: ``"slip"`` removes the velocity component into the wall,
``"sticky"`` zeroes it, ``"none"`` disables them. Material comes to rest *on* the surface
(checked by the validation suite, :mod:`benchmarks.validate`), and :func:`init_state`
accepts particles between the surfaces. (Before 0.3.0 the nodes with index ``<
wall_cells`` were constrained, as in the Taichi and Warp reference scenes: material then
rested about a cell below the documented surface, an O(dx) error in every length measured
from the wall. The reference scenes' band of ``b`` cells is ``wall_cells = b - 1`` here.)

**Deformation in float32.** The state stores the displacement gradient ``H = F - I``
(``b_e - I`` for plastic particles), not ``F``, and updates it as ``H <- H + dt C (I +
H)``. A substep changes F by about 1e-5; added to O(1) entries of ``F`` in float32 the
increments kept two digits, and the rounding of ``1 + d`` is biased (the spacing of
float32 numbers halves below 1), so an elastic solid under a steady load crept. Stored as
``H`` the increments keep their precision; ``MPMState.F`` returns ``I + H``.

**Fluids carry no tension.** A fluid particle's volume ratio is capped at ``J <= 1``: a
weakly compressible liquid pushes but does not pull, and liquid that spreads or separates
is a free surface at zero pressure (``MPMConfig(fluid_tension=True)`` lifts the cap, as
in the Taichi and Warp reference scenes). Without the cap the stretched particles' negative
pressure held a collapsing water column together (its height at the wall came out 5 % too
high against Martin & Moyce's measurements at 16 cells across; 1.9 % with the cap).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from . import _transfer
from . import colliders as col
from ._pytree import pytree_dataclass
from .materials import Material, MaterialParams
from .scan import checkpointed_scan

#: Courant number used by the stability guard: dt <= CFL * dx / (c_max + v_max).
CFL = 0.5
#: Newton iterations of the polar decomposition used by the fixed-corotated model.
POLAR_ITERS = 6
WALL_MODES = ("slip", "sticky", "none")


@dataclasses.dataclass(frozen=True)
class MPMConfig:
    """Static configuration of an MPM scene.

    materials: the material table (tuple of :class:`Material`); particles index it.
    dx: grid cell size [m].
    dt: substep [s]; checked against the stability bound (see :func:`max_stable_dt`).
    domain: domain size in cells (nx, ny, nz); the domain is [0, n * dx) per axis.
    window: active-region grid size in cells; ``None`` means the whole domain.
    gravity: acceleration [m/s^2].
    walls: ``"slip"``, ``"sticky"`` or ``"none"`` at the domain boundary.
    wall_cells: wall thickness in cells: the wall surfaces are ``wall_cells * dx`` from each
        side of the domain (see the module docstring).
    colliders: tuple of :class:`~dax_physics.colliders.ColliderSpec`.
    max_speed: the largest particle or collider speed [m/s] the scene is expected to
        reach (finite, >= 0); enters the CFL part of the stability bound. A run whose
        particles exceed the speed the time step can carry at all (:func:`max_stable_speed`)
        is flagged: its state's ``finite`` turns false and :func:`check_state` calls it
        unstable.
    fluid_tension: let fluid particles stretch past J = 1 (negative pressure), as the
        Taichi and Warp reference scenes do; the default ``False`` caps J at 1 (see the
        module docstring).
    """

    materials: tuple
    dx: float
    dt: float
    domain: tuple = (32, 32, 32)
    window: tuple | None = None
    gravity: tuple = (0.0, 0.0, -9.81)
    walls: str = "slip"
    wall_cells: int = 3
    colliders: tuple = ()
    max_speed: float = 0.0
    fluid_tension: bool = False

    def __post_init__(self):
        mats = tuple(self.materials)
        if not mats:
            raise ValueError("an MPM scene needs at least one material")
        for m in mats:
            if not isinstance(m, Material):
                raise TypeError(f"materials must be dax_physics.Material entries, got {m!r}")
        object.__setattr__(self, "materials", mats)
        object.__setattr__(self, "colliders", tuple(self.colliders))
        domain = tuple(int(d) for d in self.domain)
        window = domain if self.window is None else tuple(int(w) for w in self.window)
        if len(domain) != 3 or len(window) != 3:
            raise ValueError(f"domain and window must have 3 entries, got {domain}, {window}")
        if any(w < 4 for w in window) or any(w > d for w, d in zip(window, domain, strict=True)):
            raise ValueError(f"window {window} must be >= 4 cells and fit in domain {domain}")
        object.__setattr__(self, "domain", domain)
        object.__setattr__(self, "window", window)
        gravity = tuple(_real(g, "gravity") for g in _entries(self.gravity, "gravity"))
        if len(gravity) != 3 or not all(math.isfinite(g) for g in gravity):
            raise ValueError(f"gravity must be 3 finite numbers in m/s^2, got {self.gravity}")
        object.__setattr__(self, "gravity", gravity)
        if not (math.isfinite(_real(self.dx, "dx")) and self.dx > 0):
            raise ValueError(f"dx must be a positive cell size in m, got {self.dx}")
        if not (math.isfinite(_real(self.dt, "dt")) and self.dt > 0):
            raise ValueError(f"dt must be a positive time step in s, got {self.dt}")
        # A NaN max_speed made the stability bound NaN, and every dt passed the comparison;
        # a negative one could divide by zero or suggest a negative dt.
        if not (math.isfinite(_real(self.max_speed, "max_speed")) and self.max_speed >= 0):
            raise ValueError(f"max_speed must be a finite speed >= 0 in m/s, got "
                             f"{self.max_speed}")
        if self.walls not in WALL_MODES:
            raise ValueError(f"unknown wall mode {self.walls!r}; valid: {', '.join(WALL_MODES)}")
        if not (isinstance(self.wall_cells, (int, np.integer))
                and not isinstance(self.wall_cells, bool) and self.wall_cells >= 0):
            raise ValueError(f"wall_cells must be an int >= 0, got {self.wall_cells!r}")
        for c in self.colliders:
            if not isinstance(c, col.ColliderSpec):
                raise TypeError(f"colliders must be ColliderSpec entries, got {c!r}")
        limit = max_stable_dt(self)
        if self.dt > limit:
            raise ValueError(
                f"unstable time step: dt = {self.dt:.3g} s exceeds the largest stable dt "
                f"{limit:.3g} s for dx = {self.dx:.3g} m (CFL {CFL} on the fastest wave speed "
                f"{max(m.wave_speed for m in self.materials):.3g} m/s plus max_speed "
                f"{self.max_speed:.3g} m/s); use dt <= {limit:.3g}")

    @property
    def kinds(self) -> frozenset:
        return frozenset(m.kind for m in self.materials)

    @property
    def full_grid(self) -> bool:
        return self.window == self.domain

    @property
    def params(self) -> MaterialParams:
        """The scene's numbers as a differentiable :class:`MaterialParams`: the material
        table and the colliders' friction coefficients (build it once and reuse it)."""
        return MaterialParams.from_materials(
            self.materials, friction=[c.friction for c in self.colliders])


def _real(value, name: str) -> float:
    """``value`` as a float; ``TypeError`` naming the field if it is not a real number."""
    if isinstance(value, (bool, str, bytes, complex)):
        raise TypeError(f"MPMConfig.{name} must be a real number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise TypeError(f"MPMConfig.{name} must be a real number, got {value!r}") from None


def _entries(value, name: str) -> tuple:
    try:
        return tuple(value)
    except TypeError:
        raise TypeError(f"MPMConfig.{name} must be a sequence of numbers, got "
                        f"{value!r}") from None


def max_stable_speed(cfg: MPMConfig, params: MaterialParams | None = None):
    """The particle speed [m/s] above which ``cfg.dt`` cannot be stable at all: ``dx / dt
    - c`` (Courant number 1 on the fastest wave speed ``c`` plus the particle's speed; ``c``
    from ``params`` when given, which may be traced). The guard's CFL number 0.5 is the
    margin ``dt`` is chosen with, so this speed is at least ``c + 2 max_speed``: a run
    within the speeds the configuration assumes never reaches it. :func:`step` flags a
    state whose particles exceed it (``finite`` false)."""
    if params is None:
        c = max(m.wave_speed for m in cfg.materials)
    else:
        c = jnp.max(params.wave_speed())
    return cfg.dx / cfg.dt - c


def max_stable_dt(cfg: MPMConfig, params: MaterialParams | None = None) -> float:
    """Largest stable substep [s]: ``CFL * dx / (c + max_speed)`` with ``c`` the fastest
    elastic (P-) wave or sound speed of the material table (of ``params`` when given: it
    needs concrete arrays). The ``CFL`` number 0.5 is conservative for explicit MLS-MPM
    with quadratic B-splines."""
    if params is None:
        c = max(m.wave_speed for m in cfg.materials)
    else:
        c = float(np.max(np.asarray(params.wave_speed())))
    return CFL * cfg.dx / (c + cfg.max_speed)


def check_params(cfg: MPMConfig, params: MaterialParams) -> None:
    """Raise ``ValueError`` naming the problem if ``params`` does not fit ``cfg`` or makes
    its time step unstable: wrong shapes, non-finite or non-positive densities, negative
    moduli, viscosities or friction coefficients, or ``cfg.dt`` above the largest stable
    substep of these materials. Needs concrete arrays (call it outside ``jit``)."""
    m, k = len(cfg.materials), len(cfg.colliders)
    fields = {"density": m, "mu": m, "lam": m, "viscosity": m, "yield_stress": m}
    if params.friction is not None:
        fields["friction"] = k
    for name, size in fields.items():
        a = np.asarray(getattr(params, name))
        if a.shape != (size,):
            raise ValueError(f"MaterialParams.{name} must have shape ({size},) for this "
                             f"scene, got {a.shape}")
        if name != "yield_stress" and not np.all(np.isfinite(a)):
            raise ValueError(f"MaterialParams.{name} contains NaN or inf: {a.tolist()}")
        if name == "density" and not np.all(a > 0):
            raise ValueError(f"MaterialParams.density must be > 0 kg/m^3, got {a.tolist()}")
        if name != "density" and np.any(a < 0):
            raise ValueError(f"MaterialParams.{name} must be >= 0, got {a.tolist()}")
    limit = max_stable_dt(cfg, params)
    if cfg.dt > limit:
        raise ValueError(
            f"unstable time step: dt = {cfg.dt:.3g} s exceeds the largest stable dt "
            f"{limit:.3g} s for these material parameters (fastest wave speed "
            f"{float(np.max(np.asarray(params.wave_speed()))):.3g} m/s); lower the moduli "
            f"or raise the density")


@pytree_dataclass
class MPMState:
    """Dynamic state of an MPM scene with N particles and K colliders.

    x: positions [m] (N, 3).  v: velocities [m/s] (N, 3).
    C: APIC affine velocity matrix [1/s] (N, 3, 3).
    H: displacement gradient ``F - I`` (N, 3, 3); for ``plastic`` particles ``b_e - I``
       with b_e the elastic left Cauchy-Green tensor (stored relative to the identity so
       float32 keeps the increments; see the module docstring).  :attr:`F` is ``I + H``.
    J: volume ratio (N,), tracked for fluids (capped at 1: no tension).
    vol: rest volume [m^3] (N,).  mat: material id (N,) int32.
    held: index of the collider holding the particle, -1 if free (N,) int32.
    held_offset: the held particle's position in its collider's frame [m] (N, 3).
    colliders: :class:`~dax_physics.colliders.ColliderState`.
    origin: the active window's origin in cells (3,) int32.
    finite: all positions stayed finite and no particle outran the time step (faster than
    :func:`max_stable_speed`: the run is unstable) so far ().  escaped: some particle's
    stencil left the window or domain and was clamped ().  time: simulated time [s] ().
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
        return self.x.shape[-2]

    @property
    def F(self):
        """The deformation gradient ``I + H`` (N, 3, 3) (``b_e`` for plastic particles);
        read-only: build a state with ``replace(H=F - I)``."""
        return self.H + jnp.eye(3, dtype=self.H.dtype)


def init_state(cfg: MPMConfig, x, v=None, mat=None, vol=None, colliders=None,
               dtype=jnp.float32) -> MPMState:
    """Build a validated initial state.

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
    x = np.asarray(x)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"particle positions must have shape (N, 3), got {x.shape}")
    n = x.shape[0]
    if n == 0:
        raise ValueError("an MPM state needs at least one particle, got 0")
    if not np.all(np.isfinite(x)):
        bad = int(np.argwhere(~np.isfinite(x).all(1))[0, 0])
        raise ValueError(f"particle positions contain NaN or inf (first at particle {bad})")
    v = np.zeros_like(x) if v is None else np.asarray(v)
    # Check before broadcasting: np.broadcast_to's own error does not say what is wrong.
    if not _broadcasts_to(v.shape, x.shape):
        raise ValueError(f"velocities must have shape {x.shape} (or broadcast to it), "
                         f"got {v.shape}")
    v = np.broadcast_to(v, x.shape)
    if not np.all(np.isfinite(v)):
        raise ValueError("particle velocities contain NaN or inf")
    mat = np.zeros(n, np.int32) if mat is None else np.asarray(mat)
    if mat.shape != (n,):
        raise ValueError(f"material ids must have shape ({n},), got {mat.shape}")
    if not np.issubdtype(mat.dtype, np.integer):
        raise ValueError(f"material ids must be integers, got dtype {mat.dtype}")
    bad_ids = mat[(mat < 0) | (mat >= len(cfg.materials))]
    if bad_ids.size:
        # name an offending id (the old message named mat.max(), a valid id, when the bad
        # one was negative)
        raise ValueError(f"unknown material id {int(bad_ids[0])}: the table has "
                         f"{len(cfg.materials)} materials (ids 0..{len(cfg.materials) - 1})")
    vol = np.full(n, cfg.dx ** 3 / 8) if vol is None else np.asarray(vol)
    if not _broadcasts_to(vol.shape, (n,)):
        raise ValueError(f"particle volumes must be a scalar or have shape ({n},), "
                         f"got {vol.shape}")
    vol = np.broadcast_to(vol, (n,))
    if not np.all(vol > 0):
        raise ValueError("particle volumes must be > 0 m^3")
    # Grid nodes sit at 0 .. n - 1 cells, so a particle's B-spline stencil fits in the grid
    # only for 0.5 <= x / dx < n - 1.5. Keep particles at least half a cell inside that, and
    # between the wall surfaces (wall_cells and domain - wall_cells cells, where the walls'
    # constrained nodes start). The upper bound used to be n - 1 cells without walls, which
    # accepted particles whose stencil was already outside the grid (flagged as escaped on
    # the first substep).
    walls = cfg.wall_cells if cfg.walls != "none" else 0
    lo = max(walls, 1) * cfg.dx
    hi = np.asarray(cfg.domain) * cfg.dx - max(walls, 2) * cfg.dx
    outside = np.any((x < lo) | (x > hi), axis=1)
    if outside.any():
        i = int(np.argmax(outside))
        raise ValueError(f"{int(outside.sum())} particles lie outside the simulation domain "
                         f"[{lo:.4g}, {hi.tolist()}) m (minus walls); first: particle {i} at "
                         f"{x[i].tolist()}")
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
    return state.replace(origin=_window_origin(cfg, state.x))


def _broadcasts_to(shape, target) -> bool:
    """Whether an array of ``shape`` broadcasts to exactly ``target``."""
    try:
        return np.broadcast_shapes(tuple(shape), tuple(target)) == tuple(target)
    except ValueError:
        return False


def check_state(state: MPMState, cfg: MPMConfig | None = None,
                params: MaterialParams | None = None) -> None:
    """Raise if a rollout went non-finite or unstable (a particle outran the time step,
    :func:`max_stable_speed`) or lost particles out of the window/domain. An unstable run is
    reported as such even when its particles also left the window (they did because of it);
    with ``cfg`` (and ``params``, default ``cfg.params``) the message gives the speed limit.
    (This syncs with the host: call it after a rollout, not inside one.)"""
    finite = np.asarray(state.finite)
    escaped = np.asarray(state.escaped)
    if not finite.all():
        x, v = np.asarray(state.x), np.asarray(state.v)
        if np.all(np.isfinite(x)) and np.all(np.isfinite(v)):
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
        raise FloatingPointError("the MPM state became non-finite (NaN/inf): the time step "
                                 "is probably unstable for the velocities reached")
    if escaped.any():
        raise RuntimeError("particles left the active window or the domain and were clamped; "
                           "enlarge MPMConfig.window/domain")


# ----------------------------------------------------------------------------- helpers

@jax.custom_vjp
def _mat3(M):
    """(N, 3, 3) -> nested list of contiguous (N,) components. Component-wise maths on a
    (9, N) structure-of-arrays layout is several times faster on CPU than batched 3x3
    products or strided component access. The reverse mode computes the nine component
    cotangents together (:func:`_transfer.materialise` of the tuple) before stacking them:
    stacked directly, XLA fused each one's whole computation into its own row of the
    stack, and an elastic substep's reverse redid the polar decomposition's adjoint nine
    times (60 % of its time)."""
    rows = M.reshape(-1, 9).T
    return [[rows[3 * i + j] for j in range(3)] for i in range(3)]


def _mat3_fwd(M):
    return _mat3(M), None


def _mat3_bwd(_, ct):
    return (_stack3(ct),)


_mat3.defvjp(_mat3_fwd, _mat3_bwd)


def _stack3(m):
    """Inverse of :func:`_mat3`: nested components -> (N, 3, 3), the nine computed together
    in one loop first (see :func:`_mat3`)."""
    return jnp.stack(_transfer.materialise(_flat(m))).T.reshape(-1, 3, 3)


def _flat(m):
    """Nested components -> a tuple of the nine, row-major."""
    return tuple(m[i][j] for i in range(3) for j in range(3))


def _soa(m):
    return jnp.stack(_flat(m))


def _unsoa(rows):
    return [[rows[3 * i + j] for j in range(3)] for i in range(3)]


def _mul(A, B):
    return [[A[i][0] * B[0][j] + A[i][1] * B[1][j] + A[i][2] * B[2][j] for j in range(3)]
            for i in range(3)]


def _transpose(A):
    return [[A[j][i] for j in range(3)] for i in range(3)]


def _plus_identity(H):
    """``I + H`` (component lists)."""
    return [[H[i][j] + 1.0 if i == j else H[i][j] for j in range(3)] for i in range(3)]


def _det_minus_one(H):
    """``det(I + H) - 1`` without cancellation: ``tr H + i2(H) + det H`` (``i2`` the sum of
    the principal 2x2 minors), accurate in float32 when H is small."""
    tr = H[0][0] + H[1][1] + H[2][2]
    i2 = (H[0][0] * H[1][1] - H[0][1] * H[1][0] + H[0][0] * H[2][2] - H[0][2] * H[2][0]
          + H[1][1] * H[2][2] - H[1][2] * H[2][1])
    return tr + i2 + _det(H)


def _det(A):
    return (A[0][0] * (A[1][1] * A[2][2] - A[1][2] * A[2][1])
            - A[0][1] * (A[1][0] * A[2][2] - A[1][2] * A[2][0])
            + A[0][2] * (A[1][0] * A[2][1] - A[1][1] * A[2][0]))


def _cofactor(A):
    """Cofactor matrix cof(A) = det(A) A^{-T}."""
    return [[A[1][1] * A[2][2] - A[1][2] * A[2][1], A[1][2] * A[2][0] - A[1][0] * A[2][2],
             A[1][0] * A[2][1] - A[1][1] * A[2][0]],
            [A[0][2] * A[2][1] - A[0][1] * A[2][2], A[0][0] * A[2][2] - A[0][2] * A[2][0],
             A[0][1] * A[2][0] - A[0][0] * A[2][1]],
            [A[0][1] * A[1][2] - A[0][2] * A[1][1], A[0][2] * A[1][0] - A[0][0] * A[1][2],
             A[0][0] * A[1][1] - A[0][1] * A[1][0]]]


@jax.custom_vjp
def polar_rotation(F):
    """Rotation R of the polar decomposition F = R S, by Newton iteration
    R <- (R + R^{-T}) / 2 (component-wise lists of (N,) arrays).

    Reverse mode is the closed-form differential of the polar factor, not the derivative
    of the iteration: with S = R^T F and a rotation R dR = R Omega, Omega skew with axial
    vector omega, (tr(S) I - S) omega = axial(R^T dF - dF^T R). Its transpose gives
    F_bar = R skew(c) with c = (tr(S) I - S)^{-1} b, b the axial vector of
    R^T R_bar - R_bar^T R (:func:`_polar_vjp`).
    Differentiating the six Newton steps instead cost most of an elastic substep's
    gradient; the two agree to the iteration's convergence (tested)."""
    return _polar_newton(F)


def _polar_newton(F):
    R = F
    for _ in range(POLAR_ITERS):
        cof = _cofactor(R)
        inv_det = _transfer.materialise(1.0 / _det(R))
        R = [[0.5 * (R[i][j] + cof[i][j] * inv_det) for j in range(3)] for i in range(3)]
        # Each iterate is materialised as one (9, N) array, and 1 / det before it: a stack
        # alone is no barrier on CPU, and the last iterate's cofactors and determinant were
        # redone inside each of the dozen loops that read R (the stress entries): 13 %
        # of an elastic substep (8192 particles, 177 -> 150 ms per 100 substeps).
        R = _unsoa(_transfer.materialise(_soa(R)))
    return R


def _polar_fwd(F):
    # named: a substep's reverse pass keeps R rather than redo the iteration (see step)
    R = [[checkpoint_name(r, "mpm_polar") for r in row] for row in _polar_newton(F)]
    return R, (F, R)


def _polar_vjp(res, R_bar):
    F, R = res
    Rt = _transpose(R)
    S = _mul(Rt, F)
    S = [[0.5 * (S[i][j] + S[j][i]) for j in range(3)] for i in range(3)]
    B = _mul(Rt, R_bar)
    b = [B[2][1] - B[1][2], B[0][2] - B[2][0], B[1][0] - B[0][1]]
    tr = S[0][0] + S[1][1] + S[2][2]
    K = [[(tr if i == j else 0.0) - S[i][j] for j in range(3)] for i in range(3)]
    # K is symmetric with eigenvalues s_i + s_j > 0 (sums of two singular values of F):
    # c = K^{-1} b through the cofactor matrix
    cof = _cofactor(K)
    det = _det(K)
    det = jnp.where(jnp.abs(det) > 1e-30, det, 1e-30)
    c = [(cof[0][i] * b[0] + cof[1][i] * b[1] + cof[2][i] * b[2]) / det for i in range(3)]
    skew = [[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]]
    return (_mul(R, skew),)


polar_rotation.defvjp(_polar_fwd, _polar_vjp)


def _window_origin(cfg: MPMConfig, x):
    """Integer origin (3,) of the active window, centred on the particles' bounding box."""
    if cfg.full_grid:
        return jnp.zeros((3,), jnp.int32)
    lo = jnp.floor(jnp.min(x, axis=0) / cfg.dx)
    hi = jnp.floor(jnp.max(x, axis=0) / cfg.dx)
    half = jnp.asarray(cfg.window, x.dtype) // 2
    origin = jnp.floor(0.5 * (lo + hi)) - half + 1
    upper = jnp.asarray(cfg.domain, x.dtype) - jnp.asarray(cfg.window, x.dtype)
    return jnp.clip(origin, 0, upper).astype(jnp.int32)


def _kirchhoff_stress(cfg: MPMConfig, params: MaterialParams, state: MPMState, Hm, Cm):
    """Kirchhoff stress tau (component lists) per particle, for the kinds in the table,
    from ``Hm`` = F - I (b_e - I for plastic particles) as component lists."""
    kinds = cfg.kinds
    mu = params.mu[state.mat]
    lam = params.lam[state.mat]
    zero = jnp.zeros_like(mu)
    tau = [[zero, zero, zero] for _ in range(3)]

    def add(a, b, sel=None):
        if sel is None:
            return [[a[i][j] + b[i][j] for j in range(3)] for i in range(3)]
        return [[a[i][j] + jnp.where(sel, b[i][j], 0.0) for j in range(3)] for i in range(3)]

    single = len(kinds) == 1
    mat_kind = _particle_kinds(cfg, state.mat)

    if "fluid" in kinds:
        J = state.J
        p = lam * J * (J - 1.0)
        eta = params.viscosity[state.mat] * J
        t = [[(p if i == j else zero) + eta * (Cm[i][j] + Cm[j][i]) for j in range(3)]
             for i in range(3)]
        tau = add(tau, t, None if single else mat_kind == KIND_CODE["fluid"])
    if "elastic" in kinds:
        Fm = _plus_identity(Hm)
        R = polar_rotation(Fm)
        Jm1 = _det_minus_one(Hm)
        FmR = [[Fm[i][j] - R[i][j] for j in range(3)] for i in range(3)]
        P = _mul(FmR, _transpose(Fm))
        vol_term = lam * (1.0 + Jm1) * Jm1
        t = [[2.0 * mu * P[i][j] + (vol_term if i == j else zero) for j in range(3)]
             for i in range(3)]
        tau = add(tau, t, None if single else mat_kind == KIND_CODE["elastic"])
    if "plastic" in kinds:
        # H slot holds B = b_e - I; J^2 = det(b_e). dev(b_e) = dev(B), so the stress is
        # computed from B without cancellation.
        B = Hm
        J2m1 = _det_minus_one(B)
        scale = jnp.maximum(1.0 + J2m1, 1e-12) ** (-1.0 / 3.0)
        trB3 = (B[0][0] + B[1][1] + B[2][2]) / 3.0
        kappa = lam + 2.0 / 3.0 * mu
        t = [[mu * scale * (B[i][j] - (trB3 if i == j else 0.0))
              + (0.5 * kappa * J2m1 if i == j else zero) for j in range(3)]
             for i in range(3)]
        tau = add(tau, t, None if single else mat_kind == KIND_CODE["plastic"])
    return tau


KIND_CODE = {"fluid": 0, "elastic": 1, "plastic": 2}


def _particle_kinds(cfg: MPMConfig, mat):
    """Per-particle material kind code (see :data:`KIND_CODE`) from material ids."""
    return jnp.asarray([KIND_CODE[m.kind] for m in cfg.materials], jnp.int32)[mat]


def _return_map(params: MaterialParams, mat, B):
    """Von Mises radial return on b_e = I + B (component lists of B): project the deviator
    of bbar_e = J^{-2/3} b_e onto |mu dev(bbar_e)| <= sqrt(2/3) sigma_y, keeping det;
    returns the new ``b_e - I``. Inside the yield surface B comes back unchanged, bit for
    bit (the projection's rounding would otherwise accumulate like F's did)."""
    mu = params.mu[mat]
    sy = params.yield_stress[mat]
    scale = jnp.maximum(1.0 + _det_minus_one(B), 1e-12) ** (-1.0 / 3.0)
    trB3 = (B[0][0] + B[1][1] + B[2][2]) / 3.0
    # The return map's shared scalars and 3x3 intermediates are materialised: left to
    # fusion, each of the nine outputs (and, in reverse mode, each of the nine adjoint
    # components) redid the whole map (a plastic gradient took 46x its forward at 20
    # substeps of 8192 particles, 4.2x now).
    scale, trB3 = _transfer.materialise((scale, trB3))
    dev = [[scale * (B[i][j] - (trB3 if i == j else 0.0)) for j in range(3)]
           for i in range(3)]
    dev = _unsoa(_transfer.materialise(_flat(dev)))
    tr3 = scale * (1.0 + trB3)
    norm = jnp.sqrt(sum(dev[i][j] * dev[i][j] for i in range(3) for j in range(3)) + 1e-20)
    s_norm = mu * norm
    limit = math.sqrt(2.0 / 3.0) * sy
    yielding = s_norm > limit
    # Both sides of the division are replaced where the particle does not yield: a particle
    # that cannot yield (sigma_y = inf: every non-plastic particle in a mixture) had
    # limit / s_norm = inf there, whose unselected derivative inf * 0 made every
    # particle's reverse-mode derivative NaN after one substep.
    factor = jnp.where(yielding, jnp.where(yielding, limit, 1.0)
                       / jnp.where(yielding, s_norm, 1.0), 1.0)
    factor, tr3 = _transfer.materialise((factor, tr3))
    new_bbar = [[dev[i][j] * factor + (tr3 if i == j else 0.0) for j in range(3)]
                for i in range(3)]
    new_bbar = _unsoa(_transfer.materialise(_flat(new_bbar)))
    # keep det(bbar) = 1 (isochoric plastic flow) by renormalising the new isochoric part.
    d = jnp.maximum(_det(new_bbar), 1e-12)
    renorm = d ** (-1.0 / 3.0) / scale
    renorm = _transfer.materialise(renorm)
    return [[jnp.where(yielding, new_bbar[i][j] * renorm - (1.0 if i == j else 0.0), B[i][j])
             for j in range(3)] for i in range(3)]


# ----------------------------------------------------------------------------- substep

#: Driven-mass fraction above which a grid node moves with the driven particles
#: (:func:`step`'s ``drive``); below it the drive fades out smoothly to zero driven mass.
DRIVE_FRACTION = 1e-3


def _drive_grid(gv, driven_mass, gm, velocity, heavy):
    """Grid velocities ``gv`` (M, 3) with every node that carries more than
    :data:`DRIVE_FRACTION` driven mass set to ``velocity`` (3,): the infinite-mass limit of
    a rigid grip. Without it the driven (held) particles were only reset after the
    substep, while the stress of the rope they pull slowed the nodes they share with it:
    the velocity field moved slower than the grip, so the gap opening between the grip
    and the free particles never entered any particle's F, and no force closed it (a
    rope pulled at 1 m/s came off its held end)."""
    # Below DRIVE_FRACTION the node blends in the drive with a C1 ramp (smoothstep) of
    # the driven fraction: a hard switch made the velocity of a node jump as its driven
    # fraction crossed the threshold, a jump of the whole rollout in the action (Whip-Rope
    # reward: +4.9e-6 within 2e-4 m/s of the action; autodiff cannot see it).
    # The fraction's reverse-mode derivative (-d / m^2) overflows float32 on the nearly
    # empty nodes, as in step's grid velocity: there (``heavy`` false) the fraction keeps
    # its forward value and passes no gradient (a Young's-modulus gradient through
    # Whip-Rope was NaN without this).
    frac_heavy = driven_mass / (DRIVE_FRACTION * jnp.where(heavy, gm, 1.0))
    frac_light = jax.lax.stop_gradient(
        driven_mass / (DRIVE_FRACTION * jnp.where(gm > 0.0, gm, 1.0)))
    t = jnp.clip(jnp.where(heavy, frac_heavy, frac_light), 0.0, 1.0)
    alpha = (t * t * (3.0 - 2.0 * t))[:, None]
    return gv + alpha * (velocity - gv)


@jax.custom_vjp
def _per_mass(p, mass):
    """The node velocities ``p / mass[:, None]`` of the (M, C) node momenta. Its reverse
    mode writes the mass cotangent ``-sum_c dv_c v_c / mass`` as a C-term sum: autodiff's
    sum over the broadcast channel axis ran as a YNNPACK reduction (200 us per fluid
    substep on a 32^3 grid), and a channel-by-channel division as five padded grid adds."""
    return p / mass[:, None]


def _per_mass_fwd(p, mass):
    v = p / mass[:, None]
    return v, (v, mass)


def _per_mass_bwd(res, dv):
    v, mass = res
    dmass = -sum(dv[:, c] * v[:, c] for c in range(v.shape[1])) / mass
    return dv / mass[:, None], dmass


_per_mass.defvjp(_per_mass_fwd, _per_mass_bwd)


def step(cfg: MPMConfig, params: MaterialParams, state: MPMState, drive=None) -> MPMState:
    """Advance the scene by one substep of ``cfg.dt`` seconds (pure; jit with ``cfg``
    static). The colliders' friction is ``params.friction`` when set.

    drive: ``None`` or ``(weight, velocity)``: particles moved kinematically at the
        velocity ``velocity`` (3,) [m/s] (a held part of the object; ``weight`` (N,) is 1
        for them, 0 for the free ones). The grid carries the constraint: the nodes that
        carry driven mass move at ``velocity`` (:func:`_drive_grid`), so the velocity
        field that the free particles and every particle's F see moves with the driven
        part. The caller still sets the driven particles' positions after the substep.
        Costs a fifth scatter channel; ``None`` leaves the substep as it was.

    Reverse mode keeps only the substep's input state and :data:`REVERSE_SAVED` (the P2G
    grid, the G2P moments and the elastic rotation) and recomputes the rest, all of it
    elementwise, in the backward pass (:data:`_REMAT_POLICY`)."""
    return _remat_step(cfg, params, state, drive)


#: The intermediates of a substep that its reverse pass keeps: the P2G grid (the grid
#: update's adjoint divides by its masses), the G2P moments (the new velocity, C and J are
#: affine in them) and the polar rotation of elastic particles (an iteration). Everything
#: else is recomputed from the substep's input state: weights, stresses, the grid update.
#: Kept whole, a fluid substep's residuals were 4.2 MB (8192 particles, 32^3 grid): a
#: 100-substep gradient allocated 417 MB of fresh pages per call (107 000 page faults,
#: 0.2 s of system time). Kept like this they are 1.6 MB and that gradient is 16 % faster
#: (elastic 20 %), with the same values; recomputing them costs less than storing them.
REVERSE_SAVED = ("mpm_grid", "mpm_moments", "mpm_polar")
_REMAT_POLICY = jax.checkpoint_policies.save_only_these_names(*REVERSE_SAVED)


def _step(cfg: MPMConfig, params: MaterialParams, state: MPMState, drive) -> MPMState:
    dt, dx = cfg.dt, cfg.dx
    inv_dx = 1.0 / dx
    dtype = state.x.dtype
    x, v = state.x, state.v
    Wx, Wy, Wz = cfg.window

    origin = _window_origin(cfg, x)
    Xp = x * inv_dx
    base_f = jnp.floor(Xp - 0.5)
    fx = Xp - base_f
    base = base_f.astype(jnp.int32) - origin
    hi = jnp.asarray(cfg.window, jnp.int32) - 3
    escaped = jnp.any((base < 0) | (base > hi))
    if not cfg.full_grid:
        dom_base = base + origin
        escaped = escaped | jnp.any(
            (dom_base < 0) | (dom_base > jnp.asarray(cfg.domain, jnp.int32) - 3))
    # Block corners and quadratic B-spline weights per axis, w[:, o, a], each computed once
    # (materialised): left to fusion, both were recomputed inside every fused reader,
    # once per gathered or scattered row.
    base = _transfer.materialise(jnp.clip(base, 0, hi))
    w = _transfer.materialise(jnp.stack(
        [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2],
        axis=1))  # (N, offset, axis)

    Cm = _mat3(state.C)
    Hm = _mat3(state.H)
    m = state.vol * params.density[state.mat]
    tau = _kirchhoff_stress(cfg, params, state, Hm, Cm)
    k_stress = -dt * state.vol * 4.0 * inv_dx * inv_dx
    A = [[k_stress * tau[i][j] + m * Cm[i][j] for j in range(3)] for i in range(3)]
    # momentum at offset o: w_o (m v + A (o - fx) dx) = w_o (b + dx A o), b = m v - dx A fx
    # Gravity's impulse enters here, as momentum m g dt per particle (the grid's nodes then
    # hold p + m_i g dt), not as g dt added to the grid velocity after the division: that
    # add contracted into a fused multiply-add in the vectorised part of the grid loop but
    # not in its remainder, so a node's rounding depended on where it sat in the grid and
    # the active window no longer reproduced the full grid bit for bit. (Since the G2P
    # moments are contracted axis by axis, XLA fuses their multiply-adds differently on a
    # window than on the full grid: the two now agree to float32 rounding.)
    vg = [v[:, i] + dt * cfg.gravity[i] if cfg.gravity[i] else v[:, i] for i in range(3)]
    b = [m * vg[i] - dx * (A[i][0] * fx[:, 0] + A[i][1] * fx[:, 1] + A[i][2] * fx[:, 2])
         for i in range(3)]
    # Per-particle rows R (N, 4, nc) of the affine node values w_o (b + dx A o, m) (see
    # _transfer): b (then the mass channels) and dx times the columns of A (zero in the
    # mass channels). Passing their 13 (14 with a drive) distinct entries through an identity matmul
    # materialises them: left elementwise, XLA fuses the stress computation into the
    # 27-fold scatter input and recomputes it for every stencil node (measured 30-60x
    # slower for the fixed-corotated model; an identity matmul on R's last axis is fused
    # with its input on CPU and was as slow).
    masses = [m] if drive is None else [m, m * jnp.asarray(drive[0], dtype)]  # 5th channel
    entries = list(_transfer.materialise(tuple(
        b + [dx * A[c][a] for a in range(3) for c in range(3)] + masses)))
    b, dxA, masses = entries[:3], entries[3:12], entries[12:]
    zeros = [jnp.zeros_like(m)] * len(masses)
    R = _transfer.materialise(jnp.stack(
        [jnp.stack(b + masses, axis=-1)]
        + [jnp.stack(dxA[3 * a:3 * a + 3] + zeros, axis=-1) for a in range(3)], axis=1))
    nc = R.shape[-1]
    # one windowed scatter-add of each particle's 3x3x3 block (about 2x faster on CPU than
    # 27 N point scatters)
    grid = checkpoint_name(_transfer.spread(cfg.window, base, w, R).reshape(-1, nc),
                           "mpm_grid")

    # grid update, on all four channels (momentum, mass): a (M, 3) velocity padded to four
    # channels for the aligned G2P gather made the pad the root of the grid update's fused
    # loop, which then ran several times slower. The fourth channel ends up m / m (1 or 0)
    # and is never read.
    gm = grid[:, 3]
    has_mass = gm > 0.0
    gv_exact = _per_mass(grid[:, :4], jnp.where(has_mass, gm, 1.0))
    # A node touched only by the far tail of the B-spline weights can hold a vanishing mass
    # (1e-30 kg). Dividing by it is fine forward, but its reverse-mode derivative (-p / m^2)
    # overflows float32 to inf and then NaN (seen on Push-Rope: NaN action gradients at
    # 160+ substeps). Below a millionth of the lightest particle's mass the velocity keeps
    # its exact forward value but passes no gradient (such a node moves nothing).
    heavy = gm > 1e-6 * jax.lax.stop_gradient(jnp.min(m))
    gv_heavy = _per_mass(grid[:, :4], jnp.where(heavy, gm, 1.0))
    gv = jnp.where(heavy[:, None], gv_heavy,
                   jnp.where(has_mass[:, None], jax.lax.stop_gradient(gv_exact), 0.0))
    # drive, walls, colliders, in this order (the drive and the colliders act on the
    # three velocity channels)
    if drive is not None:
        gv = jnp.concatenate([_drive_grid(gv[:, :3], grid[:, 4], gm,
                                          jnp.asarray(drive[1], dtype), heavy), gv[:, 3:]],
                             axis=1)
    if cfg.walls != "none":
        # nodes on or beyond the wall surfaces (see the module docstring); the mass
        # channel's column is never a wall
        node = jnp.asarray(np.indices(cfg.window).reshape(3, -1).T, jnp.int32) + origin
        lo_wall = jnp.pad(node <= cfg.wall_cells, ((0, 0), (0, 1)))
        hi_wall = jnp.pad(node >= jnp.asarray(cfg.domain, jnp.int32) - cfg.wall_cells,
                          ((0, 0), (0, 1)))
        if cfg.walls == "sticky":
            gv = jnp.where(jnp.any(lo_wall | hi_wall, axis=1, keepdims=True), 0.0, gv)
        else:
            gv = jnp.where((lo_wall & (gv < 0)) | (hi_wall & (gv > 0)), 0.0, gv)
    if cfg.colliders:
        gv = jnp.concatenate([col.apply_colliders_grid(
            cfg.colliders, state.colliders, gv[:, :3], dx, cfg.window, origin,
            params.friction), gv[:, 3:]], axis=1)
    gv = jnp.where(has_mass[:, None], gv, 0.0)

    # G2P: gather each particle's 3x3x3 block of the four channels (aligned rows gather
    # faster than three).
    # Materialised: otherwise XLA fuses the whole grid update (division, walls, colliders)
    # into the gather and redoes it for every one of the 27 reads per particle (measured:
    # a third of the substep time).
    gv4 = _transfer.materialise(gv.reshape(Wx, Wy, Wz, 4))
    S = checkpoint_name(_transfer.collect(gv4, base, w), "mpm_moments")
    new_v = [S[:, 0, c] for c in range(3)]
    new_C = [[4.0 * inv_dx * (S[:, 1 + j, i] - new_v[i] * fx[:, j]) for j in range(3)]
             for i in range(3)]
    new_v_arr = jnp.stack(new_v, axis=-1)
    new_x = x + dt * new_v_arr

    kinds = cfg.kinds
    trC = new_C[0][0] + new_C[1][1] + new_C[2][2]
    new_J = state.J
    if "fluid" in kinds:
        new_J = state.J * (1.0 + dt * trC)
        if not cfg.fluid_tension:  # a liquid pushes but does not pull (module docstring)
            new_J = jnp.minimum(new_J, 1.0)
    if kinds == {"fluid"}:
        new_H = state.H
    else:
        # F <- (I + D) F with D = dt C, as H <- H + (D + D H): the increment is added to
        # the small H, not to O(1) entries of F (see the module docstring).
        # D's and B_trial's cotangents are materialised: each gathers the adjoints of the
        # H update (and of the return map), and every component of the next adjoint reads
        # all of them (fused, a plastic substep's reverse pass redid that chain per
        # component: 80 ms a substep at 8192 particles)
        D = _unsoa(_transfer.materialise_cotangent(_flat(
            [[dt * c for c in row] for row in new_C])))
        DH = _mul(D, Hm)
        Hn = [[Hm[i][j] + (D[i][j] + DH[i][j]) for j in range(3)] for i in range(3)]
        if "plastic" in kinds:
            is_pl = _particle_kinds(cfg, state.mat) == KIND_CODE["plastic"]
            # b_trial = (I + D) b (I + D)^T; with (I + D) b = I + Hn:
            # b_trial - I = Hn + D^T + Hn D^T
            HnDt = _mul(Hn, _transpose(D))
            B_trial = [[Hn[i][j] + (D[j][i] + HnDt[i][j]) for j in range(3)]
                       for i in range(3)]
            B_trial = _unsoa(_transfer.materialise_cotangent(_flat(B_trial)))
            B_new = _return_map(params, state.mat, B_trial)
            Hn = [[jnp.where(is_pl, B_new[i][j], Hn[i][j]) for j in range(3)]
                  for i in range(3)]
        if "fluid" in kinds:
            # Fluids use J only; keep their F at identity so a long mixture rollout never
            # polar-decomposes an ill-conditioned, unused F (whose gradient could overflow).
            is_fl = _particle_kinds(cfg, state.mat) == KIND_CODE["fluid"]
            Hn = [[jnp.where(is_fl, 0.0, Hn[i][j]) for j in range(3)] for i in range(3)]
        new_H = _stack3(Hn)

    new_C_arr = _stack3(new_C)
    cstate = col.advance(state.colliders, dt)
    held = state.held
    if cfg.colliders:
        k = jnp.maximum(held, 0)
        Rk = jax.vmap(col.quat_to_matrix)(cstate.quat)[k]
        hx = cstate.pos[k] + jnp.einsum("nij,nj->ni", Rk, state.held_offset,
                                            precision=_transfer.HIGHEST)
        hv = cstate.lin_vel[k] + jnp.cross(cstate.ang_vel[k], hx - cstate.pos[k])
        is_held = (held >= 0)[:, None]
        new_x = jnp.where(is_held, hx, new_x)
        new_v_arr = jnp.where(is_held, hv, new_v_arr)
        new_C_arr = jnp.where(is_held[:, :, None], 0.0, new_C_arr)

    # A particle faster than dx / dt - c breaks the CFL condition outright: flag the run
    # as unstable (it may still be finite, and then only its escaped flag would show it).
    speed_limit = max_stable_speed(cfg, params)
    # (``any`` of a comparison of explicit sums: a float ``max`` or ``sum`` over an axis
    # runs as a YNNPACK reduction on CPU, 25-50 us each here)
    speed2 = sum(new_v_arr[:, i] * new_v_arr[:, i] for i in range(3))
    outran = jnp.any(speed2 > speed_limit * jnp.abs(speed_limit))
    finite = state.finite & jnp.all(jnp.isfinite(new_x)) & ~outran
    return state.replace(
        x=new_x, v=new_v_arr, C=new_C_arr, H=new_H, J=new_J, colliders=cstate,
        origin=origin, finite=finite, escaped=state.escaped | escaped, time=state.time + dt)


_remat_step = jax.checkpoint(_step, static_argnums=(0,), prevent_cse=False,
                             policy=_REMAT_POLICY)


@functools.partial(jax.jit, static_argnums=(0, 3, 4))
def rollout(cfg: MPMConfig, params: MaterialParams, state: MPMState, n_substeps: int,
            segment: int | None = None) -> MPMState:
    """Run ``n_substeps`` substeps of :func:`step` as one scan (jitted; ``cfg``,
    ``n_substeps`` and ``segment`` are static).

    segment: substeps per checkpointed segment (:func:`dax_physics.checkpointed_scan`,
        whose remainder rule applies); reverse-mode memory then grows with the number of
        segments, not substeps, at the cost of recomputing each segment once in the
        backward pass. ``None``: no checkpointing. Forward values are the same either way.
    A negative or non-integer ``n_substeps`` raises ``ValueError`` (0 returns ``state``).
    """
    if isinstance(n_substeps, bool) or not isinstance(n_substeps, (int, np.integer)) \
            or n_substeps < 0:
        raise ValueError(f"n_substeps must be an int >= 0, got {n_substeps!r}")

    def body(s, _):
        return step(cfg, params, s), None

    return checkpointed_scan(body, state, length=n_substeps, segment=segment)[0]


# ----------------------------------------------------------------------------- grasping

def grasp(cfg: MPMConfig, state: MPMState, index: int, radius: float) -> MPMState:
    """Attach to collider ``index`` every free particle within ``radius`` [m] of its
    surface; attached particles then move rigidly with the collider."""
    spec = cfg.colliders[index]
    cs = state.colliders
    phi, _ = col.sdf(spec, cs.pos[index], cs.quat[index], state.x)
    take = (phi < radius) & (state.held < 0)
    R = col.quat_to_matrix(cs.quat[index])
    local = _transfer.mm(state.x - cs.pos[index], R)
    return state.replace(held=jnp.where(take, index, state.held),
                         held_offset=jnp.where(take[:, None], local, state.held_offset))


def release(state: MPMState, index: int) -> MPMState:
    """Detach every particle held by collider ``index``."""
    return state.replace(held=jnp.where(state.held == index, -1, state.held))


def set_collider_velocity(state: MPMState, index: int, lin_vel=None, ang_vel=None) -> MPMState:
    """Set the velocity command of collider ``index`` [m/s, rad/s, world frame]."""
    return state.replace(colliders=state.colliders.with_velocity(index, lin_vel, ang_vel))


# ----------------------------------------------------------------------------- diagnostics

def total_mass(params: MaterialParams, state: MPMState):
    """Total particle mass [kg]."""
    return jnp.sum(state.vol * params.density[state.mat])


def momentum(params: MaterialParams, state: MPMState):
    """Total linear momentum [kg m/s] (3,)."""
    m = state.vol * params.density[state.mat]
    return jnp.sum(m[:, None] * state.v, axis=0)


def kinetic_energy(params: MaterialParams, state: MPMState):
    """Translational kinetic energy of the particles [J]: sum_p m_p |v_p|^2 / 2."""
    m = state.vol * params.density[state.mat]
    return 0.5 * jnp.sum(m * jnp.sum(state.v ** 2, axis=1))


def potential_energy(cfg: MPMConfig, params: MaterialParams, state: MPMState):
    """Gravitational potential [J] relative to z = 0 plus stored elastic energy [J]."""
    m = state.vol * params.density[state.mat]
    g = jnp.asarray(cfg.gravity, state.x.dtype)
    grav = -jnp.sum(m[:, None] * state.x * g)
    return grav + jnp.sum(state.vol * strain_energy_density(cfg, params, state))


def strain_energy_density(cfg: MPMConfig, params: MaterialParams, state: MPMState):
    """Stored energy per rest volume [J/m^3] per particle: fixed-corotated for elastic,
    ``K/2 (J - 1)^2``-type for fluids (consistent with their pressure), neo-Hookean-like
    for plastic particles."""
    mu = params.mu[state.mat]
    lam = params.lam[state.mat]
    Hm = _mat3(state.H)
    Fm = _plus_identity(Hm)
    R = polar_rotation(Fm)
    fr = sum((Fm[i][j] - R[i][j]) ** 2 for i in range(3) for j in range(3))
    e_el = mu * fr + 0.5 * lam * _det_minus_one(Hm) ** 2
    Jf = state.J
    # Kirchhoff pressure tau = K J (J - 1) = J psi'(J)  <=>  psi(J) = K (J - 1)^2 / 2.
    # (This used to be K (J^3/3 - J^2/2 + 1/6), whose psi' = K J (J - 1) is the Kirchhoff
    # stress itself, i.e. the potential of tau = K J^2 (J - 1): off by a factor J.)
    e_fl = 0.5 * lam * (Jf - 1.0) ** 2
    J2 = jnp.maximum(1.0 + _det_minus_one(Hm), 1e-12)
    tr = (3.0 + Hm[0][0] + Hm[1][1] + Hm[2][2]) * J2 ** (-1.0 / 3.0)
    kappa = lam + 2.0 / 3.0 * mu
    e_pl = 0.5 * mu * (tr - 3.0) + 0.25 * kappa * (J2 - 1.0 - jnp.log(J2))
    kind = _particle_kinds(cfg, state.mat)
    return jnp.where(kind == 0, e_fl, jnp.where(kind == 1, e_el, e_pl))
