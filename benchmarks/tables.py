"""Tables generated from result files, and the README blocks that hold them.

    python -m benchmarks.tables scores DIR [--tasks T1,T2] [--methods M1,M2]
                                           [--budget quick|full] [--include-stale]
    python -m benchmarks.tables KIND FILE [FILE ...]     # a kind of FILE_KINDS
    python -m benchmarks.tables check [README.md ...]
    python -m benchmarks.tables update [README.md ...]

``scores``: the score table of a published grid (a directory under ``benchmarks/results/``
holding ``results.csv`` and ``run.json``, or a results CSV), as ``dax-bench report
--markdown`` prints it (:func:`dax_algos.bench.summary.markdown_tables`): methods as rows,
tasks as columns, the standard-error convention and where the rows come from stated under
the table, stale rows (:mod:`dax_algos.bench.provenance`) left out unless
``--include-stale`` (then marked †). Every other kind (:data:`FILE_KINDS`) is the table of
one benchmark's result file(s), rendered by a function of the benchmark module that writes
them, with what the file records of its machine, load and date under the table.

A README holds a generated table between two markers::

    <!-- generated: python -m benchmarks.tables scores benchmarks/results/DIR --include-stale -->
    ...the command's output...
    <!-- end generated -->

``check`` renders every block of the given READMEs (default: every ``README.md`` and
``README_*.md`` of the repository) again and exits 1 naming each block that differs;
``update`` rewrites them. Paths in a marker are relative to the repository root; run from
there.
"""

from __future__ import annotations

import argparse
import difflib
import re
import shlex
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BEGIN = "<!-- generated: python -m benchmarks.tables "
END = "<!-- end generated -->"
_BLOCK = re.compile(r"^<!-- generated: python -m benchmarks\.tables (?P<args>.*?) -->\n"
                    r"(?P<body>.*?)^<!-- end generated -->$", re.M | re.S)
#: directories never searched for READMEs
_SKIP = {".git", ".nox", ".venv", "venv", "node_modules", "__pycache__", "build", "dist"}


def _names(text: str | None):
    return None if text is None else [n.strip() for n in text.split(",") if n.strip()]


def render_scores(path, tasks=None, methods=None, budget=None, include_stale=False) -> str:
    """The score table of the grid at ``path`` (see the module docstring)."""
    from dax_algos.bench import summary

    path = Path(path)
    full = path if path.is_absolute() else ROOT / path
    label = (path if path.suffix == ".csv" else path / "results.csv").as_posix()
    return summary.markdown_tables(full, budget, include_stale, _names(tasks),
                                   _names(methods), label=label)


#: The table kinds rendered from result files: kind -> (module, function, what the table
#: is, how many files). ``function(*paths)`` returns the Markdown table of the files.
FILE_KINDS = {
    "throughput": ("benchmarks.tasks", "render_throughput_table",
                   "the task throughput table of a benchmarks.tasks throughput JSON file", 1),
    "task_speed": ("benchmarks.tasks", "render_speed_table",
                   "the per-task step times at the default and the reference resolution "
                   "(benchmarks.tasks --json records gathered in one JSON file)", 1),
    "self_collision": ("benchmarks.cloth_self_collision", "render_table",
                       "the cloth self-collision table of a benchmarks.cloth_self_collision "
                       "JSONL file", 1),
    "self_collision_before_after": ("benchmarks.cloth_self_collision", "render_before_after",
                                    "the cloth self-collision step before and after a code "
                                    "change, arms interleaved (a benchmarks.before_after "
                                    "JSONL file of benchmarks.cloth_self_collision records)",
                                    1),
    "resolution": ("benchmarks.resolution", "render_table",
                   "one row per task of resolution studies (benchmarks.tasks resolution "
                   "JSON files)", "+"),
    "physics_gpu_cpu": ("benchmarks.physics", "render_gpu_cpu_table",
                        "the solver benchmarks on an accelerator beside a CPU (the "
                        "accelerator's JSON lines, a side_by_side and a grad_over_forward "
                        "document)", "+"),
    "cloth_mesh": ("benchmarks.physics_cloth", "render_mesh_table",
                   "the cloth mesh path's stencil against its scatter spring sum (a "
                   "benchmarks.physics cloth-mesh JSONL file)", 1),
    "cloth_sag": ("benchmarks.physics_cloth", "render_sag_table",
                  "the hanging-cloth sag against resolution and substep (a benchmarks.physics "
                  "cloth-sag-study JSON file)", 1),
    "side_by_side": ("benchmarks.side_by_side", "render_table",
                     "DaX beside the peer engines per scene (a benchmarks.side_by_side JSON "
                     "file)", 1),
    "scaling": ("benchmarks.scaling", "render_table",
                "rollouts forward and backward per device count (benchmarks.scaling JSON "
                "files)", "+"),
    "apg_horizon": ("benchmarks.horizon_sweep", "render_table",
                    "APG's gradient norm and score per backpropagation window "
                    "(benchmarks.horizon_sweep JSONL files)", "+"),
    "rl_speed": ("benchmarks.rl_speed", "render_table",
                 "time per RL training update (a benchmarks.rl_speed JSONL file)", 1),
    "rl_speed_before_after": ("benchmarks.rl_speed", "render_before_after",
                              "time per training update before and after a code change, "
                              "arms interleaved (a JSONL file of benchmarks.rl_speed and "
                              "benchmarks.il_speed records tagged code, commit, arm)", 1),
    "il_speed": ("benchmarks.il_speed", "render_table",
                 "Transporter's and ILD's training and inference cost (a "
                 "benchmarks.il_speed JSONL file)", 1),
    "findings": ("benchmarks.findings", "render_findings",
                 "the original benchmark's findings checked against a grid directory's "
                 "results.csv", 1),
    "untrained": ("benchmarks.findings", "render_untrained",
                  "each learner against its untrained policy, from a grid directory's "
                  "results.csv", 1),
    "added_seeds": ("benchmarks.findings", "render_added_seeds",
                    "each learner cell holding more seeds than the grid's others against "
                    "its untrained policy on the common seeds, the added ones and all, "
                    "from a grid directory's results.csv", 1),
    "budgets": ("benchmarks.budgets", "render_table",
                "each learner's budget per task and whether its learning curve has "
                "flattened, from a grid directory's results and learning curves", 1),
    "budget_reads": ("benchmarks.budgets", "render_reads",
                     "each budget's curve read off a longer run of its config, and the "
                     "longer run's score against the budget's (benchmarks.ablate JSONL "
                     "files)", "+"),
    "training_throughput": ("benchmarks.budgets", "render_throughput",
                            "each learner's env steps per second during training beside "
                            "the env's own rate at its batch (a grid directory and a "
                            "benchmarks.tasks throughput JSON file)", 2),
    "ablation": ("benchmarks.ablate", "render_table",
                 "learner ablations: each variant against the baseline, paired by seed "
                 "(benchmarks.ablate JSONL files)", "+"),
    "gradient_noise": ("benchmarks.gradient_noise", "render_table",
                       "the signal-to-noise ratio of a learner's first policy gradient "
                       "across independent batches (a benchmarks.gradient_noise JSONL "
                       "file)", 1),
    "planner_objective": ("benchmarks.planner_objective", "render_table",
                          "the planners' score beside what they optimise, per step of the "
                          "grid's episodes (a benchmarks.planner_objective JSONL file)", 1),
    "transporter_picks": ("benchmarks.transporter_picks", "render_table",
                          "where the trained Transporter networks pick and place against "
                          "the expert along their evaluation episodes (a "
                          "benchmarks.transporter_picks JSONL file)", 1),
    "ild_weighting": ("benchmarks.ild_weighting", "render_table",
                      "ILD's score per state-distance weighting (a benchmarks.ild_weighting "
                      "JSONL file)", 1),
}


#: The kinds rendered from a grid directory's rows, which take ``--include-stale``.
GRID_KINDS = ("findings", "untrained", "added_seeds", "budgets", "training_throughput")


def render_file_kind(kind: str, paths, include_stale: bool = False) -> str:
    """The table of ``kind`` (:data:`FILE_KINDS`) from the result files ``paths`` (a
    grid's stale rows counted too with ``include_stale``, :data:`GRID_KINDS` only)."""
    import importlib

    module, function, _, _ = FILE_KINDS[kind]
    render_fn = getattr(importlib.import_module(module), function, None)
    if render_fn is None:
        raise ValueError(f"{module} has no {function}")
    extra = {"include_stale": True} if include_stale else {}
    try:
        text = render_fn(*[Path(p) for p in paths], **extra)
    except (KeyError, TypeError, IndexError, AttributeError) as err:  # a file of another kind
        raise ValueError(f"{' '.join(map(str, paths))}: not a {kind} result file "
                         f"({type(err).__name__}: {err})") from None
    lines = text.splitlines()
    if len(lines) < 3 or not lines[2].startswith("|"):
        raise ValueError(f"{' '.join(map(str, paths))}: no {kind} rows in it")
    return text if text.endswith("\n") else text + "\n"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.tables",
                                description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="kind", required=True)
    s = sub.add_parser("scores", help="the score table of a published grid")
    s.add_argument("path", help="a grid directory (results.csv, run.json) or a results CSV")
    s.add_argument("--tasks", default=None, help="only these tasks, in this order")
    s.add_argument("--methods", default=None, help="only these methods, in this order")
    s.add_argument("--budget", default=None, choices=("quick", "full"))
    s.add_argument("--include-stale", action="store_true",
                   help="count stale rows (marked †)")
    for kind, (_, _, what, nargs) in FILE_KINDS.items():
        k = sub.add_parser(kind, help=what)
        k.add_argument("paths", nargs=nargs, metavar="FILE",
                       help="result file(s), relative to the repository root or absolute")
        if kind in GRID_KINDS:
            k.add_argument("--include-stale", action="store_true",
                           help="count a grid's stale rows too (the footer says how many "
                                "and why)")
    for name, what in (("check", "exit 1 if a README's generated block differs from what "
                                 "its command renders now"),
                       ("update", "rewrite every README's generated blocks")):
        c = sub.add_parser(name, help=what)
        c.add_argument("readmes", nargs="*", help="README files (default: every README.md "
                                                  "and README_*.md of the repository)")
    return p


def render(argv) -> str:
    """What ``python -m benchmarks.tables`` prints for the table arguments ``argv``."""
    args = _parser().parse_args(list(argv))
    if args.kind == "scores":
        return render_scores(args.path, args.tasks, args.methods, args.budget,
                             args.include_stale)
    if args.kind in FILE_KINDS:
        return render_file_kind(args.kind, args.paths, getattr(args, "include_stale", False))
    raise ValueError(f"{args.kind} renders no table")


def readmes(root: Path = ROOT) -> list[Path]:
    """Every ``README.md`` and ``README_*.md`` under ``root`` (not in hidden,
    virtual-environment or build directories), sorted."""
    found = []
    for path in sorted({*root.rglob("README.md"), *root.rglob("README_*.md")}):
        rel = path.relative_to(root).parts[:-1]
        if not any(p in _SKIP or p.startswith(".") for p in rel):
            found.append(path)
    return found


def blocks(text: str) -> list[tuple[re.Match, list]]:
    """The generated blocks of a README's ``text``: ``(match, table arguments)``."""
    return [(m, shlex.split(m["args"])) for m in _BLOCK.finditer(text)]


def stale_blocks(path: Path) -> list[tuple[str, str]]:
    """``(marker arguments, unified diff)`` for each block of ``path`` whose body is not
    what its command renders now (a block whose command fails: the error as the diff)."""
    text = path.read_text()
    out = []
    for m, argv in blocks(text):
        try:
            now = render(argv)
        except (ValueError, OSError, SystemExit) as err:
            out.append((m["args"], f"the command fails: {err}"))
            continue
        if now != m["body"]:
            diff = "".join(difflib.unified_diff(m["body"].splitlines(True),
                                                now.splitlines(True), "README", "now"))
            out.append((m["args"], diff))
    return out


def update(path: Path) -> int:
    """Rewrite the generated blocks of ``path``; returns how many changed."""
    text = path.read_text()
    changed = 0

    def fill(m):
        nonlocal changed
        now = render(shlex.split(m["args"]))
        changed += now != m["body"]
        return f"{BEGIN}{m['args']} -->\n{now}{END}"

    new = _BLOCK.sub(fill, text)
    if new != text:
        path.write_text(new)
    return changed


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    if args.kind not in ("check", "update"):  # a table kind: render() dispatches it
        try:
            print(render(argv if argv is not None else sys.argv[1:]), end="")
        except ValueError as err:
            print(f"benchmarks.tables: error: {err}", file=sys.stderr)
            return 2
        return 0
    paths = [Path(p) for p in args.readmes] or readmes()
    if args.kind == "update":
        for p in paths:
            n = update(p)
            if n:
                print(f"{p}: {n} block(s) rewritten")
        return 0
    bad = [(p, a, d) for p in paths for a, d in stale_blocks(p)]
    for p, a, d in bad:
        print(f"{p}: the block of `python -m benchmarks.tables {a}` differs from its "
              f"files:\n{d}")
    if bad:
        print(f"{len(bad)} generated block(s) out of date; `python -m benchmarks.tables "
              f"update` rewrites them", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
