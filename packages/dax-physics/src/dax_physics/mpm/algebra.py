"""3x3 matrices per particle as nested lists of their nine (N,) components.

A matrix field ``M`` (N, 3, 3) becomes ``m[i][j]``, each a contiguous (N,) array
(:func:`mat3`), and the algebra below works on those components: XLA:CPU vectorises
elementwise maths on contiguous rows, not batched 3x3 products or strided component
access. :func:`stack3` turns components back into (N, 3, 3). Values keep the units of
the matrices they hold; every function is pure and differentiable.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._fusion import materialise, materialise_cotangent


@jax.custom_vjp
def mat3(M):
    """(N, 3, 3) -> nested list of its nine contiguous (N,) components, ``m[i][j]``. The
    reverse mode stacks the nine component cotangents with :func:`stack3`, which computes
    them together first."""
    rows = M.reshape(-1, 9).T
    return [[rows[3 * i + j] for j in range(3)] for i in range(3)]


def _mat3_fwd(M):
    return mat3(M), None


def _mat3_bwd(_, ct):
    return (stack3(ct),)


mat3.defvjp(_mat3_fwd, _mat3_bwd)


def stack3(m):
    """Inverse of :func:`mat3`: nested components -> (N, 3, 3). The nine are materialised
    as one tuple first: stacked directly, XLA fuses each component's whole computation into
    its own row of the stack and redoes their shared work (a polar decomposition, its
    adjoint) once per row."""
    return jnp.stack(materialise(flat(m))).T.reshape(-1, 3, 3)


def flat(m):
    """Nested components -> a tuple of the nine, row-major."""
    return tuple(m[i][j] for i in range(3) for j in range(3))


def soa(m):
    """Nested components -> one (9, N) array, row-major."""
    return jnp.stack(flat(m))


def unsoa(rows):
    """Nine row-major components (a (9, N) array or a tuple) -> nested components."""
    return [[rows[3 * i + j] for j in range(3)] for i in range(3)]


def materialised(m):
    """``m`` (nested components) with its nine components materialised together
    (:func:`dax_physics._fusion.materialise` of the tuple)."""
    return unsoa(materialise(flat(m)))


def cotangent_materialised(m):
    """``m`` (nested components) itself; in reverse mode the nine cotangents are
    materialised together (:func:`dax_physics._fusion.materialise_cotangent`)."""
    return unsoa(materialise_cotangent(flat(m)))


def mul(A, B):
    """The product ``A B``."""
    return [[A[i][0] * B[0][j] + A[i][1] * B[1][j] + A[i][2] * B[2][j] for j in range(3)]
            for i in range(3)]


def transpose(A):
    """``A^T``."""
    return [[A[j][i] for j in range(3)] for i in range(3)]


def plus_identity(H):
    """``I + H``."""
    return [[H[i][j] + 1.0 if i == j else H[i][j] for j in range(3)] for i in range(3)]


def det(A):
    """``det A`` (N,)."""
    return (A[0][0] * (A[1][1] * A[2][2] - A[1][2] * A[2][1])
            - A[0][1] * (A[1][0] * A[2][2] - A[1][2] * A[2][0])
            + A[0][2] * (A[1][0] * A[2][1] - A[1][1] * A[2][0]))


def det_minus_one(H):
    """``det(I + H) - 1`` (N,) without cancellation: ``tr H + i2(H) + det H`` (``i2`` the
    sum of the principal 2x2 minors), accurate in float32 when H is small."""
    tr = H[0][0] + H[1][1] + H[2][2]
    i2 = (H[0][0] * H[1][1] - H[0][1] * H[1][0] + H[0][0] * H[2][2] - H[0][2] * H[2][0]
          + H[1][1] * H[2][2] - H[1][2] * H[2][1])
    return tr + i2 + det(H)


def cofactor(A):
    """The cofactor matrix ``cof(A) = det(A) A^{-T}``."""
    return [[A[1][1] * A[2][2] - A[1][2] * A[2][1], A[1][2] * A[2][0] - A[1][0] * A[2][2],
             A[1][0] * A[2][1] - A[1][1] * A[2][0]],
            [A[0][2] * A[2][1] - A[0][1] * A[2][2], A[0][0] * A[2][2] - A[0][2] * A[2][0],
             A[0][1] * A[2][0] - A[0][0] * A[2][1]],
            [A[0][1] * A[1][2] - A[0][2] * A[1][1], A[0][2] * A[1][0] - A[0][0] * A[1][2],
             A[0][0] * A[1][1] - A[0][1] * A[1][0]]]
