"""MPM validation: the longitudinal elastic wave speed in a thin bar is sqrt(E / rho).

A free-free bar of length L (24 cells, 2 x 2 cells cross-section, no gravity, no walls)
starts in its fundamental longitudinal mode, v_x = v0 cos(pi s / L) with s the distance
from one end. The mode's amplitude oscillates as cos(omega t) with omega = pi c / L, so two
successive zero crossings are half a period, L / c, apart: c = L / (t2 - t1).

The bar is thin and its sides are free, so the speed is the bar speed sqrt(E / rho) for
any Poisson ratio. With nu = 0 this equals the P-wave speed; with nu = 0.3 the P-wave speed
sqrt((lam + 2 mu) / rho) is 16 % higher, so a solver that propagated P-waves along the bar
would fail the 10 % tolerance. Running E and E / 4 with one compiled program checks that
the speed scales like sqrt(E).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dax_physics import materials, mpm, sampling

DX = 1.0 / 32
DT = 5e-4
LENGTH_CELLS = 24
RHO = 1000.0
E_REF = 1.0e5
V0 = 0.05  # [m/s], strain amplitude v0 / c = 0.5 %: linear regime
N_STEPS = 500


@functools.partial(jax.jit, static_argnums=(0, 3))
def _mode_amplitude(cfg, params, state, n):
    """Projection of v_x on the initial mode shape after each of ``n`` substeps."""
    shape = state.v[:, 0] / V0

    def body(s, _):
        s = mpm.step(cfg, params, s)
        return s, jnp.sum(shape * s.v[:, 0]) / jnp.sum(shape * shape)

    return jax.lax.scan(body, state, None, length=n)


@pytest.fixture(scope="module")
def bar():
    # The table declares nu = 0.3 (the faster P-wave) so dt is stable for every case run.
    mat = materials.Material("elastic", RHO, youngs_modulus=E_REF, poisson_ratio=0.3)
    cfg = mpm.MPMConfig(materials=(mat,), dx=DX, dt=DT, domain=(LENGTH_CELLS + 8, 8, 8),
                        walls="none", gravity=(0.0, 0.0, 0.0))
    a = 4 * DX
    x, vol = sampling.box((a, 3 * DX, 3 * DX), (a + LENGTH_CELLS * DX, 5 * DX, 5 * DX), DX,
                          ppc=8)
    v = np.zeros_like(x)
    v[:, 0] = V0 * np.cos(np.pi * (x[:, 0] - a) / (LENGTH_CELLS * DX))
    return cfg, mpm.init_state(cfg, x, v=v, vol=vol)


def _zero_crossings(t, a):
    i = np.nonzero(np.sign(a[1:]) != np.sign(a[:-1]))[0]
    return t[i] - a[i] * (t[i + 1] - t[i]) / (a[i + 1] - a[i])


@pytest.mark.parametrize("youngs_modulus, poisson_ratio",
                         [(E_REF, 0.0), (E_REF / 4, 0.0), (E_REF, 0.3)])
def test_bar_wave_speed_is_sqrt_e_over_rho(bar, youngs_modulus, poisson_ratio):
    cfg, state = bar
    params = cfg.params.with_youngs_modulus(0, youngs_modulus, poisson_ratio)
    final, amp = _mode_amplitude(cfg, params, state, N_STEPS)
    mpm.check_state(final)
    t = DT * np.arange(N_STEPS + 1)
    amp = np.concatenate([[V0], np.asarray(amp, np.float64)])
    zc = _zero_crossings(t, amp)
    assert len(zc) >= 2, f"the mode did not oscillate: zero crossings at {zc} s"
    c = LENGTH_CELLS * DX / (zc[1] - zc[0])
    expected = np.sqrt(youngs_modulus / RHO)
    nu = poisson_ratio
    p_wave = expected * np.sqrt((1 - nu) / ((1 + nu) * (1 - 2 * nu)))
    assert c == pytest.approx(expected, rel=0.10), (
        f"bar wave speed {c:.3f} m/s, expected sqrt(E/rho) = {expected:.3f} m/s "
        f"(the P-wave speed would be {p_wave:.3f} m/s)")
