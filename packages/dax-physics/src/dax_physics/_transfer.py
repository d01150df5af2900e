"""The two particle-grid transfers of MLS-MPM, with hand-written reverse modes.

Both act on a particle's 3x3x3 block of grid nodes ``base + o`` (o in {0, 1, 2}^3, in
row-major order where flattened: o = (i, j, k) at 9 i + 3 j + k) with quadratic B-spline
weights ``W_o = w[o_x, 0] w[o_y, 1] w[o_z, 2]`` built from the per-axis weights
``w`` (N, 3 offsets, 3 axes). The values they move are affine in the offset: a particle's
rows ``R`` (N, 4, C) stand for the node values
``U_o = R[:, 0] + o_x R[:, 1] + o_y R[:, 2] + o_z R[:, 3]`` (``e_o = (1, o)`` below).

* :func:`spread` (P2G): ``grid[base + o] += W_o U_o`` summed over particles, a
  scatter-add of nine z-rows per particle into the flattened (Wx, Wy, Wz, C) grid.
* :func:`collect` (G2P): ``S[:, d] = sum_o W_o e_o[d] grid[base + o]`` (N, 4, C): the
  weighted value (d = 0) and its first offset moments (d = 1..3).

For fixed weights the two are adjoint (<spread(R), g> = <R, collect(g)>), so each one's
reverse mode is mostly the other; the weights' cotangent is ``dW_o = sum_c G_oc U_oc`` with
the gathered block ``G`` and the affine rows on the other side, pushed through the
product ``W_o`` by hand. Autodiff of the same forward code would keep the (N, 27, C)
stencil values of every substep as residuals and reduce them over small axes (library
calls on XLA:CPU); here a substep keeps only its inputs (``w``, ``R``, the grid) and the
reverse pass re-gathers the block it needs.

Shapes: ``base`` (N, 3) int32 block corners in window cells, every block inside the grid
(the caller clamps and flags); ``w`` (N, 3, 3) dimensionless; the grid (Wx, Wy, Wz, C)
with fewer than 2^31 entries (int32 flat indices). The transfers are linear in ``R`` and
the grid and carry whatever units those have (momentum [kg m/s] and mass [kg] in P2G,
velocity [m/s] in G2P).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._fusion import materialise

# A particle's block is read and written as nine z-rows of 3 C contiguous floats of the
# flattened grid (channels last): one flat gather or scatter with (N, 9) starts and a
# 3 C-wide window. A (3, 3, 3, C) window on the 4-D grid would run its index arithmetic
# per element on XLA:CPU.
_ROW_SCATTER = jax.lax.ScatterDimensionNumbers(
    update_window_dims=(2,), inserted_window_dims=(), scatter_dims_to_operand_dims=(0,))
_ROW_GATHER = jax.lax.GatherDimensionNumbers(
    offset_dims=(2,), collapsed_slice_dims=(), start_index_map=(0,))
_IN_BOUNDS = jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS


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


def _row_starts(shape, base):
    """(N, 9, 1) flat offsets of the nine z-rows of each particle's block in a grid of
    ``shape`` (Wx, Wy, Wz, C), flattened (the grid must have fewer than 2^31 entries)."""
    if int(np.prod(shape)) >= 2 ** 31:
        raise ValueError(f"grid {tuple(shape)} has too many entries for int32 indices")
    _, Wy, Wz, C = shape
    flat = base[:, 0] * (Wy * Wz * C) + base[:, 1] * (Wz * C) + base[:, 2] * C
    rows = np.array([i * Wy * Wz * C + j * Wz * C for i in range(3) for j in range(3)],
                    np.int32)
    # materialised: the scatter and the gather of a substep share it (XLA merges the two
    # identical computations), and left fused it is recomputed per row inside each; the
    # trailing index axis is added after the barrier (with it, XLA writes the starts in a
    # transposed layout and copies them back)
    return materialise(flat[:, None] + rows)[:, :, None]


def _gather(grid, base):
    """(N, 3, 3, 3, C) block of each particle (the grid must already be materialised)."""
    n, c = base.shape[0], grid.shape[-1]
    G = jax.lax.gather(grid.reshape(-1), _row_starts(grid.shape, base), _ROW_GATHER,
                       (3 * c,), mode=_IN_BOUNDS)
    return G.reshape(n, 3, 3, 3, c)


def _along(T, wa, axis, moment=False):
    """``sum_k wa[:, k] T_k`` (or the moment ``sum_k k wa[:, k] T_k``) over the length-3
    ``axis`` of ``T`` (N, ..., 3, ..., C): one axis of a separable stencil contraction."""
    part = [jnp.take(T, k, axis=axis) for k in range(3)]
    wk = [wa[(slice(None), k) + (None,) * (part[0].ndim - 1)] for k in range(3)]
    if moment:
        return wk[1] * part[1] + 2.0 * (wk[2] * part[2])
    return wk[0] * part[0] + wk[1] * part[1] + wk[2] * part[2]


def _moments(G, w):
    """(N, 4, C): ``sum_o W_o e_o[d] G_o``, contracted one axis at a time (W_o is a
    product over the axes, e_o affine in o): z with ``w_z`` and ``k w_z``, then y, then x,
    about 90 multiply-adds per channel against 190 for the 27-term sums."""
    wx, wy, wz = (w[:, :, a] for a in range(3))
    Z0, Z1 = _along(G, wz, 3), _along(G, wz, 3, moment=True)    # (N, 3, 3, C)
    Y00, Y01, Y10 = _along(Z0, wy, 2), _along(Z0, wy, 2, moment=True), _along(Z1, wy, 2)
    # stacked on a leading axis, then moved to axis 1
    return jnp.moveaxis(materialise(jnp.stack(
        [_along(Y00, wx, 1), _along(Y00, wx, 1, moment=True),
         _along(Y01, wx, 1), _along(Y10, wx, 1)], axis=0)), 0, 1)


def _weight_cotangent(G, R, w):
    """Cotangent of the per-axis weights ``w`` (N, 3, 3) given ``dW_o = sum_c G_oc U_oc``
    (G the (N, 3, 3, 3, C) block, U from the rows ``R``), through W_o = w[o_x, 0] w[o_y, 1]
    w[o_z, 2] by the product rule, one axis at a time: dw_x[i] = sum_jk dW_ijk w_y[j]
    w_z[k], and so on. ``dW`` is materialised first: each of the nine outputs reads all of
    it, and fused into them its 27 channel sums would be redone for each."""
    c = G.shape[-1]
    U = _node_values(R)
    dW = materialise(sum(G[..., k] * U[..., k] for k in range(c)))  # (N, 3, 3, 3)
    wx, wy, wz = (w[:, :, a] for a in range(3))
    Wz = _along(dW, wz, 3)                     # (N, 3 x, 3 y): sum over z
    dwx = _along(Wz, wy, 2)                    # (N, 3): sum over y, z
    dwy = _along(Wz, wx, 1)                    # sum over x, z
    dwz = _along(_along(dW, wy, 2), wx, 1)     # sum over x, y
    return jnp.stack([dwx, dwy, dwz], axis=-1)  # (N, offset, axis)


def _spread(window, base, w, R):
    n, c = R.shape[0], R.shape[-1]
    shape = tuple(window) + (c,)
    vals = (stencil_weights(w).reshape(n, 3, 3, 3, 1) * _node_values(R)).reshape(n, 9, 3 * c)
    flat = jax.lax.scatter_add(jnp.zeros((int(np.prod(shape)),), R.dtype),
                               _row_starts(shape, base), vals, _ROW_SCATTER, mode=_IN_BOUNDS)
    return flat.reshape(shape)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def spread(window, base, w, R):
    """P2G: the (Wx, Wy, Wz, C) grid ``sum_p W_o U_o`` at the nodes ``base + o`` (see the
    module docstring). ``window``: static grid size; ``base`` (N, 3) int32 block corners,
    every block inside the grid (not checked here)."""
    return _spread(window, base, w, R)


def _spread_fwd(window, base, w, R):
    return _spread(window, base, w, R), (base, w, R)


def _spread_bwd(window, res, dgrid):
    # residuals materialised again: in a checkpointed reverse pass XLA otherwise
    # recomputes the weights from the positions inside every fused reader
    base, w, R = materialise(res)
    G = _gather(materialise(dgrid), base)
    return (np.zeros(base.shape, jax.dtypes.float0), _weight_cotangent(G, R, w),
            _moments(G, w))


spread.defvjp(_spread_fwd, _spread_bwd)


@jax.custom_vjp
def collect(grid, base, w):
    """G2P: ``S[:, d] = sum_o W_o e_o[d] grid[base + o]`` (N, 4, C) (module docstring).
    The grid should be materialised by the caller (XLA:CPU may otherwise fuse its whole
    computation into the 27 reads per particle)."""
    return _collect(grid, base, w)


def _collect(grid, base, w):
    # _moments' result is materialised: a dozen fusions read it (velocity, C, J, position)
    return _moments(_gather(grid, base), w)


def _collect_fwd(grid, base, w):
    return _collect(grid, base, w), (grid, base, w)


def _collect_bwd(res, dS):
    grid, base, w = materialise(res)  # see _spread_bwd
    dS = materialise(dS)  # built from many slices' cotangents: compute it once
    dgrid = _spread(grid.shape[:3], base, w, dS)
    dw = _weight_cotangent(_gather(grid, base), dS, w)
    return dgrid, np.zeros(base.shape, jax.dtypes.float0), dw


collect.defvjp(_collect_fwd, _collect_bwd)
