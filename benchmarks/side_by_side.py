"""Side-by-side benchmark: DaX against the Taichi and Warp reference scripts, in one run.

Runs, interleaved in one process tree so that all engines see the same machine state:

* the peer reference scripts (``mpm3d_taichi.py``, ``mpm3d_warp.py``, ``cloth_taichi.py``,
  ``cloth_warp.py``) with their own interpreter (``--peers-python``; they need numpy,
  taichi and warp-lang, which DaX must not depend on). They are run as subprocesses and
  only their ``RESULT {json}`` line is read: nothing of theirs is imported here;
* DaX's own benchmark, ``python -m benchmarks.physics ... --json``, with ``--dax-python``
  (default: the interpreter running this script). Its output is the last stdout line
  that starts with ``{``.

Scenes (see the peers' README.md for the exact scene definitions):

=========  ===============================  ===========================================
name       scene                            measured
=========  ===============================  ===========================================
fluid32    MPM block drop, fluid, 32^3      throughput (100 substeps) + agreement (500)
elastic32  MPM block drop, elastic, 32^3    throughput (100 substeps) + agreement (500)
fluid64    MPM block drop, fluid, 64^3      throughput only (N = 32768)
cloth      mass-spring cloth 64x64          throughput + mean height after 1000 substeps
=========  ===============================  ===========================================

Order of work: first one agreement ("check") run per engine and scene, then ``--reps``
rounds of throughput runs. In each round, every scene is run by every engine back to back,
and the engine order rotates from round to round so no engine always runs first.

Axis convention. The peers use y up: a peer position is (x, up, z). DaX uses z up. The
same physical point is DaX [x, y, z] = peer [x, z_peer, y_peer], i.e. DaX
``mean_position[1]`` <-> peer ``mean_x[2]`` and DaX ``mean_position[2]`` <-> peer
``mean_x[1]``. The mapping is a swap of the last two axes, so it is its own inverse
(``swap_yz``). Agreement is reported in the peers' y-up order. For cloth, DaX's
``mean_height`` is compared with the peers' ``mean_x[1]``.

Notes on the numbers.

* Every ``substeps_per_s`` and ``compile_s`` in the output is the median over the
  successful repetitions (``runs`` lists each one; ``min``/``max`` give the range).
  ``ratio_dax_over_peer`` is median(DaX) / median(peer) of ``substeps_per_s``: above 1
  means DaX is faster.
* The peers' ``compile_s`` is a cold compile (Warp uses a fresh kernel cache, Taichi runs
  with ``offline_cache=False``). To compare like with like, DaX runs without
  ``JAX_COMPILATION_CACHE_DIR`` in its environment unless ``--keep-jax-cache`` is given.
* The peers' ``mean_x`` is numpy's float32 mean of float32 positions; it differs from a
  float64 mean by a few 1e-7, which bounds how far "agreement" can be read.
* Taichi runs with 2 threads, Warp's CPU backend runs on one thread; DaX uses whatever
  XLA chooses.

Usage (from anywhere)::

    python -m benchmarks.side_by_side                     # all scenes, 3 rounds
    python -m benchmarks.side_by_side --scenes fluid32,cloth --reps 5 --out bench_out/sbs.json

Before/after a change of DaX: ``--dax-baseline-python PY`` adds the engine ``dax-baseline``,
DaX's benchmark run by another interpreter (e.g. a wrapper that puts an older checkout's
``packages/dax-physics/src`` first on ``PYTHONPATH``), interleaved with the others; its
ratio is reported like a peer's (``ratio_dax_over_peer["dax-baseline"]`` = after / before).

Only the final JSON object goes to stdout; progress goes to stderr. A failing command
(e.g. DaX's bench not being available) is recorded under ``errors`` for its scene and
engine, and the run continues. Standard library only.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

from benchmarks._report import write_report

PEER_ENGINES = ("taichi", "warp")
ALL_SCENES = ("fluid32", "elastic32", "fluid64", "cloth")

# Scene definitions. "check_steps" is None for throughput-only scenes.
SCENES: dict[str, dict] = {
    "fluid32": dict(
        kind="mpm", material="fluid", grid=32, particles=8192, bench_steps=100, check_steps=500
    ),
    "elastic32": dict(
        kind="mpm", material="elastic", grid=32, particles=8192, bench_steps=100, check_steps=500
    ),
    "fluid64": dict(
        kind="mpm", material="fluid", grid=64, particles=32768, bench_steps=100, check_steps=None
    ),
    "cloth": dict(kind="cloth", n=64, bench_steps=1000, check_steps=1000),
}


# ----------------------------------------------------------------------------- paths


def repo_root() -> Path:
    """The repository root: the parent of benchmarks/, checked, else git's answer."""
    here = Path(__file__).resolve().parent.parent
    if (here / "noxfile.py").is_file() or (here / "packages").is_dir():
        return here
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--show-toplevel"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        if out:
            return Path(out)
    except (OSError, subprocess.CalledProcessError):
        pass
    return here


def resolve_peers_dir(arg: str, root: Path) -> Path | None:
    """Find the peers' directory: absolute as given; relative to the repo root, then cwd
    (None when not given or not found)."""
    if not arg:
        return None
    p = Path(arg).expanduser()
    candidates = [p] if p.is_absolute() else [root / p, Path.cwd() / p]
    for c in candidates:
        if all((c / f"{s}_{e}.py").is_file() for s in ("mpm3d", "cloth") for e in PEER_ENGINES):
            return c.resolve()
    return None


# ----------------------------------------------------------------------------- commands


def swap_yz(v: list[float]) -> list[float]:
    """DaX z-up [x, y, z] <-> peer y-up [x, up, z]: swap the last two axes (self-inverse)."""
    return [v[0], v[2], v[1]]


def peer_cmd(py: str, peers_dir: Path, engine: str, scene: dict, mode: str) -> list[str]:
    if scene["kind"] == "mpm":
        cmd = [
            py,
            str(peers_dir / f"mpm3d_{engine}.py"),
            f"--mode={mode}",
            f"--n={scene['grid']}",
            f"--N={scene['particles']}",
            f"--material={scene['material']}",
        ]
    else:
        cmd = [py, str(peers_dir / f"cloth_{engine}.py"), f"--mode={mode}", f"--n={scene['n']}"]
    steps = scene["check_steps"] if mode == "check" else scene["bench_steps"]
    return cmd + [f"--steps={steps}"]


def dax_cmd(py: str, scene: dict, substeps: int) -> list[str]:
    if scene["kind"] == "mpm":
        return [
            py,
            "-m",
            "benchmarks.physics",
            "mpm-block",
            "--material",
            scene["material"],
            "--grid",
            str(scene["grid"]),
            "--particles",
            str(scene["particles"]),
            "--substeps",
            str(substeps),
            "--json",
        ]
    return [
        py,
        "-m",
        "benchmarks.physics",
        "cloth-drop",
        "--n",
        str(scene["n"]),
        "--substeps",
        str(substeps),
        "--json",
    ]


def _tail(text: str, limit: int = 800) -> str:
    text = (text or "").strip()
    return text if len(text) <= limit else "..." + text[-limit:]


def run_json(cmd: list[str], *, prefix: str, cwd: Path, env: dict, timeout: float) -> dict:
    """Run cmd; return {"ok": bool, "record"|"error", "wall_s", "rc"}.

    prefix "RESULT " -> the last stdout line starting with it (the rest is the JSON);
    prefix "{" -> the last stdout line starting with "{" (the whole line is the JSON).
    """
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired as e:
        return dict(
            ok=False,
            rc=None,
            wall_s=time.perf_counter() - t0,
            error=f"timeout after {timeout:.0f} s; stderr: "
            f"{_tail(e.stderr if isinstance(e.stderr, str) else '')}",
        )
    except OSError as e:
        return dict(
            ok=False, rc=None, wall_s=time.perf_counter() - t0, error=f"{type(e).__name__}: {e}"
        )
    wall = time.perf_counter() - t0
    res: dict = dict(rc=proc.returncode, wall_s=wall)
    if proc.returncode != 0:
        res.update(
            ok=False,
            error=f"exit code {proc.returncode}; stderr: "
            f"{_tail(proc.stderr)}; stdout: {_tail(proc.stdout, 300)}",
        )
        return res
    lines = [ln.strip() for ln in proc.stdout.splitlines() if ln.strip().startswith(prefix)]
    if not lines:
        res.update(
            ok=False,
            error=f"no line starting with {prefix!r} on stdout; stdout: "
            f"{_tail(proc.stdout, 300)}; stderr: {_tail(proc.stderr)}",
        )
        return res
    text = lines[-1][len(prefix) :] if prefix != "{" else lines[-1]
    try:
        rec = json.loads(text)
    except json.JSONDecodeError as e:
        res.update(ok=False, error=f"unparsable JSON ({e}): {_tail(text, 300)}")
        return res
    if not isinstance(rec, dict):
        res.update(ok=False, error=f"JSON is not an object: {_tail(text, 300)}")
        return res
    res.update(ok=True, record=rec)
    return res


# ----------------------------------------------------------------------------- statistics


def summarize(values: list[float]) -> dict | None:
    vals = [float(v) for v in values if isinstance(v, (int, float))]
    if not vals:
        return None
    return dict(
        median=statistics.median(vals), min=min(vals), max=max(vals), n=len(vals), runs=vals
    )


def _num_list(v, n: int) -> list[float] | None:
    if isinstance(v, (list, tuple)) and len(v) == n and all(isinstance(a, (int, float)) for a in v):
        return [float(a) for a in v]
    return None


def max_abs_diff(a: list[float] | None, b: list[float] | None) -> float | None:
    if a is None or b is None:
        return None
    return max(abs(x - y) for x, y in zip(a, b, strict=True))


# ----------------------------------------------------------------------------- main


def log(msg: str) -> None:
    print(f"[side_by_side {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def loadavg() -> list[float] | None:
    try:
        return list(os.getloadavg())
    except OSError:
        return None


def _cpu_ticks() -> tuple[int, int] | None:
    """(idle, total) jiffies over all CPUs from /proc/stat (Linux); None elsewhere."""
    try:
        with open("/proc/stat") as f:
            vals = [int(v) for v in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    return vals[3] + vals[4], sum(vals)


def idle_cpus(window: float) -> float | None:
    """How many CPUs were idle during `window` seconds (nothing of ours runs meanwhile).

    A value well below cpu_count means something else is using the machine and the
    throughput figures of the command that follows are suspect.
    """
    if window <= 0:
        return None
    a = _cpu_ticks()
    time.sleep(window)
    b = _cpu_ticks()
    if a is None or b is None or b[1] == a[1]:
        return None
    return round((b[0] - a[0]) / (b[1] - a[1]) * (os.cpu_count() or 1), 2)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--reps", type=int, default=3, help="throughput rounds (default 3)")
    ap.add_argument(
        "--scenes",
        default=",".join(ALL_SCENES),
        help=f"comma-separated subset of {','.join(ALL_SCENES)} (default: all)",
    )
    ap.add_argument(
        "--peers",
        default=",".join(PEER_ENGINES),
        help="comma-separated peer engines to run (default: taichi,warp)",
    )
    ap.add_argument(
        "--peers-python",
        default=os.environ.get("DAX_PEERS_PYTHON", "python3"),
        help="interpreter with numpy, taichi, warp-lang (default: $DAX_PEERS_PYTHON or "
        "python3)",
    )
    ap.add_argument(
        "--peers-dir",
        default=os.environ.get("DAX_PEERS_DIR", ""),
        help="directory of the Taichi and Warp reference scripts (mpm3d_<engine>.py, "
        "cloth_<engine>.py; they are not part of this repository); a relative path is "
        "looked up from the repo root, then from the cwd (default: $DAX_PEERS_DIR)",
    )
    ap.add_argument(
        "--dax-python",
        default=sys.executable,
        help="interpreter with dax-physics installed (default: this one)",
    )
    ap.add_argument(
        "--idle-probe",
        type=float,
        default=0.5,
        help="seconds to sample idle CPUs before each command, to flag a busy machine "
        "(default %(default)s; 0 disables)",
    )
    ap.add_argument(
        "--dax-baseline-python",
        default=None,
        help="also run DaX's benchmark with this interpreter as the engine 'dax-baseline' "
        "(e.g. a wrapper putting an older checkout first on PYTHONPATH): before/after",
    )
    ap.add_argument("--no-dax", action="store_true", help="run the peers only")
    ap.add_argument("--no-check", action="store_true", help="skip the agreement runs")
    ap.add_argument(
        "--keep-jax-cache",
        action="store_true",
        help="leave JAX_COMPILATION_CACHE_DIR in DaX's environment (warm compile)",
    )
    ap.add_argument(
        "--peers-out",
        default=None,
        help="keep the peers' .npy position dumps here (default: a temp dir, removed at the end)",
    )
    ap.add_argument(
        "--timeout",
        type=float,
        default=1800.0,
        help="seconds allowed per command (default %(default)s)",
    )
    ap.add_argument("--out", default=None, help="also write the JSON object to this file")
    ap.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    args = ap.parse_args(argv)
    args.scene_list = [s.strip() for s in args.scenes.split(",") if s.strip()]
    args.peer_list = [s.strip() for s in args.peers.split(",") if s.strip()]
    bad = [s for s in args.scene_list if s not in SCENES]
    bad += [e for e in args.peer_list if e not in PEER_ENGINES]
    if bad:
        ap.error(f"unknown scene/engine: {', '.join(bad)}")
    if args.reps < 1:
        ap.error("--reps must be >= 1")
    return args


def render_table(path) -> str:
    """The Markdown table of a document of :func:`main` (``--out``): per scene and engine
    the median substeps per second (range and count of the runs), the median compile
    time, DaX's median over the engine's, and the largest difference of the engine's
    check-run positions from DaX's [m]; the run's date, machine, load and warnings under
    the table."""
    from benchmarks._report import file_date, load_range, read_result

    path, doc = read_result(path)
    meta = doc["meta"]
    out = ["| scene | engine | substeps/s: median (range, runs) | compile [s] | DaX ÷ "
           "engine | max abs position difference from DaX [m] |",
           "|---|---|---|---|---|---|"]
    for name, s in doc["scenes"].items():
        params = ", ".join(f"{k} {v}" for k, v in s["params"].items() if v is not None)
        agree = (s.get("agreement") or {}).get("max_abs_diff", {})
        for engine, th in s["throughput"].items():
            st = th.get("substeps_per_s")
            rate = ("failed" if not st else
                    f"{st['median']:.0f} ({st['min']:.0f}-{st['max']:.0f}, {st['n']})")
            comp = th.get("compile_s")
            ratio = s.get("ratio_dax_over_peer", {}).get(engine)
            diff = agree.get(f"dax_vs_{engine}")
            out.append(f"| {name} ({params}) | {engine} | {rate} | "
                       f"{'-' if not comp else format(comp['median'], '.2f')} | "
                       f"{'-' if ratio is None else format(ratio, '.2f')} | "
                       f"{'-' if diff is None else format(diff, '.1e')} |")
    load = load_range([meta["loadavg_start"][0], meta["loadavg_end"][0]])
    warn = f" Warning recorded: {meta['busy_machine_warning']}." \
        if meta.get("busy_machine_warning") else ""
    out += ["", f"{meta['cpu_count']} cores ({meta['machine']}), started "
            f"{meta['started_utc']}, 1-minute load {load} (start, end), {meta['reps']} runs "
            f"per engine, DaX's compilation cache {meta.get('dax_jax_compilation_cache')}. "
            + " ".join(meta.get("notes", [])) + warn
            + f" `{path.as_posix()}` ({file_date(path) or 'date not recorded'})."]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    root = repo_root()
    peers_dir = resolve_peers_dir(args.peers_dir, root)
    engines = ([] if args.no_dax else ["dax"]) + list(args.peer_list)
    if args.dax_baseline_python:
        engines.append("dax-baseline")

    tmp = Path(tempfile.mkdtemp(prefix="dax_side_by_side_"))
    peers_out = Path(args.peers_out).resolve() if args.peers_out else tmp / "peers_out"
    peers_out.mkdir(parents=True, exist_ok=True)
    peer_env = dict(os.environ, PEERS_OUT=str(peers_out), TMPDIR=str(tmp))  # warp caches
    dax_env = dict(os.environ)
    if not args.keep_jax_cache:
        dax_env.pop("JAX_COMPILATION_CACHE_DIR", None)

    commands: list[dict] = []
    # results[scene][engine] = {"check": run, "bench": [runs], "errors": [...]}
    results: dict[str, dict[str, dict]] = {
        s: {e: dict(check=None, bench=[], errors=[]) for e in engines} for s in args.scene_list
    }

    def run(scene_name: str, engine: str, phase: str, rnd: int) -> None:
        scene = SCENES[scene_name]
        slot = results[scene_name][engine]
        if engine in ("dax", "dax-baseline"):
            steps = scene["check_steps"] if phase == "check" else scene["bench_steps"]
            py = args.dax_python if engine == "dax" else args.dax_baseline_python
            cmd = dax_cmd(py, scene, steps)
            prefix, cwd, env = "{", root, dax_env
        else:
            if peers_dir is None:
                slot["errors"].append(f"{phase}: peer scripts not found at {args.peers_dir!r} "
                                      f"(set --peers-dir or DAX_PEERS_DIR)")
                return
            cmd = peer_cmd(args.peers_python, peers_dir, engine, scene, phase)
            prefix, cwd, env = "RESULT ", peers_out, peer_env
        entry = dict(
            scene=scene_name,
            engine=engine,
            phase=phase,
            round=rnd,
            cmd=cmd,
            loadavg_before=loadavg(),
        )
        if not args.dry_run:
            entry["idle_cpus_before"] = idle_cpus(args.idle_probe)
        commands.append(entry)
        if args.dry_run:
            log(f"{scene_name}/{engine}/{phase}: {' '.join(cmd)}")
            return
        log(f"{scene_name}/{engine}/{phase} round {rnd}: {' '.join(cmd)}")
        r = run_json(cmd, prefix=prefix, cwd=cwd, env=env, timeout=args.timeout)
        entry.update(rc=r["rc"], wall_s=round(r["wall_s"], 3), ok=r["ok"])
        if not r["ok"]:
            slot["errors"].append(f"{phase} round {rnd}: {r['error']}")
            log(f"  -> FAILED: {r['error'][:300]}")
            return
        rec = r["record"]
        if rec.get("finite") is False:
            slot["errors"].append(f"{phase} round {rnd}: non-finite state reported")
        missing = [k for k in ("substeps_per_s", "compile_s") if k not in rec]
        if phase == "bench" and missing:
            slot["errors"].append(f"bench round {rnd}: missing keys {missing}")
        if phase == "check":
            slot["check"] = rec
        else:
            slot["bench"].append(rec)
        sps = rec.get("substeps_per_s")
        log(
            f"  -> ok in {r['wall_s']:.1f} s"
            + (f", substeps_per_s={sps:.1f}" if isinstance(sps, (int, float)) else "")
            + (
                f", compile_s={rec['compile_s']:.2f}"
                if isinstance(rec.get("compile_s"), (int, float))
                else ""
            )
        )

    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    load_start = loadavg()
    t_start = time.perf_counter()
    try:
        if not args.no_check:
            for i, s in enumerate(args.scene_list):
                if SCENES[s]["check_steps"] is None:
                    continue
                k = i % len(engines)
                for e in engines[k:] + engines[:k]:
                    run(s, e, "check", 0)
        for rnd in range(1, args.reps + 1):
            k = (rnd - 1) % len(engines)
            order = engines[k:] + engines[:k]
            for s in args.scene_list:
                for e in order:
                    run(s, e, "bench", rnd)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # warp kernel caches; .npy unless --peers-out

    idle = [c["idle_cpus_before"] for c in commands if c.get("idle_cpus_before") is not None]
    min_idle = min(idle) if idle else None
    ncpu = os.cpu_count() or 1
    busy = (
        f"only {min_idle} of {ncpu} CPUs were idle before some command: other processes "
        "were running, throughput figures are suspect (see commands[].idle_cpus_before)"
        if min_idle is not None and min_idle < ncpu - 0.5
        else None
    )
    out = dict(
        meta=dict(
            tool="benchmarks/side_by_side.py",
            started_utc=started,
            duration_s=round(time.perf_counter() - t_start, 1),
            dry_run=args.dry_run,
            host=platform.node(),
            machine=platform.machine(),
            cpu_count=os.cpu_count(),
            loadavg_start=load_start,
            loadavg_end=loadavg(),
            min_idle_cpus_before_command=min_idle,
            busy_machine_warning=busy,
            reps=args.reps,
            scenes=args.scene_list,
            engines=engines,
            repo_root=str(root),
            peers_dir=str(peers_dir) if peers_dir else f"NOT FOUND: {args.peers_dir}",
            peers_python=args.peers_python,
            dax_python=args.dax_python,
            dax_baseline_python=args.dax_baseline_python,
            dax_jax_compilation_cache="kept" if args.keep_jax_cache else "removed (cold)",
            peers_out=str(peers_out) if args.peers_out else None,
            notes=[
                "substeps_per_s and compile_s: median over the successful throughput runs "
                "(runs lists each; min/max is the range).",
                "ratio_dax_over_peer = median DaX substeps_per_s / median peer "
                "substeps_per_s; > 1 means DaX is faster.",
                "Positions are in the peers' y-up order (x, up, z); DaX's z-up "
                "mean_position [x, y, z] is mapped to [x, z, y].",
                "Agreement: one check run per engine (MPM: 500 substeps; cloth: 1000).",
                "Peers: Taichi 2 threads, Warp CPU 1 thread; compile_s is cold for both.",
            ],
        ),
        scenes={},
        commands=commands,
    )
    for s in args.scene_list:
        out["scenes"][s] = scene_summary(s, results[s], engines)
    write_report(out, args.out, indent=2)
    return 0


def scene_summary(name: str, res: dict[str, dict], engines: list[str]) -> dict:
    scene = SCENES[name]
    peers = [e for e in engines if e != "dax"]
    params = {k: v for k, v in scene.items() if k != "kind"}
    summ: dict = dict(kind=scene["kind"], params=params, throughput={}, errors={})
    for e in engines:
        runs = res[e]["bench"]
        summ["throughput"][e] = dict(
            substeps_per_s=summarize([r.get("substeps_per_s") for r in runs]),
            compile_s=summarize([r.get("compile_s") for r in runs]),
        )
        if res[e]["errors"]:
            summ["errors"][e] = res[e]["errors"]

    def med(e: str, key: str = "substeps_per_s") -> float | None:
        st = summ["throughput"].get(e, {}).get(key)
        return st["median"] if st else None

    summ["substeps_per_s_median"] = {e: med(e) for e in engines}
    summ["compile_s_median"] = {e: med(e, "compile_s") for e in engines}
    ratio = {}
    if "dax" in engines:
        for p in peers:
            d, q = med("dax"), med(p)
            ratio[p] = d / q if d is not None and q else None
    summ["ratio_dax_over_peer"] = ratio

    if scene["check_steps"] is None:
        return summ
    agree: dict = dict(steps=scene["check_steps"])
    pos: dict[str, list[float] | None] = {}
    for e in engines:
        rec = res[e]["check"]
        if rec is None:
            pos[e] = None
            continue
        if scene["kind"] == "mpm":
            if e in ("dax", "dax-baseline"):
                zup = _num_list(rec.get("mean_position"), 3)
                agree[f"{e.replace('-', '_')}_mean_position_zup"] = zup
                pos[e] = swap_yz(zup) if zup else None
                if zup is None:
                    res[e]["errors"].append("check: no usable mean_position [x, y, z]")
            else:
                pos[e] = _num_list(rec.get("mean_x"), 3)
        else:  # cloth: compare heights only
            if e in ("dax", "dax-baseline"):
                h = rec.get("mean_height")
                pos[e] = [float(h)] if isinstance(h, (int, float)) else None
                if pos[e] is None:
                    res[e]["errors"].append("check: no usable mean_height")
            else:
                mx = _num_list(rec.get("mean_x"), 3)
                pos[e] = [mx[1]] if mx else None
        agree.setdefault("finite", {})[e] = rec.get("finite")
        agree.setdefault("check_compile_s", {})[e] = rec.get("compile_s")
    if scene["kind"] == "mpm":
        agree["mean_position_yup"] = pos
    else:
        agree["mean_height"] = {e: (v[0] if v else None) for e, v in pos.items()}
    diffs = {}
    if "dax" in engines:
        for p in peers:
            diffs[f"dax_vs_{p}"] = max_abs_diff(pos.get("dax"), pos.get(p))
    for i, a in enumerate(peers):
        for b in peers[i + 1 :]:
            diffs[f"{a}_vs_{b}"] = max_abs_diff(pos.get(a), pos.get(b))
    agree["max_abs_diff"] = diffs
    summ["agreement"] = agree
    errs = {e: res[e]["errors"] for e in engines if res[e]["errors"]}
    summ["errors"] = errs
    return summ


if __name__ == "__main__":
    sys.exit(main())
