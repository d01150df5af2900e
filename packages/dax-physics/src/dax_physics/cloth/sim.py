"""Mass-spring cloth on triangle meshes: model, state, one substep, rollouts.

Split like the rest of dax-physics:

* :class:`ClothConfig` (static, hashable): substep, gravity, air drag, table contact and
  friction, self-collision thickness, strain limit, colliders;
* :class:`Cloth` (pytree of arrays): the material - vertex masses and the spring network
  with rest lengths, stiffness and damping per spring, optionally the table friction as
  data (differentiable; :func:`scale_moduli` scales it);
* :class:`ClothState` (pytree of arrays): vertex positions and velocities, gripper
  attachments, gripper poses and velocity commands, collider poses.

The verbs are those of :mod:`dax_physics.mpm`, with the same argument order: :func:`step`,
:func:`rollout` (neither jitted: the caller jits), :func:`check_params` (eager, once: the
stable ``dt`` depends on the springs and masses, so :class:`ClothConfig` alone cannot
check it), :func:`max_stable_dt`, :func:`check_state`; ``grasp`` and ``release`` are in
:mod:`dax_physics.cloth.grasp`.

Units are SI, z is up; V vertices, E springs, G grippers. Every public function but the
checks is pure and works under ``jax.jit``, ``jax.vmap`` and ``jax.grad``.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import colliders as _col
from .._checks import step_count, unstable_dt
from .._fusion import materialise
from .._pytree import pytree_dataclass, static_field
from ..scan import checkpointed_scan
from . import mesh as _mesh
from . import selfcollision as _sc
from .selfcollision import SELF_SEARCHES, NeighbourList

_TINY = 1e-20
#: Table friction laws (:attr:`ClothConfig.friction_model`).
FRICTION_MODELS = ("coulomb", "smooth")


# ----------------------------------------------------------------------------- static config

@dataclasses.dataclass(frozen=True)
class ClothConfig:
    """Static cloth-solver configuration (hashable; pass as a jit static argument).

    dt: substep [s], > 0; checked against :func:`max_stable_dt` by :func:`check_params`.
    gravity: acceleration (gx, gy, gz) [m/s^2].
    air_drag: linear air drag per unit cloth area [kg/(m^2 s)]; force ``-air_drag A_i v_i``.
    table_height: height of the table plane [m]; ``None`` for no table.
    friction_static, friction_dynamic: Coulomb coefficients [-] of cloth on the table
        (``friction_dynamic=None`` means equal to the static one).
    friction_model: ``"coulomb"`` (default): stick while ``|v_t| <= mu_s dv_n``, else
        ``|v_t| -= mu_d dv_n``; ``"smooth"``: ``|v_t| <- |v_t|^2 / (|v_t| + mu_d dv_n)``,
        a regularised Coulomb law for gradient-based planning (see :func:`_table_contact`).
    thickness: self-collision thickness h [m]; vertices closer than h repel. 0 disables
        self-collision.
    self_stiffness: repulsion stiffness [N/m] of a vertex pair closer than h.
    self_damping: normal damping [N s/m] of an approaching pair closer than h.
    self_friction: tangential (viscous) friction [N s/m] between a pair closer than h: a
        force ``-self_friction * v_t,rel`` that keeps stacked layers from sliding apart.
    self_search: how contact pairs are found (:mod:`dax_physics.cloth.selfcollision`):
        ``"list"`` (default) a Verlet neighbour list with a skin, kept in the state and
        rebuilt when a vertex has moved more than half the skin: a substep costs the
        listed pairs, exact while the list's overflow is 0; ``"all"`` every vertex pair
        (V^2 pair tests per substep, exact, no list).
    self_skin: the list's skin [m] (pairs closer than ``h + self_skin`` are listed);
        ``None``: h / 2.
    self_capacity: pair slots of the list per vertex [-] (static; the list holds
        ``self_capacity * V`` pairs, rounded up to a multiple of 8; more are counted as
        overflow).
    self_candidates: vertices the list's cell search examines per neighbouring cell
        (static; a crowded cell's extra vertices are counted as overflow).
    self_exclude: pairs whose rest distance is below ``self_exclude * h`` never repel (mesh
        neighbours).
    strain_limit: maximum relative stretch of structural springs (e.g. 0.1 = 10 %), enforced
        by position projection after each substep; ``None`` disables it.
    strain_iterations: Jacobi projection sweeps per substep for the strain limit.
    colliders: tuple of :class:`dax_physics.colliders.ColliderSpec` (kinematic SDF shapes,
        velocity-level contact on cloth vertices).
    """

    dt: float = 1e-4
    gravity: tuple = (0.0, 0.0, -9.81)
    air_drag: float = 0.0
    table_height: float | None = 0.0
    friction_static: float = 0.0
    friction_dynamic: float | None = None
    thickness: float = 0.0
    self_stiffness: float = 200.0
    self_damping: float = 0.0
    self_friction: float = 0.0
    self_search: str = "list"
    self_skin: float | None = None
    self_capacity: float = 4.0
    self_candidates: int = 16
    self_exclude: float = 2.0
    strain_limit: float | None = None
    strain_iterations: int = 4
    colliders: tuple = ()
    friction_model: str = "coulomb"

    def __post_init__(self):
        object.__setattr__(self, "gravity", tuple(float(g) for g in self.gravity))
        object.__setattr__(self, "colliders", tuple(self.colliders))
        if len(self.gravity) != 3:
            raise ValueError(f"gravity must be a 3-vector [m/s^2], got {self.gravity}")
        if not self.dt > 0:
            raise ValueError(f"dt must be > 0 s, got {self.dt}")
        if self.friction_static < 0 or (self.friction_dynamic or 0.0) < 0:
            raise ValueError("friction coefficients must be >= 0, got "
                             f"{self.friction_static}, {self.friction_dynamic}")
        if self.thickness < 0:
            raise ValueError(f"thickness must be >= 0 m, got {self.thickness}")
        if self.self_candidates < 1:
            raise ValueError(f"self_candidates must be >= 1, got {self.self_candidates}")
        if not self.self_capacity > 0:
            raise ValueError(f"self_capacity must be > 0, got {self.self_capacity}")
        if self.self_skin is not None and not self.self_skin > 0:
            raise ValueError(f"self_skin must be > 0 m or None, got {self.self_skin}")
        if self.self_search not in SELF_SEARCHES:
            raise ValueError(f"unknown self_search {self.self_search!r}; valid: "
                             f"{', '.join(SELF_SEARCHES)}")
        if self.strain_limit is not None and not self.strain_limit > 0:
            raise ValueError(f"strain_limit must be > 0 or None, got {self.strain_limit}")
        if self.friction_model not in FRICTION_MODELS:
            raise ValueError(f"unknown friction_model {self.friction_model!r}; valid: "
                             f"{', '.join(FRICTION_MODELS)}")

    @property
    def mu_dynamic(self) -> float:
        return self.friction_static if self.friction_dynamic is None else self.friction_dynamic


# ----------------------------------------------------------------------------- model

@pytree_dataclass
class Cloth:
    """Material and spring network of one cloth (arrays; differentiable floats).

    rest_pos (V, 3) [m]: rest configuration (used for self-collision exclusion).
    mass (V,) [kg], area (V,) [m^2]: lumped vertex mass and area.
    pairs (E, 2) int32: spring end vertices. kind (E,) int8: 0 structural, 1 shear, 2 bending.
    rest_length (E,) [m], stiffness (E,) [N/m], damping (E,) [N s/m] (dashpot along spring).
    faces (F, 3) int32: the triangles (for rendering and export).
    table_friction (2,): static and dynamic Coulomb coefficients [-] of the cloth on the
        table, as data; ``None`` (the default of :func:`make_cloth`) uses the
        :class:`ClothConfig`'s ``friction_static`` and ``friction_dynamic``.
    offsets, stencil_edge, residual: the spring network sorted for a scatter-free force
        sum (:func:`spring_layout`, filled in by :func:`make_cloth`): ``offsets`` (static
        tuple of S ints, ``(+o, -o)`` per class) are the index offsets of the stencil
        slots; ``stencil_edge`` (S, V) int32 is the spring between vertex i and vertex
        ``i + offsets[s]`` (E where there is none); ``residual`` (R,) int32 the springs in
        no slot. With the defaults (``()``, ``None``, ``None``) every spring is summed with
        a scatter; the forces are the same up to float rounding either way.
    """

    rest_pos: jnp.ndarray
    mass: jnp.ndarray
    area: jnp.ndarray
    pairs: jnp.ndarray
    kind: jnp.ndarray
    rest_length: jnp.ndarray
    stiffness: jnp.ndarray
    damping: jnp.ndarray
    faces: jnp.ndarray
    table_friction: jnp.ndarray | None = None
    stencil_edge: jnp.ndarray | None = None
    residual: jnp.ndarray | None = None
    offsets: tuple = static_field(default=())

    @property
    def n_vertices(self) -> int:
        return self.mass.shape[-1]


def scale_moduli(cloth: Cloth, stretch=1.0, shear=1.0, bend=1.0, damping=1.0,
                 density=1.0) -> Cloth:
    """``cloth`` with its structural, shear and bending stiffness, its dashpots and its
    vertex masses multiplied by the given factors (scalars, possibly traced: the result is
    differentiable in them). Stiffness scales linearly with the spring modulus
    (:func:`make_cloth`), so a factor is a modulus relative to the one ``cloth`` was built
    with; factors of 1 return the same arrays bit for bit."""
    factor = jnp.stack([jnp.asarray(f, cloth.stiffness.dtype) for f in (stretch, shear, bend)])
    return cloth.replace(stiffness=cloth.stiffness * factor[cloth.kind.astype(jnp.int32)],
                         damping=cloth.damping * damping, mass=cloth.mass * density)


def make_cloth(vertices, faces, density: float = 0.2, stretch: float = 100.0,
               shear: float | None = None, bend: float | None = None,
               damping: float = 0.0, dtype=jnp.float32, validate: bool = True) -> Cloth:
    """Build a :class:`Cloth` from a triangle mesh (rest shape = ``vertices``).

    density: areal density [kg/m^2] (cotton ~0.1-0.25).
    stretch, shear, bend: spring moduli [N/m] of the structural, shear and bending springs.
        Each spring gets ``k = modulus * A / L^2`` with ``A`` the summed area of the
        triangles next to its mesh edge and ``L`` its rest length, so on a regular grid an
        edge gets ``k = stretch`` independently of resolution. Defaults: ``shear = stretch``,
        ``bend = stretch / 10``.
    damping: dashpot modulus [N s/m], scaled per spring the same way.

    Raises :class:`dax_physics.cloth.MeshError` for degenerate or non-manifold meshes.
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    if validate:
        _mesh.validate_mesh(v, f)
    shear = stretch if shear is None else shear
    bend = 0.1 * stretch if bend is None else bend
    for name, val in (("density", density), ("stretch", stretch), ("shear", shear),
                      ("bend", bend), ("damping", damping)):
        if not (np.isfinite(val) and val >= 0):
            raise ValueError(f"{name} must be finite and >= 0, got {val}")
    if not density > 0:
        raise ValueError(f"density must be > 0 kg/m^2, got {density}")
    pairs, kind, e_area = _mesh.mesh_springs(v, f)
    rest = np.linalg.norm(v[pairs[:, 1]] - v[pairs[:, 0]], axis=1)
    modulus = np.array([stretch, shear, bend])[kind]
    k = modulus * e_area / rest ** 2
    c = damping * e_area / rest ** 2
    varea = _mesh.vertex_areas(v, f)
    offsets, table, residual = spring_layout(pairs, len(v))
    return Cloth(rest_pos=jnp.asarray(v, dtype), mass=jnp.asarray(density * varea, dtype),
                 area=jnp.asarray(varea, dtype), pairs=jnp.asarray(pairs, jnp.int32),
                 kind=jnp.asarray(kind, jnp.int8), rest_length=jnp.asarray(rest, dtype),
                 stiffness=jnp.asarray(k, dtype), damping=jnp.asarray(c, dtype),
                 faces=jnp.asarray(f, jnp.int32), stencil_edge=jnp.asarray(table, jnp.int32),
                 residual=jnp.asarray(residual, jnp.int32), offsets=offsets)


#: Offset classes summed in one loop by :func:`spring_forces` (:func:`spring_layout`).
CLASS_GROUP = 8


def spring_layout(pairs, n_vertices: int, min_share: float = 0.125,
                  group_springs: int = 1024):
    """Sort a spring network into index-offset classes for :func:`spring_forces` (NumPy).

    A class is an offset ``o > 0`` shared by at least ``min_share * n_vertices`` springs
    ``(i, i + o)`` (a second spring on the same pair of vertices goes to a second class of
    the same offset), the largest first, in groups of :data:`CLASS_GROUP`: the first group,
    then each further group while it holds at least ``group_springs`` springs.
    :func:`spring_forces` sums each group in a loop of its own (past 8 classes XLA:CPU no
    longer reads the classes' neighbours in one loop); a further group costs a few
    microseconds per substep even when small, so small meshes keep one. Each vertex sums
    the springs of a class from both ends, ``(i, i + o)`` and ``(i - o, i)``, with the
    vertex arrays shifted by ``+o`` and ``-o``: no gather of positions and no scatter of
    forces, like a stencil on a regular grid.
    Meshes numbered row by row profit (:func:`dax_physics.cloth.square_mesh`: every
    spring is in a class; :func:`dax_physics.cloth.tshirt_mesh`: most); the other springs
    (``residual``) are summed with a scatter.

    Returns ``(offsets (tuple of 2 C ints: +o then -o per class), table (2 C, V) int64:
    the spring between vertex i and vertex i + offsets[s], E where there is none,
    residual (R,) int64)``.
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    E, V = len(pairs), int(n_vertices)
    lo, hi = pairs.min(1), pairs.max(1)
    off = hi - lo
    # (offset, layer): layer k holds the k-th spring on a pair with that offset
    key = off * (E + 1)
    order = np.lexsort((lo, off))
    layer = np.zeros(E, np.int64)
    same = (off[order][1:] == off[order][:-1]) & (lo[order][1:] == lo[order][:-1])
    for n, e in enumerate(order[1:], start=1):
        layer[e] = layer[order[n - 1]] + 1 if same[n - 1] else 0
    key = key + layer
    cand, counts = np.unique(key[off > 0], return_counts=True)
    rank = np.argsort(-counts, kind="stable")
    eligible = [r for r in rank if counts[r] >= max(min_share * V, 1)]
    chosen = [int(cand[r]) for r in eligible[:CLASS_GROUP]]
    for g in range(CLASS_GROUP, len(eligible), CLASS_GROUP):
        group = eligible[g:g + CLASS_GROUP]
        if sum(int(counts[r]) for r in group) < group_springs:
            break
        chosen += [int(cand[r]) for r in group]
    offsets, rows = [], []
    in_class = np.zeros(E, bool)
    for kc in chosen:
        o = kc // (E + 1)
        members = np.flatnonzero(key == kc)
        plus, minus = np.full(V, E, np.int64), np.full(V, E, np.int64)
        plus[lo[members]] = members
        minus[hi[members]] = members
        in_class[members] = True
        offsets += [o, -o]
        rows += [plus, minus]
    table = np.stack(rows) if rows else np.zeros((0, V), np.int64)
    return tuple(offsets), table, np.flatnonzero(~in_class)


def square_cloth(n: int, m: int | None = None, size=(1.0, 1.0), origin=(0.0, 0.0),
                 height: float = 0.0, **kwargs) -> Cloth:
    """A flat ``n x m`` vertex rectangle (see :func:`dax_physics.cloth.mesh.square_mesh`)
    as a :class:`Cloth`; ``kwargs`` go to :func:`make_cloth`."""
    v, f = _mesh.square_mesh(n, m, size, origin, height)
    return make_cloth(v, f, **kwargs)


def tshirt_cloth(spacing: float = 0.025, height: float = 0.0, outline: dict | None = None,
                 **kwargs) -> Cloth:
    """A flat one-layer T-shirt (:func:`dax_physics.cloth.mesh.tshirt_mesh`) as a
    :class:`Cloth`; ``outline`` holds :func:`tshirt_outline` keywords."""
    v, f = _mesh.tshirt_mesh(spacing, height, **(outline or {}))
    return make_cloth(v, f, **kwargs)


def mesh_cloth(path, **kwargs) -> Cloth:
    """A cloth from a mesh file read with meshio (optional ``mesh`` extra)."""
    v, f = _mesh.load_mesh(path)
    return make_cloth(v, f, **kwargs)


# ----------------------------------------------------------------------------- state

@pytree_dataclass
class ClothState:
    """Dynamic state.

    x, v (V, 3): positions [m] and velocities [m/s].
    grip (G, V): 1 where vertex is attached to gripper g, else 0.
    gripper_pos (G, 3) [m], gripper_vel (G, 3) [m/s]: gripper poses and velocity commands;
        attached vertices move with their gripper's velocity.
    colliders: :class:`dax_physics.colliders.ColliderState` of ``cfg.colliders``.
    t: simulated time [s].
    neighbours: the self-collision's :class:`NeighbourList` (valid for the positions it
        was last checked at; :func:`step` checks it first), or ``None`` (see
        :func:`with_neighbours`).
    """

    x: jnp.ndarray
    v: jnp.ndarray
    grip: jnp.ndarray
    gripper_pos: jnp.ndarray
    gripper_vel: jnp.ndarray
    colliders: _col.ColliderState
    t: jnp.ndarray
    neighbours: NeighbourList | None = None

    @staticmethod
    def create(cloth: Cloth, x=None, v=None, n_grippers: int = 1,
               colliders: _col.ColliderState | None = None,
               cfg: ClothConfig | None = None) -> ClothState:
        """Rest state (``x = cloth.rest_pos`` unless given), grippers at the origin; with
        ``cfg``, the neighbour list it uses (:func:`with_neighbours`)."""
        dtype = cloth.mass.dtype
        x = cloth.rest_pos if x is None else jnp.asarray(x, dtype)
        v = jnp.zeros_like(x) if v is None else jnp.asarray(v, dtype)
        V = x.shape[0]
        cs = _col.ColliderState.empty(dtype) if colliders is None else colliders
        state = ClothState(x=x, v=v, grip=jnp.zeros((n_grippers, V), dtype),
                           gripper_pos=jnp.zeros((n_grippers, 3), dtype),
                           gripper_vel=jnp.zeros((n_grippers, 3), dtype), colliders=cs,
                           t=jnp.zeros((), dtype))
        return state if cfg is None else with_neighbours(cfg, cloth, state)


# ----------------------------------------------------------------------------- stability

def max_stable_dt(cfg: ClothConfig, cloth: Cloth, safety: float = 0.9) -> float:
    """Largest stable substep [s] (needs concrete arrays).

    Per vertex, Gershgorin bounds the highest mode: omega^2 <= 2 sum_k k / m_i and the
    damping rate gamma <= 2 sum_k c / m_i + air_drag A_i / m_i (two self-contacts at
    ``self_stiffness`` are counted when self-collision is on); semi-implicit Euler is stable
    for omega^2 dt^2 + 2 gamma dt < 4. Returns ``safety`` times the smallest such dt.
    """
    pairs = np.asarray(cloth.pairs)
    V = int(np.asarray(cloth.mass).shape[-1])
    k = np.asarray(cloth.stiffness, float)
    c = np.asarray(cloth.damping, float)
    ks = np.bincount(pairs[:, 0], k, V) + np.bincount(pairs[:, 1], k, V)
    cs = np.bincount(pairs[:, 0], c, V) + np.bincount(pairs[:, 1], c, V)
    if cfg.thickness > 0:
        ks = ks + 2 * cfg.self_stiffness
        cs = cs + 2 * (cfg.self_damping + cfg.self_friction)
    m = np.asarray(cloth.mass, float)
    w2 = 2 * ks / m
    g = 2 * cs / m + cfg.air_drag * np.asarray(cloth.area, float) / m
    with np.errstate(divide="ignore", invalid="ignore"):
        dt = np.where(w2 > 0, (-g + np.sqrt(g * g + 4 * w2)) / np.where(w2 > 0, w2, 1),
                      np.where(g > 0, 2 / np.where(g > 0, g, 1), np.inf))
    return float(safety * dt.min())


def check_params(cfg: ClothConfig, cloth: Cloth) -> None:
    """Raise ``ValueError`` naming the problem if ``cloth`` does not fit together or makes
    ``cfg.dt`` unstable: arrays of mismatched shapes, non-finite or non-positive masses or
    rest lengths, negative or non-finite stiffness, damping or table friction, or ``cfg.dt``
    above :func:`max_stable_dt` (named in the message). Needs concrete arrays (call it
    once, outside ``jit``)."""
    V, E = int(np.shape(cloth.mass)[-1]), int(np.shape(cloth.pairs)[0])
    fields = {"mass": ((V,), 0.0, False), "area": ((V,), 0.0, True),
              "rest_length": ((E,), 0.0, False), "stiffness": ((E,), 0.0, True),
              "damping": ((E,), 0.0, True)}
    if cloth.table_friction is not None:
        fields["table_friction"] = ((2,), 0.0, True)
    for name, (shape, low, may_equal) in fields.items():
        a = np.asarray(getattr(cloth, name), float)
        if a.shape != shape:
            raise ValueError(f"Cloth.{name} must have shape {shape}, got {a.shape}")
        ok = np.isfinite(a) & ((a >= low) if may_equal else (a > low))
        if not ok.all():
            raise ValueError(f"Cloth.{name} must be finite and {'>=' if may_equal else '>'} "
                             f"{low:g}, got {a[~ok][:5].tolist()} (first offenders)")
    limit = max_stable_dt(cfg, cloth)
    if not cfg.dt <= limit:
        raise unstable_dt(cfg.dt, limit, "for these springs and masses (Gershgorin bound on "
                          "the fastest mode, 0.9 safety)",
                          "lower dt or the stiffness, or raise the vertex mass")


def check_state(state: ClothState) -> None:
    """Raise ``FloatingPointError`` if positions or velocities went non-finite (NaN/inf).
    (This syncs with the host: call it after a rollout, not inside one.)"""
    if not (np.all(np.isfinite(np.asarray(state.x)))
            and np.all(np.isfinite(np.asarray(state.v)))):
        raise FloatingPointError("the cloth state became non-finite (NaN/inf): the substep "
                                 "is probably unstable (see max_stable_dt)")


# ----------------------------------------------------------------------------- forces

def _safe_norm(d):
    return jnp.sqrt(jnp.sum(d * d, axis=-1) + _TINY)


def _scatter_spring_forces(cloth: Cloth, x, v, edges=None):
    """Forces (V, 3) of the springs ``edges`` (all when ``None``), summed with a scatter."""
    pairs = cloth.pairs if edges is None else cloth.pairs[edges]
    k, L, c = cloth.stiffness, cloth.rest_length, cloth.damping
    if edges is not None:
        k, L, c = k[edges], L[edges], c[edges]
    i, j = pairs[:, 0], pairs[:, 1]
    d = x[j] - x[i]
    ln = _safe_norm(d)
    dh = d / ln[:, None]
    s = k * (ln - L) + c * jnp.sum((v[j] - v[i]) * dh, -1)
    fs = s[:, None] * dh
    V = x.shape[0]
    return (jax.ops.segment_sum(fs, i, V, indices_are_sorted=False)
            - jax.ops.segment_sum(fs, j, V))


def _stencil_spring_forces(cloth: Cloth, xt, vt):
    """Forces (3, V) of the springs in the offset classes (:func:`spring_layout`), from
    component-major positions and velocities ``xt``, ``vt`` (3, V).

    One slot per class and end: vertex i reads its neighbour ``i + offsets[s]`` from the
    zero-padded arrays by a static slice, so every spring is evaluated from both ends and
    nothing is scattered (:func:`_stencil_sum`)."""
    return _stencil_sum(cloth.offsets, cloth.stencil_edge, cloth.pairs, cloth.stiffness,
                        cloth.rest_length, cloth.damping, xt, vt)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _stencil_sum(offsets, table, pairs, k, L, c, xt, vt):
    """``f_i = sum_s (k (ln - L) + c dv.u) u`` with ``d = x_{i + o_s} - x_i``, ``u = d / ln``,
    over the stencil slots (``offsets`` a static tuple ``(+o_1, -o_1, +o_2, -o_2, ...)``,
    ``table`` (S, V) the slots' springs, E for none, row ``2 c + 1`` being row ``2 c`` shifted
    by ``o_c``, as :func:`spring_layout` makes them; k, L, c (E,) per spring).

    Two loops. The first computes each class's spring factor ``s`` once per spring, at
    its lower end, as one (C, V + w) array (w the largest offset; index ``w + i`` is the
    spring ``(i, i + o_c)``, the w leading entries are no spring): the class's neighbour
    positions and velocities are read as one stacked (C, 6, V + w) slice of the padded
    ``[x; v]``, so every class shares one loop (computed slot by slot, XLA:CPU gave each
    slot's square root, division and factor loops of their own). The second sums
    ``f_i = sum_c s_c(i) d_c(i) - s_c(i - o_c) d_c(i - o_c)`` in the slot order,
    recomputing the differences (cheap): the slot ``-o_c`` of vertex i is the spring
    ``(i - o_c, i)``, whose factor is the same number, so the forces equal those of a
    factor per slot bit for bit. Classes are taken :data:`CLASS_GROUP` at a time, each group
    summed by its own two loops (:func:`_class_group_sum`) and the groups' sums added."""
    plus = offsets[0::2]
    if tuple(offsets[1::2]) != tuple(-o for o in plus) or min(plus) <= 0:
        raise ValueError(f"stencil offsets must be (+o, -o) pairs with o > 0, got {offsets}")
    f = None
    for g in range(0, len(plus), CLASS_GROUP):
        part = _class_group_sum(plus[g:g + CLASS_GROUP], table[2 * g:2 * (g + CLASS_GROUP)],
                                k, L, c, xt, vt)
        f = part if f is None else f + part
    return f


def _class_group_sum(plus, table, k, L, c, xt, vt):
    """The forces (3, V) of one group of classes (offsets ``plus``, their (2 C, V) slot
    rows ``table``) for :func:`_stencil_sum`."""
    V = xt.shape[1]
    w = max(plus)
    n = V + w
    zero = jnp.zeros((1,), k.dtype)
    tp = jnp.pad(table[0::2], ((0, 0), (w, 0)), constant_values=k.shape[0])  # (C, n)
    ks, Ls, cs = (jnp.concatenate([a, zero])[tp] for a in (k, L, c))  # E: k = c = L = 0
    xvp = jnp.pad(jnp.concatenate([xt, vt]), ((0, 0), (w, w)))  # (6, V + 2w)
    D = jnp.stack([xvp[:, o:o + n] for o in plus]) - xvp[None, :, :n]  # (C, 6, n)
    d, dv = D[:, :3], D[:, 3:]
    ln = jnp.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2] + _TINY)
    inv = 1.0 / ln
    s = materialise((ks * (ln - Ls)
                     + cs * (dv[:, 0] * d[:, 0] + dv[:, 1] * d[:, 1] + dv[:, 2] * d[:, 2])
                     * inv) * inv)  # (C, n)
    f = []
    for q in range(3):
        xq = xvp[q, w:w + V]
        terms = []
        for cl, o in enumerate(plus):
            terms.append(s[cl, w:w + V] * (xvp[q, w + o:w + o + V] - xq))
            terms.append(s[cl, w - o:w - o + V] * (xvp[q, w - o:w - o + V] - xq))
        f.append(sum(terms))
    return materialise(jnp.stack(f))


def _stencil_sum_fwd(offsets, table, pairs, k, L, c, xt, vt):
    return _stencil_sum(offsets, table, pairs, k, L, c, xt, vt), (table, pairs, k, L, c, xt, vt)


def _stencil_sum_bwd(offsets, res, g):
    """Reverse pass: the autodiff of the same springs summed per spring with a scatter
    (:func:`_scatter_spring_forces`), whose transpose is gathers where the slot sum's would
    be a padded slice per slot and substep; the two agree to rounding."""
    table, pairs, k, L, c, xt, vt = res
    in_stencil = jnp.zeros(k.shape[0] + 1, k.dtype).at[table.reshape(-1)].set(1.0)[:-1]

    def per_spring(k, L, c, xt, vt):
        i, j = pairs[:, 0], pairs[:, 1]
        d = xt[:, j] - xt[:, i]
        ln = jnp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + _TINY)
        dh = d / ln
        dv = vt[:, j] - vt[:, i]
        s = in_stencil * (k * (ln - L) + c * (dv[0] * dh[0] + dv[1] * dh[1] + dv[2] * dh[2]))
        fs = s[None] * dh
        V = xt.shape[1]
        return (jax.ops.segment_sum(fs.T, i, V) - jax.ops.segment_sum(fs.T, j, V)).T

    _, vjp = jax.vjp(per_spring, k, L, c, xt, vt)
    return (None, None) + vjp(g)


_stencil_sum.defvjp(_stencil_sum_fwd, _stencil_sum_bwd)


def spring_forces(cloth: Cloth, x, v):
    """Spring + dashpot forces [N] on every vertex, (V, 3).

    Springs in the offset classes of :func:`spring_layout` are summed stencil-wise (shifted
    slices, no scatter), the others with a scatter; a cloth without a layout sums all of
    them with a scatter. The two sums agree up to float rounding."""
    return _spring_forces_cm(cloth, x.T, v.T).T


def _spring_forces_cm(cloth: Cloth, xt, vt):
    """:func:`spring_forces` on component-major positions and velocities (3, V)."""
    if not cloth.offsets:
        return _scatter_spring_forces(cloth, xt.T, vt.T).T
    f = _stencil_spring_forces(cloth, xt, vt)
    if cloth.residual is not None and cloth.residual.shape[-1] > 0:
        f = f + _scatter_spring_forces(cloth, xt.T, vt.T, cloth.residual).T
    return f


def self_collision_forces(cfg: ClothConfig, cloth: Cloth, x, v, neighbours=None):
    """Vertex-vertex repulsion [N] (V, 3) at thickness h: ``k (h - d)`` along the pair
    direction (plus ``self_damping`` on the approaching normal speed and ``self_friction``
    on the relative velocity) for pairs closer than h whose rest distance exceeds
    ``self_exclude * h``. The pairs are every pair (``self_search="all"``) or those of the
    neighbour list ``neighbours`` (:class:`NeighbourList`; one built at ``x`` when
    ``None``); the forces are the same wherever the list's overflow is 0 (see
    :mod:`dax_physics.cloth.selfcollision`)."""
    return _sc.forces_cm(cfg, cloth, x.T, v.T, neighbours).T


def self_collision_overflow(cfg: ClothConfig, cloth: Cloth, state: ClothState):
    """How many contacts the self-collision search may have missed (int32 scalar,
    jit-able): with a neighbour list in ``state``, its ``overflow`` (the most any of its
    builds could not see: pairs beyond the list's slots and unexamined candidates of
    crowded cells); without one, the overflow of a list built at ``state.x``; 0 with the
    all-pairs search. A non-zero count asks for a larger ``self_capacity`` or
    ``self_candidates``."""
    if cfg.self_search == "all" or not cfg.thickness > 0:
        return jnp.zeros((), jnp.int32)
    nbrs = state.neighbours
    if nbrs is None:
        nbrs = _sc.neighbour_list(cfg, cloth, state.x)
    return nbrs.overflow


def _uses_list(cfg: ClothConfig) -> bool:
    return cfg.thickness > 0 and cfg.self_search == "list"


def with_neighbours(cfg: ClothConfig, cloth: Cloth, state: ClothState) -> ClothState:
    """``state`` with a new neighbour list built at ``state.x`` when ``cfg`` uses one
    (self-collision on, ``self_search="list"``), else with none. A state that carries its
    list keeps it from substep to substep (:func:`step` rebuilds it only when a vertex
    has moved more than half the skin); one without has a list built on every call of
    :func:`step` (and once per :func:`rollout`)."""
    nbrs = _sc.neighbour_list(cfg, cloth, state.x) if _uses_list(cfg) else None
    return state.replace(neighbours=nbrs)


# ----------------------------------------------------------------------------- substep

def _strain_limit(cfg: ClothConfig, cloth: Cloth, x, inv_w):
    """Jacobi projection of structural springs longer than (1 + strain_limit) rest
    (continuous in the positions, so it keeps gradients and vmap-vs-loop results stable)."""
    i, j = cloth.pairs[:, 0], cloth.pairs[:, 1]
    lmax = (1.0 + cfg.strain_limit) * cloth.rest_length
    struct = cloth.kind == 0
    V = x.shape[0]
    # Jacobi averaging over the vertex's structural degree (not over the currently violated
    # springs, which would make the result jump when a spring crosses the limit)
    sf = struct.astype(x.dtype)
    cnt = jax.ops.segment_sum(sf, i, V) + jax.ops.segment_sum(sf, j, V)
    for _ in range(cfg.strain_iterations):
        d = x[j] - x[i]
        ln = _safe_norm(d)
        over = struct & (ln > lmax)
        wsum = inv_w[i] + inv_w[j]
        corr = jnp.where(over & (wsum > 0), (ln - lmax) / jnp.where(wsum > 0, wsum, 1.0), 0.0)
        dd = (corr / ln)[:, None] * d
        dx = (jax.ops.segment_sum(dd * inv_w[i][:, None], i, V)
              - jax.ops.segment_sum(dd * inv_w[j][:, None], j, V))
        x = x + dx / jnp.maximum(cnt, 1.0)[:, None]
    return x


def _table_contact(cfg: ClothConfig, xt, vt, free, friction=None):
    """Table plane with Coulomb friction (``friction`` (2,) as data, else the config's);
    on component-major ``xt``, ``vt`` (3, V); returns (x_new, v_new).

    ``friction_model="coulomb"``: a vertex sticks while ``|v_t| <= mu_s dv_n`` (dv_n the
    normal velocity the contact removes), else slides with ``|v_t| - mu_d dv_n``. The
    switch makes the rollout non-smooth: a finite difference of a fold's reward changes
    erratically with its step (stick-slip), so the exact local slope says little about
    the reward a step away. ``"smooth"`` replaces it with ``|v_t| <- |v_t|^2 / (|v_t| + mu_d
    dv_n)``: the friction impulse ``|v_t| a / (|v_t| + a)`` (a = mu_d dv_n) never exceeds
    Coulomb's bound a, equals it for fast sliding (``|v_t| >> a``) and nearly stops slow
    sliding (``|v_t|^2 / a``), with no static coefficient and no switch. It is smooth in
    the velocities, so gradients match finite differences, at the price of a cloth that
    creeps slowly where Coulomb would hold it."""
    zt = cfg.table_height
    dt = cfg.dt
    z_pred = xt[2] + dt * vt[2]
    contact = (z_pred < zt) & free
    vx, vy, vz = vt[0], vt[1], vt[2]
    if friction is None:
        mu_s, mu_d = cfg.friction_static, cfg.mu_dynamic
    else:
        mu_s, mu_d = friction[0], friction[1]
    if friction is not None or cfg.friction_static > 0 or cfg.mu_dynamic > 0:
        dvn = jnp.where(contact, jnp.maximum(-vz, 0.0), 0.0)  # normal impulse / mass
        vtn = jnp.sqrt(vx * vx + vy * vy + _TINY)
        if cfg.friction_model == "smooth":
            g_dt = dt * float(np.linalg.norm(cfg.gravity))
            scale = vtn / (vtn + mu_d * jnp.minimum(dvn, g_dt))
        else:
            stick = vtn <= mu_s * dvn
            scale = jnp.where(stick, 0.0, jnp.maximum(1.0 - mu_d * dvn / vtn, 0.0))
        vx = jnp.where(contact, vx * scale, vx)
        vy = jnp.where(contact, vy * scale, vy)
    z = jnp.where(contact, jnp.asarray(zt, xt.dtype), z_pred)
    vz = jnp.where(contact, jnp.maximum(vz, 0.0), vz)
    return (jnp.stack([xt[0] + dt * vx, xt[1] + dt * vy, z]), jnp.stack([vx, vy, vz]))


def step(cfg: ClothConfig, cloth: Cloth, state: ClothState) -> ClothState:
    """One semi-implicit Euler substep of ``cfg.dt`` seconds.

    Order: the self-collision's neighbour list (``self_search="list"``) is brought up to
    date with the positions (:func:`dax_physics.cloth.selfcollision.update_neighbours`; a
    state without one gets one for this substep only); spring, dashpot, gravity, drag and
    self-collision forces -> velocity; SDF colliders (velocity projection); attached
    vertices take their gripper's velocity; table contact with Coulomb friction (position
    clamp, approaching normal velocity removed; the coefficients are
    ``cloth.table_friction`` when set); position update; strain limiting; grippers and
    colliders advance.

    Computed on component-major (3, V) positions and velocities (the layout of the
    stencil sum, :func:`spring_forces`; :func:`rollout` keeps its scan in that layout).
    """
    return _transposed(_step_cm(cfg, cloth, _transposed(state)))


def _transposed(state: ClothState) -> ClothState:
    """``state`` with its positions and velocities transposed, (V, 3) <-> (3, V)."""
    return state.replace(x=state.x.T, v=state.v.T)


def _step_cm(cfg: ClothConfig, cloth: Cloth, state: ClothState) -> ClothState:
    """:func:`step` on a state whose ``x`` and ``v`` are component-major (3, V)."""
    xt, vt = state.x, state.v
    dt = cfg.dt
    m = cloth.mass
    nbrs = state.neighbours
    if _uses_list(cfg):
        nbrs = (_sc.neighbour_list(cfg, cloth, xt.T) if nbrs is None
                else _sc.update_neighbours(cfg, cloth, nbrs, xt.T))
    f = _spring_forces_cm(cloth, xt, vt) + m * jnp.asarray(cfg.gravity, xt.dtype)[:, None]
    if cfg.air_drag > 0:
        f = f - cfg.air_drag * cloth.area * vt
    if cfg.thickness > 0:
        f = f + _sc.forces_cm(cfg, cloth, xt, vt, nbrs)
    vt = vt + dt * f / m
    if cfg.colliders:
        vt = _col.apply_colliders(cfg.colliders, state.colliders, xt.T, vt.T).T
    cnt = jnp.sum(state.grip, axis=0)
    attached = cnt > 0
    # a sum of products, not a matmul: it fuses with its neighbours (a dot does not)
    v_grip = jnp.sum(state.gripper_vel[:, :, None] * state.grip[:, None, :], axis=0) \
        / jnp.maximum(cnt, 1.0)
    vt = jnp.where(attached, v_grip, vt)
    if cfg.table_height is not None:
        x_new, vt = _table_contact(cfg, xt, vt, ~attached, cloth.table_friction)
    else:
        x_new = xt + dt * vt
    if cfg.strain_limit is not None:
        inv_w = jnp.where(attached, 0.0, 1.0 / cloth.mass)
        x_lim = _strain_limit(cfg, cloth, x_new.T, inv_w).T
        vt = vt + (x_lim - x_new) / dt
        x_new = x_lim
    cs = _col.advance(state.colliders, dt) if cfg.colliders else state.colliders
    keep = nbrs if state.neighbours is not None else None
    return state.replace(x=x_new, v=vt, gripper_pos=state.gripper_pos + dt * state.gripper_vel,
                         colliders=cs, t=state.t + dt, neighbours=keep)


def rollout(cfg: ClothConfig, cloth: Cloth, state: ClothState, n_substeps: int, *,
            segment: int | None = None, unroll: int = 1, gripper_vel=None) -> ClothState:
    """Run ``n_substeps`` substeps of :func:`step` as one scan (pure, not jitted: jit it
    with ``cfg``, ``n_substeps`` and ``segment`` static).

    segment: substeps per checkpointed segment (:func:`dax_physics.checkpointed_scan`,
        with ``short_last=True``: a last segment of the substeps left, not surplus substeps
        whose carry, neighbour list included, would be selected on every substep), so
        reverse-mode memory grows with the number of
        segments rather than substeps; ``None``: no checkpointing. Forward values are the
        same either way up to float rounding (XLA may fuse a segment's substeps differently).
    unroll: passed to the scan.
    gripper_vel: optional (n_substeps, G, 3) [m/s] gripper velocity command per substep
        (otherwise ``state.gripper_vel`` is held).
    A negative or non-integer ``n_substeps`` raises ``ValueError`` (0 returns ``state``).
    The time step is checked by :func:`check_params`, not here. A state without a
    neighbour list (when ``cfg`` uses one) gets one for the rollout and is returned
    without; the scan carries the positions and velocities component-major.
    """
    n_substeps = step_count(n_substeps, "n_substeps")
    if n_substeps == 0:
        return state
    if gripper_vel is not None:
        gripper_vel = jnp.asarray(gripper_vel, state.x.dtype)
        if gripper_vel.shape[0] != n_substeps:
            raise ValueError(f"gripper_vel must have {n_substeps} rows (one per substep), "
                             f"got shape {gripper_vel.shape}")

    def body(s, gv):
        if gv is not None:
            s = s.replace(gripper_vel=gv)
        return _step_cm(cfg, cloth, s), None

    lend = _uses_list(cfg) and state.neighbours is None
    carry = _transposed(with_neighbours(cfg, cloth, state) if lend else state)
    out = _transposed(checkpointed_scan(body, carry, gripper_vel, length=n_substeps,
                                        segment=segment, unroll=unroll,
                                        short_last=True)[0])
    return out.replace(neighbours=None) if lend else out


def energy(cfg: ClothConfig, cloth: Cloth, state: ClothState):
    """Total mechanical energy [J]: kinetic + gravitational (relative to the origin) +
    spring potential (self-collision springs excluded)."""
    x, v = state.x, state.v
    ke = 0.5 * jnp.sum(cloth.mass * jnp.sum(v * v, -1))
    pe_g = -jnp.sum(cloth.mass * jnp.sum(x * jnp.asarray(cfg.gravity, x.dtype), -1))
    d = x[cloth.pairs[:, 1]] - x[cloth.pairs[:, 0]]
    pe_s = 0.5 * jnp.sum(cloth.stiffness * (_safe_norm(d) - cloth.rest_length) ** 2)
    return ke + pe_g + pe_s
