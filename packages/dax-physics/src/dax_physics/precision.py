"""What an accelerator computes differently: matrix products below full float32 precision
(:data:`HIGHEST` and :func:`mm` ask for full precision, :func:`dots` finds the products
that do not) and scatter-adds in a run-to-run order (:func:`deterministic_gpu_ops` fixes
it).

JAX's default precision lets a float32 dot product round its inputs to TF32 (a 10-bit
mantissa) on NVIDIA GPUs since Ampere, and to bfloat16 on TPUs. CPU ignores the setting,
so a CPU run never shows the error; the lowered program does, since every ``dot_general``
in it carries its precision. The solvers ask for HIGHEST on each of theirs (a rotation
or a frame change would otherwise carry a 1e-3 relative error); tests use :func:`dots`
to keep it so.

The MPM particle-to-grid transfer and the mesh cloth's strain limiting (and its scatter
spring sum) are scatter-adds. On a GPU, XLA accumulates them with atomics whose order
changes from run to run, so the same program on the same inputs gives different low bits,
and through contact those bits can grow. ``--xla_gpu_deterministic_ops=true`` makes XLA
sum in a fixed order, at a cost in speed that ``benchmarks/accelerator.py`` measures.
"""

from __future__ import annotations

import os
import re

import jax
import jax.numpy as jnp

#: The precision every float32 matrix product in the solvers asks for (full float32 on
#: GPUs with TF32 and on TPUs; CPU computes every product at full precision anyway).
HIGHEST = jax.lax.Precision.HIGHEST

_FULL = re.compile(r"precision = \[HIGHEST, HIGHEST\]")


def dots(fn, *args) -> tuple[list[str], list[str]]:
    """``(all_dots, below_full)``: the ``dot_general`` lines of ``jax.jit(fn).lower(*args)``
    (StableHLO text) and those among them that do not ask for HIGHEST on both operands."""
    text = jax.jit(fn).lower(*args).as_text()
    found = [line.strip() for line in text.splitlines() if "dot_general" in line]
    return found, [d for d in found if not _FULL.search(d)]


def mm(a, b):
    """``a @ b`` at full float32 precision (:data:`HIGHEST`): the one spelling of a matrix
    product in the solvers (``jnp.einsum`` calls pass ``precision=HIGHEST`` themselves)."""
    return jnp.matmul(a, b, precision=HIGHEST)


DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"


def deterministic_gpu_ops() -> None:
    """Ask XLA for run-to-run identical scatter-adds on GPUs (same inputs, same bits), by
    adding ``--xla_gpu_deterministic_ops=true`` to ``XLA_FLAGS``; other platforms ignore the
    flag. XLA reads its flags once, when JAX starts its first backend: call this before any
    JAX computation (the test suites' ``conftest.py`` does). A setting of the flag already
    in ``XLA_FLAGS``, true or false, is left as it is."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "--xla_gpu_deterministic_ops" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {DETERMINISTIC_FLAG}".strip()
