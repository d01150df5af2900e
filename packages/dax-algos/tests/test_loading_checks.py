"""What dax-algos reads from files is checked before use (issue 38): a policy file forged
with a recomputed checksum and NaN parameters, parameters of another shape than the
method's network, a broken observation normaliser, a demonstration file edited with h5py
and one whose goal is corrupted are each one ``ValueError`` naming the file."""

import json

import jax
import numpy as np
import pytest
from algos_helpers import cheap_cloth_overrides
from flax import serialization

import dax_data
import dax_tasks
from dax_algos import registry
from dax_algos.bench import policy_io, trained
from dax_algos.il import demos
from dax_algos.learner import Policy
from dax_algos.mlp_policy import ObsNorm, feature_dim

TASK = "fold_cloth1"


def forge(path, params: dict, meta: dict):
    """A policy file as a forger writes it: any parameters, the checksum recomputed."""
    text = json.dumps(meta, sort_keys=True)
    payload = {"format": policy_io.FORMAT, "version": policy_io.VERSION, "meta": text,
               "params": params, "sha256": policy_io._digest(text, params)}
    path.write_bytes(serialization.msgpack_serialize(payload))
    return path


def test_a_forged_policy_file_with_nan_parameters_is_refused(tmp_path):
    params = {"w": np.asarray([[0.5, np.nan]], np.float32), "b": np.zeros(2, np.float32)}
    path = forge(tmp_path / "nan.msgpack", params, {"method": "ppo"})
    with pytest.raises(ValueError, match=r"nan.msgpack: parameter /w contains NaN or inf"):
        policy_io.load_policy(path)
    path = forge(tmp_path / "cplx.msgpack", {"w": np.asarray([1 + 2j], np.complex64)}, {})
    with pytest.raises(ValueError, match="cplx.msgpack: parameter /w is not an array of real"):
        policy_io.read_meta(path)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A PPO policy of the quick config for a coarse fold_cloth1, saved as the runner saves
    it."""
    env = dax_tasks.make(TASK, cache_goal=False, **cheap_cloth_overrides(horizon=2))
    m = registry.get("ppo")
    config = m.config("quick", TASK)
    params = m.learner.network(env, config).init(jax.random.PRNGKey(0))
    policy = Policy(params, ObsNorm.create(feature_dim(env)))
    path = tmp_path_factory.mktemp("policy") / "ppo.msgpack"
    trained.save_trained(path, "ppo", env, config, policy)
    return env, path


def test_a_saved_policy_loads_and_a_reshaped_one_is_refused(saved, tmp_path):
    env, path = saved
    act, policy = trained.load_trained(path, env, "ppo")
    tree, meta = policy_io.load_policy(path)

    def first_leaf(t):
        key = sorted(t)[0]
        return (t, key) if not isinstance(t[key], dict) else first_leaf(t[key])

    parent, key = first_leaf(tree["policy"])
    parent[key] = np.zeros((*np.shape(parent[key]), 2), np.float32)
    bad = policy_io.save_policy(tmp_path / "shape.msgpack", tree, meta)
    with pytest.raises(ValueError, match=r"shape.msgpack: .*has shape .*expected"):
        trained.load_trained(bad, env, "ppo")
    tree, _ = policy_io.load_policy(path)
    tree["obs_norm"]["mean"] = np.zeros(3, np.float32)
    bad = policy_io.save_policy(tmp_path / "norm.msgpack", tree, meta)
    with pytest.raises(ValueError, match=r"norm.msgpack: obs_norm/mean has shape \(3,\)"):
        trained.load_trained(bad, env, "ppo")
    tree, _ = policy_io.load_policy(path)
    tree["obs_norm"]["var"] = -np.ones_like(tree["obs_norm"]["var"])
    bad = policy_io.save_policy(tmp_path / "var.msgpack", tree, meta)
    with pytest.raises(ValueError, match="var.msgpack: obs_norm has a negative variance"):
        trained.load_trained(bad, env, "ppo")


def test_a_corrupted_demonstration_goal_is_a_one_line_error_naming_the_file(tmp_path):
    import h5py

    overrides = cheap_cloth_overrides(horizon=1)
    env = dax_tasks.make(TASK, **overrides)
    path = tmp_path / "demo.h5"
    dax_data.generate(TASK, 1, 0, path, overrides=overrides, progress=False)
    assert len(demos.load_episodes(path, env, 1)) == 1
    edited = tmp_path / "edited.h5"  # an action rewritten with h5py (its checksums redone)
    edited.write_bytes(path.read_bytes())
    with h5py.File(edited, "a") as f:
        a = f["episodes/000000/actions"][()]
        a[0, 0] = 100.0
        f["episodes/000000/actions"][...] = a
    with pytest.raises(dax_data.DataFileError, match=f"{edited}: episode 0: dataset "
                                                     f"'actions': content digest mismatch"):
        demos.load_episodes(edited, env, 1)
    with h5py.File(path, "r") as f:
        info = f["goal"].id.get_chunk_info(0)
    raw = bytearray(path.read_bytes())
    raw[info.byte_offset + info.size // 2] ^= 0x08
    path.write_bytes(bytes(raw))
    with pytest.raises(dax_data.DataFileError, match=f"{path}: /goal unreadable"):
        demos.load_episodes(path, env, 1)
