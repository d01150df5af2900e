"""dax_tasks.core.sharding and dax_tasks.core.distributed in this (one-device) process: the
no-op on one device, the errors for bad input. The multi-device behaviour (4 forced CPU
devices, two processes) is tested in tests/multidevice (``nox -s multidevice``), each in
fresh processes since the device count is fixed when JAX starts; the multi-host command
line (``benchmarks.distributed``) in tests/benchmarks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dax_tasks.core import distributed, sharding

one_device = pytest.mark.skipif(jax.device_count() != 1, reason="needs one device")


@one_device
def test_one_device_mesh_and_no_split():
    mesh = sharding.batch_mesh()
    assert mesh.axis_names == ("batch",) and mesh.devices.size == 1
    assert sharding.batch_mesh() is mesh  # built once
    assert not any(sharding.is_sharded(n) for n in (1, 2, 4, 8, 128))


@one_device
def test_shard_batch_is_a_no_op_on_one_device_in_and_out_of_jit():
    tree = {"x": jnp.arange(8.0).reshape(4, 2), "k": jax.random.split(jax.random.PRNGKey(0), 4)}
    assert sharding.shard_batch(tree) is tree
    out = jax.jit(lambda t: sharding.shard_batch(t))(tree)
    np.testing.assert_array_equal(out["x"], tree["x"])
    assert isinstance(out["x"].sharding, jax.sharding.SingleDeviceSharding)


def test_shard_batch_refuses_a_leaf_without_the_batch_axis():
    with pytest.raises(ValueError, match=r"leaf \['b'\] is a scalar"):
        sharding.shard_batch({"a": jnp.zeros(4), "b": jnp.zeros(())})
    with pytest.raises(ValueError, match=r"different leading \(batch\) sizes .*\['b'\]: 3"):
        sharding.shard_batch({"a": jnp.zeros(4), "b": jnp.zeros((3, 2))})
    assert sharding.shard_batch({}) == {}


@pytest.mark.parametrize("args, match", [
    (("localhost", 2, 0), "coordinator must be HOST:PORT"),
    (("localhost:99999", 2, 0), "coordinator must be HOST:PORT"),
    (("localhost:1234", 0, 0), "num_processes must be a positive int"),
    (("localhost:1234", 2, 2), r"process_id must be an int in \[0, 2\)"),
    (("localhost:1234", 2, True), "process_id must be an int"),
])
def test_initialize_refuses_bad_arguments_before_joining(args, match):
    with pytest.raises(ValueError, match=match):
        distributed.initialize(*args)


def test_rollout_gradient_refuses_a_bad_batch():
    with pytest.raises(ValueError, match="batch must be a positive int"):
        distributed.rollout_gradient(None, 0, 3)
    with pytest.raises(ValueError, match="steps must be a positive int"):
        distributed.rollout_gradient(None, 4, 2.0)
