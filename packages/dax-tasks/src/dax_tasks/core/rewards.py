"""Distances between particle sets and the rewards built on them (pure JAX, SI units).

* :func:`l2_correspondence`: mean Euclidean distance [m] between particles with the same
  index, ``D = 1/N sum_i ||x_i - g_i||``. For objects whose particles keep their identity
  (rope, cloth).
* :func:`chamfer`: symmetric Chamfer distance [m], the mean of the two directed mean
  nearest-neighbour distances, ``D = (1/N sum_i min_j ||x_i - g_j|| + 1/M sum_j min_i
  ||x_i - g_j||) / 2``. For sets without correspondence (liquids); O(N M) memory.
* :func:`ground_truth_reward`: ``r_gt = exp(-lam D)`` in [0, 1], ``lam`` in 1/m.
* :func:`auxiliary_reward`: ``r_aux = exp(-min_i ||e - x_i||)`` with ``e`` the end-effector
  position and the distance in metres (so the implied scale is 1/m), in (0, 1].

Norms use ``sqrt(|v|^2 + eps)`` so gradients stay finite when two points coincide.
"""

from __future__ import annotations

import jax.numpy as jnp

#: Added under the square root of every norm so that gradients stay finite at 0 [m^2].
EPS = 1e-12


def _norm(v, axis=-1):
    return jnp.sqrt(jnp.sum(v * v, axis=axis) + EPS)


def l2_correspondence(x, g):
    """Mean distance [m] between corresponding points ``x`` (N, 3) and ``g`` (N, 3)."""
    if x.shape != g.shape:
        raise ValueError(f"index correspondence needs equal shapes, got {x.shape} and {g.shape}")
    return jnp.mean(_norm(x - g))


def chamfer(x, g):
    """Symmetric Chamfer distance [m] between point sets ``x`` (N, 3) and ``g`` (M, 3)."""
    d = _norm(x[:, None, :] - g[None, :, :])
    return 0.5 * (jnp.mean(jnp.min(d, axis=1)) + jnp.mean(jnp.min(d, axis=0)))


#: Distances by the name a :class:`~dax_tasks.TaskSpec` uses.
DISTANCES = {"l2": l2_correspondence, "chamfer": chamfer}


def ground_truth_reward(distance, lam):
    """``exp(-lam D)``: 1 at the goal, towards 0 far from it (``lam`` [1/m], D [m])."""
    return jnp.exp(-lam * distance)


def auxiliary_reward(end_effector, points):
    """``exp(-min_i ||end_effector - points_i||)``: 1 when touching the object."""
    return jnp.exp(-jnp.min(_norm(points - end_effector)))
