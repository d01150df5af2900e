"""What every results row records about how it was made, and whether a row still describes
today's code (:func:`stale_reasons`).

Each row of ``results.csv`` carries (:data:`COLUMNS`):

* ``task_fingerprint``: ``env.spec.fingerprint()``, 12 hex digits of the task's spec (every
  field, the scene included) and of the dax-tasks and dax-physics sources;
* ``spec_digest``: 12 hex digits of the spec alone (:func:`spec_digest`), which tells a
  changed spec from changed code;
* ``params_digest``: 12 hex digits of the env params the episode used (every leaf's
  dtype, shape and bytes, :func:`tree_digest`);
* ``config_digest``: 12 hex digits of the method's full config (its class and fields,
  :func:`config_digest`);
* ``versions``: the DaX packages', JAX's and jaxlib's versions (``name=version`` joined
  by spaces); ``commit``: the git commit of the checkout the runner's code was imported
  from (``+dirty`` appended when files differ from it; empty outside a checkout);
* ``precision``: ``float32``, or ``float64`` under ``JAX_ENABLE_X64``;
* ``device``: the JAX platform and device kind, ``platform:kind`` (``cpu:cpu``,
  ``gpu:NVIDIA H100 80GB HBM3``).

Beside them (not part of staleness) a row records ``machine``, the host's machine class
(:func:`dax_algos.bench.rundir.machine_class`: the CPU features XLA compiles for):
training, a chaotic computation, repeats to the bit only within one class, so a row
stands in for a seed trained again only on a machine of its class.

A row is **stale** when what it was measured on is no longer what the code builds: its
fingerprint differs from the task's today (built with the run's task overrides; unless
the ledger of :mod:`dax_algos.bench.equivalence` says today's code gives the row's forward
programs and the row's method never differentiates through the env, or says it gives the
same numbers forward and in reverse), or its
config digest differs from the config the same method name gives today (budget, task and
method overrides as the run had them), or it has no provenance at all (a file written
before rows carried it: "provenance unknown"). Stale rows stay in ``results.csv``; the
reports leave them out of the means unless asked to include them.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib.metadata
import json
import subprocess
from collections.abc import Mapping
from pathlib import Path

import jax
import numpy as np

import dax_tasks
from dax_tasks.core.registry import PARAM_OVERRIDES, check_overrides

from .. import registry
from ..checks import OMIT_DEFAULT
from . import rundir
from .equivalence import LEDGER, forward_equivalent

#: the provenance columns of results.csv, in order
COLUMNS = ("task_fingerprint", "spec_digest", "params_digest", "config_digest", "versions",
           "commit", "precision", "device")
#: the packages whose versions a row records
VERSIONED = ("dax-physics", "dax-tasks", "dax-data", "dax-algos", "jax", "jaxlib")
PRECISIONS = ("float32", "float64")

UNKNOWN = "provenance unknown (the row was written before rows recorded what they were " \
          "measured on)"


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def config_digest(config) -> str:
    """12 hex digits of a method config (a frozen dataclass): its class and every field,
    except a field marked :data:`OMIT_DEFAULT` while it holds its default."""
    data = rundir.canonical(config)
    for f in dataclasses.fields(config):
        if f.metadata.get("digest") == OMIT_DEFAULT["digest"] \
                and getattr(config, f.name) == f.default:
            del data[f.name]
    return _digest(json.dumps(data, sort_keys=True))


def spec_digest(spec) -> str:
    """12 hex digits of a task spec's fields alone (not the code, unlike its
    ``fingerprint()``)."""
    return _digest(json.dumps(spec.to_json(), sort_keys=True))


def tree_digest(tree) -> str:
    """12 hex digits of a pytree of arrays: its structure and each leaf's dtype, shape and
    bytes."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    h = hashlib.sha256(str(treedef).encode())
    for leaf in leaves:
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{a.dtype.str}|{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:12]


def precision() -> str:
    """``float64`` when JAX computes in double precision (``JAX_ENABLE_X64``), else
    ``float32``."""
    return "float64" if jax.config.jax_enable_x64 else "float32"


def device() -> str:
    """``platform:kind`` of JAX's default device (``cpu:cpu``, ``gpu:NVIDIA H100 ...``)."""
    d = jax.devices()[0]
    return f"{d.platform}:{d.device_kind}"


@functools.lru_cache(maxsize=1)
def versions() -> str:
    """``name=version`` of :data:`VERSIONED`, joined by spaces (``name=none`` if missing)."""
    parts = []
    for name in VERSIONED:
        try:
            parts.append(f"{name}={importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            parts.append(f"{name}=none")
    return " ".join(parts)


@functools.lru_cache(maxsize=1)
def commit() -> str:
    """The git commit of the checkout this package was imported from, with ``+dirty`` when
    tracked files differ from it; ``""`` when it was not imported from a checkout (or git
    is not installed)."""
    where = Path(__file__).resolve().parent

    def git(*args):
        return subprocess.run(["git", "-C", str(where), *args], capture_output=True,
                              text=True, timeout=20, check=True).stdout.strip()

    try:
        head = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return ""
    return head + ("+dirty" if dirty else "")


def of_run(env=None, config=None) -> dict:
    """The provenance columns of a row made on ``env`` (a built task, or ``None``) with the
    method ``config`` (or ``None``), and its ``machine``: those that cannot be known are
    ``""``."""
    row = dict(versions=versions(), commit=commit(), precision=precision(), device=device(),
               machine=rundir.machine_class())
    if env is not None:
        row.update(task_fingerprint=env.spec.fingerprint(), spec_digest=spec_digest(env.spec),
                   params_digest=tree_digest(env.default_params))
    if config is not None:
        row["config_digest"] = config_digest(config)
    return row


def has_provenance(row: Mapping) -> bool:
    """The row records what it was measured on (a task fingerprint or a config digest)."""
    return bool(row.get("task_fingerprint") or row.get("config_digest"))


def task_spec(task: str, overrides: Mapping | None = None):
    """The :class:`dax_tasks.TaskSpec` that ``dax_tasks.make(task, **overrides)`` builds
    (the overrides checked as ``make`` checks them; ``lam`` and ``aux_weight`` change
    params, not the spec), without building the task."""
    overrides = check_overrides(task, dict(overrides or {}))
    fields = {k: v for k, v in overrides.items() if k not in PARAM_OVERRIDES}
    return dataclasses.replace(dax_tasks.get_spec(task), **fields)


@dataclasses.dataclass
class Today:
    """What the code gives today for the rows of a run made with ``task_overrides``
    (``{task: make overrides}``) and ``method_overrides`` (``{method: config overrides}``),
    asked lazily and remembered."""

    task_overrides: Mapping = dataclasses.field(default_factory=dict)
    method_overrides: Mapping = dataclasses.field(default_factory=dict)
    _fingerprints: dict = dataclasses.field(default_factory=dict)
    _configs: dict = dataclasses.field(default_factory=dict)

    def fingerprint(self, task: str) -> tuple:
        """``((fingerprint, spec_digest), "")`` of ``task`` today, or ``(None, error)``."""
        if task not in self._fingerprints:
            def both():
                spec = task_spec(task, self.task_overrides.get(task))
                return spec.fingerprint(), spec_digest(spec)

            self._fingerprints[task] = _attempt(both)
        return self._fingerprints[task]

    def config(self, method: str, budget: str, task: str) -> tuple:
        """``(config digest, "")`` of ``method`` today, or ``(None, error)``."""
        key = (method, budget, task)
        if key not in self._configs:
            overrides = _tuples(self.method_overrides.get(method, {}))
            self._configs[key] = _attempt(lambda: config_digest(registry.get(method).config(
                budget, task, **overrides)))
        return self._configs[key]


def _tuples(value):
    """Config overrides read back from JSON: lists become tuples (what config fields hold),
    nested dicts stay dicts."""
    if isinstance(value, Mapping):
        return {k: _tuples(v) for k, v in value.items()}
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    return value


def _attempt(fn) -> tuple:
    try:
        return fn(), ""
    except Exception as err:  # noqa: BLE001 - the stale reason says why
        return None, " ".join(f"{type(err).__name__}: {err}".split())[:120]


def _forward_only(method: str) -> bool:
    """Whether ``method`` never differentiates through the env (an unknown method: no)."""
    try:
        return not registry.get(method).uses_gradients
    except ValueError:
        return False


def stale_reason(row: Mapping, today: Today, ledger: tuple = LEDGER) -> str:
    """Why ``row`` no longer describes today's code (``""``: it does). See the module
    docstring; ``ledger``: the equivalences honoured (:mod:`.equivalence`)."""
    if not has_provenance(row):
        return UNKNOWN
    reasons = []
    fp = row.get("task_fingerprint")
    if fp:
        now, error = today.fingerprint(row["task"])
        if now is None:
            reasons.append(f"the task cannot be built today ({error})")
        elif now[0] != fp and not (
                row.get("spec_digest") == now[1] and forward_equivalent(
                    fp, now[0], ledger, gradients=not _forward_only(row.get("method", "")))):
            what = ("the task's spec changed" if row.get("spec_digest") != now[1] else
                    "the dax-tasks or dax-physics code changed")
            reasons.append(f"{what} (fingerprint {fp}, today {now[0]})")
    cd = row.get("config_digest")
    if cd:
        now, error = today.config(row["method"], row["budget"], row["task"])
        if now is None:
            reasons.append(f"the method's config cannot be built today ({error})")
        elif now != cd:
            reasons.append(f"the method's config changed (config {cd}, today {now})")
    return "; ".join(reasons)
