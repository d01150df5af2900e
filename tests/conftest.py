"""The cross-package tests: the repository root on ``sys.path``, so that the tests of the
benchmark and validation scripts (``tests/benchmarks``) import them as ``benchmarks.*``;
same seed, same bits on a GPU too (:func:`dax_physics.precision.deterministic_gpu_ops`)."""

import sys
from pathlib import Path

from dax_physics.precision import deterministic_gpu_ops

ROOT = str(Path(__file__).resolve().parents[1])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

deterministic_gpu_ops()
