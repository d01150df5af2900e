"""Append-only CSV logs that survive a killed writer (results.csv, learning_<task>.csv).

Rows are appended in one write, flushed and fsynced, so a kill leaves at most one
incomplete last line; :func:`read_complete` cuts such a line off the file (and
:func:`append` does so before writing, so new rows never join it).
"""

from __future__ import annotations

import os
from pathlib import Path


def read_complete(path) -> str:
    """The file's text up to its last newline, the file truncated there if needed ("" if
    there is no file)."""
    path = Path(path)
    if not path.exists():
        return ""
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        cut = data.rfind(b"\n") + 1
        with open(path, "r+b") as f:
            f.truncate(cut)
        data = data[:cut]
    return data.decode()


def append(path, text: str) -> None:
    """Append ``text`` (whole lines) in a single write, flushed and fsynced."""
    read_complete(path)
    with open(path, "a", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def is_empty(path) -> bool:
    """No file at ``path``, or an empty one (a writer starts it with the header)."""
    path = Path(path)
    return not path.exists() or path.stat().st_size == 0
