"""Learning and planning methods, reference rows and the benchmark runner for the DaX
tasks.

Methods (``dax_algos.registry``): reinforcement learning ``ppo``, ``apg``, ``shac`` (each
``make_train(env, config) -> train(key, params)``, pure and jittable whole; networks in
Flax NNX, :mod:`dax_algos.nets`); planners ``cem_mpc``, ``diff_mpc``, ``diff_cem_mpc``
(each a small module with a pure core and a ``make_planner(env, config)``); reference rows
``random`` and ``expert``. The runner is ``dax-bench`` (:mod:`dax_algos.bench`); trained
policies are saved and loaded with :mod:`dax_algos.trained`. See README.md.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__: str = version("dax-algos")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

from . import (  # noqa: E402 - trained.py reads __version__
    apg,
    cem_mpc,
    common,
    diff_cem_mpc,
    diff_mpc,
    ppo,
    reference,
    registry,
    rl,
    shac,
    trained,
)
from .apg import APGConfig  # noqa: E402
from .cem_mpc import CEMConfig  # noqa: E402
from .diff_cem_mpc import DiffCEMConfig  # noqa: E402
from .diff_mpc import DiffMPCConfig  # noqa: E402
from .ppo import PPOConfig  # noqa: E402
from .shac import SHACConfig  # noqa: E402

__all__ = ["APGConfig", "CEMConfig", "DiffCEMConfig", "DiffMPCConfig", "PPOConfig",
           "SHACConfig", "__version__", "apg", "cem_mpc", "common", "diff_cem_mpc",
           "diff_mpc", "ppo", "reference", "registry", "rl", "shac", "trained"]
