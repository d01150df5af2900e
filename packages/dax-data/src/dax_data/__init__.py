"""Scripted-expert demonstrations, goal sets and exports for the DaX tasks.

* :func:`generate` records episodes of a task's scripted expert (or random actions) into an
  HDF5 file, resumably (:mod:`dax_data.record`); :func:`score` compares policies;
* :func:`open_file` / :func:`load` read such files as NumPy (or JAX) arrays, checking the
  schema (:mod:`dax_data.fileformat`; the layout is in README.md), pictures included;
* :func:`ensure_standard` records (or reuses) the standard demonstration sets the
  imitation-learning methods train on (:mod:`dax_data.standard`);
* :func:`write_goals` writes goal files in dax-tasks' format (:mod:`dax_data.goalsets`);
* :func:`export_episode` writes VTU / XDMF / PLY for ParaView and Blender
  (:mod:`dax_data.export`); :func:`export_minari` a whole file as a Minari dataset
  (:mod:`dax_data.minari_export`, optional extra ``minari``);
* the ``dax-data`` command line (:mod:`dax_data.cli`).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__: str = version("dax-data")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

from .fileformat import (  # noqa: E402  (h5py and NumPy only: no JAX import)
    FORMAT_VERSION,
    DataFileError,
    DemoFile,
    Episode,
    UncheckedDataWarning,
    load,
    open_file,
)

# Imported on first use, so reading and validating files does not import JAX.
_LAZY = {"export_episode": "export", "export_minari": "minari_export",
         "write_goal": "goalsets", "write_goals": "goalsets", "Recorder": "record",
         "generate": "record", "score": "record", "ensure_standard": "standard",
         "standard_path": "standard", "STANDARD_SETS": "standard"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'dax_data' has no attribute {name!r}")


__all__ = [
    "FORMAT_VERSION", "STANDARD_SETS", "DataFileError", "DemoFile", "Episode", "Recorder",
    "UncheckedDataWarning", "__version__", "ensure_standard", "export_episode",
    "export_minari", "generate", "load", "open_file", "score", "standard_path",
    "write_goal", "write_goals",
]
