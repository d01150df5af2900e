"""Learning and planning methods, reference rows and the benchmark runner for the DaX
tasks.

The methods by family: reinforcement learning (:mod:`dax_algos.rl`: PPO, APG, SHAC),
imitation learning (:mod:`dax_algos.il`: Transporter, ILD), planning
(:mod:`dax_algos.planning`: CEM-MPC, diff-MPC, diff-CEM-MPC, and the random and expert
reference rows). A method is registered as a value (:mod:`dax_algos.method`: a planner
builder or a :class:`dax_algos.learner.Learner`); :mod:`dax_algos.registry` names them
with their budgets. What several families share: normalised actions
(:mod:`dax_algos.actions`), config checks (:mod:`dax_algos.checks`), the episode's output
(:mod:`dax_algos.episode`), the MLP policies' inputs (:mod:`dax_algos.mlp_policy`), the
optimiser (:mod:`dax_algos.optim`) and the networks (:mod:`dax_algos.nets`). The benchmark
runner ``dax-bench`` and what it writes (results, page, episodes, learning curves, policy
files, the Ray backend) are :mod:`dax_algos.bench`, which imports the methods and never
the other way. See README.md.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__: str = version("dax-algos")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

from . import il, learner, method, planning, registry, rl  # noqa: E402
from .il.ild import ILDConfig  # noqa: E402
from .il.transporter import TransporterConfig  # noqa: E402
from .planning.cem_mpc import CEMConfig  # noqa: E402
from .planning.diff_cem_mpc import DiffCEMConfig  # noqa: E402
from .planning.diff_mpc import DiffMPCConfig  # noqa: E402
from .rl.apg import APGConfig  # noqa: E402
from .rl.ppo import PPOConfig  # noqa: E402
from .rl.shac import SHACConfig  # noqa: E402

__all__ = ["APGConfig", "CEMConfig", "DiffCEMConfig", "DiffMPCConfig", "ILDConfig",
           "PPOConfig", "SHACConfig", "TransporterConfig", "__version__", "il", "learner",
           "method", "planning", "registry", "rl"]
