"""Registry (the nine tasks, a task of one's own), spec validation and input checks that
need no compiled step."""

import dataclasses
import subprocess
import sys
from pathlib import Path

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


def test_importing_dax_tasks_registers_the_nine_without_importing_a_task_module():
    code = ("import sys, dax_tasks; print(','.join(dax_tasks.available())); "
            "print([m for m in sys.modules if m.startswith('dax_tasks.tasks.')]); "
            "env = dax_tasks.make('pour_water', cache_goal=False); "
            "print(type(env).__module__, type(env).__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    names, loaded, built = out.stdout.strip().splitlines()
    assert tuple(names.split(",")) == dax_tasks.TASKS, names
    assert loaded == "[]", f"expected no task module imported, got {loaded}"
    assert built == "dax_tasks.tasks.pour Pour", built


def test_the_core_names_no_task():
    core = Path(dax_tasks.core.__file__).parent
    for path in sorted(core.glob("*.py")):
        text = path.read_text()
        for task_word in ("dax_tasks.tasks.", "from ..tasks", "pour_water", "fold_cloth1"):
            assert task_word not in text, f"{path.name} names {task_word!r}"


@pytest.fixture
def registry(monkeypatch):
    """dax_tasks.core.registry with a copy of the registered tasks, restored afterwards."""
    from dax_tasks.core import registry

    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    return registry


def test_a_task_registers_by_object_or_by_module_attribute_string(registry):
    spec = dataclasses.replace(dax_tasks.get_spec("push_rope"), name="my_rope")
    here = f"{__name__}:MY_ROPE_SPEC"
    globals()["MY_ROPE_SPEC"] = spec
    dax_tasks.register("my_rope", "dax_tasks.tasks.push_rope:PushRope", here)
    dax_tasks.register("my_rope", "dax_tasks.tasks.push_rope:PushRope", here)  # the same: ok
    dax_tasks.register("my_rope_object", dax_tasks.env_class("push_rope"),
                       dataclasses.replace(spec, name="my_rope_object"))
    assert dax_tasks.available()[:9] == dax_tasks.TASKS
    assert dax_tasks.available()[9:] == ("my_rope", "my_rope_object")
    assert dax_tasks.get_spec("my_rope") is spec
    assert dax_tasks.env_class("my_rope") is dax_tasks.env_class("my_rope_object")
    assert dax_tasks.check_overrides("my_rope", {"horizon": 2}) == {"horizon": 2}
    with pytest.raises(ValueError, match="'my_rope' has no reference resolution"):
        dax_tasks.get_spec("my_rope", "reference")


def test_register_refuses_a_clash_and_bad_entries(registry):
    spec = dax_tasks.get_spec("push_rope")
    with pytest.raises(ValueError, match="'push_rope' is already registered.*replace=True"):
        dax_tasks.register("push_rope", "dax_tasks.tasks.pour:Pour", spec)
    with pytest.raises(ValueError, match="its spec is named 'push_rope'"):
        dax_tasks.register("other_rope", "dax_tasks.tasks.push_rope:PushRope", spec)
    with pytest.raises(ValueError, match="env must be an Env subclass or a 'module:attr"):
        dax_tasks.register("other_rope", "PushRope", spec)
    with pytest.raises(ValueError, match="spec must be a TaskSpec"):
        dax_tasks.register("other_rope", dax_tasks.Env, {"name": "other_rope"})
    with pytest.raises(ValueError, match="non-empty string"):
        dax_tasks.register("", dax_tasks.Env, spec)
    dax_tasks.register("push_rope", "dax_tasks.tasks.pour:Pour", "dax_tasks.tasks.pour:POUR_SOUP",
                       replace=True)
    assert dax_tasks.env_class("push_rope").__name__ == "Pour"


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
