"""Test, lint and demo sessions for the DaX monorepo.

`nox` runs the default sessions (lint, each package alone, the combinations, the
cross-package tests, the multi-device and two-process tests); `nox -s demo` runs the main
job, the benchmark runner on its demo preset; `nox -s report` writes its results page
again and `nox -s bench -- ARGS` runs any `dax-bench` command; `nox -s physics-demo` the
physics demo; `nox -s validate` the physics validation suite; `nox -s ray` the benchmark
runner's Ray backend; `nox -l` lists them all.
Arguments after `--` go to pytest, e.g. `nox -s physics -- -k free_fall -x`.

Each package session installs only that package and the siblings it declares, so a
package's tests pass with nothing more than its own dependencies (docs/ARCHITECTURE.md,
section 1).
The sibling packages are not on any index: they are always installed from packages/.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import nox

nox.options.default_venv_backend = "uv"
nox.options.error_on_external_run = True
nox.options.sessions = [
    "lint",
    "physics",
    "tasks",
    "data",
    "algos",
    "combos",
    "integration",
    "multidevice",
]

ROOT = Path(__file__).resolve().parent

# Each package with the sibling packages it declares, lowest layer first.
SIBLINGS: dict[str, list[str]] = {
    "dax-physics": [],
    "dax-tasks": ["dax-physics"],
    "dax-data": ["dax-tasks", "dax-physics"],
    "dax-algos": ["dax-data", "dax-tasks", "dax-physics"],
}
LAYERS = list(SIBLINGS)

# What the scripts in benchmarks/ need beyond the packages (they are not a package).
BENCHMARK_DEPS = ["matplotlib>=3.7"]

# Heavy dependencies that belong to higher layers; dax-physics must not pull them in.
NOT_IN_PHYSICS = ["gymnasium", "h5py", "flax", "optax"]
# Optional everywhere: only the `gym` extra of dax-tasks (and test extras) install it.
OPTIONAL = ["gymnasium"]

# A persistent XLA compilation cache outside the repo, shared by every session, so
# repeated runs do not recompile the same programs. XLA_FLAGS is left as it is.
_cache_home = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
PYTEST_ENV = {
    "JAX_COMPILATION_CACHE_DIR": os.environ.get(
        "JAX_COMPILATION_CACHE_DIR", str(_cache_home / "dax" / "jax")
    ),
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0.5",
}


def _module(dist: str) -> str:
    return dist.replace("-", "_")


def _install_local(
    session: nox.Session, dists: list[str], extras: dict[str, str] | None = None
) -> None:
    """Install the given packages from packages/; `extras` maps a package to its extra.

    `--reinstall-package` makes uv rebuild each local package from the current source
    tree every time instead of trusting an earlier build; nox's documentation warns
    that uv may not reinstall local packages in a reused environment (`nox -r`).
    """
    extras = extras or {}
    targets = [
        str(ROOT / "packages" / d) + (f"[{extras[d]}]" if d in extras else "") for d in dists
    ]
    reinstall = [arg for d in dists for arg in ("--reinstall-package", d)]
    session.install(*reinstall, *targets)


def _assert_not_importable(session: nox.Session, modules: list[str]) -> None:
    """Fail the session if any of `modules` can be imported in its environment."""
    if not modules:
        return
    code = (
        f"import importlib.util as u, sys; m = {modules!r}; "
        "f = [x for x in m if u.find_spec(x)]; "
        "sys.exit(f'expected none of {m} to be importable, got {f}') if f "
        "else print('not importable, as expected:', *m)"
    )
    session.run("python", "-c", code)


def _assert_importable(session: nox.Session, modules: list[str]) -> None:
    code = "import " + ", ".join(modules) + f"; print('imported: {', '.join(modules)}')"
    session.run("python", "-c", code)


#: The package test runs are compile-bound (XLA compiles on one core), so they run in one
#: worker per core (pytest-xdist; at most 4), each test file in one worker so a module's
#: compiled fixtures are built once: on 2 cores the dax-tasks tests take 6.8 instead of
#: 10.3 minutes. `nox -s tasks -- -n 0` runs them in one process.
PARALLEL = ["-n", "auto", "--maxprocesses", "4", "--dist", "loadfile"]


def _pytest(session: nox.Session, *paths: str, parallel: bool = True, env=None) -> None:
    args = PARALLEL if parallel else []
    session.run("pytest", *args, *paths, *session.posargs, env={**PYTEST_ENV, **(env or {})})


BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def _browser_env(session: nox.Session) -> dict:
    """PATH for the results-page browser test: the machine's Chromium if it has one, else
    Debian's unpacked by `.ci/chromium` into the user cache (no root, nothing installed
    system-wide; reused on later runs). Where neither can be had (no apt, no mirror, or
    DAX_NO_BROWSER=1) the test skips and says why."""
    if any(shutil.which(b) for b in BROWSERS) or os.environ.get("DAX_NO_BROWSER") == "1":
        return {}
    got = subprocess.run(["bash", ".ci/chromium"], capture_output=True, text=True,
                         timeout=900, check=False)
    if got.returncode != 0:
        reason = (got.stderr.strip().splitlines() or ["unknown failure"])[-1]
        session.log(f"no browser for the page test ({reason}); it will skip")
        return {}
    session.log(f"browser for the page test: {got.stdout.strip()}/chromium")
    return {"PATH": got.stdout.strip() + os.pathsep + os.environ.get("PATH", "")}


def _package_session(session: nox.Session, dist: str, env=None) -> None:
    """Install `dist` with its test extra and its siblings (without theirs); run its tests."""
    _install_local(session, [dist, *SIBLINGS[dist]], extras={dist: "test"})
    higher = [_module(d) for d in LAYERS[LAYERS.index(dist) + 1 :]]
    forbidden = higher + (NOT_IN_PHYSICS if dist == "dax-physics" else [])
    _assert_not_importable(session, forbidden)
    _pytest(session, f"packages/{dist}/tests", env=env)


@nox.session
def physics(session: nox.Session) -> None:
    """dax-physics alone; checks that no higher layer's dependencies came with it."""
    _package_session(session, "dax-physics")


@nox.session
def tasks(session: nox.Session) -> None:
    """dax-tasks with dax-physics."""
    _package_session(session, "dax-tasks")


@nox.session
def data(session: nox.Session) -> None:
    """dax-data with dax-tasks and dax-physics."""
    _package_session(session, "dax-data")


@nox.session
def algos(session: nox.Session) -> None:
    """dax-algos with all its siblings; the results page is also checked in a headless
    Chromium (see `_browser_env`)."""
    _package_session(session, "dax-algos", env=_browser_env(session))


@nox.session
@nox.parametrize(
    "combo",
    [LAYERS[:2], LAYERS[:3], LAYERS[:4]],
    ids=["physics+tasks", "physics+tasks+data", "all"],
)
def combos(session: nox.Session, combo: list[str]) -> None:
    """Install a combination (no test extras); check dependencies and imports, and that no
    optional dependency (gymnasium) came with it."""
    _install_local(session, combo)
    session.run("uv", "pip", "check")
    _assert_importable(session, [_module(d) for d in combo])
    _assert_not_importable(session, [_module(d) for d in LAYERS if d not in combo] + OPTIONAL)


@nox.session
def integration(session: nox.Session) -> None:
    """All four packages together; runs the cross-package tests in tests/ and the tests of
    the benchmark and validation scripts (tests/benchmarks)."""
    _install_local(session, LAYERS, extras={d: "test" for d in LAYERS})
    # the cross-package tests parse the requirements; the scripts draw charts
    session.install("packaging>=23", *BENCHMARK_DEPS)
    _pytest(session, "tests", "--ignore=tests/multidevice")


@nox.session
def multidevice(session: nox.Session) -> None:
    """Sharding over several devices and processes (tests/multidevice): every test starts
    fresh JAX processes with 1 or 4 forced CPU devices
    (``--xla_force_host_platform_device_count``, fixed when JAX starts) or two processes
    joined by ``jax.distributed``, and compares them (docs/ARCHITECTURE.md, section 4).
    On 2 CPU cores: about 1 minute with a warm compilation cache, 2.3 minutes cold."""
    _install_local(session, LAYERS, extras={d: "test" for d in LAYERS})
    _pytest(session, "tests/multidevice", parallel=False)


@nox.session
def ray(session: nox.Session) -> None:
    """`dax-bench run --backend ray` (not a default session; it installs Ray): dax-algos with
    its `ray` extra, then the Ray backend's tests, which start a local Ray instance with 2
    CPUs and check its rows, recordings, curves and policies against the local backend's,
    resuming and a killed driver (packages/dax-algos/tests/test_bench_ray.py)."""
    _install_local(session, LAYERS, extras={"dax-algos": "test,ray"})
    _assert_importable(session, ["ray"])
    _pytest(session, "packages/dax-algos/tests/test_bench_ray.py", parallel=False)


@nox.session
def lint(session: nox.Session) -> None:
    """ruff over the whole repository, configured by ruff.toml."""
    session.install("ruff==0.17.6")
    session.run("ruff", "check", ".", *session.posargs)


#: The main job: `dax-bench run --preset demo` (dax_algos.bench.presets: Fold-Cloth-1; random,
#: expert, CEM-MPC, diff-MPC and ILD; two seeds; quick budgets). Arguments after `--`
#: replace it, e.g. `nox -s demo -- --preset cloth` (the grid of three cloth tasks, every
#: method) or `nox -s demo -- --tasks all --methods all --seeds 5 --out results`.
DEMO_ARGS = ["--preset", "demo"]


@nox.session
def demo(session: nox.Session) -> None:
    """The main job: the benchmark runner (dax-bench) on its demo preset; writes
    bench_out/results.csv, results.md, a chart per task, the learning curves and the
    results page bench_out/index.html (tables, charts, one episode animation per task and
    method), prints the page's path as its last line (open it in a browser), and fails
    (non-zero exit, one line saying which runs failed and why) if any run failed. A status
    line ticks every second with the run under way and an estimate of the time left."""
    _install_local(session, LAYERS)
    session.run("dax-bench", "run", *(session.posargs or DEMO_ARGS), env=PYTEST_ENV)


@nox.session
def report(session: nox.Session) -> None:
    """`dax-bench report` in an environment of its own: writes the results page, tables
    and charts of an output directory again (default `--out bench_out`, the demo's);
    arguments after `--` replace that, e.g. `nox -s report -- --out results
    --include-stale`."""
    _install_local(session, LAYERS)
    session.run("dax-bench", "report", *(session.posargs or ["--out", "bench_out"]),
                env=PYTEST_ENV)


@nox.session
def bench(session: nox.Session) -> None:
    """Any `dax-bench` command, its arguments after `--` (default `list`), e.g. `nox -s
    bench -- run --preset paper --max-minutes 60` (the paper grid in a chunk of an hour;
    the same command continues it)."""
    _install_local(session, LAYERS)
    session.run("dax-bench", *(session.posargs or ["list"]), env=PYTEST_ENV)


@nox.session
def validate(session: nox.Session) -> None:
    """The validation suite (not a default session; under 10 minutes on 2 cores): every
    solver against analytic answers and Martin & Moyce's measurements, with convergence
    charts, and the task-level gradient rows (benchmarks.validate.tasks); writes validation_out/
    (validation.json, validation.md, one chart per check) and fails if a check fails.
    Arguments after `--` go to `python -m benchmarks.validate`, e.g. `-- --quick`."""
    _install_local(session, ["dax-physics", "dax-tasks"])
    session.install(*BENCHMARK_DEPS)
    args = session.posargs or ["--out", "validation_out"]
    session.run("python", "-m", "benchmarks.validate", *args, env=PYTEST_ENV)


@nox.session(name="physics-demo")
def physics_demo(session: nox.Session) -> None:
    """The physics demo: prints its figures as JSON and writes a picture to demo_out/."""
    _install_local(session, ["dax-physics"])
    session.install(*BENCHMARK_DEPS)
    session.run(
        "python", "-m", "benchmarks.physics_demo", "--out", "demo_out", *session.posargs,
        env=PYTEST_ENV
    )
