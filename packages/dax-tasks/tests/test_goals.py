"""Goal files: lookup order (explicit path, cache, computed), atomic writes, clear errors."""

import json

import numpy as np
import pytest

import dax_tasks
from conftest import small_overrides
from dax_tasks.core import goals
from dax_tasks.tasks import push_rope


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("DAX_CACHE_DIR", str(tmp_path))
    return tmp_path / "goals"


def _spec(**extra):
    import dataclasses

    return dataclasses.replace(push_rope.PUSH_ROPE, **small_overrides(**extra))


@pytest.fixture(scope="module")
def env():
    return push_rope.PushRope(_spec())


@pytest.fixture(scope="module")
def goal(env):
    return env.canonical_goal()


def test_goal_is_computed_then_cached_with_provenance(cache, env):
    pts, prov = goals.resolve_goal(env)
    path = goals.goal_file(env.spec)
    assert path.parent == cache and path.is_file(), f"expected a cached goal at {path}"
    again, prov2 = goals.load_goal(path, env.spec, pts.shape[0])
    np.testing.assert_array_equal(pts, again)
    assert prov2["task"] == "push_rope" and prov2["fingerprint"] == env.spec.fingerprint()
    assert list(cache.glob("*.tmp")) == [], "a temporary file was left behind"


def test_cached_goal_is_used_instead_of_recomputing(cache, env):
    pts, _ = goals.resolve_goal(env)
    moved = pts + np.float32(0.01)
    goals.save_goal(goals.goal_file(env.spec), moved, goals.provenance(env.spec, "test"))
    got, prov = goals.resolve_goal(env)
    np.testing.assert_array_equal(got, moved)
    assert prov["method"] == "test"


def test_fingerprint_covers_every_spec_field_and_the_code(monkeypatch):
    import dataclasses

    from dax_tasks.core import spec as spec_module
    base = _spec()
    assert base.fingerprint() == _spec().fingerprint()
    finer = dataclasses.replace(base, scene=dataclasses.replace(base.scene, ppc=4))
    # the horizon counts too: Whip-Rope's goal is the throw over the whole horizon
    for other in (finer, dataclasses.replace(base, horizon=3),
                  dataclasses.replace(base, obs_stride=2)):
        assert base.fingerprint() != other.fingerprint(), other
    before = base.fingerprint()
    monkeypatch.setattr(spec_module, "code_digest", lambda module=None: "other code")
    assert base.fingerprint() != before, "the fingerprint ignores the source code"


def test_the_code_digest_reads_every_module_of_both_packages():
    """The tasks' own modules count (a changed fold or settling time changes results
    without changing the spec), not only dax_tasks.core."""
    from dax_tasks.core.spec import code_files

    names = {src.relative_to(package.parent).as_posix() for package, src in code_files()}
    for module in ("dax_tasks/tasks/cloth.py", "dax_tasks/tasks/_cloth.py",
                   "dax_tasks/core/spec.py", "dax_physics/cloth/sim.py"):
        assert module in names, module


def test_a_tasks_fingerprint_leaves_out_only_the_other_kinds_files():
    """A cloth task's fingerprint does not read the MPM solver nor the pour and rope
    modules, a pour's neither the cloth's nor the ropes', a rope's not the pour's; shared
    code (dax_tasks.core, the colliders, the checkpointed scan) counts for all, and a task
    whose scene is defined outside dax_tasks counts every file."""
    from dax_tasks.core.spec import code_files, scene_module

    def names(task):
        module = scene_module(dax_tasks.get_spec(task))
        return {src.relative_to(package.parent).as_posix()
                for package, src in code_files(module)}

    every = {src.relative_to(package.parent).as_posix() for package, src in code_files()}
    cloth, pour, push = names("fold_cloth1"), names("pour_water"), names("push_rope")
    shared = {"dax_tasks/core/env.py", "dax_tasks/core/spec.py", "dax_physics/scan.py",
              "dax_physics/colliders.py", "dax_tasks/viz/images.py"}
    assert shared <= cloth & pour & push
    assert {"dax_physics/cloth/sim.py", "dax_tasks/tasks/cloth.py"} <= cloth - pour - push
    assert {"dax_physics/mpm/substep.py"} <= (pour & push) - cloth
    assert "dax_tasks/tasks/pour.py" in pour - push - cloth
    assert "dax_tasks/tasks/_rope.py" in (push & names("whip_rope")) - pour - cloth
    assert names("unfold_cloth3") == cloth and names("pour_soup") == pour
    assert code_files("my_lab.tasks") == code_files() and len(every) > len(cloth | pour)



def _reached(task):
    """Files of dax_tasks and dax_physics (paths from the packages' parent) with a
    function called while building ``task``, resetting it, tracing its step's gradient
    with respect to the action (which traces the step) and its expert's action."""
    import sys
    from pathlib import Path

    import jax
    import jax.numpy as jnp

    import dax_physics

    roots = tuple(str(Path(m.__file__).resolve().parent) for m in (dax_tasks, dax_physics))
    files = set()  # every file a function was called from (the hook runs per call: cheap)

    def profile(frame, event, arg):
        if event == "call":
            files.add(frame.f_code.co_filename)

    sys.setprofile(profile)
    try:  # traced, never lowered or run: shapes stand in for the arrays
        env = dax_tasks.make(task)
        params = env.default_params
        _, state = jax.eval_shape(env.reset, jax.random.PRNGKey(0), params)

        def reward(action, state):
            return env.step(state, action, params)[2]

        jax.eval_shape(jax.grad(reward), jnp.zeros(env.spec.action_dim), state)
        jax.eval_shape(env.expert_action, state, params)
    finally:
        sys.setprofile(None)
    return {Path(name).relative_to(Path(root).parent).as_posix()
            for name in files for root in roots if name.startswith(root)}


@pytest.mark.parametrize("task", ["fold_cloth1", "pour_water", "push_rope", "whip_rope"])
def test_a_tasks_program_reaches_only_the_files_its_fingerprint_reads(task):
    """What makes leaving files out of a fingerprint safe: the task's program calls no
    function of a file its fingerprint does not digest (one task per scene module)."""
    from dax_tasks.core.spec import code_files, scene_module

    reached = _reached(task)
    digested = {src.relative_to(package.parent).as_posix()
                for package, src in code_files(scene_module(dax_tasks.get_spec(task)))}
    assert "dax_tasks/core/env.py" in reached  # (the profile saw the program)
    assert reached <= digested, sorted(reached - digested)


def test_a_kinds_own_modules_import_nothing_its_fingerprint_leaves_out():
    """The profile sees calls, not a constant read across kinds: so a file that only
    some tasks reach (``ONLY_FOR``) imports, by name or as a module, nothing from a file
    those tasks' fingerprints leave out."""
    import ast
    import importlib
    import inspect
    from pathlib import Path

    from dax_tasks.core.spec import ONLY_FOR, code_files

    for kind in sorted({m for modules in ONLY_FOR.values() for m in modules}):
        files = code_files(kind)
        digested = {src.resolve() for _, src in files}
        roots = {package.resolve() for package, _ in files}
        for package, src in files:
            name = src.relative_to(package.parent).with_suffix("").as_posix()
            if not name.startswith(tuple(p.rstrip("/").removesuffix(".py")
                                         for p in ONLY_FOR)):
                continue  # shared: the profile test covers it
            here = name.replace("/", ".").removesuffix(".__init__")
            parent = here if src.name == "__init__.py" else here.rsplit(".", 1)[0]
            for node in ast.walk(ast.parse(src.read_bytes())):
                if isinstance(node, ast.ImportFrom):
                    base = importlib.util.resolve_name("." * node.level + (node.module or ""),
                                                       parent)
                    if not base.startswith(("dax_tasks", "dax_physics")):
                        continue  # (another package: not digested by any task)
                    module = importlib.import_module(base)
                    found = [getattr(module, a.name, None)
                             or importlib.import_module(f"{base}.{a.name}")
                             for a in node.names]
                elif isinstance(node, ast.Import):
                    found = [importlib.import_module(a.name) for a in node.names
                             if a.name.startswith(("dax_tasks", "dax_physics"))]
                else:
                    continue
                for obj in found:
                    where = (obj if inspect.ismodule(obj) else inspect.getmodule(obj)
                             or module)
                    path = Path(getattr(where, "__file__", None) or "").resolve()
                    if any(path.is_relative_to(root) for root in roots):
                        assert path in digested, f"{kind}: {name} imports {obj!r} from {path}"


def test_the_code_digest_follows_the_program_not_its_comments_or_docstrings():
    from dax_tasks.core.spec import _program_text

    base = _program_text(b'"""Module."""\nX = 1\n\n\ndef f(a):\n    """Doc."""\n    return a + X\n')
    reworded = _program_text(b'"""Other words."""\nX = 1  # a comment\n\ndef f(a):\n'
                             b'    """New doc."""\n    return a + X\n')
    changed = _program_text(b'"""Module."""\nX = 1\n\n\ndef f(a):\n    """Doc."""\n'
                            b'    return a - X\n')
    assert base == reworded, "a docstring, comment or layout edit changed the digest"
    assert base != changed, "a changed program kept its digest"


def test_the_program_text_is_the_same_on_every_python():
    """``ast.dump`` of one source differs between 3.11, 3.12 (``type_params=[]``) and 3.13
    (empty fields dropped); the program text does not: this is what 3.10.13, 3.11.7,
    3.12.1 and 3.13.0 all give (checked under each when it was written)."""
    from dax_tasks.core.spec import _program_text

    source = (b'class A:\n    """Doc."""\n    def f(self, x=1.5, *, k=None):\n'
              b'        return g(x, k=k)[0]\n')
    assert _program_text(source) == (
        "Module(body=[ClassDef(name='A', body=[FunctionDef(name='f', args=arguments("
        "args=[arg(arg='self'), arg(arg='x')], kwonlyargs=[arg(arg='k')], "
        "kw_defaults=[Constant()], defaults=[Constant(value=1.5)]), body=[Return("
        "value=Subscript(value=Call(func=Name(id='g', ctx=Load()), args=[Name(id='x', "
        "ctx=Load())], keywords=[keyword(arg='k', value=Name(id='k', ctx=Load()))]), "
        "slice=Constant(value=0), ctx=Load()))])])])")


def test_spec_round_trips_through_json_without_module_paths():
    import json as _json

    for name in dax_tasks.TASKS:
        spec = dax_tasks.get_spec(name)
        data = _json.loads(_json.dumps(spec.to_json()))
        assert "dax_tasks" not in _json.dumps(data), f"{name}: a module path in {data}"
        back = dax_tasks.spec_from_json(data)
        assert back == spec and back.fingerprint() == spec.fingerprint(), name
    data = _spec().to_json()
    with pytest.raises(ValueError, match="pass its class"):
        dax_tasks.TaskSpec.from_json(data)
    data["scene"]["dx_typo"] = 1.0
    with pytest.raises(ValueError, match="dx_typo"):
        dax_tasks.spec_from_json(data)


def test_make_uses_an_explicit_goal_path(cache, tmp_path, goal):
    spec = _spec()
    pts = goal + np.float32(0.02)
    path = goals.save_goal(tmp_path / "mine.npz", pts, goals.provenance(spec, "by hand"))
    env = dax_tasks.make("push_rope", goal_path=path, **small_overrides())
    np.testing.assert_allclose(np.asarray(env.default_params.goal), pts)
    assert env.goal_provenance["method"] == "by hand"


@pytest.mark.parametrize("damage", ["truncate", "garbage", "wrong_shape", "missing"])
def test_bad_goal_file_is_refused_with_the_file_named(tmp_path, damage, goal):
    spec = _spec()
    path = tmp_path / "goal.npz"
    good = goal
    goals.save_goal(path, good, goals.provenance(spec, "test"))
    if damage == "truncate":
        path.write_bytes(path.read_bytes()[:100])
    elif damage == "garbage":
        path.write_bytes(b"not a zip file at all")
    elif damage == "wrong_shape":
        goals.save_goal(path, good[:10], goals.provenance(spec, "test"))
    else:
        path.unlink()
    with pytest.raises(goals.GoalFileError) as err:
        goals.load_goal(path, spec, n_points=good.shape[0])
    assert str(path) in str(err.value), f"error does not name the file: {err.value}"


def test_goal_of_another_task_is_refused(tmp_path, goal):
    spec = _spec()
    prov = goals.provenance(spec, "test")
    prov["task"] = "fold_cloth1"
    path = goals.save_goal(tmp_path / "g.npz", goal, prov)
    with pytest.raises(goals.GoalFileError, match="fold_cloth1"):
        goals.load_goal(path, spec)


def test_corrupted_cache_file_is_regenerated_with_a_warning(cache, env):
    path = goals.goal_file(env.spec)
    path.parent.mkdir(parents=True)
    path.write_bytes(b"\x00" * 10)
    with pytest.warns(UserWarning, match="regenerating"):
        pts, _ = goals.resolve_goal(env)
    np.testing.assert_array_equal(goals.load_goal(path)[0], pts)


def test_goal_files_hold_no_pickled_objects(cache, env):
    goals.resolve_goal(env)
    with np.load(goals.goal_file(env.spec), allow_pickle=False) as data:
        assert sorted(data.files) == ["points", "provenance"]
        json.loads(str(data["provenance"]))
