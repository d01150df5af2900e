"""What the two rope tasks share (:mod:`dax_tasks.tasks.push_rope`,
:mod:`dax_tasks.tasks.whip_rope`): the straight reference rope's particles, the random
bend of a start and the centre line it bends the rope onto.

A scene here is either task's scene: it has ``dx``, ``ppc``, ``rope_length``,
``rope_radius``, ``bend_modes``, ``bend_amplitude`` and ``heading_range`` (SI units).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from dax_physics import sampling

#: Points of the centre line per rope, integrated by the midpoint rule.
CENTRE_LINE_POINTS = 257


def rest_particles(scene):
    """Reference particles ``(s, u, w)`` [m] of the straight rope (s along it from its
    ``s = 0`` end, u across, w up, both relative to its axis) and the rest volume per
    particle [m^3] (NumPy)."""
    r, length = scene.rope_radius, scene.rope_length
    x, vol = sampling.box([0.0, -r, -r], [length, r, r], scene.dx, ppc=scene.ppc, seed=0)
    keep = x[:, 1] ** 2 + x[:, 2] ** 2 <= r * r
    return x[keep], vol


def bend_modes(scene, k_amp, k_phase):
    """``(k, a_k, phi_k)`` (each ``(bend_modes,)`` float32) of a random start: mode numbers
    ``k = 1 ..``, amplitudes ``a_k`` uniform in ``[-A/k, A/k]`` (``A = bend_amplitude``
    [rad]) drawn from ``k_amp`` and phases ``phi_k`` uniform in ``[0, 2 pi)`` from
    ``k_phase``. The draws are float32 in either precision, so a seed gives the same rope
    under x64."""
    modes = jnp.arange(1, scene.bend_modes + 1, dtype=jnp.float32)
    amp = jax.random.uniform(k_amp, (scene.bend_modes,), jnp.float32, minval=-1.0,
                             maxval=1.0)
    amp = amp * scene.bend_amplitude / modes
    phase = jax.random.uniform(k_phase, (scene.bend_modes,), jnp.float32,
                               maxval=2 * math.pi)
    return modes, amp, phase


def start_heading(scene, key):
    """The start's heading ``theta0`` [rad] drawn from ``key`` (the third of its four
    split keys): uniform in ``±scene.heading_range``."""
    k_head = jax.random.split(key, 4)[2]
    h = scene.heading_range
    return jax.random.uniform(k_head, (), jnp.float32, minval=-h, maxval=h)


def centre_line(scene, rest, theta_fn):
    """The reference particles ``rest`` (N, 3) on the centre line with tangent angle
    ``theta_fn(s)`` [rad] starting at the origin: ``(px, py, pt, u, w)`` (each (N,)), the
    centre-line point [m] and tangent angle at each particle's ``s``, and its offsets ``u``
    across and ``w`` up. Arc length is kept, so the particles keep their count and
    order."""
    n = CENTRE_LINE_POINTS
    s = jnp.linspace(0.0, scene.rope_length, n)
    th = theta_fn(s)
    ds = scene.rope_length / (n - 1)
    mid = 0.5 * (th[1:] + th[:-1])
    cx = jnp.concatenate([jnp.zeros(1), jnp.cumsum(jnp.cos(mid) * ds)])
    cy = jnp.concatenate([jnp.zeros(1), jnp.cumsum(jnp.sin(mid) * ds)])
    sp, u, w = rest[:, 0], rest[:, 1], rest[:, 2]
    px, py, pt = jnp.interp(sp, s, cx), jnp.interp(sp, s, cy), jnp.interp(sp, s, th)
    return px, py, pt, u, w
