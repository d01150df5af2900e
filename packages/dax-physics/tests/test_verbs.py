"""The two solvers expose the same verbs with the same argument order, check their time
step at the same moments, and refuse bad input in the same words."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

import dax_physics.cloth as dc
from dax_physics import materials, mpm

VERBS = ("step", "rollout", "check_params", "check_state", "max_stable_dt", "grasp",
         "release")


def _cloth():
    cloth = dc.square_cloth(5, size=(0.1, 0.1), stretch=50.0)
    return dc.ClothConfig(dt=0.5 * dc.max_stable_dt(dc.ClothConfig(), cloth)), cloth


def _mpm():
    cfg = mpm.MPMConfig(materials=(materials.tofu(),), dx=0.05, dt=1e-3, domain=(12, 12, 12))
    x = np.stack(np.meshgrid(*[np.linspace(0.25, 0.35, 3)] * 3), -1).reshape(-1, 3)
    return cfg, mpm.init_state(cfg, x)


@pytest.mark.parametrize("verb", VERBS)
def test_both_solvers_expose_the_verb(verb):
    assert callable(getattr(mpm, verb, None)), f"dax_physics.mpm lacks {verb}"
    assert callable(getattr(dc, verb, None)), f"dax_physics.cloth lacks {verb}"


def test_rollouts_take_the_same_arguments_in_the_same_order():
    def params(fn):
        return [(p.name, p.kind) for p in inspect.signature(fn).parameters.values()]

    m, c = params(mpm.rollout), params(dc.rollout)
    assert [k for _, k in m[:4]] == [k for _, k in c[:4]] == [
        inspect.Parameter.POSITIONAL_OR_KEYWORD] * 4, (m, c)
    assert m[0][0] == c[0][0] == "cfg" and m[2][0] == c[2][0] == "state", (m, c)
    assert m[3][0] == c[3][0] == "n_substeps", (m, c)
    for name in ("segment", "unroll"):
        assert (name, inspect.Parameter.KEYWORD_ONLY) in m, f"mpm.rollout: {name}: {m}"
        assert (name, inspect.Parameter.KEYWORD_ONLY) in c, f"cloth.rollout: {name}: {c}"


def test_neither_rollout_is_jitted_at_definition():
    for module in (mpm, dc):
        assert inspect.isfunction(module.rollout), (
            f"{module.__name__}.rollout is {type(module.rollout)}, expected a plain function")


def test_both_refuse_a_negative_or_fractional_substep_count_in_the_same_words():
    cfg, state = _mpm()
    ccfg, cloth = _cloth()
    cstate = dc.ClothState.create(cloth)
    for n in (-1, 2.5, True):
        with pytest.raises(ValueError, match=rf"n_substeps must be an int >= 0, got {n!r}"):
            mpm.rollout(cfg, cfg.params, state, n)
        with pytest.raises(ValueError, match=rf"n_substeps must be an int >= 0, got {n!r}"):
            dc.rollout(ccfg, cloth, cstate, n)


def test_both_refuse_an_unstable_dt_in_check_params_naming_the_limit():
    cfg, _ = _mpm()
    ccfg, cloth = _cloth()
    params = cfg.params.with_youngs_modulus(0, 1e9, 0.3)
    limit = mpm.max_stable_dt(cfg, params)
    with pytest.raises(ValueError, match=rf"unstable time step: dt = .* exceeds the largest "
                                         rf"stable dt {limit:.3g} s"):
        mpm.check_params(cfg, params)
    stiff = dc.scale_moduli(cloth, stretch=100.0, shear=100.0, bend=100.0)
    limit = dc.max_stable_dt(ccfg, stiff)
    with pytest.raises(ValueError, match=rf"unstable time step: dt = .* exceeds the largest "
                                         rf"stable dt {limit:.3g} s"):
        dc.check_params(ccfg, stiff)
    mpm.check_params(cfg, cfg.params)  # the defaults pass
    dc.check_params(ccfg, cloth)


@pytest.mark.parametrize("field, value, message", [
    ("stiffness", -1.0, r"Cloth.stiffness must be finite and >= 0"),
    ("mass", 0.0, r"Cloth.mass must be finite and > 0"),
    ("damping", np.nan, r"Cloth.damping must be finite and >= 0"),
])
def test_cloth_check_params_refuses_bad_material_arrays(field, value, message):
    ccfg, cloth = _cloth()
    bad = cloth.replace(**{field: getattr(cloth, field).at[0].set(value)})
    with pytest.raises(ValueError, match=message):
        dc.check_params(ccfg, bad)


def test_cloth_check_params_refuses_mismatched_shapes():
    ccfg, cloth = _cloth()
    with pytest.raises(ValueError, match=r"Cloth.table_friction must have shape \(2,\)"):
        dc.check_params(ccfg, cloth.replace(table_friction=np.zeros(3, np.float32)))
