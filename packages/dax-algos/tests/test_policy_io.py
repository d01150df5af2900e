"""Policy files: round trip, refusals (another task or config, truncated, bit-flipped,
garbage, foreign), no broken policy saved, atomic replacement."""

import json

import numpy as np
import pytest

from dax_algos.bench import policy_io
from dax_tasks.io import temporaries

PARAMS = {"mean": {"layers": {"0": {"kernel": np.arange(12, dtype=np.float32).reshape(3, 4),
                                    "bias": np.full(4, 0.5, np.float32)}}},
          "log_std": np.asarray([-0.5, -0.25], np.float32),
          "count": np.asarray(7, np.int32)}
META = {"method": "ppo", "task": "fold_cloth1", "task_fingerprint": "abc123",
        "config": {"learning_rate": 0.001, "policy_hidden": [64, 64]}}


@pytest.fixture
def saved(tmp_path):
    return policy_io.save_policy(tmp_path / "p.msgpack", PARAMS, META)


def _flat(tree, prefix=""):
    for k, v in sorted(tree.items()):
        if isinstance(v, dict):
            yield from _flat(v, f"{prefix}/{k}")
        else:
            yield f"{prefix}/{k}", v


def test_round_trip_keeps_values_dtypes_and_meta(saved):
    params, meta = policy_io.load_policy(saved, expect={"task": "fold_cloth1"})
    assert meta == META
    got, want = dict(_flat(params)), dict(_flat(PARAMS))
    assert got.keys() == want.keys()
    for k, v in want.items():
        assert got[k].dtype == v.dtype and got[k].shape == v.shape, k
        np.testing.assert_array_equal(got[k], v)
    assert json.loads(saved.with_name(saved.name + ".json").read_text()) == META


def test_another_task_or_config_is_refused_naming_it(saved):
    with pytest.raises(ValueError, match="task='fold_cloth1', expected 'pour_water'"):
        policy_io.load_policy(saved, expect={"task": "pour_water"})
    with pytest.raises(ValueError, match=r"config differs in learning_rate \(saved 0.001"):
        policy_io.load_policy(saved, expect={"config": {**META["config"],
                                                        "learning_rate": 0.01}})
    with pytest.raises(ValueError, match="no 'seed'"):
        policy_io.load_policy(saved, expect={"seed": 0})


def test_truncated_flipped_and_garbage_files_are_refused(saved, tmp_path):
    data = saved.read_bytes()
    cut = tmp_path / "cut.msgpack"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="cut.msgpack: not a readable policy file"):
        policy_io.load_policy(cut)
    flipped = tmp_path / "flipped.msgpack"
    raw = bytearray(data)
    at = raw.find(PARAMS["mean"]["layers"]["0"]["kernel"].tobytes())
    assert at > 0
    raw[at + 9] ^= 0x04
    flipped.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="checksum mismatch"):
        policy_io.load_policy(flipped)
    garbage = tmp_path / "garbage.msgpack"
    garbage.write_bytes(b"\x00not a policy at all")
    with pytest.raises(ValueError, match="garbage.msgpack"):
        policy_io.read_meta(garbage)
    from flax import serialization
    foreign = tmp_path / "foreign.msgpack"
    foreign.write_bytes(serialization.msgpack_serialize({"format": "other", "x": 1}))
    with pytest.raises(ValueError, match="not a dax-policy file"):
        policy_io.load_policy(foreign)
    with pytest.raises(FileNotFoundError, match="missing.msgpack"):
        policy_io.load_policy(tmp_path / "missing.msgpack")


def test_broken_policy_or_metadata_is_not_saved(tmp_path):
    bad = {"w": np.asarray([1.0, np.nan], np.float32)}
    with pytest.raises(ValueError, match="params/w contains NaN"):
        policy_io.save_policy(tmp_path / "a.msgpack", bad, META)
    with pytest.raises(ValueError, match="not strict JSON"):
        policy_io.save_policy(tmp_path / "b.msgpack", PARAMS, {"lr": float("nan")})
    assert not list(tmp_path.iterdir())


def test_failed_save_leaves_the_old_file_and_no_temporaries(saved, monkeypatch):
    before = saved.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")

    import dax_algos.bench.policy_io as mod

    monkeypatch.setattr(mod, "atomic_write", lambda path, data: _write_then_fail(path, data))
    with pytest.raises(OSError, match="disk full"):
        policy_io.save_policy(saved, {"w": np.ones(3, np.float32)}, META)
    assert saved.read_bytes() == before
    assert temporaries(saved) == []


def _write_then_fail(path, data):
    from dax_tasks.io import atomic_write

    def write(f):
        f.write(data[:10])
        raise OSError("disk full")

    atomic_write(path, write)
