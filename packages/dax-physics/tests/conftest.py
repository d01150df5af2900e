"""Same seed, same bits on a GPU too: XLA is asked for scatter-adds in a fixed order before
JAX starts (:func:`dax_physics.precision.deterministic_gpu_ops`; CPU ignores it)."""

from dax_physics.precision import deterministic_gpu_ops

deterministic_gpu_ops()
