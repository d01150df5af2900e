"""Constitutive models for MPM particles, in SI units.

A scene holds a *material table*: a tuple of :class:`Material` entries. Every particle
carries an integer material id indexing that table, so water, rope, tofu and dough can
share one grid. The table splits in two parts:

* the *kinds* (``"fluid"``, ``"elastic"``, ``"plastic"``) are static: they decide which
  stress code is compiled;
* the numbers (density, moduli, yield stress, viscosity) become a :class:`MaterialParams`
  pytree of arrays, so they can be differentiated, vmapped or changed without recompiling.

Models (Kirchhoff stress ``tau``; ``J = det F``):

``fluid``    weakly compressible fluid, ``tau = K J (J - 1) I + J eta (C + C^T)`` with bulk
             modulus ``K`` [Pa] and dynamic viscosity ``eta`` [Pa s]; ``J`` is tracked per
             particle (``J <- J (1 + dt tr C)``), ``C`` is the APIC velocity gradient.
``elastic``  fixed-corotated hyperelasticity (Stomakhin et al. 2012),
             ``tau = 2 mu (F - R) F^T + lam J (J - 1) I`` with Lame parameters from Young's
             modulus ``E`` [Pa] and Poisson's ratio ``nu`` [-].
``plastic``  von Mises (J2) elasto-plasticity with a radial return mapping on the elastic
             left Cauchy-Green tensor ``b_e`` (Simo & Hughes 1998, box 9.1):
             ``tau = K/2 (J^2 - 1) I + mu dev(bbar_e)``, ``bbar_e = J^{-2/3} b_e``; the trial
             deviator is projected back onto ``|s| <= sqrt(2/3) sigma_y`` with yield stress
             ``sigma_y`` [Pa]; plastic flow is isochoric. For these particles the state's
             ``H`` slot stores ``b_e - I`` (zero at rest; ``MPMState.F`` is then ``b_e``),
             not a displacement gradient.

The return mapping needs no SVD, so it is differentiable everywhere except on the yield
surface itself (and finite there).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ._pytree import pytree_dataclass

KINDS = ("fluid", "elastic", "plastic")


@dataclasses.dataclass(frozen=True)
class Material:
    """One entry of a scene's material table (SI units).

    kind: ``"fluid"``, ``"elastic"`` or ``"plastic"``.
    density: mass density rho [kg/m^3].
    youngs_modulus: E [Pa] (elastic, plastic).
    poisson_ratio: nu [-], in (-1, 0.5) (elastic, plastic).
    bulk_modulus: K [Pa] (fluid only; solids derive K from E and nu).
    viscosity: dynamic viscosity eta [Pa s] (fluid only).
    yield_stress: von Mises yield stress sigma_y [Pa] (plastic only).
    """

    kind: str
    density: float
    youngs_modulus: float = 0.0
    poisson_ratio: float = 0.0
    bulk_modulus: float = 0.0
    viscosity: float = 0.0
    yield_stress: float = math.inf

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(
                f"unknown material kind {self.kind!r}; valid kinds: {', '.join(KINDS)}")
        if not self.density > 0:
            raise ValueError(f"material density must be > 0 kg/m^3, got {self.density}")
        if self.kind == "fluid":
            if not self.bulk_modulus > 0:
                raise ValueError(f"fluid bulk_modulus must be > 0 Pa, got {self.bulk_modulus}")
            if self.viscosity < 0:
                raise ValueError(f"fluid viscosity must be >= 0 Pa s, got {self.viscosity}")
        else:
            if not self.youngs_modulus > 0:
                raise ValueError(
                    f"{self.kind} youngs_modulus must be > 0 Pa, got {self.youngs_modulus}")
            if not -1.0 < self.poisson_ratio < 0.5:
                raise ValueError(
                    f"{self.kind} poisson_ratio must lie in (-1, 0.5), got {self.poisson_ratio}")
            if self.kind == "plastic" and not self.yield_stress > 0:
                raise ValueError(f"plastic yield_stress must be > 0 Pa, got {self.yield_stress}")

    @property
    def lame(self) -> tuple[float, float]:
        """(mu, lambda) [Pa]; for a fluid mu = 0 and lambda = K."""
        if self.kind == "fluid":
            return 0.0, self.bulk_modulus
        return lame_parameters(self.youngs_modulus, self.poisson_ratio)

    @property
    def wave_speed(self) -> float:
        """Fastest (P-)wave speed [m/s]: sqrt((lambda + 2 mu) / rho), sqrt(K / rho) for fluid."""
        mu, lam = self.lame
        return math.sqrt((lam + 2 * mu) / self.density)


def lame_parameters(E, nu):
    """Lame parameters (mu, lambda) [Pa] from Young's modulus E [Pa] and Poisson's ratio nu
    (works on floats and traced arrays)."""
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


# Convenient presets (SI). Values are representative, not measurements of a product.
def water(bulk_modulus: float = 2.0e4, viscosity: float = 1.0e-3) -> Material:
    """Weakly compressible water: rho 1000 kg/m^3. The bulk modulus is lowered from the real
    2.2 GPa to keep the explicit time step practical (the usual weakly compressible choice:
    the sound speed, here sqrt(K/rho) = 4.5 m/s, stays well above flow speeds)."""
    return Material("fluid", 1000.0, bulk_modulus=bulk_modulus, viscosity=viscosity)


def rope(youngs_modulus: float = 2.0e5, poisson_ratio: float = 0.3) -> Material:
    """A soft elastic rope (rubber-like), rho 1100 kg/m^3."""
    return Material("elastic", 1100.0, youngs_modulus=youngs_modulus, poisson_ratio=poisson_ratio)


def tofu(youngs_modulus: float = 5.0e4, poisson_ratio: float = 0.3) -> Material:
    """A stiff elastic chunk (tofu, soup ingredients), rho 1050 kg/m^3."""
    return Material("elastic", 1050.0, youngs_modulus=youngs_modulus, poisson_ratio=poisson_ratio)


def dough(youngs_modulus: float = 5.0e4, poisson_ratio: float = 0.3,
          yield_stress: float = 1.0e3) -> Material:
    """Elasto-plastic dough: von Mises with a low yield stress, rho 1200 kg/m^3."""
    return Material("plastic", 1200.0, youngs_modulus=youngs_modulus,
                    poisson_ratio=poisson_ratio, yield_stress=yield_stress)


@pytree_dataclass
class MaterialParams:
    """The differentiable numbers of an MPM scene: one entry per material (shape (M,)) and
    one friction coefficient per collider (shape (K,)).

    density [kg/m^3], mu and lam: Lame parameters [Pa] (lam = K for fluids),
    viscosity [Pa s], yield_stress [Pa] (inf where not plastic).
    friction: Coulomb coefficient [-] of each collider of the scene, in the order of
        ``MPMConfig.colliders``; ``None`` means the coefficients of the static
        :class:`~dax_physics.colliders.ColliderSpec` entries (:attr:`MPMConfig.params`
        fills it in, so the friction is data there).
    """

    density: jnp.ndarray
    mu: jnp.ndarray
    lam: jnp.ndarray
    viscosity: jnp.ndarray
    yield_stress: jnp.ndarray
    friction: jnp.ndarray | None = None

    @staticmethod
    def from_materials(materials, dtype=jnp.float32, friction=None) -> MaterialParams:
        """The numbers of the material table ``materials``; ``friction``: optional
        per-collider coefficients (a sequence of floats)."""
        materials = tuple(materials)
        mu = [m.lame[0] for m in materials]
        lam = [m.lame[1] for m in materials]
        return MaterialParams(
            density=jnp.asarray([m.density for m in materials], dtype),
            mu=jnp.asarray(mu, dtype),
            lam=jnp.asarray(lam, dtype),
            viscosity=jnp.asarray([m.viscosity for m in materials], dtype),
            yield_stress=jnp.asarray(
                [m.yield_stress if m.kind == "plastic" else np.inf for m in materials], dtype),
            friction=None if friction is None else jnp.asarray(friction, dtype).reshape(-1),
        )

    def with_youngs_modulus(self, index: int, E, nu) -> MaterialParams:
        """Replace material ``index``'s (mu, lam) from E [Pa] and nu [-] (E may be traced)."""
        mu, lam = lame_parameters(E, nu)
        return self.replace(mu=self.mu.at[index].set(mu), lam=self.lam.at[index].set(lam))

    def youngs_modulus(self, index: int):
        """Young's modulus E [Pa] of material ``index`` from its Lame parameters."""
        mu, lam = self.mu[index], self.lam[index]
        return mu * (3 * lam + 2 * mu) / (lam + mu)

    def wave_speed(self):
        """Fastest (P-)wave or sound speed [m/s] of each material (M,):
        ``sqrt((lam + 2 mu) / rho)``."""
        return jnp.sqrt((self.lam + 2 * self.mu) / self.density)
