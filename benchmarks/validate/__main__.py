"""``python -m benchmarks.validate --out DIR``: run the validation suite and write
``validation.json``, ``validation.md`` and one chart per check; exit status 1 when a check
fails (2 when a check crashed). ``--only NAME ...`` runs some checks, ``--list`` names
them, ``--quick`` runs the smallest sweeps (a quick look, not the record)."""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
import traceback

from . import Result, _finite, checks


def _fmt(x, pct=True):
    if x is None:
        return "-"
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return f"{x:.2%}" if pct else f"{x:.2f}"


def markdown(results: list[Result], crashed: dict, header: str, docs: dict) -> str:
    """The validation table and, per check, its docstring (the reference) and sweep."""
    lines = [header, "",
             "| check | solver | reference | default resolution | error | tolerance | pass "
             "| order expected | order measured | Pareto note |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        lines.append(
            f"| {r.name} | {r.solver} | {r.reference} | {r.default:g} "
            f"{r.resolution_label} | {_fmt(r.error)} | {_fmt(r.tolerance)} | "
            f"{'PASS' if r.passed else 'FAIL'} | "
            f"{'-' if r.expected_order is None else f'{r.expected_order:g}'} | "
            f"{_fmt(r.measured_order, pct=False)} | {r.pareto_note} |")
    for name, err in crashed.items():
        lines.append(f"| {name} | - | - | - | - | - | CRASHED: {err} | - | - | - |")
    for r in results:
        doc = " ".join((docs.get(r.name) or "").split())
        lines += ["", f"### {r.name}", "", doc, "", "Measured: " + r.quantity
                  + (". Conditions: " + ", ".join(
                      f"{k}: {'yes' if v else 'NO'}" for k, v in r.conditions.items())
                     if r.conditions else "") + (f". {r.notes}" if r.notes else ""), "",
                  f"| {r.resolution_label} | cell size / step | {r.error_label} (signed) "
                  "| measured | expected | wall s |", "|---|---|---|---|---|---|"]
        for p in r.points:
            meas = "-" if p.measured is None else f"{p.measured:.6g}"
            exp = "-" if p.expected is None else f"{p.expected:.6g}"
            lines.append(f"| {p.resolution:g} | {p.cell_size:.4g} | {p.error:+.3%} | {meas} | "
                         f"{exp} | {p.wall_s:.3g} |")
    return "\n".join(lines) + "\n"


def chart(r: Result, path: str) -> bool:
    """Error against cell size (or FD step) and against wall time; False without
    matplotlib."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    pts = [p for p in r.points if p.error and math.isfinite(p.error)]
    fig, ax = plt.subplots(1, 2, figsize=(8, 3.2))
    h = [p.cell_size for p in pts]
    e = [abs(p.error) for p in pts]
    ax[0].loglog(h, e, "o-", label="measured")
    for p in pts:
        ax[0].annotate(f"{p.resolution:g}", (p.cell_size, abs(p.error)), fontsize=7)
    if r.expected_order and pts:
        ref = max(pts, key=lambda p: p.cell_size)
        hh = sorted(h)
        ax[0].loglog(hh, [abs(ref.error) * (x / ref.cell_size) ** r.expected_order for x in hh],
                     "k--", lw=0.8, label=f"order {r.expected_order:g}")
    ax[0].axhline(r.tolerance, color="r", lw=0.8, ls=":", label="tolerance")
    ax[0].set_xlabel("FD step h (relative)" if "FD step" in r.resolution_label
                     else "cell size / edge [m]")
    ax[0].set_ylabel(f"|{r.error_label}|")
    ax[0].legend(fontsize=7)
    ax[1].loglog([p.wall_s for p in pts], e, "s-")
    for p in pts:
        ax[1].annotate(f"{p.resolution:g}", (p.wall_s, abs(p.error)), fontsize=7)
    ax[1].axhline(r.tolerance, color="r", lw=0.8, ls=":")
    ax[1].set_xlabel("wall time of the run [s]")
    fig.suptitle(f"{r.name}: {r.quantity}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return True


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.validate", description=__doc__)
    ap.add_argument("--out", default="validation_out", help="output directory")
    ap.add_argument("--only", nargs="+", help="run only these checks")
    ap.add_argument("--quick", action="store_true", help="smallest sweeps (not the record)")
    ap.add_argument("--list", action="store_true", help="list the checks and exit")
    ap.add_argument("--no-tasks", action="store_true",
                    help="skip the task-level rows (they need dax-tasks)")
    args = ap.parse_args(argv)
    found = checks(tasks=not args.no_tasks)
    if args.list:
        for name, fn in found.items():
            print(f"{name}: {(fn.__doc__ or '').strip().splitlines()[0]}")
        return 0
    names = args.only or list(found)
    unknown = [n for n in names if n not in found]
    if unknown:
        raise SystemExit(f"unknown check(s) {unknown}; valid: {', '.join(found)}")
    os.makedirs(args.out, exist_ok=True)
    level = "quick" if args.quick else "default"
    results, crashed, seconds = [], {}, {}
    t_all = time.perf_counter()
    for name in names:
        t0 = time.perf_counter()
        print(f"[validate] {name} ...", file=sys.stderr, flush=True)
        try:
            r = found[name](level)
        except Exception as err:  # a crash is reported, and fails the run
            traceback.print_exc()
            crashed[name] = f"{type(err).__name__}: {err}"
            continue
        seconds[name] = time.perf_counter() - t0
        results.append(r)
        chart(r, os.path.join(args.out, f"{name}.png"))
        print(f"[validate] {name}: error {r.error:.3%} (tolerance {r.tolerance:.2%}) "
              f"{'PASS' if r.passed else 'FAIL'} in {seconds[name]:.1f} s", file=sys.stderr,
              flush=True)
    total = time.perf_counter() - t_all
    import jax

    from dax_physics import __version__

    meta = dict(level=level, total_s=total, seconds=seconds, jax=jax.__version__,
                dax_physics=__version__, backend=jax.default_backend(),
                machine=platform.machine(), cpus=os.cpu_count())
    with open(os.path.join(args.out, "validation.json"), "w") as fh:
        json.dump(_finite(dict(meta=meta, results=[r.to_dict() for r in results],
                               crashed=crashed)), fh, indent=1)
    header = (f"# dax-physics validation ({level})\n\n{sum(r.passed for r in results)} of "
              f"{len(results) + len(crashed)} checks pass; {total:.0f} s on {os.cpu_count()} "
              f"CPUs, jax {jax.__version__}, dax-physics {__version__}. Errors are relative "
              "and at the default resolution; orders are least-squares slopes of log |error| "
              "against log cell size.")
    with open(os.path.join(args.out, "validation.md"), "w") as fh:
        fh.write(markdown(results, crashed, header, {n: found[n].__doc__ for n in names}))
    print(json.dumps(dict(passed=[r.name for r in results if r.passed],
                          failed=[r.name for r in results if not r.passed],
                          crashed=list(crashed), total_s=round(total, 1))))
    if crashed:
        return 2
    return 0 if all(r.passed for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
