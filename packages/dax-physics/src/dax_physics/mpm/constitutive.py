"""The constitutive models of the MPM particles (:mod:`dax_physics.materials` describes
them): the Kirchhoff stress of each kind, the polar rotation of the fixed-corotated
model, the plastic return map and the stored energy.

Matrices are component lists (:mod:`dax_physics.mpm.algebra`): ``Hm`` holds ``F - I``
(``b_e - I`` for plastic particles), ``Cm`` the APIC matrix [1/s]; stresses are in Pa.
Only the kinds present in the material table are computed.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

from .._fusion import materialise
from ..materials import MaterialParams
from . import algebra as alg
from .config import MPMConfig

#: Newton iterations of the polar decomposition used by the fixed-corotated model.
POLAR_ITERS = 6
#: Integer code of each material kind (:func:`particle_kinds`).
KIND_CODE = {"fluid": 0, "elastic": 1, "plastic": 2}


def particle_kinds(cfg: MPMConfig, mat):
    """Per-particle material kind code (N,) int32 (see :data:`KIND_CODE`) from the
    material ids ``mat`` (N,)."""
    return jnp.asarray([KIND_CODE[m.kind] for m in cfg.materials], jnp.int32)[mat]


@jax.custom_vjp
def polar_rotation(F):
    """Rotation R of the polar decomposition F = R S, by Newton iteration
    R <- (R + R^{-T}) / 2 (component-wise lists of (N,) arrays).

    Reverse mode is the closed-form differential of the polar factor, not the derivative
    of the iteration: with S = R^T F and a rotation R dR = R Omega, Omega skew with axial
    vector omega, (tr(S) I - S) omega = axial(R^T dF - dF^T R). Its transpose gives
    F_bar = R skew(c) with c = (tr(S) I - S)^{-1} b, b the axial vector of
    R^T R_bar - R_bar^T R (:func:`_polar_vjp`). It agrees with the derivative of the six
    Newton steps to the iteration's convergence (tested)."""
    return _polar_newton(F)


def _polar_newton(F):
    R = F
    for _ in range(POLAR_ITERS):
        cof = alg.cofactor(R)
        inv_det = materialise(1.0 / alg.det(R))
        R = [[0.5 * (R[i][j] + cof[i][j] * inv_det) for j in range(3)] for i in range(3)]
        # each iterate is materialised as one (9, N) array, and its 1 / det before it: a
        # stack alone is no barrier on XLA:CPU, and the last iterate's cofactors and
        # determinant would be redone inside each of the dozen loops that read R
        R = alg.unsoa(materialise(alg.soa(R)))
    return R


def _polar_fwd(F):
    # named: a substep's reverse pass keeps R rather than redo the iteration (see step)
    R = [[checkpoint_name(r, "mpm_polar") for r in row] for row in _polar_newton(F)]
    return R, (F, R)


def _polar_vjp(res, R_bar):
    F, R = res
    Rt = alg.transpose(R)
    S = alg.mul(Rt, F)
    S = [[0.5 * (S[i][j] + S[j][i]) for j in range(3)] for i in range(3)]
    B = alg.mul(Rt, R_bar)
    b = [B[2][1] - B[1][2], B[0][2] - B[2][0], B[1][0] - B[0][1]]
    tr = S[0][0] + S[1][1] + S[2][2]
    K = [[(tr if i == j else 0.0) - S[i][j] for j in range(3)] for i in range(3)]
    # K is symmetric with eigenvalues s_i + s_j > 0 (sums of two singular values of F):
    # c = K^{-1} b through the cofactor matrix
    cof = alg.cofactor(K)
    det = alg.det(K)
    det = jnp.where(jnp.abs(det) > 1e-30, det, 1e-30)
    c = [(cof[0][i] * b[0] + cof[1][i] * b[1] + cof[2][i] * b[2]) / det for i in range(3)]
    skew = [[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]]
    return (alg.mul(R, skew),)


polar_rotation.defvjp(_polar_fwd, _polar_vjp)


@jax.named_scope("stress")
def kirchhoff_stress(cfg: MPMConfig, params: MaterialParams, state, Hm, Cm):
    """Kirchhoff stress tau [Pa] (component lists of (N,)) of every particle of ``state``,
    from ``Hm`` = F - I (b_e - I for plastic particles) and the APIC matrix ``Cm``."""
    kinds = cfg.kinds
    mu = params.mu[state.mat]
    lam = params.lam[state.mat]
    zero = jnp.zeros_like(mu)
    tau = [[zero, zero, zero] for _ in range(3)]

    def add(a, b, sel=None):
        if sel is None:
            return [[a[i][j] + b[i][j] for j in range(3)] for i in range(3)]
        return [[a[i][j] + jnp.where(sel, b[i][j], 0.0) for j in range(3)] for i in range(3)]

    single = len(kinds) == 1
    mat_kind = particle_kinds(cfg, state.mat)

    def select(kind):
        return None if single else mat_kind == KIND_CODE[kind]

    if "fluid" in kinds:
        tau = add(tau, _fluid_stress(params, state, lam, zero, Cm), select("fluid"))
    if "elastic" in kinds:
        tau = add(tau, _elastic_stress(mu, lam, zero, Hm), select("elastic"))
    if "plastic" in kinds:
        tau = add(tau, _plastic_stress(mu, lam, zero, Hm), select("plastic"))
    return tau


def _fluid_stress(params: MaterialParams, state, lam, zero, Cm):
    """Weakly compressible fluid: ``K J (J - 1) I + J eta (C + C^T)``."""
    J = state.J
    p = lam * J * (J - 1.0)
    eta = params.viscosity[state.mat] * J
    return [[(p if i == j else zero) + eta * (Cm[i][j] + Cm[j][i]) for j in range(3)]
            for i in range(3)]


def _elastic_stress(mu, lam, zero, Hm):
    """Fixed-corotated: ``2 mu (F - R) F^T + lam J (J - 1) I``."""
    Fm = alg.plus_identity(Hm)
    R = polar_rotation(Fm)
    Jm1 = alg.det_minus_one(Hm)
    FmR = [[Fm[i][j] - R[i][j] for j in range(3)] for i in range(3)]
    P = alg.mul(FmR, alg.transpose(Fm))
    vol_term = lam * (1.0 + Jm1) * Jm1
    return [[2.0 * mu * P[i][j] + (vol_term if i == j else zero) for j in range(3)]
            for i in range(3)]


def _plastic_stress(mu, lam, zero, B):
    """Von Mises elasto-plastic: ``K/2 (J^2 - 1) I + mu dev(bbar_e)`` from ``B = b_e - I``
    (J^2 = det b_e; dev(b_e) = dev(B), so the stress has no cancellation)."""
    J2m1 = alg.det_minus_one(B)
    scale = jnp.maximum(1.0 + J2m1, 1e-12) ** (-1.0 / 3.0)
    trB3 = (B[0][0] + B[1][1] + B[2][2]) / 3.0
    kappa = lam + 2.0 / 3.0 * mu
    return [[mu * scale * (B[i][j] - (trB3 if i == j else 0.0))
             + (0.5 * kappa * J2m1 if i == j else zero) for j in range(3)]
            for i in range(3)]


def return_map(params: MaterialParams, mat, B):
    """Von Mises radial return on b_e = I + B (component lists of B, dimensionless): project
    the deviator of bbar_e = J^{-2/3} b_e onto |mu dev(bbar_e)| <= sqrt(2/3) sigma_y,
    keeping det; returns the new ``b_e - I``. Inside the yield surface B comes back
    unchanged, bit for bit (the projection's rounding would otherwise accumulate).

    Its shared scalars and 3x3 intermediates are materialised: fused, each of the nine
    outputs (and, in reverse mode, each of the nine adjoint components) would redo the
    whole map."""
    mu = params.mu[mat]
    sy = params.yield_stress[mat]
    scale = jnp.maximum(1.0 + alg.det_minus_one(B), 1e-12) ** (-1.0 / 3.0)
    trB3 = (B[0][0] + B[1][1] + B[2][2]) / 3.0
    scale, trB3 = materialise((scale, trB3))
    dev = [[scale * (B[i][j] - (trB3 if i == j else 0.0)) for j in range(3)]
           for i in range(3)]
    dev = alg.materialised(dev)
    tr3 = scale * (1.0 + trB3)
    norm = jnp.sqrt(sum(dev[i][j] * dev[i][j] for i in range(3) for j in range(3)) + 1e-20)
    s_norm = mu * norm
    limit = math.sqrt(2.0 / 3.0) * sy
    yielding = s_norm > limit
    # Both sides of the division are replaced where the particle does not yield: where
    # sigma_y = inf (every non-plastic particle of a mixture) limit / s_norm is inf, and
    # its unselected derivative inf * 0 would be NaN.
    factor = jnp.where(yielding, jnp.where(yielding, limit, 1.0)
                       / jnp.where(yielding, s_norm, 1.0), 1.0)
    factor, tr3 = materialise((factor, tr3))
    new_bbar = [[dev[i][j] * factor + (tr3 if i == j else 0.0) for j in range(3)]
                for i in range(3)]
    new_bbar = alg.materialised(new_bbar)
    # keep det(bbar) = 1 (isochoric plastic flow) by renormalising the new isochoric part
    d = jnp.maximum(alg.det(new_bbar), 1e-12)
    renorm = d ** (-1.0 / 3.0) / scale
    renorm = materialise(renorm)
    return [[jnp.where(yielding, new_bbar[i][j] * renorm - (1.0 if i == j else 0.0), B[i][j])
             for j in range(3)] for i in range(3)]


def strain_energy_density(cfg: MPMConfig, params: MaterialParams, state):
    """Stored energy per rest volume [J/m^3] per particle (N,): fixed-corotated for elastic,
    ``K/2 (J - 1)^2`` for fluids (the potential of their Kirchhoff pressure ``K J (J -
    1) = J psi'(J)``), neo-Hookean-like for plastic particles."""
    mu = params.mu[state.mat]
    lam = params.lam[state.mat]
    Hm = alg.mat3(state.H)
    Fm = alg.plus_identity(Hm)
    R = polar_rotation(Fm)
    fr = sum((Fm[i][j] - R[i][j]) ** 2 for i in range(3) for j in range(3))
    e_el = mu * fr + 0.5 * lam * alg.det_minus_one(Hm) ** 2
    e_fl = 0.5 * lam * (state.J - 1.0) ** 2
    J2 = jnp.maximum(1.0 + alg.det_minus_one(Hm), 1e-12)
    tr = (3.0 + Hm[0][0] + Hm[1][1] + Hm[2][2]) * J2 ** (-1.0 / 3.0)
    kappa = lam + 2.0 / 3.0 * mu
    e_pl = 0.5 * mu * (tr - 3.0) + 0.25 * kappa * (J2 - 1.0 - jnp.log(J2))
    kind = particle_kinds(cfg, state.mat)
    return jnp.where(kind == 0, e_fl, jnp.where(kind == 1, e_el, e_pl))
