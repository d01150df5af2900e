"""Pour-Water and Pour-Soup: pour the contents of a held bowl into a target bowl.

Scene (SI units, z up). The MPM domain is ``domain`` cells of ``dx`` = 1 cm (0.34 x 0.24 x
0.28 m); its slip walls (:data:`WALL_CELLS` = 3 cells) are the table: the floor is the
walls' surface, ``floor_z`` = 3 cm, where water comes to rest. The whole domain is
simulated (no moving window: spilled liquid may spread anywhere on it).

* The *source* bowl (collider 0, shape ``bowl``, outer radius 5 cm, height 6 cm, wall
  2 cm = two cells so particles cannot tunnel, i.e. a 3 cm x 4 cm cavity) is held by the
  gripper. It is kinematic: the action sets its velocity each substep.
* The *target* bowl (collider 1, outer radius 6 cm, height 6 cm, wall 2 cm) stands on the
  table at ``target_xy`` plus a random offset (see "Start"), fixed for the episode.
* Pour-Water: water (weakly compressible fluid, ``bulk_modulus`` 2e4 Pa, rho 1000 kg/m^3)
  fills the source cavity to ``fill_height`` = 2.5 cm: 476 particles at 8 per cell.
* Pour-Soup: water to 2 cm plus ``n_chunks`` = 3 stiff elastic cubes (tofu-like,
  fixed-corotated, E = 2e4 Pa, nu = 0.3, rho 1050 kg/m^3) of side 1.5 cm replacing the
  water where they sit; at 4 particles per cell, 139 water + 24 chunk particles (8 per
  chunk, sharing the cube's volume). E keeps the chunks' P-wave speed near water's, so
  the substep is no shorter than Pour-Water's. The particles per cell are the resolution
  study's choice (the dax-tasks README).
* The materials (:data:`WATER`, :data:`CHUNK`) and the bowls' friction
  (:data:`BOWL_FRICTION`) are ``params.physics`` (a :class:`dax_physics.MaterialParams`:
  material 0 water, material 1 the chunks), so viscosity, bulk modulus or friction can be
  changed, batched or differentiated without recompiling. Each bowl collider acts only on
  the grid nodes around it (``dax_physics.colliders.apply_colliders_grid``).

Substeps: ``dt`` = 0.025 / 30 s (water) and 0.025 / 36 s (soup), within the CFL bound for
``max_speed`` 1.5 m/s; ``substeps`` = 30 / 36, so one environment step is 0.025 s of
simulated time and the horizon of 100 steps is 2.5 s.

Action (low-level velocity): ``(vx, vy, vz, omega)``: the wrist's linear velocity [m/s]
and the angular velocity [rad/s] of the bowl about the world y axis through the wrist
(positive omega lowers the bowl's +x rim, towards the target bowl). The wrist is the
centre of the source bowl's rim. Bounds: |v| <= 0.4 m/s per axis, |omega| <= 3 rad/s, so
the bowl can tilt past its spill angle in a few steps and open sideways (pi/2) well
within the horizon. Each action is held for the env step; the wrist is kept inside
``wrist_low``/``wrist_high`` and the tilt inside ``tilt_range`` by clipping the commanded
velocity (a clipped component has zero gradient).

Start, drawn from the key: the source bowl's wrist at ``source_wrist`` (0.09, 0.12, 0.17) m
plus a uniform offset of up to ``init_range`` (±2 cm in x, ±3 cm in y, ±1 cm in z),
upright, contents at rest; the target bowl at ``target_xy`` (0.23, 0.12) m plus a uniform
offset of up to ``target_range`` (±2 cm in x and y). The ranges keep both bowls inside the
table (the floor inside the walls spans x 0.03-0.31 m and y 0.03-0.21 m; the target
bowl's rim reaches x 0.31 m at most and the source bowl's y 0.04-0.20 m), the held bowl
above the target's rim, and the pour point (below) inside the wrist's workspace.
Particles keep their index (same count, same order) for every seed.

Distance: ``D = 1/N sum_i d_i`` [m], ``d_i`` the smooth (C1) Euclidean distance of particle
i to the target bowl's cavity (a cylinder of the inner radius from the inner bottom to the
rim, grown by ``dx/2`` for particles resting against the walls), 0 inside:
``d = sqrt(relu(rho - r_in)^2 + relu(z_bot - z)^2 + relu(z - z_rim)^2 + eps) - sqrt(eps)``.
For the soup the chunks' particles count like water's (the ingredients must go too).
λ = 20 /m: ``r_gt = exp(-20 D)`` is 1 with everything poured. The goal set the template
stores (:meth:`Pour.canonical_goal`, (N, 3)) is N particles packed on a regular lattice in
the target cavity at ``target_xy``, from its bottom up; ``D`` does not use it: it measures
to the cavity of the episode's own target bowl (``physics.colliders.pos[TARGET]``).

Expert (privileged state, :meth:`Pour.expert`): drive the wrist to the pour point above the
episode's target bowl (read from the state), start tilting once within 2 cm of it, tilt
to ``pour_angle`` (2.3 rad) and hold, and tilt back over the last steps of the horizon.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from dax_physics import (
    ColliderSpec,
    ColliderState,
    Material,
    MPMConfig,
    checkpointed_scan,
    init_state,
    sampling,
    step,
)
from dax_physics.colliders import quat_to_matrix

from ..core.env import MPMEnv
from ..core.spec import TaskSpec

SOURCE, TARGET = 0, 1
_EPS = 1e-10
#: Default materials (``params.physics``): water (material 0) and the soup's chunks (1).
WATER = Material("fluid", 1000.0, bulk_modulus=2.0e4, viscosity=1.0e-3)
CHUNK = Material("elastic", 1050.0, youngs_modulus=2.0e4, poisson_ratio=0.3)
#: Default Coulomb coefficient of both bowls (``params.physics.friction``).
BOWL_FRICTION = 0.2
#: Thickness of the domain's slip walls [cells]; their surface is the table.
WALL_CELLS = 3


@dataclasses.dataclass(frozen=True)
class PourScene:
    """Static scene of Pour-Water / Pour-Soup (SI units). Bowl dims: (r_outer, height, wall)."""

    dx: float = 0.01                     # grid cell [m]
    dt: float = 0.025 / 30               # substep [s]
    domain: tuple = (34, 24, 28)         # cells (whole domain simulated)
    ppc: int = 8                         # particles per cell
    fill_height: float = 0.025           # water depth in the source cavity [m]
    n_chunks: int = 0                    # solid ingredients (0: water only)
    chunk_size: float = 0.015            # cube side [m]
    source_bowl: tuple = (0.05, 0.06, 0.02)
    target_bowl: tuple = (0.06, 0.06, 0.02)
    target_xy: tuple = (0.23, 0.12)      # target bowl centre [m]
    source_wrist: tuple = (0.09, 0.12, 0.17)  # initial wrist (rim centre) [m]
    init_range: tuple = (0.02, 0.03, 0.01)    # uniform random wrist offset [m]
    target_range: tuple = (0.02, 0.02)   # uniform random target bowl offset (x, y) [m]
    wrist_low: tuple = (0.07, 0.08, 0.15)
    wrist_high: tuple = (0.27, 0.16, 0.21)
    tilt_range: tuple = (-0.5, 2.6)      # [rad]
    max_speed: float = 1.5               # [m/s] (stability guard)
    pour_angle: float = 2.3              # expert's tilt [rad]
    pour_offset: tuple = (-0.005, 0.0, 0.16)  # expert's wrist target relative to the target
    segment: int = 10                    # substeps per checkpointed segment
    #: the bowls put particles that end a substep inside their walls back on the surface
    #: (``ColliderSpec.project``); False: the grid condition alone, which lets water seep
    #: into the walls (``benchmarks/bowl_walls.py`` measures how far)
    project: bool = True

    @property
    def floor_z(self) -> float:
        """The table: the surface of the domain's floor wall [m]."""
        return WALL_CELLS * self.dx


def mpm_config(scene: PourScene) -> MPMConfig:
    """The MPM configuration of the scene (raises if ``dt`` is unstable)."""
    mats = [WATER] + ([CHUNK] if scene.n_chunks else [])
    colliders = (
        ColliderSpec("bowl", scene.source_bowl, mode="separate", friction=BOWL_FRICTION,
                     project=scene.project),
        ColliderSpec("bowl", scene.target_bowl, mode="separate", friction=BOWL_FRICTION,
                     project=scene.project),
    )
    return MPMConfig(materials=tuple(mats), dx=scene.dx, dt=scene.dt, domain=scene.domain,
                     walls="slip", wall_cells=WALL_CELLS, colliders=colliders,
                     max_speed=scene.max_speed)


def contents(scene: PourScene):
    """Particles of the source bowl's contents in the bowl frame (origin at the cavity's
    bottom centre) (NumPy): positions (N, 3), material ids (N,), chunk id (N,) (-1 for
    water) and the rest volume per particle [m^3]: a scalar (``dx^3 / ppc``) without
    chunks, else (N,), each chunk's particles sharing its volume ``chunk_size^3`` (a
    chunk's lattice holds a whole number of particles per side, so ``dx^3 / ppc`` each
    would give it the volume of that lattice, not of the cube: 2.0 of 3.375 cm^3 at 4
    particles per cell)."""
    r_out, _, wall = scene.source_bowl
    r_in = r_out - wall
    fill = scene.fill_height
    gap = 0.25 * scene.dx
    x, vol = sampling.cylinder([0.0, 0.0, 0.0], r_in - gap, fill, scene.dx, ppc=scene.ppc,
                               seed=0, jitter=0.5)
    mat = np.zeros(len(x), np.int32)
    chunk = np.full(len(x), -1, np.int32)
    if scene.n_chunks:
        s = scene.chunk_size
        cubes, cmat, cid, cvol = [], [], [], []
        ring = 0.5 * (r_in - gap) - 0.1 * s
        keep = np.ones(len(x), bool)
        for k in range(scene.n_chunks):
            a = 2 * math.pi * k / scene.n_chunks
            c = np.array([ring * math.cos(a), ring * math.sin(a), fill - 0.5 * s])
            lo, hi = c - 0.5 * s, c + 0.5 * s
            keep &= ~np.all((x > lo - 0.1 * scene.dx) & (x < hi + 0.1 * scene.dx), axis=1)
            xc, _ = sampling.box(lo, hi, scene.dx, ppc=scene.ppc, seed=1 + k, jitter=0.0)
            cubes.append(xc)
            cmat.append(np.ones(len(xc), np.int32))
            cid.append(np.full(len(xc), k, np.int32))
            cvol.append(np.full(len(xc), s ** 3 / len(xc)))
        x = np.concatenate([x[keep]] + cubes)
        mat = np.concatenate([mat[keep]] + cmat)
        chunk = np.concatenate([chunk[keep]] + cid)
        vol = np.concatenate([np.full(int(keep.sum()), vol)] + cvol)
    return x.astype(np.float32), mat, chunk, vol


def _target_pos(scene: PourScene):
    return [scene.target_xy[0], scene.target_xy[1], scene.floor_z]


def tilt(colliders) -> jnp.ndarray:
    """The source bowl's tilt about the world y axis [rad] (its only rotation)."""
    q = colliders.quat[SOURCE]
    return 2.0 * jnp.arctan2(q[2], q[0])


def wrist(scene: PourScene, colliders):
    """The wrist: the centre of the source bowl's rim [m] (3,)."""
    R = quat_to_matrix(colliders.quat[SOURCE])
    return colliders.pos[SOURCE] + R[:, 2] * scene.source_bowl[1]


def _cavity(scene: PourScene, physics):
    r_out, h, wall = scene.target_bowl
    base = physics.colliders.pos[TARGET]
    tol = 0.5 * scene.dx
    return base, r_out - wall + tol, base[2] + wall - tol, base[2] + h


def particle_distance(scene: PourScene, physics):
    """Per-particle smooth distance [m] to the target bowl's cavity (0 inside) (N,)."""
    base, r_in, z_bot, z_rim = _cavity(scene, physics)
    x = physics.x
    rho = jnp.sqrt(jnp.sum((x[:, :2] - base[:2]) ** 2, axis=1) + _EPS)
    a = jax.nn.relu(rho - r_in)
    b = jax.nn.relu(z_bot - x[:, 2]) + jax.nn.relu(x[:, 2] - z_rim)
    return jnp.sqrt(a * a + b * b + _EPS) - math.sqrt(_EPS)


class Pour(MPMEnv):
    """Pour-Water and Pour-Soup (see the module docstring). ``params.physics`` is the
    scene's :class:`dax_physics.MaterialParams`: water (and the chunks) and the bowls'
    friction."""

    LAM = 20.0
    mpm_config = staticmethod(mpm_config)

    def __init__(self, spec: TaskSpec):
        super().__init__(spec)
        scene = spec.scene
        x, mat, _, vol = contents(scene)
        # upright source bowl: collider origin (bottom centre) one bowl height below the
        # wrist
        base = np.asarray(scene.source_wrist) - np.array([0.0, 0.0, scene.source_bowl[1]])
        cav = base + np.array([0.0, 0.0, scene.source_bowl[2]])
        colliders = ColliderState.create(np.stack([base, np.asarray(_target_pos(scene))]))
        self._template = init_state(self.cfg, x + cav.astype(np.float32), mat=mat, vol=vol,
                                    colliders=colliders)

    def init(self, key, params):
        """The source bowl at a random offset from ``source_wrist``, upright, contents at
        rest, and the target bowl at a random offset from ``target_xy``."""
        scene = self.spec.scene
        k_src, k_tgt = jax.random.split(key)
        rng = jnp.asarray(scene.init_range, jnp.float32)
        off = jax.random.uniform(k_src, (3,), jnp.float32, minval=-1.0, maxval=1.0) * rng
        trng = jnp.asarray(scene.target_range + (0.0,), jnp.float32)
        t_off = jax.random.uniform(k_tgt, (3,), jnp.float32, minval=-1.0, maxval=1.0) * trng
        template = self._template
        cs = template.colliders
        pos = cs.pos.at[SOURCE].add(off).at[TARGET].add(t_off)
        return template.replace(x=template.x + off, colliders=cs.replace(pos=pos))

    def apply_action(self, physics, action, params):
        """Hold ``(vx, vy, vz, omega)`` for ``spec.substeps`` substeps (see the module
        docstring)."""
        scene, cfg = self.spec.scene, self.cfg
        material = params.physics
        T = self.dt
        w0 = wrist(scene, physics.colliders)
        th0 = tilt(physics.colliders)
        lo, hi = jnp.asarray(scene.wrist_low), jnp.asarray(scene.wrist_high)
        v = jnp.clip(action[:3], (lo - w0) / T, (hi - w0) / T)
        omega = jnp.clip(action[3], (scene.tilt_range[0] - th0) / T,
                         (scene.tilt_range[1] - th0) / T)
        ang = jnp.stack([jnp.zeros_like(omega), omega, jnp.zeros_like(omega)])

        def body(s, _):
            cs = s.colliders
            w = wrist(scene, cs)
            lin = v + jnp.cross(ang, cs.pos[SOURCE] - w)
            cs = cs.replace(lin_vel=cs.lin_vel.at[SOURCE].set(lin),
                            ang_vel=cs.ang_vel.at[SOURCE].set(ang))
            return step(cfg, material, s.replace(colliders=cs)), None

        physics = checkpointed_scan(body, physics, jnp.arange(self.spec.substeps,
                                                              dtype=jnp.int32),
                                    segment=scene.segment)[0]
        cs = physics.colliders
        return physics.replace(colliders=cs.replace(lin_vel=jnp.zeros_like(cs.lin_vel),
                                                    ang_vel=jnp.zeros_like(cs.ang_vel)))

    @property
    def n_goal_points(self) -> int:
        """The goal is the contents packed in the target cavity: one point per particle
        (``D`` does not read it, but renderings and demonstration files do; a goal of
        another size was made for another scene)."""
        return self.n_object_points

    def distance(self, physics, goal):
        """``D`` [m]: the mean distance of the particles to the target cavity (the contents
        not transferred); ``goal`` is not used (see the module docstring)."""
        return jnp.mean(particle_distance(self.spec.scene, physics))

    def canonical_goal(self) -> np.ndarray:
        """N particles packed on a lattice in the target cavity from the bottom up
        (N, 3)."""
        scene = self.spec.scene
        x0, _, _, vol = contents(scene)
        n = len(x0)
        total = float(np.sum(np.broadcast_to(vol, (n,))))
        r_out, h, wall = scene.target_bowl
        r_in = r_out - wall - 0.25 * scene.dx
        height = 2.0 * total / (math.pi * r_in ** 2) + 2 * scene.dx
        base = np.asarray(_target_pos(scene)) + np.array([0.0, 0.0, wall])
        pts, _ = sampling.cylinder(base, r_in, height, scene.dx, ppc=scene.ppc, seed=0,
                                   jitter=0.0)
        order = np.lexsort((pts[:, 1], pts[:, 0], pts[:, 2]))
        return np.asarray(pts[order[:n]], np.float32)

    def expert(self, state, params):
        """Scripted pour: drive the wrist to the pour point (``pour_offset`` from the
        episode's target bowl's centre at the table), tilt to ``pour_angle`` once within 2 cm
        of it, hold, and tilt back to upright in the last steps of the horizon. Pure and
        jittable."""
        scene, spec = self.spec.scene, self.spec
        T = self.dt
        cs = state.physics.colliders
        w = wrist(scene, cs)
        th = tilt(cs)
        target = cs.pos[TARGET]  # where this episode's target bowl stands
        p = jnp.stack([target[0] + scene.pour_offset[0], target[1] + scene.pour_offset[1],
                       jnp.asarray(scene.pour_offset[2], target.dtype)])
        err = p - w
        v = err / (2.0 * T)
        near = jnp.sqrt(jnp.sum(err[:2] ** 2)) < 0.02
        w_max = spec.action_high[3]
        back = math.ceil(scene.pour_angle / (w_max * T)) + 2
        pouring = near | (th > 0.2)
        th_goal = jnp.where((state.t < spec.horizon - back) & pouring, scene.pour_angle, 0.0)
        omega = (th_goal - th) / T
        return jnp.concatenate([v, omega[None]])

    @property
    def object_colors(self):
        """The contents' colours by material: water blue, the soup's chunks beige."""
        palette = np.asarray([[0.2, 0.45, 0.9], [0.9, 0.75, 0.45]], np.float32)
        return palette[np.asarray(self._template.mat)]

    def end_effector(self, physics):
        """The wrist (source bowl's rim centre) [m] (3,)."""
        return wrist(self.spec.scene, physics.colliders)

    def observe(self, physics):
        """Every ``obs_stride``-th particle, the wrist [m] and the tilt [rad], flattened."""
        pts = physics.x[:: self.spec.obs_stride]
        return jnp.concatenate([pts.reshape(-1), self.end_effector(physics),
                                tilt(physics.colliders)[None]])


def _spec(name: str, scene: PourScene, substeps: int) -> TaskSpec:
    return TaskSpec(name=name, horizon=100, action_kind="velocity",
                    action_low=(-0.4, -0.4, -0.4, -3.0), action_high=(0.4, 0.4, 0.4, 3.0),
                    substeps=substeps, distance="chamfer", contact_adjustment=False,
                    obs_stride=4, scene=scene)


POUR_WATER = _spec("pour_water", PourScene(), 30)
POUR_SOUP = _spec("pour_soup", PourScene(dt=0.025 / 36, fill_height=0.02, n_chunks=3, ppc=4),
                  36)
#: The original benchmark's resolution (``make(name, resolution="reference")``).
#: Pour-Water: its 702 particles (``ppc`` 11 for 8: 690); its 23 substeps per 0.025 s
#: step would exceed this fluid's stable dt (8.4e-4 s), so the default's 30 stay; the whole
#: 34 x 24 x 28 grid stays too (the bowls need it: 22848 cells for its active
#: 26 x 20 x 26 = 13520). Pour-Soup: its 7631 particles with the grid refined to
#: dx = 5 mm (68 x 48 x 56 = 182784 cells for its 128 x 64 x 128 = 1048576) and ``ppc``
#: 19 (7891 particles; 17 and 18 give 6977); 72 substeps of 3.5e-4 s (the stable bound at
#: 5 mm; it has 25).
POUR_WATER_REFERENCE = _spec("pour_water", PourScene(ppc=11), 30)
POUR_SOUP_REFERENCE = _spec("pour_soup", PourScene(
    dx=0.005, domain=(68, 48, 56), ppc=19, dt=0.025 / 72, fill_height=0.02, n_chunks=3), 72)
