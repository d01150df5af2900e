"""Atomic file writes: the one helper every DaX package uses for what it writes (goal files
and GIFs here, demonstration files in dax-data, benchmark reports in dax-algos).

A write goes to a temporary file in the target's directory, is flushed and fsynced, and is
renamed onto the target only when complete (then the directory is fsynced too), so a
reader sees the old file or the new one, never half of one; a failed or interrupted write
leaves no temporary file behind.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO


def temporaries(path: str | os.PathLike) -> list:
    """Temporary files a killed writer of ``path`` may have left (``.NAME.*.tmp``)."""
    path = Path(path)
    return sorted(path.parent.glob(f".{path.name}.*.tmp"))


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory file descriptors
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, copy_existing: bool = False) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s directory to write to (a copy of ``path`` when
    ``copy_existing``, for an in-place update such as appending to an HDF5 file); when the
    block ends without an error the file is fsynced and renamed onto ``path``, otherwise it
    is deleted. Creates the directory if needed. New files get the usual permissions
    (``0666 & ~umask``), copies keep the original's."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        if copy_existing:
            shutil.copyfile(path, tmp)
            shutil.copymode(path, tmp)
        else:  # mkstemp makes the file private (0600)
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
        yield tmp
        with open(tmp, "rb+") as f:
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write(path: str | os.PathLike, data: bytes | str | Callable[[BinaryIO], None]
                 ) -> Path:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`): bytes, text (UTF-8)
    or a function ``write(f)`` given the temporary file opened for binary writing."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        if callable(data):
            data(f)
        else:
            f.write(data.encode() if isinstance(data, str) else data)
    return Path(path)
