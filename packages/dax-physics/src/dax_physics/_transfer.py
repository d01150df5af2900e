"""The two particle-grid transfers of MLS-MPM, with hand-written reverse modes.

Both act on a particle's 3x3x3 block of grid nodes ``base + o`` (o in {0, 1, 2}^3, the
order of :data:`OFFSETS`) with quadratic B-spline weights ``W_o = w[o_x, 0] w[o_y, 1]
w[o_z, 2]`` built from the per-axis weights ``w`` (N, 3 offsets, 3 axes). The values they
move are affine in the offset: a particle's rows ``R`` (N, 4, C) stand for the node values
``U_o = R[:, 0] + o_x R[:, 1] + o_y R[:, 2] + o_z R[:, 3]`` (``e_o = (1, o)`` below).

* :func:`spread` (P2G): ``grid[base + o] += W_o U_o`` summed over particles, a windowed
  scatter-add into a (Wx, Wy, Wz, C) grid.
* :func:`collect` (G2P): ``S[:, d] = sum_o W_o e_o[d] grid[base + o]`` (N, 4, C): the
  weighted value (d = 0) and its first offset moments (d = 1..3).

For fixed weights the two are adjoint (<spread(R), g> = <R, collect(g)>), so each one's
reverse mode is mostly the other; the weights' cotangent is ``dW_o = sum_c G_oc U_oc`` with
the gathered block ``G`` and the affine rows on the other side, pushed through the
product ``W_o`` by hand. Autodiff of the same forward code saved the (N, 27, C) stencil
values of every substep as residuals and reduced them with slow small-axis reductions
(XLA:CPU); here a substep keeps only its inputs (``w``, ``R``, the grid) and the reverse
pass re-gathers the block it needs.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

OFFSETS = np.array([(i, j, k) for i in range(3) for j in range(3) for k in range(3)],
                   np.int32)
_SCATTER = jax.lax.ScatterDimensionNumbers(
    update_window_dims=(1, 2, 3, 4), inserted_window_dims=(),
    scatter_dims_to_operand_dims=(0, 1, 2))
_GATHER = jax.lax.GatherDimensionNumbers(
    offset_dims=(1, 2, 3, 4), collapsed_slice_dims=(), start_index_map=(0, 1, 2))
_IN_BOUNDS = jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS
#: Every float32 matmul in the solvers asks for full precision: on GPUs with TF32 (Ampere
#: and later) JAX's default lets a float32 dot round its inputs to a 10-bit mantissa, which
#: would turn the identity matmuls below from a copy into a 1e-3 relative error. On CPU it
#: changes nothing.
HIGHEST = jax.lax.Precision.HIGHEST


def mm(a, b):
    """``a @ b`` at full float32 precision (:data:`HIGHEST`): the one spelling of a matrix
    product in the solvers (``jnp.einsum`` calls pass ``precision=HIGHEST`` themselves)."""
    return jnp.matmul(a, b, precision=HIGHEST)


def stencil_weights(w):
    """(N, 27) weights ``W_o`` from the per-axis weights ``w`` (N, 3, 3), one fused loop."""
    n = w.shape[0]
    return (w[:, :, None, None, 0] * w[:, None, :, None, 1]
            * w[:, None, None, :, 2]).reshape(n, 27)


def _node_values(R):
    """(N, 3, 3, 3, C) affine node values ``U_o`` from the rows ``R`` (N, 4, C)."""
    o = jnp.arange(3, dtype=R.dtype)
    return (R[:, None, None, None, 0]
            + o[None, :, None, None, None] * R[:, None, None, None, 1]
            + o[None, None, :, None, None] * R[:, None, None, None, 2]
            + o[None, None, None, :, None] * R[:, None, None, None, 3])


def _gather(grid, base):
    """(N, 27, C) block of each particle (the grid must already be materialised)."""
    n, c = base.shape[0], grid.shape[-1]
    return jax.lax.gather(grid, base, _GATHER, (3, 3, 3, c), mode=_IN_BOUNDS).reshape(
        n, 27, c)


def _moments_sums(G, W):
    """(N, 4, C): ``sum_o W_o e_o[d] G_o`` as explicit 27-term sums: the forward G2P's
    form, whose moments fuse into their consumers (an einsum ran through a fused gather
    and transpose into a small-matrix kernel, the slowest part of the substep)."""
    wg = [W[:, q, None] * G[:, q] for q in range(27)]
    s0 = sum(wg)
    sa = [sum(int(OFFSETS[q, a]) * wg[q] for q in range(27) if OFFSETS[q, a])
          for a in range(3)]
    return jnp.stack([s0] + sa, axis=1)


def _moments(G, W):
    """(N, 4, C): ``sum_o W_o e_o[d] G_o`` in :func:`spread`'s reverse pass, as one plain
    matmul (N, 27 C) @ (27 C, 4 C)
    with the Kronecker product of the moment matrix E (27, 4) and the identity over
    channels: no transposed operand, one read of the block, and a materialised result
    (written as sums, each of the 16 moments re-read the block in its own fused loop)."""
    n, c = G.shape[0], G.shape[-1]
    wg = (W[:, :, None] * G).reshape(n, 27 * c)
    return mm(wg, jnp.asarray(_kron_moments(c), G.dtype)).reshape(n, 4, c)


@functools.cache
def _kron_moments(c):
    E = np.concatenate([np.ones((27, 1)), OFFSETS], axis=1)  # e_o = (1, o)
    return np.einsum("od,ce->ocde", E, np.eye(c)).reshape(27 * c, 4 * c).astype(np.float32)


def _weight_cotangent(G, R, w):
    """Cotangent of the per-axis weights ``w`` (N, 3, 3) given ``dW_o = sum_c G_oc U_oc``
    (U from the rows ``R``): through W_o = w[o_x, 0] w[o_y, 1] w[o_z, 2] by the product
    rule."""
    n = G.shape[0]
    U = _node_values(R).reshape(n, 27, -1)
    c = G.shape[-1]
    dW = [sum(G[:, q, k] * U[:, q, k] for k in range(c)) for q in range(27)]
    dw = [[0.0] * 3 for _ in range(3)]  # dw[offset][axis]
    for q, (i, j, k) in enumerate(OFFSETS):
        dw[i][0] = dw[i][0] + dW[q] * (w[:, j, 1] * w[:, k, 2])
        dw[j][1] = dw[j][1] + dW[q] * (w[:, i, 0] * w[:, k, 2])
        dw[k][2] = dw[k][2] + dW[q] * (w[:, i, 0] * w[:, j, 1])
    return jnp.stack([jnp.stack(row, axis=-1) for row in dw], axis=1)


def _spread(window, base, w, R):
    n, c = R.shape[0], R.shape[-1]
    vals = stencil_weights(w).reshape(n, 3, 3, 3, 1) * _node_values(R)
    return jax.lax.scatter_add(jnp.zeros(tuple(window) + (c,), R.dtype), base, vals,
                               _SCATTER, mode=_IN_BOUNDS)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def spread(window, base, w, R):
    """P2G: the (Wx, Wy, Wz, C) grid ``sum_p W_o U_o`` at the nodes ``base + o`` (see the
    module docstring). ``window``: static grid size; ``base`` (N, 3) int32 block corners,
    every block inside the grid (not checked here)."""
    return _spread(window, base, w, R)


def _spread_fwd(window, base, w, R):
    return _spread(window, base, w, R), (base, w, R)


def materialise(a):
    """``a`` computed into a buffer of its own before a stencil reads it. XLA:CPU otherwise
    fuses its whole computation into the consumer and redoes it for each of the 27 reads
    per particle; ``lax.optimization_barrier`` does not stop that on CPU, an identity
    matmul (a library call, never fused) does."""
    c = a.shape[-1]
    return mm(a.reshape(-1, c), jnp.eye(c, dtype=a.dtype)).reshape(a.shape)


def _spread_bwd(window, res, dgrid):
    base, w, R = res
    G = _gather(materialise(dgrid), base)
    dR = _moments(G, stencil_weights(w))
    return (np.zeros(base.shape, jax.dtypes.float0), _weight_cotangent(G, R, w), dR)


spread.defvjp(_spread_fwd, _spread_bwd)


@jax.custom_vjp
def collect(grid, base, w):
    """G2P: ``S[:, d] = sum_o W_o e_o[d] grid[base + o]`` (N, 4, C) (module docstring).
    The grid should be materialised by the caller (XLA:CPU may otherwise fuse its whole
    computation into the 27 reads per particle)."""
    return _collect(grid, base, w)


def _collect(grid, base, w):
    return _moments_sums(_gather(grid, base), stencil_weights(w))


def _collect_fwd(grid, base, w):
    return _collect(grid, base, w), (grid, base, w)


def _collect_bwd(res, dS):
    grid, base, w = res
    dS = materialise(dS)  # built from many slices' cotangents: compute it once
    dgrid = _spread(grid.shape[:3], base, w, dS)
    dw = _weight_cotangent(_gather(grid, base), dS, w)
    return dgrid, np.zeros(base.shape, jax.dtypes.float0), dw


collect.defvjp(_collect_fwd, _collect_bwd)
