"""Atomic file writes and one writer per file: the helpers every DaX package uses for what
it writes (goal files and GIFs here, demonstration files in dax-data, benchmark reports in
dax-algos).

A write goes to a temporary file in the target's directory, is flushed and fsynced, and is
renamed onto the target only when complete (then the directory is fsynced too), so a
reader sees the old file or the new one, never half of one; a failed or interrupted write
leaves no temporary file behind.

A file that is *updated* over a long run (a demonstration file gaining an episode at a
time, a benchmark's results) also needs a single writer: two runs copying, extending and
renaming the same file lose each other's work. :func:`exclusive` holds an advisory lock
(``flock(2)``) on a lock file beside it, ``.<name>.lock``, for the whole run: a second
writer is refused at once (:class:`FileLockedError`, naming the holder's pid, host,
program and start time) or waits for it. The kernel releases the lock when its holder
exits, however it exits (even ``kill -9``), so a lock is never stale; the holder removes
the lock file when done. Readers take no lock: they see whole files, thanks to the atomic
renames. The lock is advisory (only DaX's writers take it) and assumes a local file
system (``flock`` on NFS may not be seen by other hosts).

**The real file.** Locks, temporary files and renames act on the file a path names after
every symbolic link is resolved (:func:`real_path`): writing to a link updates its target
in place of the link (the link stays a link), and the link and its target share one lock,
so two writers that name the same file differently still exclude each other. A link loop
is refused (``ValueError``). Hard links are not followed: a rename replaces the one name
written to.

**Waiting.** A writer that waits for the lock (``wait > 0``) says once who holds it
(``notify``, default one line on stderr) and gives up with :class:`FileLockedError` after
``wait`` seconds; a holder stopped by a signal (state ``T`` in ``/proc``) is named as
stopped.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import math
import os
import shutil
import socket
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no locks (documented)
    fcntl = None


def real_path(path: str | os.PathLike) -> Path:
    """The absolute path of the file ``path`` names, every symbolic link resolved (the
    file itself need not exist: a dangling link resolves to the file it would create).
    ``ValueError`` naming ``path`` for a link loop."""
    path = Path(path)
    real = Path(os.path.realpath(path))
    if real.is_symlink():  # the resolution stopped at a link: a loop
        raise ValueError(f"{path}: its symbolic links form a loop (at {real})")
    return real


def temporaries(path: str | os.PathLike) -> list:
    """Temporary files a killed writer of ``path`` may have left (``.NAME.*.tmp`` beside the
    real file, :func:`real_path`)."""
    path = real_path(path)
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
    (``0666 & ~umask``), copies keep the original's. A symbolic link is written through:
    the temporary file and the rename are beside its target (:func:`real_path`), and the
    link stays."""
    path = real_path(path)
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


class FileLockedError(OSError):
    """Another process holds the write lock of a file (:func:`exclusive`); the message
    names the file and the holder."""


def lock_path(path: str | os.PathLike) -> Path:
    """The lock file of ``path``: ``.<name>.lock`` beside the real file
    (:func:`real_path`), so a link and its target share it."""
    path = real_path(path)
    return path.parent / f".{path.name}.lock"


def _stopped(pid) -> bool:
    """Whether process ``pid`` of this host is stopped (state ``T`` or ``t`` in
    ``/proc/<pid>/stat``; false where that cannot be read)."""
    try:
        stat = Path(f"/proc/{int(pid)}/stat").read_text()
    except (OSError, ValueError, TypeError):
        return False
    fields = stat.rpartition(")")[2].split()
    return bool(fields) and fields[0] in ("T", "t")


def _holder(fd: int) -> str:
    """What the lock file says about its holder (written by :func:`exclusive`)."""
    try:
        info = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        info = {}
    if not isinstance(info, dict) or "pid" not in info:
        return "another process"
    host = info.get("host", "?")
    stopped = " (stopped)" if host == socket.gethostname() and _stopped(info["pid"]) else ""
    return (f"pid {info.get('pid')}{stopped} on {host}, {info.get('program', '?')}, "
            f"since {info.get('since', '?')}")


def _to_stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@contextlib.contextmanager
def exclusive(path: str | os.PathLike, wait: float = 0.0, program: str | None = None,
              poll: float = 0.1, notify: Callable[[str], None] | None = _to_stderr
              ) -> Iterator[Path]:
    """Hold the write lock of ``path`` for the ``with`` block (see the module docstring).

    wait: seconds to wait for another holder to finish (0: refuse at once; ``math.inf``:
        wait as long as it takes).
    program: what the lock file records as the holder (default: the command line).
    notify: called once with a one-line message naming ``path``, the holder and ``wait``
        when the lock is held by another process and ``wait > 0`` (default: printed on
        stderr; ``None``: silent).
    Raises :class:`FileLockedError` if another process holds the lock after ``wait``
    seconds, ``ValueError`` for a symbolic-link loop, and ``OSError`` (e.g.
    ``PermissionError``) if the lock file cannot be created, so an unwritable directory is
    found before any work. Yields the lock file's path (beside the real file,
    :func:`lock_path`). The lock is per open file: a second ``exclusive`` of the same file
    in the same process is refused too. Without ``fcntl`` (not POSIX) nothing is locked.
    """
    path = Path(path)
    lock = lock_path(path)
    if fcntl is None:  # pragma: no cover
        yield lock
        return
    fd = _acquire(path, lock, wait, poll, notify)
    try:
        _record_holder(fd, program)
        yield lock
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)  # while still holding it (see _acquire)
        os.close(fd)


def _acquire(path: Path, lock: Path, wait: float, poll: float,
             notify: Callable[[str], None] | None) -> int:
    """An open descriptor of ``lock`` (the current lock file of ``path``) holding its
    ``flock``; :class:`FileLockedError` if another process still holds it after ``wait``
    seconds (tried every ``poll`` seconds; ``notify`` told once who holds it)."""
    deadline = time.monotonic() + wait
    told = False
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            for _ in range(5):  # the holder writes who it is just after taking the lock
                if holder != "another process":
                    break
                time.sleep(0.02)
                holder = _holder(fd)
            os.close(fd)
            if time.monotonic() >= deadline:
                waited = f" (waited {wait:g} s)" if wait > 0 else ""
                raise FileLockedError(
                    f"{path}: another process is writing it ({holder}; lock file "
                    f"{lock}){waited}; wait for it to finish, or write elsewhere") from None
            if not told and notify is not None:
                limit = "as long as it takes" if math.isinf(wait) else f"up to {wait:g} s"
                notify(f"{path}: waiting for another process to finish writing it "
                       f"({holder}); waiting {limit}")
                told = True
            time.sleep(min(poll, max(deadline - time.monotonic(), 0.0)))
            continue
        except BaseException:
            os.close(fd)
            raise
        # The previous holder removes the lock file when it is done: a lock taken on the
        # file it removed guards nothing, so take the lock again on the current one.
        try:
            current = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            current = False
        if current:
            return fd
        os.close(fd)


def _record_holder(fd: int, program: str | None) -> None:
    """Write who holds the lock (pid, host, ``program`` or the command line, start time)
    into the lock file ``fd``, as JSON."""
    info = {"pid": os.getpid(), "host": socket.gethostname(),
            "program": program or " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])[:200],
            "since": datetime.datetime.now(datetime.timezone.utc).isoformat(
                timespec="seconds")}
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(info).encode(), 0)
