"""``results.csv``: one row per run of a (task, method, seed, budget), its columns, and
reading (every row validated) and appending rows so that a killed writer costs at most its
own incomplete last line (:mod:`.csvlog`).

The file is a log: a run that failed and was run again on resume keeps its ``failed`` row,
and the new row lists the earlier errors in ``previous_errors`` (a JSON list of strings);
a stale run measured again (``--rerun-stale``) keeps its old row beside the new one, whose
task fingerprint or config digest differs (:func:`remeasured`); :func:`latest` gives the
row that counts for each (task, method, seed, budget).
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

from dax_tasks.io import atomic_write

from ..method import BUDGETS
from . import csvlog, provenance

#: the columns of files written before rows recorded their provenance (read as
#: "provenance unknown", upgraded to :data:`COLUMNS` before a run appends to them)
OLD_COLUMNS = ("task", "method", "seed", "budget", "status", "score", "final_distance",
               "wall_s", "compile_s", "env_steps", "backprop_steps", "grad_norm",
               "grad_norm_mean", "nonfinite_grads", "error")
#: the columns before learner rows carried their untrained policy's score
PROVENANCE_COLUMNS = (*OLD_COLUMNS, *provenance.COLUMNS, "previous_errors")
#: ``untrained_score``: a learner's untrained policy on the same evaluation starts (empty
#: for a planner)
UNTRAINED_COLUMNS = (*PROVENANCE_COLUMNS, "untrained_score")
#: ``machine``: the host's machine class (:func:`.rundir.machine_class`; empty in rows
#: written before rows recorded it: unknown)
COLUMNS = (*UNTRAINED_COLUMNS, "machine")
#: every header a results file may have, oldest first
HEADERS = (OLD_COLUMNS, PROVENANCE_COLUMNS, UNTRAINED_COLUMNS, COLUMNS)
STATUSES = ("ok", "failed", "skipped")
#: what a task or method name may be: it becomes a directory or file name
NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_-]{0,99}")
_FLOATS = ("final_distance", "grad_norm", "grad_norm_mean")
_SCORES = ("score", "untrained_score")
_TIMES = ("wall_s", "compile_s")
_COUNTS = ("env_steps", "backprop_steps", "nonfinite_grads")
_DIGESTS = ("task_fingerprint", "spec_digest", "params_digest", "config_digest")
_HEX12 = re.compile(r"[0-9a-f]{12}")


def check_name(kind: str, name) -> str:
    """``name`` if it can become a path component (letters, digits, ``_`` and ``-``, not
    starting with ``-``, at most 100 characters); ``ValueError`` naming it otherwise."""
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise ValueError(f"{kind} name {name!r} is not allowed: a {kind} name is letters, "
                         f"digits, '_' and '-' (it becomes a file name)")
    return name


def make_row(task, method, seed, budget, **values) -> dict:
    """A row: every column of :data:`COLUMNS` (``""`` where ``values`` gives none)."""
    row = dict.fromkeys(COLUMNS, "")
    row.update(task=task, method=method, seed=seed, budget=budget, **values)
    return row


def key(row: Mapping) -> tuple:
    """``(task, method, seed, budget)`` of a row (seed as an int)."""
    return row["task"], row["method"], int(row["seed"]), row["budget"]


def latest(rows: Iterable[Mapping]) -> list:
    """The row that counts for each (task, method, seed, budget): the last one in the file
    (a failed run retried on resume is superseded by its retry)."""
    last: dict = {}
    for r in rows:
        last.pop(key(r), None)
        last[key(r)] = r
    return list(last.values())


def remeasured(before: Mapping, after: Mapping) -> bool:
    """``after`` is the same run as ``before`` measured again on other dax-tasks /
    dax-physics code, task spec or method config (``dax-bench run --rerun-stale``): both
    record their provenance and their task fingerprints or config digests differ."""
    fields = ("task_fingerprint", "config_digest")
    if not all(before.get(f) and after.get(f) for f in fields):
        return False
    return any(before[f] != after[f] for f in fields)


def previous_errors(row: Mapping) -> list:
    """The errors of the run's earlier attempts (its ``previous_errors``, decoded)."""
    text = row.get("previous_errors") or ""
    return json.loads(text) if text else []


def errors_of(row: Mapping) -> list:
    """The row's error history: its ``previous_errors`` and, if it failed, its error."""
    return previous_errors(row) + ([row["error"]] if row.get("status") == "failed" else [])


def _float(row, col) -> float:
    try:
        return float(row[col])
    except ValueError:
        raise ValueError(f"{col} {row[col]!r} is not a number") from None


def check_row(row: Mapping) -> None:
    """``ValueError`` saying what is wrong with one row read from a results file: a name
    that cannot be a path, a seed that is not an integer >= 0, an unknown budget, status or
    precision, a score that is not a number in [0, 1] (an ``ok`` row must have one), a
    negative or non-numeric time or count, a malformed digest or error history."""
    check_name("task", row["task"])
    check_name("method", row["method"])
    if not re.fullmatch(r"[0-9]+", row["seed"]):
        raise ValueError(f"seed {row['seed']!r} is not an integer >= 0")
    if row["budget"] not in BUDGETS:
        raise ValueError(f"budget {row['budget']!r} is not one of {', '.join(BUDGETS)}")
    if row["status"] not in STATUSES:
        raise ValueError(f"status {row['status']!r} is not one of {', '.join(STATUSES)}")
    for col in _SCORES:
        if row[col] or (col == "score" and row["status"] == "ok"):
            score = _float(row, col)
            if (row["status"] == "ok" or math.isfinite(score)) and not 0.0 <= score <= 1.0:
                raise ValueError(f"{col} {row[col]!r} is not in [0, 1] (a final-step r_gt)")
    for col in (*_FLOATS, *_TIMES):
        if row[col]:
            x = _float(row, col)
            if col in _TIMES and not x >= 0.0:
                raise ValueError(f"{col} {row[col]!r} is not a time >= 0")
    for col in _COUNTS:
        if row[col] and not re.fullmatch(r"[0-9]+", row[col]):
            raise ValueError(f"{col} {row[col]!r} is not an integer >= 0")
    for col in _DIGESTS:
        if row[col] and not _HEX12.fullmatch(row[col]):
            raise ValueError(f"{col} {row[col]!r} is not 12 hex digits")
    if row["precision"] and row["precision"] not in provenance.PRECISIONS:
        raise ValueError(f"precision {row['precision']!r} is not one of "
                         f"{', '.join(provenance.PRECISIONS)}")
    if row["previous_errors"]:
        try:
            history = json.loads(row["previous_errors"])
        except ValueError:
            history = None
        if not (isinstance(history, list) and all(isinstance(e, str) for e in history)):
            raise ValueError(f"previous_errors {row['previous_errors'][:80]!r} is not a "
                             f"JSON list of strings")


def read_rows(path: Path) -> list[dict]:
    """Every row of ``results.csv``, in file order, each with all of :data:`COLUMNS` (a
    file with :data:`OLD_COLUMNS` reads with empty provenance, one with
    :data:`PROVENANCE_COLUMNS` with no untrained scores, one of :data:`HEADERS` without
    ``machine`` with it empty). An incomplete last line,
    from an interrupted write, is dropped from the file. A file that is not a results file
    (not UTF-8 text, other columns) is a ``ValueError`` naming it; a row that is not valid
    (:func:`check_row`; a row with too few or too many fields; a second row for a (task,
    method, seed, budget) that is not the retry of a failed run) is a ``ValueError`` naming
    the file and the line."""
    path = Path(path)

    def garbled(problem):
        return ValueError(f"{path}: not a dax-bench results file ({problem}); use another "
                          f"--out directory")

    try:  # checked before read_complete cuts an incomplete last line off the file
        text = path.read_bytes().decode() if path.is_file() else ""
        header = next(csv.reader([text.split("\n", 1)[0]])) if text else list(COLUMNS)
    except UnicodeDecodeError:
        raise garbled("not UTF-8 text") from None
    except csv.Error as err:
        raise garbled(f"bad CSV: {err}") from None
    if tuple(header) not in HEADERS:
        raise garbled(f"columns {header}, expected {list(COLUMNS)}")
    rows = _parse(path, text[:text.rfind("\n") + 1], header)
    csvlog.read_complete(path)  # a results file: cut the incomplete line off it now
    return rows


def _parse(path: Path, text: str, header) -> list[dict]:
    reader = csv.reader(io.StringIO(text))
    rows, seen = [], {}
    try:
        next(reader, None)
        for fields in reader:
            line = reader.line_num
            where = f"{path}, line {line}"
            if len(fields) != len(header):
                raise ValueError(f"{where}: {len(fields)} fields, expected {len(header)} "
                                 f"(a truncated or garbled row); fix or remove that line")
            row = make_row(**dict(zip(header, fields, strict=True)))
            try:
                check_row(row)
            except ValueError as err:
                raise ValueError(f"{where}: {err}; fix or remove that line") from None
            k = key(row)
            if k in seen:
                first_line, first = seen[k]
                retry = first["status"] == "failed" and row["previous_errors"]
                if not (retry or remeasured(first, row)):
                    raise ValueError(f"{where}: a second row for {k[0]} / {k[1]} / seed "
                                     f"{k[2]} / {k[3]} (line {first_line}), neither the "
                                     f"retry of a failed run nor a run measured again on "
                                     f"other code or config; remove one of them")
            seen[k] = (line, row)
            rows.append(row)
    except csv.Error as err:
        raise ValueError(f"{path}, line {reader.line_num}: bad CSV ({err})") from None
    return rows


def upgrade(path: Path, rows: list) -> None:
    """Rewrite a results file of older columns (the earlier :data:`HEADERS`) with
    :data:`COLUMNS` (atomically; its rows keep their
    values, the new columns stay empty), so that new rows can be appended; nothing for a
    file that has them already."""
    path = Path(path)
    if csvlog.is_empty(path):
        return
    with open(path, encoding="utf-8") as f:
        header = next(csv.reader([f.readline()]))
    if tuple(header) == COLUMNS:
        return
    buf = io.StringIO()
    writer = csv.DictWriter(buf, COLUMNS, lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: r.get(k, "") for k in COLUMNS})
    atomic_write(path, buf.getvalue())


def append_row(path: Path, row: Mapping) -> None:
    """Append one row with a single write, flushed and fsynced (header first if new)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, COLUMNS, lineterminator="\n")
    if csvlog.is_empty(path):
        writer.writeheader()
    writer.writerow({k: _fmt(row.get(k, "")) for k in COLUMNS})
    csvlog.append(path, buf.getvalue())


def _fmt(v):
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else str(v)
    return v
