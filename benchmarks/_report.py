"""The benchmark scripts' one JSON document: printed to stdout and, with ``--out``, written
atomically (``dax_tasks.io.atomic_write``: a temporary file in the same directory, fsynced,
renamed), so an interrupted run never leaves half a results file."""

from __future__ import annotations

import json
import re
from pathlib import Path


def write_report(doc: dict, out: str | None, indent: int = 1) -> None:
    text = json.dumps(doc, indent=indent)
    print(text, flush=True)
    if out:
        from dax_tasks.io import atomic_write

        atomic_write(out, text + "\n")


#: The repository root: result-file paths in the READMEs' table markers are relative to it.
ROOT = Path(__file__).resolve().parent.parent


def read_result(path) -> tuple[Path, object]:
    """``(path as given, content)`` of a result file: one JSON document, or JSON lines (a
    list of the lines' objects; always for a ``.jsonl`` file). A relative ``path`` that
    does not exist from the working directory is read from the repository root."""
    path = Path(path)
    full = path if path.is_absolute() or path.exists() else ROOT / path
    text = full.read_text()
    if path.suffix != ".jsonl":
        try:
            return path, json.loads(text)
        except json.JSONDecodeError:
            pass
    return path, [json.loads(line) for line in text.splitlines() if line.strip()]


def read_records(path) -> list[dict]:
    """The records of a JSON-lines file that a run appends to (none if it does not exist):
    every line's object except summary lines (``"summary": true``, rewritten, not read
    back); a torn line (a killed writer) is dropped."""
    path = Path(path)
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            r = json.loads(line)
        except json.JSONDecodeError:
            continue
        if not r.get("summary"):
            records.append(r)
    return records


def file_date(path) -> str | None:
    """The ``YYYY-MM-DD`` a result file's name starts with (the day it was measured), or
    None."""
    m = re.match(r"(\d{4}-\d{2}-\d{2})", Path(path).name)
    return m[1] if m else None


def load_range(values) -> str:
    """``"a-b"`` (one decimal) of the 1-minute load averages ``values`` (None dropped), or
    ``"not recorded"``."""
    vals = [float(v) for v in values if v is not None]
    if not vals:
        return "not recorded"
    lo, hi = min(vals), max(vals)
    return f"{lo:.1f}" if f"{lo:.1f}" == f"{hi:.1f}" else f"{lo:.1f}-{hi:.1f}"
