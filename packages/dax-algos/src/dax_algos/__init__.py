"""Learning and planning methods and the benchmark runner for the DaX tasks.

This release holds only the package skeleton; see README.md for what is planned.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__: str = version("dax-algos")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["__version__"]
