"""Goal files: lookup order (explicit path, cache, computed), atomic writes, clear errors."""

import json

import numpy as np
import pytest
from conftest import small_overrides

import dax_tasks
from dax_tasks import goals, push_rope


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("DAX_CACHE_DIR", str(tmp_path))
    return tmp_path / "goals"


def _spec(**extra):
    import dataclasses

    return dataclasses.replace(push_rope.PUSH_ROPE.spec, **small_overrides(**extra))


def test_goal_is_computed_then_cached_with_provenance(cache):
    spec = _spec()
    pts, prov = goals.resolve_goal(push_rope.PUSH_ROPE, spec)
    path = goals.goal_file(spec)
    assert path.parent == cache and path.is_file(), f"expected a cached goal at {path}"
    again, prov2 = goals.load_goal(path, spec, pts.shape[0])
    np.testing.assert_array_equal(pts, again)
    assert prov2["task"] == "push_rope" and prov2["fingerprint"] == goals.fingerprint(spec)
    assert list(cache.glob("*.tmp")) == [], "a temporary file was left behind"


def test_cached_goal_is_used_instead_of_recomputing(cache):
    spec = _spec()
    pts, _ = goals.resolve_goal(push_rope.PUSH_ROPE, spec)
    moved = pts + np.float32(0.01)
    goals.save_goal(goals.goal_file(spec), moved, goals.provenance(spec, "test"))
    got, prov = goals.resolve_goal(push_rope.PUSH_ROPE, spec)
    np.testing.assert_array_equal(got, moved)
    assert prov["method"] == "test"


def test_fingerprint_ignores_reward_fields_but_not_the_scene():
    base = _spec()
    assert goals.fingerprint(base) == goals.fingerprint(_spec(lam=5.0, aux_reward=True))
    import dataclasses

    finer = dataclasses.replace(base, scene=dataclasses.replace(base.scene, ppc=4))
    assert goals.fingerprint(base) != goals.fingerprint(finer)


def test_make_uses_an_explicit_goal_path(cache, tmp_path):
    spec = _spec()
    pts = push_rope.goal(spec) + np.float32(0.02)
    path = goals.save_goal(tmp_path / "mine.npz", pts, goals.provenance(spec, "by hand"))
    task = dax_tasks.make("push_rope", goal_path=path, **small_overrides())
    _, state = task.reset()
    np.testing.assert_allclose(np.asarray(state.goal), pts)
    assert task.goal_provenance["method"] == "by hand"


@pytest.mark.parametrize("damage", ["truncate", "garbage", "wrong_shape", "missing"])
def test_bad_goal_file_is_refused_with_the_file_named(tmp_path, damage):
    spec = _spec()
    path = tmp_path / "goal.npz"
    good = push_rope.goal(spec)
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


def test_goal_of_another_task_is_refused(tmp_path):
    spec = _spec()
    prov = goals.provenance(spec, "test")
    prov["task"] = "fold_cloth1"
    path = goals.save_goal(tmp_path / "g.npz", push_rope.goal(spec), prov)
    with pytest.raises(goals.GoalFileError, match="fold_cloth1"):
        goals.load_goal(path, spec)


def test_corrupted_cache_file_is_regenerated_with_a_warning(cache):
    spec = _spec()
    path = goals.goal_file(spec)
    path.parent.mkdir(parents=True)
    path.write_bytes(b"\x00" * 10)
    with pytest.warns(UserWarning, match="regenerating"):
        pts, _ = goals.resolve_goal(push_rope.PUSH_ROPE, spec)
    np.testing.assert_array_equal(goals.load_goal(path)[0], pts)


def test_goal_files_hold_no_pickled_objects(cache):
    spec = _spec()
    goals.resolve_goal(push_rope.PUSH_ROPE, spec)
    with np.load(goals.goal_file(spec), allow_pickle=False) as data:
        assert sorted(data.files) == ["points", "provenance"]
        json.loads(str(data["provenance"]))
