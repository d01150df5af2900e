"""Before-and-after timing of one change: the same benchmark commands run on two commits in
interleaved arms (ABBA by default), each record tagged with the arm it came from.

A speed claim about a change compares two codes measured in one sitting; on a shared
machine the load drifts over the hour such a run takes, so the arms alternate (before,
after, after, before: a linear drift weighs on both codes alike) and every record says
which arm, code and commit produced it and the 1-minute load when its arm began.

Each code runs from a detached git worktree of its commit (made under ``--workdir`` and
removed afterwards unless ``--keep``), with the worktree's packages and root first on
``PYTHONPATH`` and its own persistent XLA compilation cache, so that neither code reads
the other's compiled programs. Every command must print its results as JSON objects, one
per line on stdout (``--json`` of the benchmarks here); other lines are passed to stderr.

Usage::

    python -m benchmarks.before_after --before f7c51af --after HEAD \\
        --cmd "python -m benchmarks.rl_speed --json --tasks fold_cloth1 --methods apg --reps 3" \\
        --out benchmarks/results/DATE-training-speed-CHANGE.jsonl

``--out`` is JSON lines, appended record by record as each command prints them (a run cut
off, by Ctrl-C or SIGTERM, keeps what was written and removes its worktrees; :func:`main`
refuses an ``--out`` that exists unless ``--append``).
The table of such a file: ``python -m benchmarks.tables rl_speed_before_after FILE``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

#: The arms' order by name: ``abba`` alternates so that a linear drift in load cancels.
ORDERS = {"abba": ("before", "after", "after", "before"),
          "ab": ("before", "after"),
          "abab": ("before", "after", "before", "after")}


def resolve(repo: Path, ref: str) -> str:
    """The full commit hash ``ref`` names in ``repo``; ``ValueError`` when it names none."""
    res = subprocess.run(["git", "-C", str(repo), "rev-parse", "--verify", "--quiet",
                          f"{ref}^{{commit}}"], capture_output=True, text=True)
    if res.returncode != 0:
        raise ValueError(f"{ref!r} is not a commit of {repo}")
    return res.stdout.strip()


def add_worktree(repo: Path, commit: str, where: Path) -> Path:
    """A detached worktree of ``commit`` at ``where`` (made by ``git worktree add``)."""
    subprocess.run(["git", "-C", str(repo), "worktree", "add", "--detach", "--quiet",
                    str(where), commit], check=True)
    return where


def remove_worktree(repo: Path, where: Path) -> None:
    """Remove the worktree at ``where`` (forced: a benchmark may leave files in it)."""
    subprocess.run(["git", "-C", str(repo), "worktree", "remove", "--force", str(where)],
                   check=False)


def code_env(tree: Path, cache: Path) -> dict:
    """The environment of a command run on the code of ``tree``: this process's, with the
    tree's packages' ``src`` folders and its root first on ``PYTHONPATH`` and
    ``JAX_COMPILATION_CACHE_DIR`` at ``cache``."""
    env = dict(os.environ)
    paths = sorted(str(p) for p in (tree / "packages").glob("*/src"))
    env["PYTHONPATH"] = os.pathsep.join([*paths, str(tree)]
                                        + ([env["PYTHONPATH"]] if env.get("PYTHONPATH")
                                           else []))
    env["JAX_COMPILATION_CACHE_DIR"] = str(cache)
    return env


def tag(line: str, arm: int, code: str, commit: str, load: float) -> dict | None:
    """The record of one stdout line with its arm's tags added, or ``None`` for a line
    that is not a JSON object."""
    line = line.strip()
    if not line.startswith("{"):
        return None
    try:
        rec = json.loads(line)
    except json.JSONDecodeError:
        return None
    if not isinstance(rec, dict):
        return None
    rec.update(arm=arm, code=code, commit=commit[:12], load1_at_arm_start=load)
    return rec


def arm_order(records) -> str:
    """The arms of tagged ``records`` (:func:`tag`) in the order run, as a table caption
    says them: ``"before (COMMIT, load L), after (COMMIT, load L), ..."``."""
    arms = sorted({(r["arm"], r["code"], r["commit"], r.get("load1_at_arm_start"))
                   for r in records})
    return ", ".join(f"{code} ({commit}, load {load})" for _, code, commit, load in arms)


def run_arms(repo: Path, commits: dict, commands: list, order, out: Path, workdir: Path,
             keep: bool = False, log=sys.stderr) -> int:
    """Run every command of ``commands`` (argument lists) once per arm of ``order`` (a
    sequence of ``"before"`` / ``"after"``) on that arm's commit of ``commits``,
    appending each tagged record to ``out`` as it arrives. Returns the number of records
    written; ``RuntimeError`` names the first command that failed (records written before
    it stay)."""
    trees = {code: add_worktree(repo, commits[code], workdir / code)
             for code in dict.fromkeys(order)}
    written = 0
    try:
        for arm, code in enumerate(order, start=1):
            env = code_env(trees[code], workdir / f"jax-cache-{code}")
            load = round(os.getloadavg()[0], 2)
            print(f"arm {arm}: {code} {commits[code][:12]}, load {load}", file=log,
                  flush=True)
            for cmd in commands:
                proc = subprocess.Popen(cmd, cwd=trees[code], env=env, text=True,
                                        stdout=subprocess.PIPE)
                try:
                    for line in proc.stdout:
                        rec = tag(line, arm, code, commits[code], load)
                        if rec is None:
                            print(line, end="", file=log)
                            continue
                        with open(out, "a") as f:  # one whole line per record
                            f.write(json.dumps(rec) + "\n")
                        written += 1
                finally:
                    if proc.poll() is None:  # stopped from outside: stop the command too
                        proc.terminate()
                        proc.wait()
                if proc.wait() != 0:
                    raise RuntimeError(f"arm {arm} ({code}): {shlex.join(cmd)} exited "
                                       f"{proc.returncode}")
    finally:
        if not keep:
            for tree in trees.values():
                remove_worktree(repo, tree)
    return written


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.before_after",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--before", required=True, help="commit of the code before the change")
    p.add_argument("--after", required=True, help="commit of the code after it")
    p.add_argument("--cmd", action="append", required=True,
                   help="benchmark command printing JSON lines (repeatable; run in order)")
    p.add_argument("--order", choices=sorted(ORDERS), default="abba")
    p.add_argument("--out", required=True, help="JSON lines file the records go to")
    p.add_argument("--append", action="store_true", help="add to an existing --out")
    p.add_argument("--repo", default=".", help="the git repository (default: here)")
    p.add_argument("--workdir", help="where the worktrees and caches go (default: a "
                   "temporary folder)")
    p.add_argument("--keep", action="store_true",
                   help="keep the worktrees afterwards (with --workdir)")
    args = p.parse_args(argv)
    repo, out = Path(args.repo).resolve(), Path(args.out)
    if args.keep and not args.workdir:
        p.error("--keep needs --workdir (a temporary folder is removed at the end)")
    if out.exists() and not args.append:
        p.error(f"{out} exists: pass --append to add to it, or name a new file")
    try:
        commits = {"before": resolve(repo, args.before), "after": resolve(repo, args.after)}
    except ValueError as err:
        p.error(str(err))
    commands = [shlex.split(c) for c in args.cmd]
    # a run stopped with SIGTERM (kill, a job scheduler) unwinds like Ctrl-C: the running
    # command is stopped and the worktrees are removed; the records written stay
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="before-after-") as tmp:
        workdir = Path(args.workdir) if args.workdir else Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        try:
            n = run_arms(repo, commits, commands, ORDERS[args.order], out.resolve(),
                         workdir, keep=args.keep)
        except RuntimeError as err:
            print(err, file=sys.stderr)
            return 1
    print(json.dumps({"out": str(out), "records": n, "order": args.order,
                      "before": commits["before"][:12], "after": commits["after"][:12]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
