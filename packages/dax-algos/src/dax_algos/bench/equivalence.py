"""Task fingerprints whose programs compute the same numbers (a ledger), so that a code
change that leaves a task's computation as it was does not stale the rows it cannot have
changed.

A row records its task's fingerprint (:mod:`dax_algos.bench.provenance`), which covers the
dax-tasks and dax-physics programs the task can reach: any edit of them stales every row
of the task. A change may leave every forward program as it was and change only what is
computed in reverse (a written-out VJP): a row made by a method with ``uses_gradients``
false (random, expert, CEM-MPC, PPO, Transporter) then still repeats to the bit, and a
row of one that differentiates the env (APG, SHAC, ILD, diff-MPC, diff-CEM-MPC) does not.
A change may also rewrite programs and leave every number they give as it was (the same
integer neighbour lists built in fewer calls): then the rows of every method repeat.

Each :class:`Equivalence` says that for ``task`` the code with fingerprint ``after``
computes what the code with fingerprint ``before`` did, with the evidence: ``python -m
benchmarks.forward_programs record`` run on both versions, and ``... compare`` finding
the digests equal. With ``gradients`` false (forward programs), the env's reset, expert
action and step lowered to StableHLO text, without source locations, at each recorded
batch, and the bytes of a few expert steps are equal; it keeps the rows of methods that
never differentiate the env. With ``gradients`` true (values), the bytes of the expert
steps and of their action gradients are equal at each recorded batch (``record --grad``,
``compare --values``); it keeps the rows of every method, and the change must compute
the same numbers for every input by construction (say how in the evidence), the bytes
being the check. Entries chain (``a`` to ``b`` and ``b`` to ``c`` make ``a`` to ``c``;
for a row of a method that differentiates the env, only through entries with
``gradients``), but only for fingerprints with the same spec: the spec is part of the
fingerprint, so a pair of fingerprints names one task with one set of overrides.
"""

from __future__ import annotations

import dataclasses
import functools


@dataclasses.dataclass(frozen=True)
class Equivalence:
    """``task``'s fingerprint ``before`` and ``after`` a code change that left its forward
    programs as they were, or with ``gradients`` the numbers of its steps and their action
    gradients; ``evidence``: the two ``benchmarks.forward_programs`` files and the commit
    that made the change."""

    task: str
    before: str
    after: str
    evidence: str
    gradients: bool = False


#: The forward-programs files of the self-collision force's written reverse pass.
_VJP = ("benchmarks/results/2026-12-02-forward-programs-before.json (f7c51af) and "
        "-after.json (b759f58): the self-collision force's reverse pass written out")

#: The forward-programs files of the reverse pass's column-wise pullback.
_COLUMNS = ("benchmarks/results/2026-12-05-forward-programs-before.json (042fd19) and "
            "-after.json (e8f474a): the self-collision reverse pass's contact-law pullback "
            "taken column by column")

#: The values files of the batched rebuild of the members that moved (recorded with
#: ``--grad`` at batch 1, 2, 4, 8, 16, 32 and 64, two expert steps each; the before file
#: ran a3e9abb's code with the ``--grad`` option of 5f65631's ``forward_programs``, hence
#: its "+dirty", in two sittings that it names under "merged").
_MEMBERS = ("benchmarks/results/2026-12-06-forward-programs-before.json (a3e9abb) and "
            "-after.json (d6a469f; the change is d810340 and d6a469f): a batch builds only "
            "the neighbour lists of the members that moved, each the list its own build "
            "gives (the same integers), so every value and action gradient is the same")

#: The files of the spring layout's further class groups (recorded with ``--grad`` at batch
#: 1, 2, 4, 8, 16, 32 and 64, two expert steps each; the before file is _MEMBERS's after
#: file, whose code the tasks ran until this change).
_GROUPS = ("benchmarks/results/2026-12-06-forward-programs-after.json (d6a469f) and "
           "-groups-after.json (abb99cb): the spring layout takes classes past the first 8 "
           "only in groups of at least 1024 springs, which no default-resolution cloth "
           "has, so every task's classes and programs are as they were (the StableHLO "
           "text and every value and action gradient equal)")

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
    Equivalence('fold_cloth1', '1578c574a55a', '7a10f899e4b5', _MEMBERS, gradients=True),
    Equivalence('fold_cloth3', '83d24494841d', 'c516e1a4ec7d', _MEMBERS, gradients=True),
    Equivalence('fold_tshirt', 'edffb826ed91', '01fc6efa2906', _MEMBERS, gradients=True),
    Equivalence('unfold_cloth1', '4a7dd51663d7', 'f4d11b3f162a', _MEMBERS, gradients=True),
    Equivalence('unfold_cloth3', '4fc8e025eaec', 'b7b9b6a7f444', _MEMBERS, gradients=True),
    Equivalence('fold_cloth1', '7a10f899e4b5', '0097aea38063', _GROUPS, gradients=True),
    Equivalence('fold_cloth3', 'c516e1a4ec7d', 'ec0ad598fc96', _GROUPS, gradients=True),
    Equivalence('fold_tshirt', '01fc6efa2906', '36ad9a830b29', _GROUPS, gradients=True),
    Equivalence('unfold_cloth1', 'f4d11b3f162a', 'b907dee74feb', _GROUPS, gradients=True),
    Equivalence('unfold_cloth3', 'b7b9b6a7f444', '9357bc6d284d', _GROUPS, gradients=True),
)


@functools.cache
def _closure(ledger: tuple, gradients: bool) -> frozenset:
    """Every ``(before, after)`` pair the ledger's entries give, chained (with
    ``gradients``, only the entries that cover gradients)."""
    pairs = {(e.before, e.after) for e in ledger if e.gradients or not gradients}
    while True:
        more = {(a, d) for a, b in pairs for c, d in pairs if b == c and a != d} - pairs
        if not more:
            return frozenset(pairs)
        pairs |= more


def forward_equivalent(before: str, after: str, ledger: tuple = LEDGER,
                       gradients: bool = False) -> bool:
    """Whether the code of fingerprint ``after`` gives the forward programs of the code of
    fingerprint ``before`` (the same fingerprint, or a chain of ledger entries from
    ``before`` to ``after``); with ``gradients``, also the same action gradients (a chain
    of entries that cover them)."""
    return before == after or (before, after) in _closure(tuple(ledger), gradients)
