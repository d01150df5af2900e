"""Mass-spring cloth on triangle meshes: model, state, one substep, rollouts.

Split like the rest of dax-physics:

* :class:`ClothConfig` (static, hashable): substep, gravity, air drag, table contact and
  friction, self-collision thickness, strain limit, colliders;
* :class:`Cloth` (pytree of arrays): the material - vertex masses and the spring network
  with rest lengths, stiffness and damping per spring, optionally the table friction as
  data (differentiable; :func:`scale_moduli` scales it);
* :class:`ClothState` (pytree of arrays): vertex positions and velocities, gripper
  attachments, gripper poses and velocity commands, collider poses.

Units are SI, z is up. Every public function is pure and works under ``jax.jit``,
``jax.vmap`` and ``jax.grad``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .. import colliders as _col
from .._pytree import pytree_dataclass
from ..scan import checkpointed_scan
from . import mesh as _mesh

_TINY = 1e-20
#: Table friction laws (:attr:`ClothConfig.friction_model`).
FRICTION_MODELS = ("coulomb", "smooth")


# ----------------------------------------------------------------------------- static config

@dataclasses.dataclass(frozen=True)
class ClothConfig:
    """Static cloth-solver configuration (hashable; pass as a jit static argument).

    dt: substep [s]; checked against :func:`max_stable_dt` by :func:`check_stable`.
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
    self_candidates: vertices examined per neighbour hash cell (static shape of the spatial
        hash; a cell holding more vertices than this misses the extra ones).
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
    self_candidates: int = 8
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
    return Cloth(rest_pos=jnp.asarray(v, dtype), mass=jnp.asarray(density * varea, dtype),
                 area=jnp.asarray(varea, dtype), pairs=jnp.asarray(pairs, jnp.int32),
                 kind=jnp.asarray(kind, jnp.int8), rest_length=jnp.asarray(rest, dtype),
                 stiffness=jnp.asarray(k, dtype), damping=jnp.asarray(c, dtype),
                 faces=jnp.asarray(f, jnp.int32))


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
    """

    x: jnp.ndarray
    v: jnp.ndarray
    grip: jnp.ndarray
    gripper_pos: jnp.ndarray
    gripper_vel: jnp.ndarray
    colliders: _col.ColliderState
    t: jnp.ndarray

    @staticmethod
    def create(cloth: Cloth, x=None, v=None, n_grippers: int = 1,
               colliders: _col.ColliderState | None = None) -> ClothState:
        """Rest state (``x = cloth.rest_pos`` unless given), grippers at the origin."""
        dtype = cloth.mass.dtype
        x = cloth.rest_pos if x is None else jnp.asarray(x, dtype)
        v = jnp.zeros_like(x) if v is None else jnp.asarray(v, dtype)
        V = x.shape[0]
        cs = _col.ColliderState.empty(dtype) if colliders is None else colliders
        return ClothState(x=x, v=v, grip=jnp.zeros((n_grippers, V), dtype),
                          gripper_pos=jnp.zeros((n_grippers, 3), dtype),
                          gripper_vel=jnp.zeros((n_grippers, 3), dtype), colliders=cs,
                          t=jnp.zeros((), dtype))


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


def _is_concrete(*trees) -> bool:
    return not any(isinstance(leaf, jax.core.Tracer) for t in trees
                   for leaf in jax.tree_util.tree_leaves(t))


def check_stable(cfg: ClothConfig, cloth: Cloth):
    """Raise ``ValueError`` naming the largest stable dt if ``cfg.dt`` exceeds it. A no-op
    when ``cloth`` is traced (inside jit/vmap/grad): check once outside."""
    if not _is_concrete(cloth):
        return
    dtmax = max_stable_dt(cfg, cloth)
    if not cfg.dt <= dtmax:
        raise ValueError(f"cloth substep dt={cfg.dt:g} s is unstable for these springs and "
                         f"masses: the largest stable dt is {dtmax:.4g} s (reduce dt or the "
                         f"stiffness, or raise the vertex mass)")


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


def spring_forces(cloth: Cloth, x, v):
    """Spring + dashpot forces [N] on every vertex, (V, 3)."""
    i, j = cloth.pairs[:, 0], cloth.pairs[:, 1]
    d = x[j] - x[i]
    ln = _safe_norm(d)
    dh = d / ln[:, None]
    s = cloth.stiffness * (ln - cloth.rest_length) + cloth.damping * jnp.sum(
        (v[j] - v[i]) * dh, -1)
    fs = s[:, None] * dh
    V = x.shape[0]
    return (jax.ops.segment_sum(fs, i, V, indices_are_sorted=False)
            - jax.ops.segment_sum(fs, j, V))


def _hash_cells(c):
    c = c.astype(jnp.int32)
    h = (c[..., 0] * jnp.int32(73856093)) ^ (c[..., 1] * jnp.int32(19349663)) ^ (
        c[..., 2] * jnp.int32(83492791))
    return h & jnp.int32(0x7FFFFFFF)


def self_collision_candidates(cfg: ClothConfig, x):
    """Candidate neighbours of every vertex from a spatial hash with static shapes.

    Cells have size 2h, so a vertex's h-ball overlaps at most the 2x2x2 block of cells on
    the side of its own cell it is nearest to. Vertices are bucketed by cell hash into a
    table of ``T`` buckets (``T`` the power of two >= 2V) of ``self_candidates`` slots each
    (built with one sort and one scatter; a bucket that overflows drops its extra
    vertices), and each vertex reads the 8 buckets of its cell block: gathers only.
    Returns ``(idx (V, 8 K) int32, valid (V, 8 K) bool)``; no gradient flows through it.
    """
    x = jax.lax.stop_gradient(x)
    V = x.shape[0]
    K = cfg.self_candidates
    T = 1 << max(int(2 * V - 1).bit_length(), 4)
    g = x / (2.0 * cfg.thickness)
    cell = jnp.floor(g)
    side = jnp.where(g - cell < 0.5, -1.0, 1.0)
    bucket = _hash_cells(cell) & jnp.int32(T - 1)
    order = jnp.argsort(bucket)
    sb = bucket[order]
    pos = jnp.arange(V, dtype=jnp.int32)
    first = jnp.concatenate([jnp.ones((1,), bool), sb[1:] != sb[:-1]])
    run_start = jax.lax.cummax(jnp.where(first, pos, 0))
    rank = pos - run_start
    table = jnp.full((T, K), -1, jnp.int32)
    table = table.at[sb, rank].set(order.astype(jnp.int32), mode="drop")
    offs = jnp.asarray([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], x.dtype)
    ncell = cell[:, None, :] + offs[None] * side[:, None, :]  # (V, 8, 3)
    nb = _hash_cells(ncell) & jnp.int32(T - 1)
    idx = table[nb].reshape(V, 8 * K)
    return jnp.maximum(idx, 0), idx >= 0


def self_collision_forces(cfg: ClothConfig, cloth: Cloth, x, v):
    """Vertex-vertex repulsion [N] at thickness h: ``k (h - d)`` along the pair direction
    (plus ``self_damping`` on the approaching normal speed) for pairs closer than h whose
    rest distance exceeds ``self_exclude * h``."""
    h = cfg.thickness
    idx, valid = self_collision_candidates(cfg, x)
    V = x.shape[0]
    # component-wise 1-D gathers (much faster on CPU than gathering (.., 3) rows)
    xt, rt = x.T, cloth.rest_pos.T
    d = [xt[c][:, None] - xt[c][idx] for c in range(3)]  # from neighbour to me
    r2 = sum((rt[c][:, None] - rt[c][idx]) ** 2 for c in range(3))
    dist = jnp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + _TINY)
    me = jnp.arange(V)[:, None]
    active = valid & (idx != me) & (r2 > (cfg.self_exclude * h) ** 2) & (dist < h)
    mag = jnp.where(active, cfg.self_stiffness * (h - dist), 0.0)
    inv = 1.0 / dist
    s = mag * inv
    if cfg.self_damping > 0 or cfg.self_friction > 0:
        vt = v.T
        dv = [vt[c][:, None] - vt[c][idx] for c in range(3)]
        vn = (dv[0] * d[0] + dv[1] * d[1] + dv[2] * d[2]) * inv
        s = s - jnp.where(active, (cfg.self_damping * jnp.minimum(vn, 0.0)
                                   - cfg.self_friction * vn) * inv, 0.0)
        if cfg.self_friction > 0:  # tangential part: -self_friction * (dv - vn n)
            fr = jnp.where(active, cfg.self_friction, 0.0)
            return jnp.stack([jnp.sum(s * d[c] - fr * dv[c], axis=1) for c in range(3)], 1)
    return jnp.stack([jnp.sum(s * d[c], axis=1) for c in range(3)], axis=1)


# ----------------------------------------------------------------------------- substep

def _table_contact(cfg: ClothConfig, x, v, free, friction=None):
    """Table plane with Coulomb friction (``friction`` (2,) as data, else the config's);
    returns (x_new, v_new).

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
    x_pred = x + cfg.dt * v
    contact = (x_pred[:, 2] < zt) & free
    if friction is None:
        mu_s, mu_d = cfg.friction_static, cfg.mu_dynamic
    else:
        mu_s, mu_d = friction[0], friction[1]
    if friction is not None or cfg.friction_static > 0 or cfg.mu_dynamic > 0:
        dvn = jnp.where(contact, jnp.maximum(-v[:, 2], 0.0), 0.0)  # normal impulse / mass
        vt = v[:, :2]
        vtn = _safe_norm(vt)
        if cfg.friction_model == "smooth":
            # the bound of resting contact: the weight's normal impulse g dt per substep
            g_dt = cfg.dt * float(np.linalg.norm(cfg.gravity))
            scale = vtn / (vtn + mu_d * jnp.minimum(dvn, g_dt))
        else:
            stick = vtn <= mu_s * dvn
            scale = jnp.where(stick, 0.0, jnp.maximum(1.0 - mu_d * dvn / vtn, 0.0))
        vt = jnp.where(contact[:, None], vt * scale[:, None], vt)
        v = jnp.concatenate([vt, v[:, 2:]], axis=1)
        x_pred = x + cfg.dt * v
    z = jnp.where(contact, jnp.asarray(zt, x.dtype), x_pred[:, 2])
    vz = jnp.where(contact, jnp.maximum(v[:, 2], 0.0), v[:, 2])
    return (jnp.concatenate([x_pred[:, :2], z[:, None]], 1),
            jnp.concatenate([v[:, :2], vz[:, None]], 1))


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


def step(cfg: ClothConfig, cloth: Cloth, state: ClothState) -> ClothState:
    """One semi-implicit Euler substep of ``cfg.dt`` seconds.

    Order: spring, dashpot, gravity, drag and self-collision forces -> velocity; SDF
    colliders (velocity projection); attached vertices take their gripper's velocity; table
    contact with Coulomb friction (position clamp, approaching normal velocity removed;
    the coefficients are ``cloth.table_friction`` when set); position update; strain
    limiting; grippers and colliders advance.
    """
    x, v = state.x, state.v
    dt = cfg.dt
    m = cloth.mass[:, None]
    f = spring_forces(cloth, x, v) + m * jnp.asarray(cfg.gravity, x.dtype)
    if cfg.air_drag > 0:
        f = f - cfg.air_drag * cloth.area[:, None] * v
    if cfg.thickness > 0:
        f = f + self_collision_forces(cfg, cloth, x, v)
    v = v + dt * f / m
    if cfg.colliders:
        v = _col.apply_colliders(cfg.colliders, state.colliders, x, v)
    cnt = jnp.sum(state.grip, axis=0)
    attached = cnt > 0
    v_grip = (state.grip.T @ state.gripper_vel) / jnp.maximum(cnt, 1.0)[:, None]
    v = jnp.where(attached[:, None], v_grip, v)
    if cfg.table_height is not None:
        x_new, v = _table_contact(cfg, x, v, ~attached, cloth.table_friction)
    else:
        x_new = x + dt * v
    if cfg.strain_limit is not None:
        inv_w = jnp.where(attached, 0.0, 1.0 / cloth.mass)
        x_lim = _strain_limit(cfg, cloth, x_new, inv_w)
        v = v + (x_lim - x_new) / dt
        x_new = x_lim
    cs = _col.advance(state.colliders, dt) if cfg.colliders else state.colliders
    return state.replace(x=x_new, v=v, gripper_pos=state.gripper_pos + dt * state.gripper_vel,
                         colliders=cs, t=state.t + dt)


def rollout(cfg: ClothConfig, cloth: Cloth, state: ClothState, n_steps: int,
            gripper_vel=None, segment: int | None = None, unroll: int = 1) -> ClothState:
    """Run ``n_steps`` substeps of :func:`step` as one scan.

    gripper_vel: optional (n_steps, G, 3) [m/s] gripper velocity command per substep
        (otherwise ``state.gripper_vel`` is held).
    segment: substeps per checkpointed segment (:func:`dax_physics.checkpointed_scan`,
        whose remainder rule applies), so reverse-mode memory grows with the number of
        segments rather than substeps; ``None``: no checkpointing. Forward values are the
        same either way.
    Raises ``ValueError`` (when called with concrete arrays) if ``cfg.dt`` is unstable, and
    for a negative ``n_steps``.
    """
    check_stable(cfg, cloth)
    if isinstance(n_steps, bool) or int(n_steps) != n_steps or n_steps < 0:
        raise ValueError(f"n_steps must be an int >= 0, got {n_steps!r}")
    n_steps = int(n_steps)
    if n_steps == 0:
        return state
    if gripper_vel is not None:
        gripper_vel = jnp.asarray(gripper_vel, state.x.dtype)
        if gripper_vel.shape[0] != n_steps:
            raise ValueError(f"gripper_vel must have {n_steps} rows (one per substep), got "
                             f"shape {gripper_vel.shape}")

    def body(s, gv):
        if gv is not None:
            s = s.replace(gripper_vel=gv)
        return step(cfg, cloth, s), None

    return checkpointed_scan(body, state, gripper_vel, length=n_steps, segment=segment,
                             unroll=unroll)[0]


def energy(cfg: ClothConfig, cloth: Cloth, state: ClothState):
    """Total mechanical energy [J]: kinetic + gravitational (relative to the origin) +
    spring potential (self-collision springs excluded)."""
    x, v = state.x, state.v
    ke = 0.5 * jnp.sum(cloth.mass * jnp.sum(v * v, -1))
    pe_g = -jnp.sum(cloth.mass * (x @ jnp.asarray(cfg.gravity, x.dtype)))
    d = x[cloth.pairs[:, 1]] - x[cloth.pairs[:, 0]]
    pe_s = 0.5 * jnp.sum(cloth.stiffness * (_safe_norm(d) - cloth.rest_length) ** 2)
    return ke + pe_g + pe_s
