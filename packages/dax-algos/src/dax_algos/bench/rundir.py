"""The output directory of a run: checked before any work (:func:`check_out`), and its
``run.json``, which records the task and method overrides its results were made with and
each command line run on it, with the machine and the package versions
(:func:`record_run`)."""

from __future__ import annotations

import dataclasses
import datetime
import importlib.metadata
import json
import os
import platform
import re
import tempfile
from collections.abc import Mapping
from pathlib import Path

import jax
import numpy as np

import dax_tasks
from dax_tasks.io import atomic_write

RUN_FILE = "run.json"
#: the packages whose versions a run records (run.json) and the results page shows
VERSIONED = ("dax-physics", "dax-tasks", "dax-data", "dax-algos", "jax", "jaxlib", "numpy",
             "flax", "optax", "matplotlib", "pillow")


def check_out(out: Path) -> Path:
    """``out/results.csv`` once ``out`` is known to be a directory we can write (created if
    missing) whose results file, report and run file are files if they exist; one
    ``ValueError`` naming the path otherwise, before any work."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: exists and is not a directory (--out takes a directory)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"{out}: cannot create the output directory "
                         f"({err.strerror or err})") from None
    try:  # a probe: an unwritable directory is found now, not after the first episode
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as err:
        raise ValueError(f"{out}: cannot write in the output directory "
                         f"({err.strerror or err})") from None
    for name in ("results.csv", "results.md", RUN_FILE):
        path = out / name
        if path.exists() and not path.is_file():
            raise ValueError(f"{path}: exists and is not a file; use another --out directory")
        if path.exists() and not os.access(path, os.R_OK | os.W_OK):
            raise ValueError(f"{path}: cannot be read and written")
    return out / "results.csv"


def canonical(value):
    """JSON-able form of run overrides (a scene dataclass by class and fields; see
    :func:`overrides_from_json` for the way back)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {"__class__": type(value).__name__,
                **{f.name: canonical(getattr(value, f.name))
                   for f in dataclasses.fields(value)}}
    if isinstance(value, Mapping):
        return {str(k): canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [canonical(v) for v in value]
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)


def overrides_from_json(task: str, data: Mapping) -> dict:
    """A task's ``make`` overrides from their ``run.json`` form (:func:`canonical`): a
    scene recorded by class and fields is rebuilt from the task's default scene, lists
    become tuples where the default is one."""
    spec = dax_tasks.get_spec(task)

    def decode(default, value):
        if isinstance(value, Mapping) and "__class__" in value:
            if not dataclasses.is_dataclass(default) \
                    or type(default).__name__ != value["__class__"]:
                raise ValueError(f"run.json: task {task}: cannot rebuild a "
                                 f"{value['__class__']} (the task's is "
                                 f"{type(default).__name__})")
            fields = {k: decode(getattr(default, k, None), v) for k, v in value.items()
                      if k != "__class__"}
            return dataclasses.replace(default, **fields)
        if isinstance(value, list) and isinstance(default, tuple):
            like = [default[min(i, len(default) - 1)] if default else None
                    for i in range(len(value))]
            return tuple(decode(d, v) for d, v in zip(like, value, strict=True))
        return value

    return {k: decode(getattr(spec, k, None), v) for k, v in data.items()}


def read_run_file(out: Path) -> dict:
    """``out/run.json`` (``{}`` if there is none); ``ValueError`` naming it if unreadable."""
    path = Path(out) / RUN_FILE
    if not path.exists():
        return {}
    try:
        old = json.loads(path.read_text())
        if not isinstance(old, dict):
            raise ValueError("not a JSON object")
    except ValueError as err:  # UnicodeDecodeError and JSONDecodeError too
        raise ValueError(f"{path}: unreadable run file ({err}); use another --out "
                         f"directory") from None
    return old


#: The CPU features that change what XLA's CPU compiler emits (vector width, fused
#: multiply-add, half-precision conversions); the same list dax-tasks' trajectory fixtures
#: record as their machine class.
ISA_FEATURES = ("sse4_1", "sse4_2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512dq",
                "avx512bw", "avx512vl", "avx512_vnni", "avx512_bf16", "avx512_fp16",
                "amx_tile", "asimd", "asimdhp", "sve", "sve2", "fphp")


def cpu_info(cpuinfo: str | Path = "/proc/cpuinfo") -> dict:
    """The host CPU as XLA sees it: ``{"cpu_model": str, "cpu_features": [str],
    "xla_max_isa": str | None}``: the model name and the :data:`ISA_FEATURES` of the first
    processor in ``cpuinfo`` (``flags`` on x86-64, ``Features`` on arm64), and the cap
    ``--xla_cpu_max_isa`` in ``XLA_FLAGS`` puts on them.

    XLA compiles CPU code for these features, so training (a chaotic computation) repeats
    to the bit on one machine class but not across classes: two rows with different
    features need not agree to the bit. Where ``cpuinfo`` cannot be read (not Linux) the
    model is :func:`platform.processor` and the features ``["unknown"]``."""
    cap = re.search(r"--xla_cpu_max_isa=(\S+)", os.environ.get("XLA_FLAGS", ""))
    try:
        first = Path(cpuinfo).read_text().split("\n\n")[0]
    except OSError:
        first = None
    model = first and re.search(r"^(?:model name|CPU part)\s*:\s*(.*)$", first, re.M)
    flags = first and re.search(r"^(?:flags|Features)\s*:(.*)$", first, re.M)
    have = set(flags.group(1).split()) if flags else set()
    return {"cpu_model": model.group(1).strip() if model else platform.processor() or "unknown",
            "cpu_features": ["unknown"] if first is None
            else [f for f in ISA_FEATURES if f in have],
            "xla_max_isa": cap.group(1) if cap else None}


def machine_class(info: Mapping | None = None) -> str:
    """The machine class of :func:`cpu_info`'s ``info`` (this host's if ``None``) as one
    string: the ISA features joined by ``+`` (x86-64's and arm64's names differ) and the
    XLA cap, if any (``"sse4_1+...+avx512f max_isa=AVX2"``). Two runs of one seed repeat to the bit
    when this agrees (the same code and config); a results row records it (column
    ``machine``) so that a row is only ever compared, seed by seed, with one of its class.
    ``"unknown"`` where the features could not be read, ``"none"`` where none of
    :data:`ISA_FEATURES` is there."""
    info = cpu_info() if info is None else info
    features = info.get("cpu_features")
    if features is None or features == ["unknown"]:
        return "unknown"
    cap = info.get("xla_max_isa")
    return ("+".join(features) or "none") + (f" max_isa={cap}" if cap else "")


def machine_info() -> dict:
    """The machine a run ran on: platform, Python, CPU count, model and the instruction-set
    features XLA compiles for (:func:`cpu_info`), JAX backend and devices."""
    return {"platform": platform.platform(), "python": platform.python_version(),
            "cpu_count": os.cpu_count(), **cpu_info(), "jax_backend": jax.default_backend(),
            "jax_devices": [str(d) for d in jax.devices()]}


def package_versions() -> dict:
    """``{package: version}`` of :data:`VERSIONED` (``"not installed"`` for a missing one)."""
    out = {}
    for name in VERSIONED:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


#: the run-file fields that must agree for results to share an output directory
OVERRIDES = ("task_overrides", "method_overrides")


def other_overrides(recorded: dict, has_rows: bool, config: dict) -> str | None:
    """The first of :data:`OVERRIDES` in which ``config`` differs from what an output
    directory recorded (``recorded``: its run file, ``{}`` if none; a directory with rows
    and no run file holds runs made without overrides); ``None`` when they agree or the
    directory holds nothing yet."""
    if not recorded and not has_rows:
        return None
    return next((k for k in OVERRIDES if recorded.get(k, {}) != config.get(k, {})), None)


def record_run(out: Path, rows: list, config: dict, command: str) -> None:
    """Refuse to add to ``out`` results made with other task or method overrides (they
    would be mixed with, or silently stand in for, this run's); record them on first
    use in ``out/run.json``, and with them each new command line (``invocations``: the
    command, when it started, the machine and the package versions; a resumed run with
    the same command adds nothing). ``config``: ``{"task_overrides": ...,
    "method_overrides": ...}`` in :func:`canonical` form; ``rows``: the results already in
    ``out``."""
    path = out / RUN_FILE
    old = read_run_file(out)
    key = other_overrides(old, bool(rows), config)
    if key:
        raise ValueError(
            f"{out}: holds results made with other {key.replace('_', ' ')} "
            f"({json.dumps(old.get(key, {}), sort_keys=True)[:200]}, now "
            f"{json.dumps(config[key], sort_keys=True)[:200]}); use another --out "
            f"directory")
    if not old and rows:  # results from before run files: runs without overrides
        old = dict.fromkeys(OVERRIDES, {})
    new = {**config, **old}
    invocations = list(new.get("invocations", []))
    if not any(isinstance(i, dict) and i.get("command") == command for i in invocations):
        started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        invocations.append({"command": command, "started": started,
                            "machine": machine_info(), "versions": package_versions()})
    new["invocations"] = invocations
    if new != old:
        atomic_write(path, json.dumps(new, indent=1, sort_keys=True) + "\n")
