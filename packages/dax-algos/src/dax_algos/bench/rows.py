"""``results.csv``: one row per (task, method, seed, budget), its columns, and reading and
appending rows so that a killed writer costs at most its own incomplete last line
(:mod:`.csvlog`)."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping
from pathlib import Path

from . import csvlog

COLUMNS = ("task", "method", "seed", "budget", "status", "score", "final_distance", "wall_s",
           "compile_s", "env_steps", "backprop_steps", "grad_norm", "grad_norm_mean",
           "nonfinite_grads", "error")


def make_row(task, method, seed, budget, **values) -> dict:
    """A row: every column of :data:`COLUMNS` (``""`` where ``values`` gives none)."""
    row = dict.fromkeys(COLUMNS, "")
    row.update(task=task, method=method, seed=seed, budget=budget, **values)
    return row


def read_rows(path: Path) -> list[dict]:
    """The rows of ``results.csv`` (an incomplete last line, from an interrupted write, is
    dropped from the file). A file that is not a results file (not text, other columns, a
    seed that is not an integer) is a ``ValueError`` naming it."""
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
    if set(header) != set(COLUMNS):
        raise garbled(f"columns {header}, expected {list(COLUMNS)}")
    try:  # the complete lines (an interrupted write leaves an incomplete last one)
        rows = list(csv.DictReader(io.StringIO(text[:text.rfind("\n") + 1])))
    except csv.Error as err:
        raise garbled(f"bad CSV: {err}") from None
    rows = [r for r in rows if None not in r.values()]
    for i, r in enumerate(rows):
        try:
            int(r["seed"])
        except ValueError:
            raise garbled(f"row {i + 2}: seed {r['seed']!r} is not an integer") from None
    csvlog.read_complete(path)  # a results file: cut the incomplete line off it now
    return rows


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
