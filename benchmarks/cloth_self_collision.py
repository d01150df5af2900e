"""What self-collision costs a cloth task per env step, and the cloth speed targets of
issue 35 (one interleaved run, JSON).

Each case is a task at a resolution (``TASK`` or ``TASK@RESOLUTION``); its env step (the
expert's first action from ``PRNGKey(0)``; with ``--batch B``, a ``VmapWrapper`` of B
envs from that key's B starts, as a learner steps them) is compiled ahead of time in up to
three variants: ``list``, the task's self-collision through its neighbour list (the
default); ``all``, the same contact testing every vertex pair (``self_search="all"``;
skipped above ``--all-max`` vertices); ``off``, ``thickness=0``. All variants of all cases
are then timed interleaved, one call of each in turn for ``--reps`` rounds, in this one
process, so that a load shared with other processes falls on all alike. Prints one JSON
line per case (medians, ratios to ``off``, the 1-minute load average before and after)
and a last line with the targets and whether each is met:

* every cloth task (default resolution) with self-collision <= 1.5x its step without;
* the 529-vertex square cloth at ``resolution="reference"`` <= 2x its step without;
* Fold-Cloth-1 at the reference (529 vertices, 2000 substeps) without self-collision
  >= 1.5x as fast as DaXBench (``benchmarks.tasks.DAXBENCH``: <= 0.070 / 1.5 s);
* Fold-T-shirt at the reference at least as fast as DaXBench (<= 0.664 s): at equal work
  its step without self-collision (DaXBench's cloth has none: springs, gravity, table
  friction, a clamp of the velocity and of the positions to the unit box, two suction
  grippers), and beside it the step with self-collision against the same limit.

With ``--grad`` the timed program is the step and the gradient of its summed reward with
respect to the actions. The targets are the issue's at batch 1, forward; a run at another
batch or with ``--grad`` says so in each target (the learners step their cloth tasks at
batch 4-64, where the per-substep cost of a few small XLA ops is shared by the batch, and
APG, SHAC and ILD differentiate the step).

    python -m benchmarks.cloth_self_collision --out benchmarks/results/DATE-cloth-targets.jsonl
    python -m benchmarks.cloth_self_collision --cases fold_cloth1,fold_tshirt --reps 9

Speed is measured here, never asserted in tests.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import jax
import numpy as np

import dax_tasks
from benchmarks.tasks import DAXBENCH, prepare_batch

DEFAULT_CASES = ("fold_cloth1,fold_cloth3,fold_tshirt,unfold_cloth1,unfold_cloth3,"
                 "fold_cloth1@reference,unfold_cloth3@reference,fold_tshirt@reference")


def _compiled(name, resolution, batch=1, grad=False, **scene):
    """``(compiled program, its arguments, facts)`` of ``name`` at ``resolution`` with the
    scene fields ``scene`` replaced: its env step, or with ``grad`` the step and the
    gradient of its summed reward with respect to the actions (what APG, SHAC and ILD
    differentiate), both as :func:`benchmarks.tasks.prepare_batch` compiles them;
    ``batch`` > 1: a :class:`VmapWrapper` of that many envs (its facts: the largest pair
    count, overflow and build count of the batch)."""
    base = dax_tasks.get_spec(name, resolution).scene
    env = dax_tasks.make(name, cache_goal=False, resolution=resolution,
                         scene=dataclasses.replace(base, **scene))
    prep = prepare_batch(env, None if batch == 1 else batch, grad)
    step, args = prep["step"]
    physics = step(*args)[1].physics
    info = dict(compile_s=round(prep["compile_step_s"] + (prep["compile_grad_s"] or 0.0), 2),
                n_vertices=int(physics.x.shape[-2]), substeps=env.spec.substeps)
    if physics.neighbours is not None:
        nb = physics.neighbours
        info.update(pairs=int(np.max(nb.count)), overflow=int(np.max(nb.overflow)),
                    builds=int(np.max(nb.builds)))
    program, args = prep["grad"] if grad else prep["step"]
    return program, args, info


def _variants(name, resolution, all_max, batch=1, grad=False):
    scene = dax_tasks.get_spec(name, resolution).scene
    if not scene.thickness > 0:
        raise ValueError(f"{name} has no self-collision to measure")
    out = {"list": _compiled(name, resolution, batch, grad)}
    if out["list"][2]["n_vertices"] <= all_max:
        out["all"] = _compiled(name, resolution, batch, grad, self_search="all")
    out["off"] = _compiled(name, resolution, batch, grad, thickness=0.0)
    return out


def measure(cases, reps: int, all_max: int = 1024, batch: int = 1,
            grad: bool = False) -> list[dict]:
    """One record per case (``(task, resolution)`` pairs) at ``batch``, timed
    interleaved (``grad``: the step with the action gradient; the ``step_*_s`` fields
    then time that program)."""
    runs = {}
    for name, res in cases:
        for variant, run in _variants(name, res, all_max, batch, grad).items():
            runs[(name, res, variant)] = run
    load_before = round(os.getloadavg()[0], 2)
    times = {k: [] for k in runs}
    for _ in range(reps):
        for key, (step, args, _) in runs.items():
            t0 = time.perf_counter()
            jax.block_until_ready(step(*args))
            times[key].append(time.perf_counter() - t0)
    load_after = round(os.getloadavg()[0], 2)
    records = []
    for name, res in cases:
        med = {v: float(np.median(times[(name, res, v)]))
               for (n, r, v) in runs if (n, r) == (name, res)}
        rec = dict(task=name, resolution=res, batch=batch, grad=grad,
                   thickness_m=dax_tasks.get_spec(name, res).scene.thickness,
                   **{f"step_{v}_s": round(t, 5) for v, t in med.items()},
                   ratio_list=round(med["list"] / med["off"], 2),
                   ratio_all=round(med["all"] / med["off"], 2) if "all" in med else None,
                   info={v: runs[(name, res, v)][2] for v in med},
                   reps=reps, load_1min_before=load_before, load_1min_after=load_after)
        records.append(rec)
    return records


def targets(records) -> dict:
    """The issue's targets from the records (one batch size and program): ``{name: {value,
    limit, met}}``; at a batch other than 1 or with the action gradient each name ends
    with ``(batch B, with the action gradient)`` (what applies)."""
    by = {(r["task"], r["resolution"]): r for r in records}
    first = records[0] if records else {}
    batch, grad = first.get("batch", 1), first.get("grad", False)
    tags = ([f"batch {batch}"] if batch != 1 else []) + (["with the action gradient"]
                                                           if grad else [])
    out = {}

    def add(name, value, limit):
        name = f"{name} ({', '.join(tags)})" if tags else name
        out[name] = dict(value=value, limit=limit, met=bool(value <= limit))

    for (task, res), r in by.items():
        if res == "default":
            add(f"{task}: self-collision / off", r["ratio_list"], 1.5)
        elif task != "fold_tshirt":
            add(f"{task}@{res}: self-collision / off", r["ratio_list"], 2.0)
    if ("fold_cloth1", "reference") in by:
        r = by[("fold_cloth1", "reference")]
        add("fold_cloth1@reference off [s] (DaXBench / 1.5)", r["step_off_s"],
            round(DAXBENCH["fold_cloth1"]["step_s"] / 1.5, 4))
    if ("fold_tshirt", "reference") in by:
        r = by[("fold_tshirt", "reference")]
        add("fold_tshirt@reference off [s] (DaXBench, equal work)", r["step_off_s"],
            DAXBENCH["fold_tshirt"]["step_s"])
        add("fold_tshirt@reference with self-collision [s] (DaXBench)", r["step_list_s"],
            DAXBENCH["fold_tshirt"]["step_s"])
    return out


def render_table(path) -> str:
    """The Markdown table of a result file of this script (``--out``, JSON lines): per case
    the env step [s] off, with the neighbour list and with every pair, the ratios to off,
    the list's pairs, builds and overflow; then each target with its limit and whether it
    was met, and the load the run saw."""
    lines = [json.loads(t) for t in Path(path).read_text().splitlines() if t.strip()]
    cases = [r for r in lines if "task" in r]
    summary = next((r for r in lines if "targets" in r), None)

    def sec(v):
        return "-" if v is None else f"{v:.3g}"

    out = ["| task | resolution | vertices x substeps | off [s] | neighbour list [s] | "
           "every pair [s] | pairs / builds / overflow |",
           "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in cases:
        info = r.get("info", {}).get("list", {})
        lst = (f"{sec(r.get('step_list_s'))} ({r['ratio_list']}x)"
               if r.get("step_list_s") is not None else "-")
        every = (f"{sec(r.get('step_all_s'))} ({r['ratio_all']}x)"
                 if r.get("step_all_s") is not None else "-")
        out.append(f"| {r['task']} | {r['resolution']} | {info.get('n_vertices', '?')} x "
                   f"{info.get('substeps', '?')} | {sec(r.get('step_off_s'))} | {lst} | "
                   f"{every} | {info.get('pairs', '-')} / {info.get('builds', '-')} / "
                   f"{info.get('overflow', '-')} |")
    loads = [x for r in cases for x in (r.get("load_1min_before"), r.get("load_1min_after"))
             if x is not None]
    out.append("")
    out.append(f"Medians of {cases[0]['reps'] if cases else '?'} interleaved rounds in one "
               f"process, batch {cases[0].get('batch', 1) if cases else '?'}, the expert's "
               f"first action"
               f"{', the step with the action gradient' if cases and cases[0].get('grad') else ''}"
               f"; 1-minute load "
               f"{min(loads, default=float('nan')):.1f}-{max(loads, default=float('nan')):.1f}"
               f"{'; ' + summary['date'] if summary and 'date' in summary else ''}.")
    if summary:
        out.append("")
        out.append("| target | measured | limit | met |")
        out.append("| --- | --- | --- | --- |")
        for name, t in summary["targets"].items():
            out.append(f"| {name} | {t['value']:.3g} | {t['limit']:.3g} | "
                       f"{'yes' if t['met'] else 'no'} |")
    return "\n".join(out) + "\n"


def render_before_after(path) -> str:
    """The Markdown table of a before/after comparison (``python -m benchmarks.before_after
    --cmd "python -m benchmarks.cloth_self_collision ..."``): JSON lines of this script's
    records, each tagged with ``code`` ("before" or "after"), ``commit``, ``arm`` and the
    1-minute load when its arm began. Per case (task, resolution, batch, program): the
    step without and with self-collision of each code, the mean over its arms, the ratio
    list ÷ off of each, and the factor before ÷ after of the step with self-collision."""
    from benchmarks._report import file_date, read_result
    from benchmarks.before_after import arm_order

    path, recs = read_result(path)
    cases: dict = {}
    for r in recs:
        if "step_list_s" in r:  # the file may hold other benchmarks' records too
            key = (r["task"], r["resolution"], r.get("batch", 1), bool(r.get("grad")))
            cases.setdefault(key, {}).setdefault(r["code"], []).append(r)

    def mean(rs, field):
        return sum(r[field] for r in rs) / len(rs)

    out = ["| task | batch, program | off before / after [s] | with the list before / after [s] "
           "| list ÷ off before → after | before ÷ after (with the list) |",
           "|---|---|---|---|---|---|"]
    for (task, res, batch, grad), by in cases.items():
        if set(by) != {"before", "after"}:
            continue
        off = {c: mean(by[c], "step_off_s") for c in by}
        lst = {c: mean(by[c], "step_list_s") for c in by}
        name = task if res == "default" else f"{task}@{res}"
        out.append(f"| {name} | {batch}, {'step + action gradient' if grad else 'step'} | "
                   f"{off['before']:.3g} / {off['after']:.3g} | "
                   f"{lst['before']:.3g} / {lst['after']:.3g} | "
                   f"{lst['before'] / off['before']:.2f} → {lst['after'] / off['after']:.2f} | "
                   f"{lst['before'] / lst['after']:.2f} |")
    order = arm_order(recs)
    reps = sorted({r.get("reps") for r in recs if "step_list_s" in r})
    out += ["", f"Medians of {'/'.join(map(str, reps))} interleaved rounds per arm (the list "
            "and off variants alternate in one process), the mean over each code's arms; "
            f"the expert's first action; arms in the order run: {order}. "
            f"`{path.as_posix()}` ({file_date(path) or 'date not recorded'})."]
    return "\n".join(out) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=DEFAULT_CASES,
                        help="comma-separated TASK or TASK@RESOLUTION")
    parser.add_argument("--reps", type=int, default=9)
    parser.add_argument("--all-max", type=int, default=1024,
                        help="time the all-pairs variant up to this many vertices")
    parser.add_argument("--batch", type=int, default=1,
                        help="envs stepped at once (a VmapWrapper batch; the issue's "
                             "targets are at 1)")
    parser.add_argument("--grad", action="store_true",
                        help="time the step with the gradient of its reward with respect "
                             "to the actions (the program APG, SHAC and ILD run)")
    parser.add_argument("--out", default=None, help="also write the JSON lines here")
    args = parser.parse_args(argv)
    if args.batch < 1 or args.reps < 1:
        parser.error("--batch and --reps must be >= 1")
    cases = [tuple((c + "@default").split("@")[:2]) for c in args.cases.split(",")]
    records = measure(cases, args.reps, args.all_max, args.batch, args.grad)
    summary = dict(targets=targets(records), batch=args.batch, grad=args.grad,
                   jax=jax.__version__, cpus=os.cpu_count(),
                   date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    lines = [json.dumps(r) for r in records] + [json.dumps(summary)]
    for line in lines:
        print(line, flush=True)
    if args.out:
        with open(args.out, "w") as f:
            f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
