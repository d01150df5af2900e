"""The tasks' steps, action gradients and experts run their matrix products at full float32
precision (JAX's default would round them to TF32 on GPUs, bfloat16 on TPUs; see
:mod:`dax_physics.precision`). Lowering only: nothing is compiled. One task per code
path: a pouring task (MPM, bowl colliders on the grid), a rope task (MPM, gripper), the
folding and the unfolding experts (the cloth's fitted pose, the aligned goal in D)."""

import jax
import jax.numpy as jnp
import pytest

import dax_tasks
from dax_physics.precision import dots


@pytest.mark.parametrize("name", ["pour_water", "whip_rope", "fold_cloth3", "unfold_cloth1"])
def test_step_gradient_and_expert_use_full_precision(name):
    env = dax_tasks.make(name)
    _, state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    action = jax.ShapeDtypeStruct((env.spec.action_dim,), jnp.float32)

    def reward(s, a):
        return env.step(s, a)[2]

    # the gradient's program holds the forward pass's dots too
    fns = {"step and its action gradient": (jax.grad(reward, argnums=1), state, action)}
    if env.has_expert:
        fns["expert"] = (env.expert_action, state)
    for what, (fn, *args) in fns.items():
        _, low = dots(fn, *args)
        assert not low, f"{name} {what}: dots below full precision:\n" + "\n".join(low[:3])
