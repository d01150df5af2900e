"""The static configuration of an MPM scene and its stability bounds.

:class:`MPMConfig` is hashable (a ``static_argnums`` argument; changing it recompiles).
At construction it checks what it alone determines, the time step against the material
table it holds included; :func:`check_params` checks the differentiable numbers of a
:class:`~dax_physics.materials.MaterialParams` against it, eagerly, once. SI units.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from .. import colliders as col
from .._checks import unstable_dt
from ..materials import Material, MaterialParams

#: Courant number used by the stability guard: dt <= CFL * dx / (c_max + v_max).
CFL = 0.5
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
        side of the domain (see :mod:`dax_physics.mpm`).
    colliders: tuple of :class:`~dax_physics.colliders.ColliderSpec`.
    max_speed: the largest particle or collider speed [m/s] the scene is expected to
        reach (finite, >= 0); enters the CFL part of the stability bound. A run whose
        particles exceed the speed the time step can carry at all (:func:`max_stable_speed`)
        is flagged: its state's ``finite`` turns false and ``check_state`` calls it
        unstable.
    fluid_tension: let fluid particles stretch past J = 1 (negative pressure), as the
        Taichi and Warp reference scenes do; the default ``False`` caps J at 1 (see
        :mod:`dax_physics.mpm`).
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
        self._set_grid()
        gravity = tuple(_real(g, "gravity") for g in _entries(self.gravity, "gravity"))
        if len(gravity) != 3 or not all(math.isfinite(g) for g in gravity):
            raise ValueError(f"gravity must be 3 finite numbers in m/s^2, got {self.gravity}")
        object.__setattr__(self, "gravity", gravity)
        if not (math.isfinite(_real(self.dx, "dx")) and self.dx > 0):
            raise ValueError(f"dx must be a positive cell size in m, got {self.dx}")
        if not (math.isfinite(_real(self.dt, "dt")) and self.dt > 0):
            raise ValueError(f"dt must be a positive time step in s, got {self.dt}")
        # a NaN max_speed would make the stability bound NaN and pass every dt; a negative
        # one could divide by zero or suggest a negative dt
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
            raise unstable_dt(self.dt, limit, (
                f"for dx = {self.dx:.3g} m (CFL {CFL} on the fastest wave speed "
                f"{_wave_speed(self, None):.3g} m/s plus max_speed {self.max_speed:.3g} m/s)"),
                f"use dt <= {limit:.3g}")

    def _set_grid(self):
        """Check ``domain`` and ``window`` and store them as tuples of 3 ints."""
        domain = tuple(int(d) for d in self.domain)
        window = domain if self.window is None else tuple(int(w) for w in self.window)
        if len(domain) != 3 or len(window) != 3:
            raise ValueError(f"domain and window must have 3 entries, got {domain}, {window}")
        if any(w < 4 for w in window) or any(w > d for w, d in zip(window, domain, strict=True)):
            raise ValueError(f"window {window} must be >= 4 cells and fit in domain {domain}")
        object.__setattr__(self, "domain", domain)
        object.__setattr__(self, "window", window)

    @property
    def kinds(self) -> frozenset:
        """The material kinds of the table (only their stress code is compiled)."""
        return frozenset(m.kind for m in self.materials)

    @property
    def full_grid(self) -> bool:
        """Whether the window is the whole domain."""
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
    """``value`` as a tuple; ``TypeError`` naming the field if it is not a sequence."""
    try:
        return tuple(value)
    except TypeError:
        raise TypeError(f"MPMConfig.{name} must be a sequence of numbers, got "
                        f"{value!r}") from None


def _wave_speed(cfg: MPMConfig, params: MaterialParams | None):
    """The fastest elastic (P-) wave or sound speed [m/s]: of the material table (a float)
    or of ``params`` (a scalar array, possibly traced)."""
    if params is None:
        return max(m.wave_speed for m in cfg.materials)
    return jnp.max(params.wave_speed())


def max_stable_speed(cfg: MPMConfig, params: MaterialParams | None = None):
    """The particle speed [m/s] above which ``cfg.dt`` cannot be stable at all: ``dx / dt
    - c`` (Courant number 1 on the fastest wave speed ``c`` plus the particle's speed; ``c``
    from ``params`` when given, which may be traced). The guard's CFL number 0.5 is the
    margin ``dt`` is chosen with, so this speed is at least ``c + 2 max_speed``: a run
    within the speeds the configuration assumes never reaches it. ``step`` flags a state
    whose particles exceed it (``finite`` false)."""
    return cfg.dx / cfg.dt - _wave_speed(cfg, params)


def max_stable_dt(cfg: MPMConfig, params: MaterialParams | None = None) -> float:
    """Largest stable substep [s]: ``CFL * dx / (c + max_speed)`` with ``c`` the fastest
    elastic (P-) wave or sound speed of the material table (of ``params`` when given: it
    needs concrete arrays). The ``CFL`` number 0.5 is conservative for explicit MLS-MPM
    with quadratic B-splines."""
    return CFL * cfg.dx / (float(_wave_speed(cfg, params)) + cfg.max_speed)


def check_params(cfg: MPMConfig, params: MaterialParams) -> None:
    """Raise ``ValueError`` naming the problem if ``params`` does not fit ``cfg`` or makes
    its time step unstable: wrong shapes, non-finite or non-positive densities, negative
    moduli, viscosities or friction coefficients, or ``cfg.dt`` above the largest stable
    substep of these materials (named in the message). Needs concrete arrays (call it
    once, outside ``jit``)."""
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
        raise unstable_dt(cfg.dt, limit, (
            f"for these material parameters (fastest wave speed "
            f"{float(_wave_speed(cfg, params)):.3g} m/s)"), "lower the moduli or raise the density")
