"""The benchmark scripts' one JSON document: printed to stdout and, with ``--out``, written
atomically (``dax_tasks.io.atomic_write``: a temporary file in the same directory, fsynced,
renamed), so an interrupted run never leaves half a results file."""

from __future__ import annotations

import json


def write_report(doc: dict, out: str | None, indent: int = 1) -> None:
    text = json.dumps(doc, indent=indent)
    print(text, flush=True)
    if out:
        from dax_tasks.io import atomic_write

        atomic_write(out, text + "\n")
