"""Find matrix products that would run below full float32 precision on an accelerator.

JAX's default precision lets a float32 dot product round its inputs to TF32 (a 10-bit
mantissa) on NVIDIA GPUs since Ampere, and to bfloat16 on TPUs. CPU ignores the setting,
so a CPU run never shows the error; the lowered program does, since every ``dot_general``
in it carries its precision. The solvers ask for HIGHEST on each of theirs (a rotation
or a frame change would otherwise carry a 1e-3 relative error); tests use :func:`dots`
to keep it so.
"""

from __future__ import annotations

import re

import jax

_FULL = re.compile(r"precision = \[HIGHEST, HIGHEST\]")


def dots(fn, *args) -> tuple[list[str], list[str]]:
    """``(all_dots, below_full)``: the ``dot_general`` lines of ``jax.jit(fn).lower(*args)``
    (StableHLO text) and those among them that do not ask for HIGHEST on both operands."""
    text = jax.jit(fn).lower(*args).as_text()
    found = [line.strip() for line in text.splitlines() if "dot_general" in line]
    return found, [d for d in found if not _FULL.search(d)]
