"""Eager input checks that both solvers share (host side, on Python numbers)."""

from __future__ import annotations

import numpy as np


def step_count(n, name: str) -> int:
    """``n`` as an int; ``ValueError`` naming ``name`` unless it is an int >= 0 (a bool,
    a float or a negative count is refused: ``lax.scan`` would run a negative one as zero
    steps)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"{name} must be an int >= 0, got {n!r}")
    return int(n)


def unstable_dt(dt: float, limit: float, cause: str, remedy: str) -> ValueError:
    """The error for a time step ``dt`` [s] above the largest stable one ``limit`` [s]:
    both solvers' refusals name the limit in the same words."""
    return ValueError(f"unstable time step: dt = {dt:.3g} s exceeds the largest stable dt "
                      f"{limit:.3g} s {cause}; {remedy}")
