"""Deformable-object manipulation tasks for DaX, built on dax-physics.

This release holds only the package skeleton; see README.md for what is planned.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__: str = version("dax-tasks")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["__version__"]
