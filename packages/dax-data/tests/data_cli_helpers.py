"""Helpers of the dax-data command-line tests (a uniquely named module, so it never clashes
with another package's test helpers): the command, its runner and the one-line-error check.
"""

import subprocess
import sys
from pathlib import Path

import dax_data

TASK = "fold_cloth1"  # cheap, with an expert; default (full) resolution
_SCRIPT = Path(sys.executable).with_name("dax-data")
CMD = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "dax_data"]
SMALL = ["--override", "scene.n=6", "--override", "scene.settle_substeps=200",
         "--override", "substeps=400"]  # the README example


def run(env, *args, timeout=300):
    """``dax-data ARGS`` in a subprocess with the environment ``env``."""
    return subprocess.run([*CMD, *map(str, args)], env=env, capture_output=True, text=True,
                          timeout=timeout)


def assert_one_line_error(proc, *needles):
    """The process was refused with exit code 2 and one line on stderr naming each of
    ``needles``, no traceback."""
    assert proc.returncode == 2, f"expected exit 2, got {proc.returncode}: {proc.stderr}"
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, f"got stderr {proc.stderr!r}"
    for needle in needles:
        assert needle in lines[0], f"expected {needle!r} in {lines[0]!r}"


def read_all(path):
    """Every episode of the file at ``path``."""
    with dax_data.open_file(path) as f:
        return [f.episode(k) for k in range(len(f))]
