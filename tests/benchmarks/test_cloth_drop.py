"""The peers' cloth-drop scene on the tasks' solver (``benchmarks.physics_cloth``, what
``benchmarks.side_by_side`` times): it agrees with the Taichi and Warp references and
puts every spring in a stencil class."""

import jax
import numpy as np

from benchmarks import physics_cloth

# Mean height after 1000 substeps of the standard cloth-drop scene, from the independent
# Taichi and Warp reference implementations (they agree to 5e-8).
PEERS_MEAN_HEIGHT = 0.008108


def test_mesh_cloth_drop_matches_the_peer_reference():
    cfg, cloth, state = physics_cloth.cloth_drop_scene(64)
    assert int(cloth.residual.shape[0]) == 0, "expected every spring in the stencil"
    out = jax.jit(lambda s: physics_cloth.c.rollout(cfg, cloth, s, 1000))(state)
    z = np.asarray(out.x[:, 2])
    assert abs(float(z.mean()) - PEERS_MEAN_HEIGHT) < 1e-4, (
        f"expected mean height {PEERS_MEAN_HEIGHT}, got {float(z.mean())}")
    assert float(z.min()) >= 0.0, "a vertex went below the ground clamp"
