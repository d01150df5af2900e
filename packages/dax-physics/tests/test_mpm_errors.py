"""MPM validation: bad input is refused with an error that names the problem."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from dax_physics import colliders, materials, mpm

DX = 0.05


def _cfg(**kw):
    args = dict(materials=(materials.water(), materials.tofu()), dx=DX, dt=1e-3,
                domain=(16, 16, 16))
    args.update(kw)
    return mpm.MPMConfig(**args)


def _points(n=4):
    return np.full((n, 3), 8 * DX) + DX * np.arange(n)[:, None] * np.array([1.0, 0.0, 0.0])


def test_nan_positions_are_refused():
    x = _points()
    x[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"positions contain NaN.*particle 2"):
        mpm.init_state(_cfg(), x)


def test_nan_velocities_are_refused():
    v = np.zeros((4, 3))
    v[1, 0] = np.inf
    with pytest.raises(ValueError, match="velocities contain NaN or inf"):
        mpm.init_state(_cfg(), _points(), v=v)


@pytest.mark.parametrize("kwargs, message", [
    (dict(x=np.zeros((4, 2))), r"positions must have shape \(N, 3\), got \(4, 2\)"),
    (dict(x=np.zeros(12)), r"positions must have shape \(N, 3\), got \(12,\)"),
    (dict(v=np.zeros((3, 3))), r"velocities must have shape \(4, 3\).*got \(3, 3\)"),
    (dict(vol=np.ones(5)), r"particle volumes must be a scalar or have shape \(4,\), got \(5,\)"),
    (dict(mat=np.zeros((4, 1), np.int32)), r"material ids must have shape \(4,\), got \(4, 1\)"),
    (dict(mat=np.zeros(4)), r"material ids must be integers"),
    (dict(colliders=colliders.ColliderState.create(np.zeros((2, 3)))),
     r"collider state has 2 rows but the config declares 0 colliders"),
])
def test_wrong_shapes_are_refused(kwargs, message):
    args = dict(x=_points())
    args.update(kwargs)
    x = args.pop("x")
    with pytest.raises(ValueError, match=message):
        mpm.init_state(_cfg(), x, **args)


@pytest.mark.parametrize("bad_id", [2, 7, -1])
def test_unknown_material_id_is_refused(bad_id):
    mat = np.array([0, 1, bad_id, 0], np.int32)
    with pytest.raises(ValueError, match=rf"unknown material id {bad_id}.*2 materials"):
        mpm.init_state(_cfg(), _points(), mat=mat)


def test_unknown_material_kind_is_refused():
    with pytest.raises(ValueError, match=r"unknown material kind 'gel'.*fluid, elastic, plastic"):
        materials.Material("gel", 1000.0, youngs_modulus=1e4)


@pytest.mark.parametrize("kwargs, message", [
    (dict(density=0.0), "density must be > 0"),
    (dict(youngs_modulus=-1.0), "youngs_modulus must be > 0"),
    (dict(poisson_ratio=0.5), r"poisson_ratio must lie in \(-1, 0.5\)"),
])
def test_invalid_material_parameters_are_refused(kwargs, message):
    args = dict(density=1000.0, youngs_modulus=1e4, poisson_ratio=0.3)
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        materials.Material("elastic", **args)


def test_material_table_entries_must_be_materials():
    with pytest.raises(TypeError, match="materials must be dax_physics.Material"):
        _cfg(materials=("water",))


@pytest.mark.parametrize("dt", [0.0, -1e-3, math.nan, math.inf])
def test_non_positive_dt_is_refused(dt):
    with pytest.raises(ValueError, match="dt must be a positive time step"):
        _cfg(dt=dt)


def test_non_positive_dx_is_refused():
    with pytest.raises(ValueError, match="dx must be a positive cell size"):
        _cfg(dx=0.0)


def test_particles_outside_the_domain_are_refused():
    x = _points()
    x[3] = [8 * DX, 8 * DX, 15.9 * DX]  # inside the domain but in the top wall layer
    with pytest.raises(ValueError, match=r"1 particles lie outside the simulation domain.*"
                                         r"particle 3"):
        mpm.init_state(_cfg(), x)
    x[3] = [-0.1, 0.2, 0.2]
    with pytest.raises(ValueError, match="outside the simulation domain"):
        mpm.init_state(_cfg(), x)


def test_unstable_dt_is_refused_with_the_largest_stable_dt():
    cfg = _cfg(max_speed=1.0)
    limit = mpm.max_stable_dt(cfg)
    # independent value: CFL 0.5 on the fastest (tofu P-) wave plus max_speed
    tofu = materials.tofu()
    mu, lam = tofu.lame
    expected = 0.5 * DX / (math.sqrt((lam + 2 * mu) / tofu.density) + 1.0)
    assert limit == pytest.approx(expected, rel=1e-12)
    _cfg(dt=limit, max_speed=1.0)  # the bound itself is accepted
    with pytest.raises(ValueError, match="unstable time step") as info:
        _cfg(dt=1.01 * limit, max_speed=1.0)
    assert re.search(rf"largest stable dt {limit:.3g} s", str(info.value)), (
        f"message does not name the largest stable dt {limit:.3g}: {info.value}")


@pytest.mark.parametrize("kwargs, message", [
    (dict(walls="bouncy"), "unknown wall mode 'bouncy'"),
    (dict(window=(2, 16, 16)), r"window \(2, 16, 16\) must be >= 4 cells"),
    (dict(window=(16, 16, 32)), "fit in domain"),
    (dict(domain=(16, 16)), "must have 3 entries"),
    (dict(colliders=("plane",)), "colliders must be ColliderSpec"),
    # a NaN max_speed made the stable bound NaN and every dt (here 1 s) passed
    (dict(max_speed=math.nan, dt=1.0), "max_speed must be a finite speed >= 0"),
    (dict(max_speed=math.inf), "max_speed must be a finite speed >= 0"),
    (dict(max_speed=-1.0), "max_speed must be a finite speed >= 0"),
    (dict(max_speed=-0.5 * DX / 1e-3), "max_speed must be a finite speed >= 0"),
    (dict(max_speed="fast"), "max_speed must be a real number"),
    (dict(gravity=(0.0, 0.0, math.nan)), "gravity must be 3 finite numbers"),
    (dict(gravity=(0.0, -9.81)), "gravity must be 3 finite numbers"),
    (dict(gravity=9.81), "gravity must be a sequence of numbers"),
    (dict(wall_cells=-1), "wall_cells must be an int >= 0"),
    (dict(wall_cells=1.5), "wall_cells must be an int >= 0"),
])
def test_invalid_configuration_is_refused(kwargs, message):
    with pytest.raises((ValueError, TypeError), match=message):
        _cfg(**kwargs)


@pytest.mark.parametrize("kwargs, message", [
    (dict(shape="torus"), "unknown collider shape 'torus'"),
    (dict(shape="box", dims=(0.1, 0.1)), "takes 3 dims, got 2"),
    (dict(shape="sphere", dims=(0.0,)), "dims must be > 0"),
    (dict(shape="plane", mode="glue"), "unknown contact mode 'glue'"),
    (dict(shape="plane", friction=-0.1), "friction coefficient must be >= 0"),
])
def test_invalid_collider_is_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        colliders.ColliderSpec(**kwargs)


def test_check_state_reports_a_non_finite_rollout():
    s = mpm.init_state(_cfg(), _points())
    mpm.check_state(s)  # a fresh state passes
    with pytest.raises(FloatingPointError, match="non-finite"):
        mpm.check_state(s.replace(finite=np.asarray(False)))


def test_negative_step_counts_are_refused():
    from dax_physics import checkpointed_scan

    cfg = _cfg()
    state = mpm.init_state(cfg, _points())
    with pytest.raises(ValueError, match="n_substeps must be an int >= 0, got -5"):
        mpm.rollout(cfg, cfg.params, state, -5)  # ran zero steps silently
    with pytest.raises(ValueError, match="length must be an int >= 0, got -1"):
        checkpointed_scan(lambda c, _: (c, None), 0.0, length=-1)


def test_a_particle_outrunning_the_time_step_is_flagged_unstable():
    """200 m/s with the default max_speed 0 and no walls: the particles fly 4 cells per
    substep out of the grid. The run used to keep ``finite`` true (positions ran on to 1e20
    m) and check_state reported particles that left the window; now ``finite`` turns false
    and check_state calls the run unstable."""
    cfg = _cfg(walls="none")
    limit = mpm.max_stable_speed(cfg)
    water, tofu = materials.water(), materials.tofu()
    assert limit == pytest.approx(DX / 1e-3 - max(water.wave_speed, tofu.wave_speed))
    state = mpm.init_state(cfg, _points(), v=[200.0, 0.0, 0.0])
    final = mpm.rollout(cfg, cfg.params, state, 20)
    assert np.all(np.isfinite(np.asarray(final.x))) and bool(final.escaped)
    assert not bool(final.finite), "a 200 m/s run kept its finite flag"
    with pytest.raises(FloatingPointError, match="unstable"):
        mpm.check_state(final)
    with pytest.raises(FloatingPointError, match=rf"unstable: a particle moved at 200 m/s, "
                                                 rf"faster than the {limit:.3g} m/s"):
        mpm.check_state(final, cfg)
    calm = mpm.rollout(cfg, cfg.params, mpm.init_state(cfg, _points(), v=[1.0, 0.0, 0.0]), 20)
    assert bool(calm.finite), "a 1 m/s run was flagged"
    mpm.check_state(calm, cfg)
