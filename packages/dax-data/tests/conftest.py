"""Same seed, same bits on a GPU too: XLA is asked for scatter-adds in a fixed order before
JAX starts (:func:`dax_physics.precision.deterministic_gpu_ops`; CPU ignores it). And the
command-line tests' subprocess environment (``env``)."""

import os

import pytest

from dax_physics.precision import deterministic_gpu_ops

deterministic_gpu_ops()


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """The environment of a ``dax-data`` subprocess: this one's, with a cache folder of
    its own per test module (the command-line tests)."""
    out = dict(os.environ)
    out["DAX_CACHE_DIR"] = str(tmp_path_factory.mktemp("cache"))
    return out
