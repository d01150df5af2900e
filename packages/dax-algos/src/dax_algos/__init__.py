"""Planning methods, reference rows and the benchmark runner for the DaX tasks.

Methods (``dax_algos.registry``): ``random``, ``expert``, ``cem_mpc``, ``diff_mpc``,
``diff_cem_mpc``; each planner is a small module with a pure core (``cem_optimise``,
``gradient_refine``) and a ``make_planner(task, config)``. The runner is ``dax-bench``
(:mod:`dax_algos.bench`). See README.md.
"""

from importlib.metadata import PackageNotFoundError, version

from . import cem_mpc, common, diff_cem_mpc, diff_mpc, reference, registry
from .cem_mpc import CEMConfig
from .diff_cem_mpc import DiffCEMConfig
from .diff_mpc import DiffMPCConfig

try:
    __version__: str = version("dax-algos")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["CEMConfig", "DiffCEMConfig", "DiffMPCConfig", "__version__", "cem_mpc", "common",
           "diff_cem_mpc", "diff_mpc", "reference", "registry"]
