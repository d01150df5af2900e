"""Whip-Rope: whip the held end of a rope in a loop that flips the rope over to its other side.

Scene (SI units, z up). An elastic MPM rope (fixed-corotated, :data:`ROPE`: E = 1.6e5 Pa,
nu = 0.3, rho = 1100 kg/m^3) of length 0.25 m and radius 1 cm lies on a table (a
``plane`` collider at ``table_z`` = 4.5 cm, Coulomb friction 0.4). The material and the
friction are ``params.physics`` (a :class:`dax_physics.MaterialParams`). The gripper holds
the first ``grip_length`` = 3 cm of the rope (31 of the 288 particles, the same indices
for every seed). The grip is rigid and infinitely heavy: in every substep the grid nodes
that carry held mass move at the gripper's velocity (``dax_physics.step``'s ``drive``),
and after the substep the held particles are set on the gripper's path with its velocity
and a zero APIC matrix (no gripper collider is evaluated on the grid). Driving the grid
keeps the velocity field at the junction moving with the grip, so a sudden pull of up to
the action bound does not open a gap between the held and the free rope; the rope's
stiffness keeps a whip from stretching it apart. The gripper's position is the centroid of
the held particles (the end effector).

Resolution. Cells ``dx`` = 1.25 cm; 8 particles per cell (288 particles, about 4 across
the rope); the allocated grid is a 30 x 30 x 12 cell window (0.375 x 0.375 x 0.15 m) that
follows the rope inside an 80 x 80 x 24 cell domain (1 x 1 x 0.3 m). Substep ``dt`` =
0.01 / 29 s (CFL bound 3.47e-4 s for the P-wave speed 14 m/s plus ``max_speed`` 4 m/s); 29
substeps per env step (0.01 s), horizon 50 steps (0.5 s).

Action (``velocity``): the gripper's velocity ``(vx, vy, vz)`` [m/s], held for the env
step. Bounds ±3 m/s per axis and the speed (norm) is capped at ``grip_speed`` = 3 m/s.
The gripper's end point is kept inside the workspace (:func:`workspace`; z at least the
held particles' rest height, so the held end never enters the table); a clipped
component has zero gradient.

Start, drawn from the key. The rope's particles are sampled once on a straight reference
rope and bent onto a random centre line by arc length s (from the held end),
``theta(s) = theta0 + sum_k a_k (sin(k pi s / L + phi_k) - sin(phi_k))`` (k = 1..3,
``a_k`` uniform in ``[-A/k, A/k]``, A = ``bend_amplitude`` = 0.4 rad, heading ``theta0``
uniform in ±``heading_range`` = ±0.3 rad), its held end at ``rope_start`` (0.55, 0.5) m
(the rope along +x) plus a uniform offset of up to ``offset_range`` = 5 cm in x and in y
(the held end stays inside the gripper's workspace, checked when the task is built).
Particles keep their index across seeds. The goal is a place on the table, as in the
original benchmark, so the start varies only as far as the expert's whip still lands the
rope there (the dax-tasks README says why the goal is not aligned to the start).

Goal (fixed per task): the end state (step 50) of the *canonical throw* from the canonical
initial state (the straight rope): a whip loop that flips the rope over to the other side
of the gripper. The throw (``scene.throw``) is four raised-cosine velocity bumps of the
gripper: 12 cm sideways (-y, steps 0-11) and, overlapping, 20 cm back along the rope
(-x, steps 2-19), so the rope is dragged out of its start shape and slides after the
gripper; then 12 cm back (+y, steps 14-25) and, overlapping, the turn into a 28 cm return
(+x, steps 18-43) that ends 8 cm past the start. The rope, still sliding back, swings
round the turning gripper (the loop), and the return drags it out behind: at step 50 the
held end is 8 cm from where it started and the rope lies on its other side, the far end
4 cm behind the gripper (-x) and 10 cm to its side, where it began 25 cm in front. The
gripper's 0.64 m path is too long for a slow drag within the horizon, and moving the held
end towards the goal's position earns little while the rope still points the wrong way.

Distance: ``D`` = index-correspondence mean L2 [m] between the rope's particles and the
goal's; λ = 6 /m: ``r_gt = exp(-6 D)`` is 0.9 at D = 1.8 cm and 0.5 at D = 12 cm.

Expert (:meth:`WhipRope.expert`, privileged: reads the step counter and the gripper): the
canonical throw's velocity at step t plus a feedback term that steers the gripper onto the
canonical path (:data:`TRACK_GAIN`: a quarter of the position error per step, at most
:data:`TRACK_SPEED` = 1 m/s, so a start a few cm off is caught up during the first drag
rather than in one yank). It reproduces the goal from a randomised start: the first drag
pulls the random bend out of the rope, and the return straightens what the loop leaves.
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
    step,
)

from ..core.env import MPMEnv
from ..core.spec import TaskSpec
from ..viz import images
from . import _rope
from ._rope import rest_particles

#: The rope's default material (``params.physics`` material 0).
ROPE = Material("elastic", 1100.0, youngs_modulus=1.6e5, poisson_ratio=0.3)
#: Default Coulomb coefficient of the table (``params.physics.friction[0]``).
TABLE_FRICTION = 0.4


@dataclasses.dataclass(frozen=True)
class WhipRopeScene:
    """Static scene of Whip-Rope (SI units); see the module docstring."""

    dx: float = 0.0125                # grid cell [m]
    dt: float = 0.01 / 29             # substep [s] (29 per 0.01 s env step)
    domain: tuple = (80, 80, 24)      # cells (1.0 x 1.0 x 0.3 m)
    window: tuple = (30, 30, 12)      # active-region cells
    table_z: float = 0.045            # table height [m]
    rope_length: float = 0.25         # [m]
    rope_radius: float = 0.01         # [m]
    ppc: int = 8                      # particles per cell
    grip_length: float = 0.03         # held length of rope at the s = 0 end [m]
    max_speed: float = 4.0            # largest expected particle speed [m/s] (CFL guard)
    grip_speed: float = 3.0           # largest gripper speed (norm) [m/s]
    grip_low: tuple = (0.15, 0.15)    # gripper workspace (x, y) [m]; z >= rest height
    grip_high: tuple = (0.85, 0.85, 0.13)
    rope_start: tuple = (0.55, 0.5)   # canonical (x, y) of the held end [m]
    bend_amplitude: float = 0.4       # A [rad]
    bend_modes: int = 3
    heading_range: float = 0.3        # [rad]: the start's heading is uniform in +-this
    offset_range: float = 0.05        # [m]: largest start offset of the held end in x and y
    #: canonical throw: phases (start step, steps, dx, dy, dz [m]) of the gripper, each a
    #: raised-cosine velocity bump that moves the gripper by (dx, dy, dz).
    #: A loop: out sideways and back, then the turn and the return past the start (the
    #: rope swings round the turning gripper and trails behind it, flipped).
    throw: tuple = (
        (0, 12, 0.0, -0.12, 0.0),
        (2, 18, -0.20, 0.0, 0.0),
        (14, 12, 0.0, 0.12, 0.0),
        (18, 26, 0.28, 0.0, 0.0),
    )
    segment: int = 8                  # substeps per checkpointed segment
    #: the grip drives the grid nodes its particles touch (``step``'s ``drive``); False:
    #: the held particles are only reset after each substep, which lets a fast pull tear
    #: the rope off the grip (``benchmarks/whip_tear.py`` compares the two)
    grid_grip: bool = True

    @property
    def centre(self) -> tuple:
        return (0.5 * self.domain[0] * self.dx, 0.5 * self.domain[1] * self.dx)


def mpm_config(scene: WhipRopeScene) -> MPMConfig:
    """The MPM configuration of the scene (raises if ``dt`` is unstable for :data:`ROPE`).
    The only collider is the table: the gripper is kinematic and imposed on the held
    particles (see :meth:`WhipRope.apply_action`), so it costs no signed-distance
    evaluation on the grid."""
    colliders = (ColliderSpec("plane", (), mode="separate", friction=TABLE_FRICTION),)
    return MPMConfig(materials=(ROPE,), dx=scene.dx, dt=scene.dt, domain=scene.domain,
                     window=scene.window, walls="slip", colliders=colliders,
                     max_speed=scene.max_speed)


def held_mask(scene: WhipRopeScene) -> np.ndarray:
    """(N,) bool: the particles the gripper holds (the first ``grip_length`` of the rope);
    the same indices for every seed (NumPy, a constant under ``jit``)."""
    rest, _ = rest_particles(scene)
    return rest[:, 0] < scene.grip_length


def _place(scene, rest, theta_fn, start):
    """Bend the reference particles onto the centre line with tangent angle ``theta_fn(s)``
    starting (s = 0, the held end) at ``start`` (2,), resting on the table."""
    px, py, pt, u, w = _rope.centre_line(scene, rest, theta_fn)
    x = px - u * jnp.sin(pt) + start[0]
    y = py + u * jnp.cos(pt) + start[1]
    z = scene.table_z + scene.rope_radius + w
    return jnp.stack([x, y, jnp.broadcast_to(z, x.shape)], axis=1).astype(jnp.float32)


def _rope_start(scene: WhipRopeScene) -> np.ndarray:
    """Canonical position (x, y) of the rope's s = 0 end: the rope centred on the table."""
    return np.asarray(scene.rope_start, np.float32)


def straight(scene: WhipRopeScene, rest) -> np.ndarray:
    """The reference particles laid straight along +x, centred on the table (NumPy, so it
    stays a constant under ``jit``); equals ``_place`` with ``theta = 0``."""
    x0, y0 = _rope_start(scene)
    z = scene.table_z + scene.rope_radius + rest[:, 2]
    return np.stack([rest[:, 0] + x0, rest[:, 1] + y0, z], axis=1).astype(np.float32)


def _template(scene: WhipRopeScene, cfg: MPMConfig):
    """The canonical initial state (validated by ``init_state``): the rope straight along
    +x, centred on the table; fixes dtypes and shapes."""
    rest, vol = rest_particles(scene)
    colliders = ColliderState.create([[0.0, 0.0, scene.table_z]])
    return init_state(cfg, straight(scene, rest), vol=vol, colliders=colliders)


def canonical_start(scene: WhipRopeScene) -> np.ndarray:
    """The gripper position (centroid of the held particles) of the canonical state."""
    rest, _ = rest_particles(scene)
    return straight(scene, rest)[held_mask(scene)].mean(0).astype(np.float32)


def workspace(scene: WhipRopeScene):
    """The gripper's workspace ``(low, high)`` [m] (3,) each: ``grip_low`` / ``grip_high``
    in x, y; in z from the held particles' rest height (rope lying on the table) to
    ``grip_high``'s z."""
    z0 = float(canonical_start(scene)[2])
    lo = np.asarray([*scene.grip_low, z0], np.float32)
    return lo, np.asarray(scene.grip_high, np.float32)


def _check_start_region(scene: WhipRopeScene) -> None:
    """Raise ``ValueError`` unless every start's held end (``rope_start`` +- ``offset_range``
    in x and y) lies inside the gripper's workspace with the rope's radius to spare."""
    start = np.asarray(scene.rope_start, np.float64)
    pad = scene.offset_range + scene.rope_radius
    lo, hi = np.asarray(scene.grip_low[:2]), np.asarray(scene.grip_high[:2])
    if np.any(start - pad < lo) or np.any(start + pad > hi):
        raise ValueError(f"whip_rope: the start region rope_start {tuple(start)} +- "
                         f"offset_range {scene.offset_range} m (+ the rope's radius) leaves "
                         f"the gripper's workspace {tuple(lo)}-{tuple(hi)}")


#: Feedback gain of the expert's tracking of the canonical gripper path (per env step).
TRACK_GAIN = 0.25
#: The expert's feedback velocity is capped at this speed [m/s] (norm), so a start far
#: from the canonical one is caught up over a few steps, not in one yank.
TRACK_SPEED = 1.0


class WhipRope(MPMEnv):
    """Whip-Rope (see the module docstring). ``params.physics`` is the scene's
    :class:`dax_physics.MaterialParams`: the rope's material and the table's friction."""

    LAM = 6.0
    mpm_config = staticmethod(mpm_config)

    def __init__(self, spec: TaskSpec):
        super().__init__(spec)
        scene = spec.scene
        _check_start_region(scene)
        self._rest, _ = rest_particles(scene)
        self._held = held_mask(scene)
        self._template = _template(scene, self.cfg)  # checked once

    def start_heading(self, key):
        """The start's heading ``theta0`` [rad] that :meth:`init` draws from ``key``: uniform
        in ``±scene.heading_range``."""
        return _rope.start_heading(self.spec.scene, key)

    def init(self, key, params):
        """A random rope shape on the table (see the module docstring), at rest, its first
        ``grip_length`` held by the gripper."""
        scene = self.spec.scene
        k_amp, k_phase, _, k_off = jax.random.split(key, 4)
        modes, amp, phase = _rope.bend_modes(scene, k_amp, k_phase)
        theta0 = self.start_heading(key)
        offset = jax.random.uniform(k_off, (2,), jnp.float32, minval=-scene.offset_range,
                                    maxval=scene.offset_range)

        def theta(s):
            arg = modes[:, None] * math.pi * s[None, :] / scene.rope_length + phase[:, None]
            bend = jnp.sin(arg) - jnp.sin(phase[:, None])  # zero at the held end
            return theta0 + jnp.sum(amp[:, None] * bend, axis=0)

        start = jnp.asarray(_rope_start(scene)) + offset
        return self._template.replace(x=_place(scene, jnp.asarray(self._rest), theta, start))

    def gripper(self, physics):
        """The gripper position [m] (3,): the centroid of the held particles."""
        mask = jnp.asarray(self._held, physics.x.dtype)
        return jnp.sum(physics.x * mask[:, None], axis=0) / jnp.sum(mask)

    def apply_action(self, physics, action, params):
        """One env step: the gripper moves at the commanded velocity ``action`` (3,) [m/s]
        for ``spec.substeps`` substeps; the held particles translate rigidly with it (after
        every substep their positions are set on the gripper's path, their velocity to the
        gripper's and their APIC matrix to zero). The speed is capped at ``grip_speed``
        (norm) and the gripper's end point clipped to :func:`workspace` (the velocity is
        scaled down accordingly; a clipped component has zero gradient)."""
        scene, cfg = self.spec.scene, self.cfg
        T = self.dt
        held = jnp.asarray(self._held)
        p = self.gripper(physics)
        speed = jnp.sqrt(jnp.sum(action * action) + 1e-12)
        action = action * jnp.minimum(1.0, scene.grip_speed / speed)
        lo, hi = workspace(scene)
        target = jnp.clip(p + action * T, jnp.asarray(lo), jnp.asarray(hi))
        vel = (target - p) / T
        x0 = physics.x
        material = params.physics
        h3 = held[:, None]

        drive = (held.astype(x0.dtype), vel) if scene.grid_grip else None

        def body(s, i):
            s = step(cfg, material, s, drive=drive)
            moved = x0 + vel * ((i + 1).astype(x0.dtype) * cfg.dt)
            return s.replace(x=jnp.where(h3, moved, s.x),
                             v=jnp.where(h3, jnp.broadcast_to(vel, s.v.shape), s.v),
                             C=jnp.where(held[:, None, None], 0.0, s.C)), None

        return checkpointed_scan(body, physics, jnp.arange(self.spec.substeps,
                                                           dtype=jnp.int32),
                                 segment=scene.segment)[0]

    def throw_velocities(self) -> np.ndarray:
        """The canonical throw's gripper velocity per env step (horizon, 3) [m/s]: each
        phase of ``scene.throw`` is a raised-cosine bump whose per-step averages move the
        gripper by exactly the phase's displacement."""
        T = self.dt
        v = np.zeros((self.horizon, 3), np.float64)
        for start, steps, *disp in self.spec.scene.throw:
            edges = np.linspace(0.0, 1.0, steps + 1)
            cum = edges - np.sin(2 * np.pi * edges) / (2 * np.pi)  # integral of 1 - cos
            frac = np.diff(cum)
            for k in range(steps):
                if 0 <= start + k < self.horizon:
                    v[start + k] += frac[k] * np.asarray(disp) / T
        return v.astype(np.float32)

    def canonical_path(self) -> np.ndarray:
        """The canonical gripper position at the start of each env step (horizon + 1, 3)."""
        v = self.throw_velocities()
        p0 = canonical_start(self.spec.scene).astype(np.float64)
        return (p0 + np.concatenate([np.zeros((1, 3)), np.cumsum(v * self.dt, 0)])
                ).astype(np.float32)

    def canonical_goal(self) -> np.ndarray:
        """The goal (N, 3) [m]: the rope after the canonical throw (``throw_velocities``
        for ``spec.horizon`` steps) from the canonical initial state."""
        vel = self.throw_velocities()
        params = self._shape_params()
        with jax.ensure_compile_time_eval():
            def run(s):
                return jax.lax.scan(lambda c, a: (self.apply_action(c, a, params), None), s,
                                    jnp.asarray(vel))[0]

            state = jax.jit(run)(self._template)
            return np.asarray(state.x, np.float32)

    def expert(self, state, params):
        """Track the canonical throw: its velocity at step ``t`` plus ``TRACK_GAIN`` of the
        gripper's position error to the canonical path per step, at most ``TRACK_SPEED``."""
        vel = jnp.asarray(self.throw_velocities())
        path = jnp.asarray(self.canonical_path())
        t = jnp.clip(state.t, 0, self.horizon - 1)
        err = path[t] - self.gripper(state.physics)
        fb = TRACK_GAIN * err / self.dt
        fb = fb * jnp.minimum(1.0, TRACK_SPEED / jnp.sqrt(jnp.sum(fb * fb) + 1e-12))
        return vel[t] + fb

    @property
    def object_colors(self):
        """The rope's texture: a colour ramp along its length
        (:func:`dax_tasks.viz.ramp_colors`), so its two ends differ in RGB pictures."""
        return images.ramp_colors(self._rest[:, 0])

    def end_effector(self, physics):
        """The gripper position [m] (3,) (centroid of the held particles)."""
        return self.gripper(physics)


def _spec() -> TaskSpec:
    scene = WhipRopeScene()
    vmax = scene.grip_speed
    return TaskSpec(
        name="whip_rope", horizon=50, action_kind="velocity", action_low=(-vmax,) * 3,
        action_high=(vmax,) * 3, substeps=29, distance="l2", contact_adjustment=False,
        obs_stride=2, scene=scene)


WHIP_ROPE = _spec()
#: The original benchmark's resolution (``make("whip_rope", resolution="reference")``):
#: its 70 substeps per step over the same 0.01 s, about its 67 particles (``ppc`` 2 for
#: 8), and an active window of 40 x 40 x 20 = 32000 cells for its 32^3 = 32768.
WHIP_ROPE_REFERENCE = dataclasses.replace(WHIP_ROPE, substeps=70, scene=dataclasses.replace(
    WHIP_ROPE.scene, dt=0.01 / 70, ppc=2, window=(40, 40, 20)))
