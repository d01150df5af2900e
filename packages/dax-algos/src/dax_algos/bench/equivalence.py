"""Task fingerprints whose forward programs are the same (a ledger), so that a code change
that leaves a task's forward computation as it was does not stale the rows of methods
that never differentiate through the env.

A row records its task's fingerprint (:mod:`dax_algos.bench.provenance`), which covers the
dax-tasks and dax-physics programs the task can reach: any edit of them stales every row
of the task. A change may leave every forward program as it was and change only what is
computed in reverse (a written-out VJP): a row made by a method with ``uses_gradients``
false (random, expert, CEM-MPC, PPO, Transporter) then still repeats to the bit, and a
row of one that differentiates the env (APG, SHAC, ILD, diff-MPC, diff-CEM-MPC) does not.

Each :class:`Equivalence` says that for ``task`` the code with fingerprint ``after``
gives the same forward programs as the code with fingerprint ``before``, with the
evidence: ``python -m benchmarks.forward_programs record`` run on both versions (the env's
reset, expert action and step lowered to StableHLO text, without source locations, at
each recorded batch, and the bytes of a few expert steps), and ``... compare`` finding
every digest equal. Entries chain (``a`` to ``b`` and ``b`` to ``c`` make ``a`` to ``c``),
but only for fingerprints with the same spec: the spec is part of the fingerprint, so a
pair of fingerprints names one task with one set of overrides.
"""

from __future__ import annotations

import dataclasses
import functools


@dataclasses.dataclass(frozen=True)
class Equivalence:
    """``task``'s fingerprint ``before`` and ``after`` a code change that left its forward
    programs as they were; ``evidence``: the two ``benchmarks.forward_programs`` files and
    the commit that made the change."""

    task: str
    before: str
    after: str
    evidence: str


#: The forward-programs files of the self-collision force's written reverse pass.
_VJP = ("benchmarks/results/2026-12-02-forward-programs-before.json (f7c51af) and "
        "-after.json (b759f58): the self-collision force's reverse pass written out")

#: The forward-programs files of the reverse pass's column-wise pullback.
_COLUMNS = ("benchmarks/results/2026-12-05-forward-programs-before.json (042fd19) and "
            "-after.json (e8f474a): the self-collision reverse pass's contact-law pullback "
            "taken column by column")

#: The ledger, oldest first.
LEDGER: tuple[Equivalence, ...] = (
    Equivalence('fold_cloth1', '4879dc825ad7', '84a593dd0ce9', _VJP),
    Equivalence('fold_cloth3', '886f8340254a', 'efcd33c944ba', _VJP),
    Equivalence('fold_tshirt', '3ca63f95f3d6', '3e90375c5f8a', _VJP),
    Equivalence('unfold_cloth1', 'f631a420f56c', 'e6e715750b1b', _VJP),
    Equivalence('unfold_cloth3', '20b6f156c30d', '39aade69b886', _VJP),
    Equivalence('fold_cloth1', '84a593dd0ce9', '1578c574a55a', _COLUMNS),
    Equivalence('fold_cloth3', 'efcd33c944ba', '83d24494841d', _COLUMNS),
    Equivalence('fold_tshirt', '3e90375c5f8a', 'edffb826ed91', _COLUMNS),
    Equivalence('unfold_cloth1', 'e6e715750b1b', '4a7dd51663d7', _COLUMNS),
    Equivalence('unfold_cloth3', '39aade69b886', '4fc8e025eaec', _COLUMNS),
)


@functools.cache
def _closure(ledger: tuple) -> frozenset:
    """Every ``(before, after)`` pair the ledger's entries give, chained."""
    pairs = {(e.before, e.after) for e in ledger}
    while True:
        more = {(a, d) for a, b in pairs for c, d in pairs if b == c and a != d} - pairs
        if not more:
            return frozenset(pairs)
        pairs |= more


def forward_equivalent(before: str, after: str, ledger: tuple = LEDGER) -> bool:
    """Whether the code of fingerprint ``after`` gives the forward programs of the code of
    fingerprint ``before`` (the same fingerprint, or a chain of ledger entries from
    ``before`` to ``after``)."""
    return before == after or (before, after) in _closure(tuple(ledger))
