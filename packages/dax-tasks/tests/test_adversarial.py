"""Bad input at dax-tasks' boundary (issue 17): each case a careful user tried, refused in
one clear ``ValueError`` / ``GoalFileError`` naming the problem, or handled as documented.

* goal files: another spec's goal (same point count), a ``.npy`` array, malformed
  provenance, complex points, a Pour-Water goal of 5 points;
* ``make`` overrides of the wrong type;
* a finite float64 action beyond float32's range;
* float64 (``jax_enable_x64``): the same seed gives the same initial state as float32;
* the one-writer lock of :mod:`dax_tasks.io`.
"""

import dataclasses
import json
import math
import threading
import time

import jax
import numpy as np
import pytest

import dax_tasks
from conftest import small_overrides
from dax_tasks import io
from dax_tasks.core import checks, goals
from dax_tasks.tasks.cloth import ClothScene

CHEAP_CLOTH = dict(scene=dataclasses.replace(dax_tasks.get_spec("fold_cloth1").scene, n=6,
                                             settle_substeps=200), substeps=400)


def _bare(name, **overrides):
    """Task ``name`` without computing its goal (a zero goal of the right size)."""
    spec = dataclasses.replace(dax_tasks.get_spec(name), **overrides)
    env = dax_tasks.env_class(name)(spec)
    return env.with_goal(np.zeros((env.n_object_points, 3), np.float32))


# ----------------------------------------------------------------------------- goals

@pytest.fixture(scope="module")
def rope_goal():
    env = _bare("push_rope", **small_overrides())
    return env.spec, np.asarray(env.canonical_goal())


def test_goal_made_for_another_spec_is_refused_unless_allowed(tmp_path, rope_goal):
    spec, pts = rope_goal
    other = dataclasses.replace(spec, substeps=60)  # same particles, another program
    path = goals.save_goal(tmp_path / "other.npz", pts, goals.provenance(other, "by hand"))
    with pytest.raises(goals.GoalFileError) as err:
        goals.load_goal(path, spec, pts.shape[0])
    msg = str(err.value)
    assert str(path) in msg and other.fingerprint() in msg and spec.fingerprint() in msg, msg
    assert "allow_goal_mismatch" in msg, msg
    with pytest.raises(goals.GoalFileError, match="made for fingerprint"):
        dax_tasks.make("push_rope", goal_path=path, **small_overrides())
    with pytest.warns(UserWarning, match="mismatched goal"):
        env = dax_tasks.make("push_rope", goal_path=path, allow_goal_mismatch=True,
                             **small_overrides())
    np.testing.assert_array_equal(env.goal, pts)
    no_fp = {k: v for k, v in goals.provenance(spec, "by hand").items() if k != "fingerprint"}
    path = goals.save_goal(tmp_path / "nofp.npz", pts, no_fp)
    with pytest.raises(goals.GoalFileError, match="names no fingerprint"):
        goals.load_goal(path, spec)


def test_npy_array_is_not_a_goal_file(tmp_path, rope_goal):
    spec, pts = rope_goal
    path = tmp_path / "goal.npy"
    np.save(path, pts)
    with pytest.raises(goals.GoalFileError, match=r"goal\.npy: not a goal file: a single"):
        goals.load_goal(path, spec)


@pytest.mark.parametrize("provenance", [np.asarray("[1, 2]"), np.asarray("not json"),
                                        np.arange(3.0), np.asarray('"a string"')])
def test_malformed_provenance_is_named(tmp_path, rope_goal, provenance):
    spec, pts = rope_goal
    path = tmp_path / "goal.npz"
    np.savez(path, points=pts, provenance=provenance)
    with pytest.raises(goals.GoalFileError, match="'provenance' must be a JSON object"):
        goals.load_goal(path, spec)


def test_complex_points_are_refused(tmp_path, rope_goal):
    spec, pts = rope_goal
    path = tmp_path / "goal.npz"
    np.savez(path, points=pts + 1j, provenance=np.asarray(
        json.dumps(goals.provenance(spec, "complex"))))
    with pytest.raises(goals.GoalFileError, match="must be real numbers, got dtype complex"):
        goals.load_goal(path, spec)


def test_pour_water_goal_must_have_a_point_per_particle(tmp_path):
    env = _bare("pour_water")
    assert env.n_goal_points == env.n_object_points
    path = goals.save_goal(tmp_path / "five.npz", np.zeros((5, 3)),
                           goals.provenance(env.spec, "five points"))
    with pytest.raises(goals.GoalFileError, match="goal has 5 points"):
        goals.resolve_goal(env, path)
    with pytest.raises(ValueError, match="the goal has 5 points"):
        env.with_goal(np.zeros((5, 3)))


# ----------------------------------------------------------------------------- overrides

@pytest.mark.parametrize("overrides, message", [
    (dict(scene=ClothScene(n=6.5)), "scene.n must be an integer, got float 6.5"),
    (dict(scene=ClothScene(rotation_range=math.inf)), "scene.rotation_range must be a finite"),
    (dict(action_low=5), "action_low must be a list of 6 entries"),
    (dict(action_low=(0.0, 0.0)), "action_low must have 6 entries"),
    (dict(action_low=(0, 0, 0, 0, 0, "x")), r"action_low\[5\] must be a number"),
    (dict(horizon=True), "horizon must be an integer, got bool True"),
    (dict(substeps=160.0), "substeps must be an integer"),
    (dict(contact_adjustment=1), "contact_adjustment must be true or false"),
    (dict(lam="abc"), "lam must be a number, got str 'abc'"),
    (dict(aux_weight=True), "aux_weight must be a number"),
    (dict(scene="square"), "scene must be a ClothScene"),
])
def test_overrides_of_the_wrong_type_are_refused_before_anything_is_built(overrides, message,
                                                                           monkeypatch):
    def boom(*a, **k):
        raise AssertionError("the task was built from a bad override")

    monkeypatch.setattr(dax_tasks.env_class("fold_cloth1"), "__init__", boom)
    with pytest.raises(ValueError, match=message):
        dax_tasks.make("fold_cloth1", **overrides)


def test_checked_overrides_keep_numbers_as_the_fields_declare():
    scene = dataclasses.replace(dax_tasks.get_spec("fold_cloth1").scene, size=1)
    out = dax_tasks.check_overrides("fold_cloth1", dict(scene=scene, horizon=2, lam=5,
                                                        action_low=[0, 0, 0, 0, 0, 0]))
    assert out["horizon"] == 2 and out["lam"] == 5
    assert out["action_low"] == (0.0,) * 6 and isinstance(out["action_low"], tuple)


# ----------------------------------------------------------------------------- actions

def test_finite_action_beyond_float32_is_clipped_not_made_inf():
    env = _bare("fold_cloth1", **CHEAP_CLOTH)
    big = np.full(6, 1e39)
    a = checks.check_action(env, big)  # was refused as "NaN or inf" after a float32 cast
    np.testing.assert_array_equal(a, np.asarray(env.spec.action_high, np.float32))
    with pytest.raises(ValueError,
                       match=r"not an array of numbers \(real ones; dtype complex128\)"):
        checks.check_action(env, np.full(6, 1 + 1j))
    _, state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    with jax.enable_x64(True):  # a float64 action reaching the pure step of a float32 state
        step = jax.jit(env.step)
        _, s_big, _, _, info = step(state, big)
        _, s_high, _, _, _ = step(state, np.asarray(env.spec.action_high))
    assert bool(info["finite"]), "a finite 1e39 action marked the episode non-finite"
    assert s_big.physics.x.dtype == np.float32
    np.testing.assert_array_equal(np.asarray(s_big.physics.x), np.asarray(s_high.physics.x))


# ----------------------------------------------------------------------------- float64

@pytest.mark.parametrize("name", ["pour_water", "push_rope", "whip_rope", "fold_cloth1"])
def test_float64_reset_gives_the_float32_initial_state(name):
    env = _bare(name)
    key = jax.random.PRNGKey(7)
    _, s32 = jax.jit(env.reset)(key)
    with jax.enable_x64(True):
        _, s64 = jax.jit(env.reset)(key)
    pairs = zip(jax.tree_util.tree_flatten_with_path(s32.physics)[0],
                jax.tree_util.tree_leaves(s64.physics), strict=True)
    for (path, a), b in pairs:
        where = f"{name}: physics{jax.tree_util.keystr(path)}"
        if np.issubdtype(a.dtype, np.floating):
            assert b.dtype == np.float64, f"{where} is {b.dtype} under jax_enable_x64"
            np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-6, atol=1e-6,
                                       err_msg=where)
        else:
            np.testing.assert_array_equal(np.asarray(b), np.asarray(a), err_msg=where)


def test_float64_step_stays_float64():
    env = _bare("fold_cloth1", **CHEAP_CLOTH)
    with jax.enable_x64(True):
        _, state = jax.jit(env.reset)(jax.random.PRNGKey(0))
        action = jax.jit(env.expert_action)(state)
        _, state, reward, _, info = jax.jit(env.step)(state, action)
    assert action.dtype == state.physics.x.dtype == reward.dtype == np.float64
    assert bool(info["finite"])


# ----------------------------------------------------------------------------- the lock

def test_second_writer_is_refused_naming_the_holder(tmp_path):
    target = tmp_path / "data.h5"
    with io.exclusive(target, program="first writer") as lock:
        assert lock == io.lock_path(target) and lock.is_file()
        with pytest.raises(io.FileLockedError) as err, io.exclusive(target):
            pass
        msg = str(err.value)
        assert msg.startswith(f"{target}: another process is writing it"), msg
        assert "first writer" in msg and f"pid {__import__('os').getpid()}" in msg, msg
    assert not lock.exists(), "the lock file was left behind"
    with io.exclusive(target):  # free again
        pass


def test_a_waiting_writer_gets_the_lock_when_the_holder_finishes(tmp_path):
    target = tmp_path / "data.h5"
    held = threading.Event()

    def hold():
        with io.exclusive(target):
            held.set()
            time.sleep(0.5)

    thread = threading.Thread(target=hold)
    thread.start()
    held.wait(5)
    t0 = time.monotonic()
    with pytest.raises(io.FileLockedError, match=r"waited 0.1 s"), io.exclusive(target,
                                                                                   wait=0.1):
        pass
    with io.exclusive(target, wait=10):
        assert time.monotonic() - t0 >= 0.3
    thread.join()


def test_lock_in_an_unwritable_place_is_an_os_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(OSError), io.exclusive(blocker / "data.h5"):
        pass


def test_a_schedule_of_records_takes_any_number_of_them():
    scene = dax_tasks.get_spec("whip_rope").scene
    one = dataclasses.replace(scene, throw=((0, 8, -0.015, 0.0, 0.005),))
    assert dax_tasks.check_overrides("whip_rope", dict(scene=one))["scene"] is one
    bad = dataclasses.replace(scene, throw=((0, 8.5, -0.015, 0.0, 0.005),))
    with pytest.raises(ValueError, match=r"scene.throw\[0\]\[1\] must be an integer"):
        dax_tasks.check_overrides("whip_rope", dict(scene=bad))


# ----------------------------------------------------------------------------- issue 38
# one writer per real file, waiting with a timeout, the env boundary, sizes before work

@pytest.mark.parametrize("first", ["target", "link"])
def test_a_link_and_its_target_share_one_lock_in_either_order(tmp_path, first):
    target = tmp_path / "real" / "data.h5"
    target.parent.mkdir()
    link = tmp_path / "link.h5"
    link.symlink_to(target)
    a, b = (target, link) if first == "target" else (link, target)
    with io.exclusive(a, program="first writer") as lock:
        assert lock == target.parent / ".data.h5.lock" == io.lock_path(b)
        with pytest.raises(io.FileLockedError, match="first writer"), io.exclusive(b):
            pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.h5", "real"]


def test_an_atomic_write_through_a_link_updates_its_target_and_keeps_the_link(tmp_path):
    target = tmp_path / "real" / "data.txt"
    target.parent.mkdir()
    target.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(target)
    io.atomic_write(link, "new")
    assert link.is_symlink() and target.read_text() == "new" == link.read_text()
    with io.atomic_path(link, copy_existing=True) as tmp:
        assert tmp.parent == target.parent and tmp.read_text() == "new"
        tmp.write_text("newer")
    assert link.is_symlink() and target.read_text() == "newer"
    dangling = tmp_path / "dangling.txt"
    dangling.symlink_to(tmp_path / "real" / "made.txt")
    io.atomic_write(dangling, "made")
    assert dangling.is_symlink() and (tmp_path / "real" / "made.txt").read_text() == "made"
    assert sorted(p.name for p in target.parent.iterdir()) == ["data.txt", "made.txt"]
    assert io.temporaries(link) == io.temporaries(target) == []


def test_a_link_loop_is_refused(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.symlink_to(b)
    b.symlink_to(a)
    with pytest.raises(ValueError, match="symbolic links form a loop"):
        io.atomic_write(a, "x")
    with pytest.raises(ValueError, match="symbolic links form a loop"), io.exclusive(b):
        pass


def test_a_waiting_writer_says_once_who_holds_the_lock_and_gives_up(tmp_path):
    target = tmp_path / "data.h5"
    said = []
    with io.exclusive(target, program="first writer"):
        with pytest.raises(io.FileLockedError, match=r"first writer.*waited 0.3 s"), \
                io.exclusive(target, wait=0.3, notify=said.append, poll=0.05):
            pass
    assert len(said) == 1 and said[0].startswith(f"{target}: waiting for another process")
    assert "first writer" in said[0] and "up to 0.3 s" in said[0], said


def test_a_stopped_holder_is_named_as_stopped(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    target = tmp_path / "data.h5"
    code = ("import sys, time\nfrom dax_tasks import io\n"
            "with io.exclusive(sys.argv[1], program='holder'):\n"
            "    print('held', flush=True)\n    time.sleep(120)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(target)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        os.kill(proc.pid, signal.SIGSTOP)
        with pytest.raises(io.FileLockedError, match=rf"pid {proc.pid} \(stopped\) on "), \
                io.exclusive(target, wait=0.2, notify=None):
            pass
    finally:
        proc.kill()
        proc.wait()


@pytest.mark.parametrize("action, dtype", [([0.1 + 5j] * 6, "complex"), (["a"] * 6, "<U1"),
                                           ([True] * 6, "bool")])
def test_actions_that_are_not_real_numbers_are_refused_eager_and_jitted(action, dtype):
    env = _bare("fold_cloth1", **CHEAP_CLOTH)
    _, state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="action is not an array of"):
        checks.check_action(env, action)
    with pytest.raises(ValueError, match="action is not an array of"):
        env.step(state, np.asarray(action))
    if dtype != "<U1":  # JAX refuses text arguments before tracing (a TypeError of its own)
        with pytest.raises(ValueError, match=f"not an array of real numbers.*{dtype}"):
            jax.jit(env.step)(state, np.asarray(action))


def test_params_of_the_wrong_shape_are_refused_in_reset_and_step():
    env = _bare("fold_cloth1", **CHEAP_CLOTH)
    params = env.default_params
    bad_goal = params.replace(goal=np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match=r"params.goal must have shape \(36, 3\), got \(3, 3\)"):
        env.reset(jax.random.PRNGKey(0), bad_goal)
    _, state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="params.goal must have shape"):
        jax.jit(env.step)(state, np.zeros(6, np.float32), bad_goal)
    bad_lam = dataclasses.replace(params, lam=np.ones(2, np.float32))
    with pytest.raises(ValueError, match="params.lam must be a scalar"):
        env.reset(jax.random.PRNGKey(0), bad_lam)


def test_a_negative_friction_is_refused_at_the_boundary():
    """``friction = -1`` passed in params stepped without complaint: an eager ``reset`` /
    ``step`` now runs ``check_params`` on params other than the defaults; under ``jit``
    the values are not inspected (documented)."""
    for name, overrides in (("fold_cloth1", CHEAP_CLOTH), ("push_rope", small_overrides())):
        env = _bare(name, **overrides)
        physics = env.default_params.physics
        field = "friction_static" if name == "fold_cloth1" else "friction"
        value = np.full(np.shape(getattr(physics, field)), -1.0, np.float32)
        params = env.default_params.replace(physics=physics.replace(**{field: value}))
        with pytest.raises(ValueError, match="friction"):
            checks.check_params(env, params)
        key = jax.random.PRNGKey(0)
        with pytest.raises(ValueError, match="friction"):
            env.reset(key, params)
        _, state = jax.jit(env.reset)(key)
        with pytest.raises(ValueError, match="friction"):
            env.step(state, np.zeros(env.spec.action_dim, np.float32), params)


@pytest.mark.parametrize("change, message", [
    (dict(n=100000), "building a scene of up to 10000000000 object points needs about"),
    (dict(dt=1e-300), r"scene.dt = 1e-300 is not representable in float32"),
    (dict(dt=1e-12), r"scene.dt = 1e-12 s is below 1e-06 s"),
])
def test_scenes_the_machine_cannot_run_are_refused_before_building(change, message):
    scene = dataclasses.replace(dax_tasks.get_spec("fold_cloth1").scene, **change)
    with pytest.raises(ValueError, match=message):
        dax_tasks.make("fold_cloth1", scene=scene, cache_goal=False)
    with pytest.raises(ValueError, match="a 1000000 x 1000000 picture needs about"):
        dax_tasks.make("fold_cloth1", obs_mode="rgb", image_size=10**6, cache_goal=False)
    with pytest.raises(ValueError, match="does not fit in int32"):
        dax_tasks.make("fold_cloth1", horizon=2**31, cache_goal=False)


def test_every_task_fits_at_both_resolutions():
    for name in dax_tasks.available():
        for resolution in dax_tasks.RESOLUTIONS:
            checks.check_spec(dax_tasks.get_spec(name, resolution), image_size=256)
