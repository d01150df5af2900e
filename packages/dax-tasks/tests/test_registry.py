"""Registry, spec validation and input checks that need no compiled step."""

import dataclasses

import numpy as np
import pytest

import dax_tasks
from dax_tasks.core import checks

NINE = {"pour_water", "pour_soup", "push_rope", "whip_rope", "fold_cloth1", "fold_cloth3",
        "fold_tshirt", "unfold_cloth1", "unfold_cloth3"}


def test_tasks_lists_the_nine_benchmark_names():
    assert set(dax_tasks.TASKS) == NINE and len(dax_tasks.TASKS) == 9, (
        f"expected {sorted(NINE)}, got {dax_tasks.TASKS}")


def test_unknown_name_error_lists_valid_names():
    with pytest.raises(ValueError) as err:
        dax_tasks.make("push_rop")
    for name in NINE:
        assert name in str(err.value), f"expected {name!r} in the message, got {err.value}"


def test_declared_but_unimplemented_task_says_what_is_available(monkeypatch):
    from types import MappingProxyType

    from dax_tasks.core import registry

    modules = dict(registry._MODULES)
    modules["fold_cloth1"] = ("dax_tasks.no_such_module", "ClothTask", "FOLD_CLOTH1")
    monkeypatch.setattr(registry, "_MODULES", MappingProxyType(modules))
    with pytest.raises(NotImplementedError, match="push_rope") as err:
        dax_tasks.make("fold_cloth1")
    assert "fold_cloth1" in str(err.value), f"expected the task name in {err.value}"
    assert "fold_cloth1" not in dax_tasks.available()


def test_unknown_override_is_refused():
    with pytest.raises(ValueError, match="horizn"):
        dax_tasks.make("push_rope", horizn=3)
    with pytest.raises(ValueError, match="lam"):  # lam moved to the params: still accepted
        dax_tasks.make("push_rope", lam=-1.0, **_small())


def _small():
    from conftest import small_overrides

    return small_overrides()


def test_param_overrides_change_the_default_params_not_the_spec():
    env = dax_tasks.make("push_rope", lam=5.0, aux_weight=1.0, **_small())
    assert float(env.default_params.lam) == 5.0 and float(env.default_params.aux_weight) == 1.0
    assert env.default_params.lam.dtype == np.float32
    assert not hasattr(env.spec, "lam"), "lam is a number of the params, not the spec"


def test_spec_is_hashable_and_validated():
    spec = dax_tasks.get_spec("push_rope")
    assert hash(spec) == hash(dataclasses.replace(spec))
    with pytest.raises(ValueError, match="contact_adjustment must be a bool"):
        dataclasses.replace(spec, contact_adjustment=1)
    assert spec.horizon == 6 and spec.action_dim == 6 and spec.action_kind == "push"
    with pytest.raises(ValueError, match="low <= high"):
        dataclasses.replace(spec, action_low=spec.action_high, action_high=spec.action_low)
    with pytest.raises(ValueError, match="unknown distance"):
        dataclasses.replace(spec, distance="emd")
    with pytest.raises(ValueError, match="horizon"):
        dataclasses.replace(spec, horizon=0)


def test_action_space_matches_spec_bounds(task):
    spec = task.spec
    assert task.action_space.shape == (6,)
    np.testing.assert_allclose(task.action_space.low, spec.action_low, rtol=1e-6)
    np.testing.assert_allclose(task.action_space.high, spec.action_high, rtol=1e-6)
    assert task.horizon == 6
    n = task.goal.shape[0]
    want = (len(range(0, n, spec.obs_stride)) * 3 + 3,)
    assert task.observation_space.shape == want, (
        f"expected obs shape {want}, got {task.observation_space.shape}")


def test_wrong_action_shape_is_a_clear_error(task, reset0):
    _, state = reset0
    with pytest.raises(ValueError, match=r"shape \(6,\), got \(5,\)"):
        task.step(state, np.zeros(5, np.float32))  # at trace time, inside jit
    with pytest.raises(ValueError, match=r"shape \(6,\), got \(5,\)"):
        checks.check_action(task, np.zeros(5))


def test_nan_action_is_a_clear_error_at_the_boundary(task):
    a = np.asarray(task.spec.action_low, np.float32)
    a[2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        checks.check_action(task, a)
    with pytest.raises(ValueError, match="not an array of numbers"):
        checks.check_action(task, ["a"] * 6)


def test_bad_keys_and_params_are_refused_at_the_boundary(task):
    with pytest.raises(ValueError, match=r"PRNGKey of shape \(2,\), got \(3,\)"):
        checks.check_key(np.zeros(3, np.uint32))
    params = task.default_params
    checks.check_params(task, params)  # the defaults are fine
    bad = {"goal": params.replace(goal=params.goal[:5]),
           "lam": params.replace(lam=np.nan),
           "aux_weight": params.replace(aux_weight=-1.0),
           "density": params.replace(physics=params.physics.replace(
               density=params.physics.density.at[0].set(0.0))),
           "unstable time step": params.replace(physics=params.physics.with_youngs_modulus(
               0, 5e6, 0.3)),
           "friction": params.replace(physics=params.physics.replace(
               friction=params.physics.friction[:1]))}
    for what, p in bad.items():
        with pytest.raises(ValueError, match=what):
            checks.check_params(task, p)


def test_task_without_expert_says_so():
    from dax_tasks.tasks import push_rope

    class NoExpert(push_rope.PushRope):
        expert = dax_tasks.Env.expert

    env = NoExpert(dataclasses.replace(push_rope.PUSH_ROPE, **_small()))
    assert not env.has_expert
    with pytest.raises(NotImplementedError, match="no scripted expert"):
        env.expert_action(None, "params")
