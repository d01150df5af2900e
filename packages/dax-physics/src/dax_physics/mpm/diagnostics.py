"""Conserved and stored quantities of an MPM state (pure, jit-able; SI units)."""

from __future__ import annotations

import jax.numpy as jnp

from ..materials import MaterialParams
from .config import MPMConfig
from .constitutive import strain_energy_density
from .state import MPMState


def particle_mass(params: MaterialParams, state: MPMState):
    """Mass [kg] of each particle (N,): rest volume times its material's density."""
    return state.vol * params.density[state.mat]


def total_mass(params: MaterialParams, state: MPMState):
    """Total particle mass [kg]."""
    return jnp.sum(particle_mass(params, state))


def momentum(params: MaterialParams, state: MPMState):
    """Total linear momentum [kg m/s] (3,)."""
    return jnp.sum(particle_mass(params, state)[:, None] * state.v, axis=0)


def kinetic_energy(params: MaterialParams, state: MPMState):
    """Translational kinetic energy of the particles [J]: sum_p m_p |v_p|^2 / 2."""
    return 0.5 * jnp.sum(particle_mass(params, state) * jnp.sum(state.v ** 2, axis=1))


def potential_energy(cfg: MPMConfig, params: MaterialParams, state: MPMState):
    """Gravitational potential [J] relative to z = 0 plus stored elastic energy [J]."""
    g = jnp.asarray(cfg.gravity, state.x.dtype)
    grav = -jnp.sum(particle_mass(params, state)[:, None] * state.x * g)
    return grav + jnp.sum(state.vol * strain_energy_density(cfg, params, state))
