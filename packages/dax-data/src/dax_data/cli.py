"""The ``dax-data`` command line: generate, goals, inspect, validate, export, score.

Errors a user can fix (a bad argument, a missing, truncated or corrupted file, a file made
with other arguments, a newer format version) print one line ``dax-data: error: ...`` on
stderr, without a traceback, and exit with status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

from . import __version__
from . import fileformat as ff

EXIT_ERROR = 2


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _nonneg_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}") from None
    if not value >= 0:  # NaN too
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text}")
    return value


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dax-data", description=(
        "Scripted-expert demonstrations, goal sets and exports for the DaX tasks."))
    p.add_argument("--version", action="version", version=f"dax-data {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    g = sub.add_parser("generate", help="record episodes into an HDF5 file (resumable)")
    g.add_argument("--task", required=True, help="task name, e.g. fold_cloth1")
    g.add_argument("--episodes", required=True, type=_positive_int)
    g.add_argument("--seed", type=_nonneg_int, default=0,
                   help="seed of the first episode; episode i uses seed + i (default 0; "
                        "every seed in 0 .. 4294967295)")
    g.add_argument("--out", required=True, help="output .h5 file")
    g.add_argument("--policy", choices=("expert", "random"), default="expert")
    g.add_argument("--point-stride", type=_positive_int, default=1, metavar="K",
                   help="store the object points every K steps (and the last; default 1)")
    g.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                   help="change a TaskSpec field (substeps=160) or a scene field "
                        "(scene.n=6); VALUE is JSON; repeatable (for small test runs)")
    g.add_argument("--obs", default="state", metavar="MODES",
                   help="observation modes to store, comma-separated: state (always), "
                        "height, rgb (top-down pictures; default: state)")
    g.add_argument("--image-size", type=_positive_int, default=64, metavar="S",
                   help="picture size in pixels for height / rgb (default 64)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.add_argument("--json", action="store_true", help="print the summary as JSON")
    g.add_argument("--lock-timeout", type=_seconds, default=0.0, metavar="SECONDS",
                   help="wait up to this long for another process writing the same file "
                        "(saying who it is) instead of refusing at once (default 0)")

    d = sub.add_parser("standard", help="record a task's standard demonstration sets "
                                        "(what the imitation-learning methods train on)")
    d.add_argument("--task", required=True, help="task name or 'all'")
    d.add_argument("--out", required=True, help="output directory")
    d.add_argument("--set", default="all", help="comma-separated sets (transporter, ild) "
                                                "or all (those that apply to the task)")
    d.add_argument("--image-size", type=_positive_int, default=64, metavar="S",
                   help="picture size of the image sets in pixels (default 64)")
    d.add_argument("--no-progress", action="store_true", help="no progress bar")
    d.add_argument("--lock-timeout", type=_seconds, default=300.0, metavar="SECONDS",
                   help="wait up to this long for another process making the same set, "
                        "saying who it is, then give up (default 300)")

    o = sub.add_parser("goals", help="write goal files in dax-tasks' format")
    o.add_argument("--task", required=True, help="task name or 'all'")
    o.add_argument("--out", required=True, help="output directory")

    i = sub.add_parser("inspect", help="summarise a demonstration file")
    i.add_argument("file")
    i.add_argument("--json", action="store_true")

    v = sub.add_parser("validate", help="check a demonstration file completely")
    v.add_argument("file")

    e = sub.add_parser("export", help="export an episode for ParaView / Blender, or the "
                                      "whole file as a Minari dataset")
    e.add_argument("file")
    e.add_argument("--episode", type=_nonneg_int,
                   help="episode to export (vtu, xdmf, ply; required for those)")
    e.add_argument("--format", choices=("vtu", "xdmf", "ply", "minari"), required=True)
    e.add_argument("--out", required=True, help="output directory (for minari: the "
                   "datasets root, MINARI_DATASETS_PATH)")
    e.add_argument("--dataset-id", help="minari only: the dataset id (default "
                   "dax/<task>/<policy>-v0)")

    s = sub.add_parser("score", help="expert and random final r_gt over seeds")
    s.add_argument("--task", required=True)
    s.add_argument("--seeds", type=_positive_int, default=20)
    s.add_argument("--seed", type=_nonneg_int, default=0, help="first seed (default 0)")
    s.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                   help="as for generate")
    s.add_argument("--json", action="store_true")
    return p


def _fmt_score(d: dict) -> str:
    return f"{d['mean']:.4f} ± {d['sem']:.4f} (n={len(d['scores'])}, {d['seconds']:.1f} s)"


def _generate(a) -> None:
    from .record import generate, parse_overrides

    out = generate(a.task, a.episodes, a.seed, a.out, policy=a.policy,
                   point_stride=a.point_stride, progress=not a.no_progress,
                   overrides=parse_overrides(a.task, a.override), obs=a.obs,
                   image_size=a.image_size, lock_wait=a.lock_timeout)
    if a.json:
        print(json.dumps(out, indent=1))
        return
    spe = out["seconds_per_episode"]
    spe = f"{spe:.3f} s/episode (median)" if spe is not None else "nothing to record"
    print(f"{out['path']}: {out['episodes']} episodes of {out['task']} "
          f"({out['recorded_now']} new, {out['resumed_from']} kept), score "
          f"{out['score_mean']:.4f} ± {out['score_sem']:.4f}, {spe}, "
          f"{out['file_bytes']} bytes")


def _standard(a) -> None:
    from .goalsets import task_names
    from .record import make_task
    from .standard import STANDARD_SETS, applies, ensure_standard, get_set

    names = list(STANDARD_SETS) if a.set == "all" else [n.strip() for n in a.set.split(",")]
    for n in names:
        get_set(n)
    for task in task_names(a.task):
        env = make_task(task)
        for n in names:
            if not applies(env, n):
                if a.set != "all":
                    raise ValueError(f"standard set {n!r} does not apply to {task} "
                                     f"({env.spec.action_kind} actions)")
                continue
            path = ensure_standard(task, n, a.out, image_size=a.image_size,
                                   progress=not a.no_progress, lock_wait=a.lock_timeout)
            s = get_set(n)
            print(f"{task} {n}: {s.episodes} episodes from seed {s.seed} -> {path}")


def _goals(a) -> None:
    from .goalsets import task_names, write_goal

    for name in task_names(a.task):
        r = write_goal(name, a.out)
        print(f"{r['task']}: {r['points']} points -> {r['path']} ({r['seconds']:.1f} s)")


def _inspect(a) -> None:
    with ff.DemoFile(a.file) as f:
        info = f.summary()
        shapes = f.episode_shapes(0) if len(f) else {}
    info["episode_0_shapes"] = shapes
    if a.json:
        print(json.dumps(info, indent=1))
        return
    print(f"{info['path']}: dax-data format version {info['format_version']}, "
          f"task {info['task']}, {info['episodes']} episodes, {info['file_bytes']} bytes")
    print(f"  generator: {json.dumps(info['generator'])}")
    print(f"  versions:  {json.dumps(info['versions'])}")
    print(f"  created:   {info['created_utc']}  fingerprint {info['fingerprint']}")
    if info["episodes"]:
        print(f"  score (final r_gt): {info['score_mean']:.4f} ± {info['score_sem']:.4f}")
        print(f"  episode 0 shapes: {json.dumps(shapes)}")


def _validate(a) -> None:
    from .semantics import check_semantics

    with ff.DemoFile(a.file) as f:
        f.verify()
        notes = check_semantics(f)
        n, ver = len(f), f.meta["format_version"]
    extra = f"; {'; '.join(notes)}" if notes else ""
    print(f"{a.file}: ok ({n} episodes, format version {ver}{extra})")


def _export(a) -> None:
    if a.format == "minari":
        from .minari_export import export_minari

        path = export_minari(a.file, a.out, a.dataset_id)
        print(f"wrote Minari dataset {path.relative_to(Path(a.out).resolve()).as_posix()} "
              f"under {a.out} (load it with MINARI_DATASETS_PATH={a.out})")
        return
    if a.episode is None:
        raise ValueError(f"export --format {a.format} needs --episode K")
    from .export import export_episode

    paths = export_episode(a.file, a.episode, a.format, a.out)
    print(f"wrote {len(paths)} files to {a.out}")


def _score(a) -> None:
    from .record import parse_overrides, score

    out = score(a.task, a.seeds, a.seed, overrides=parse_overrides(a.task, a.override))
    if a.json:
        print(json.dumps(out, indent=1))
        return
    for policy in ("expert", "random"):
        if policy in out:
            print(f"{a.task} {policy}: final r_gt {_fmt_score(out[policy])}")
    for policy in out["skipped"]:
        print(f"{a.task} {policy}: not available for this task")


COMMANDS = {"generate": _generate, "standard": _standard, "goals": _goals, "inspect": _inspect,
            "validate": _validate, "export": _export, "score": _score}


def _warn_in_one_line(message, category, *args, **kwargs) -> None:
    print(f"dax-data: warning: {' '.join(str(message).split())}", file=sys.stderr)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warn_in_one_line
            COMMANDS[args.command](args)
    except KeyboardInterrupt:
        print("dax-data: interrupted; completed episodes are on disk, rerun the same command "
              "to resume", file=sys.stderr)
        return 130
    except (ValueError, OSError, NotImplementedError, ImportError) as err:  # DataFileError,
        # GoalFileError; ImportError: an optional dependency (minari) is missing
        msg = " ".join(str(err).split()) or type(err).__name__
        print(f"dax-data: error: {msg}", file=sys.stderr)
        return EXIT_ERROR
    except (MemoryError, RuntimeError) as err:
        if not _out_of_memory(err):
            raise
        print(f"dax-data: error: out of memory ({_short(err)}); ask for less (fewer "
              f"points, smaller pictures, fewer seeds)", file=sys.stderr)
        return EXIT_ERROR
    return 0


def _out_of_memory(err: BaseException) -> bool:
    """Whether ``err`` is an allocation failure: NumPy's ``MemoryError`` or XLA's
    ``RESOURCE_EXHAUSTED`` (a ``RuntimeError``); other ``RuntimeError`` s are bugs."""
    return isinstance(err, MemoryError) or "RESOURCE_EXHAUSTED" in str(err)


def _short(err: BaseException) -> str:
    return " ".join(str(err).split())[:160] or type(err).__name__


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
