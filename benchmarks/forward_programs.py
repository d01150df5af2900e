"""The forward programs of the tasks, as digests, to show that a code change left them as
they were (the evidence of a :mod:`dax_algos.bench.equivalence` ledger entry).

``record``: the checkout's commit and, per task, its fingerprint and spec digest and, at
each ``--batches`` size (1: the env itself, else a :class:`dax_tasks.VmapWrapper`),
SHA-256 digests of the env's
reset, expert action and step lowered to StableHLO text without source locations
(``Lowered.as_text(debug_info=False)``: what JAX hands XLA, for any program that embeds
them), and of the bytes of ``--steps`` expert steps from ``PRNGKey(0)`` (states,
observations, rewards). Tasks without an expert step the middle of their action box.

With ``--grad``, also the bytes of the gradient of each of those steps' summed reward with
respect to its actions (what APG, SHAC and ILD differentiate), as ``gradient_values``.

``compare OLD NEW``: per task in both files, whether every digest is equal and whether the
fingerprint changed; prints the ledger entries (Python) for the tasks whose fingerprint
changed and whose forward programs did not, and exits 1 if any task's programs differ.
``compare --values``: only the values and the gradient values (both files recorded with
``--grad``) must be equal, the programs may differ; the entries printed then cover the
gradients (``gradients=True``: the rows of every method stay current), for a change that
computes the same numbers by construction.

    git worktree add /tmp/before <old commit>   # then, in each checkout:
    python -m benchmarks.forward_programs record --tasks fold_cloth1,fold_tshirt --out F.json
    python -m benchmarks.forward_programs compare BEFORE.json AFTER.json
    python -m benchmarks.forward_programs record --grad --batches 1,4,64 --out F.json
    python -m benchmarks.forward_programs compare --values BEFORE.json AFTER.json
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import dax_tasks
from benchmarks.tasks import probe_act
from dax_algos.bench.provenance import commit, spec_digest
from dax_tasks import TASKS, VmapWrapper


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def _digest(h, tree) -> None:
    """Feed the bytes of every leaf of ``tree`` (arrays) to the hash ``h``."""
    for leaf in jax.tree.leaves(tree):
        h.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())


def _lowered(fn, *args) -> str:
    return _sha(jax.jit(fn).lower(*args).as_text(debug_info=False).encode())


def record_task(name: str, batches, steps: int, grad: bool = False) -> dict:
    """The digests of ``name``'s forward programs (see the module docstring); ``grad``:
    also of its steps' action gradients."""
    spec = dax_tasks.get_spec(name)
    out = {"fingerprint": spec.fingerprint(), "spec_digest": spec_digest(spec), "batches": {}}
    for b in batches:
        env = dax_tasks.make(name, cache_goal=False)
        if b > 1:
            env = VmapWrapper(env, batch_size=b)
        params, key = env.default_params, jax.random.PRNGKey(0)
        _, state = jax.jit(env.reset)(key, params)
        act = jax.jit(probe_act(env, b if b > 1 else None))
        action = act(state, params)
        digests = {"reset": _lowered(env.reset, key, params),
                   "step": _lowered(env.step, state, action, params)}
        if env.has_expert:
            digests["expert_action"] = _lowered(env.expert_action, state, params)
        step, h, hg = jax.jit(env.step), hashlib.sha256(), hashlib.sha256()
        action_grad = jax.jit(jax.value_and_grad(
            lambda a, s, p, env=env: jnp.sum(env.step(s, a, p)[2])))
        for _ in range(steps):
            action = act(state, params)
            if grad:
                _digest(hg, action_grad(action, state, params))
            out_t = step(state, action, params)
            _digest(h, out_t)
            state = out_t[1]
        digests["values"] = h.hexdigest()[:16]
        if grad:
            digests["gradient_values"] = hg.hexdigest()[:16]
        out["batches"][str(b)] = digests
    return out


def record(names, batches, steps: int, grad: bool = False) -> dict:
    return {"bench": "forward_programs", "date": datetime.date.today().isoformat(),
            "commit": commit(), "jax": jax.__version__, "steps": steps,
            "batches": list(batches), "grad": grad,
            "tasks": {n: record_task(n, batches, steps, grad) for n in names}}


#: The digests ``compare --values`` requires equal (both present).
VALUES = ("values", "gradient_values")


def compare(old: dict, new: dict, values: bool = False) -> tuple[list, list]:
    """``(same, differ)``: the tasks in both documents whose digests are all equal (with
    ``values``, the :data:`VALUES` digests, which must be present), with their
    fingerprints ``(task, old, new)``, and those with a differing or missing digest
    ``(task, names of those digests)``."""
    same, differ = [], []
    for name in sorted(old["tasks"].keys() & new["tasks"].keys()):
        a, b = old["tasks"][name], new["tasks"][name]
        bad = []
        for batch in sorted(a["batches"].keys() | b["batches"].keys()):
            da, db = a["batches"].get(batch, {}), b["batches"].get(batch, {})
            for what in (VALUES if values else sorted(da.keys() | db.keys())):
                if da.get(what) != db.get(what) or da.get(what) is None:
                    bad.append(f"{batch}/{what}")
        if a["spec_digest"] != b["spec_digest"]:
            bad.append("spec_digest")
        if bad:
            differ.append((name, bad))
        else:
            same.append((name, a["fingerprint"], b["fingerprint"]))
    return same, differ


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.forward_programs",
                                description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("record", help="digest this checkout's forward programs")
    rec.add_argument("--tasks", default=",".join(TASKS))
    rec.add_argument("--batches", default="1,4")
    rec.add_argument("--steps", type=int, default=3)
    rec.add_argument("--grad", action="store_true",
                     help="also digest each step's action gradient")
    rec.add_argument("--out", required=True)
    cmp_ = sub.add_parser("compare", help="compare two record files")
    cmp_.add_argument("old")
    cmp_.add_argument("new")
    cmp_.add_argument("--values", action="store_true",
                      help="compare only the values and gradient values (recorded with "
                           "--grad); the entries printed cover the gradients")
    cmp_.add_argument("--evidence", default="",
                      help="the evidence text of the printed ledger entries")
    args = p.parse_args(argv)
    if args.cmd == "record":
        names = [n.strip() for n in args.tasks.split(",") if n.strip()]
        unknown = [n for n in names if n not in TASKS]
        if unknown:
            p.error(f"unknown task(s) {unknown}; valid: {', '.join(TASKS)}")
        batches = [int(b) for b in args.batches.split(",")]
        if any(b < 1 for b in batches) or args.steps < 1:
            p.error("batch sizes and --steps must be >= 1")
        doc = record(names, batches, args.steps, args.grad)
        text = json.dumps(doc, indent=1) + "\n"
        tmp = Path(args.out).with_suffix(".tmp")
        tmp.write_text(text)
        tmp.replace(args.out)
        print(text, end="")
        return 0
    old, new = (json.loads(Path(f).read_text()) for f in (args.old, args.new))
    same, differ = compare(old, new, args.values)
    what = "values" if args.values else "forward programs"
    for name, bad in differ:
        print(f"# {name}: {what} differ ({', '.join(bad)})", file=sys.stderr)
    for name, a, b in same:
        if a == b:
            print(f"# {name}: same {what}, same fingerprint {a}", file=sys.stderr)
        elif args.values:
            print(f"    Equivalence({name!r}, {a!r}, {b!r}, {args.evidence!r}, "
                  "gradients=True),")
        else:
            print(f"    Equivalence({name!r}, {a!r}, {b!r}, {args.evidence!r}),")
    return 1 if differ else 0


if __name__ == "__main__":
    raise SystemExit(main())
