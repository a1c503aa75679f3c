"""The project lock: one writing command on a project at a time.

Every command that writes a project (``generate``, ``import``, ``order``, ``init``,
``adjust``) holds ``NAME.h5.lock`` beside it from its first read to its last write, through
:mod:`filelock` (an exclusive ``flock`` of the lock file, which the kernel releases when the
holder's process ends, however it ends: a lock left by a killed run is taken over at once).
A second writer is refused at once with one line naming the holder (command, process, host
and start, which the holder writes into the lock file). The lock is the process's, held
again by nested calls (``adjust`` orders the project under its own lock). Readers (``info``,
``report``, ``export``) take no lock: a writer never changes a project in place but
replaces it whole (:class:`sapgo.project.ProjectWriter`, the commit of an adjustment).

The lock file is removed while still held at release, so a finished project leaves none
behind; a contender that opened the old file sees it unlinked and starts over (filelock
checks the link count after its ``flock``).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import functools
import inspect
import json
import os
import socket
import sys
import threading
from pathlib import Path

from .errors import SapgoError


class ProjectLockedError(SapgoError):
    """Another command is writing the project."""


_held: dict[str, list] = {}   # resolved path -> [FileLock, depth]
_guard = threading.Lock()


def lock_path(path):
    """The lock file of the project at ``path``: ``NAME.h5.lock`` beside it."""
    path = Path(path)
    return path.with_name(path.name + ".lock")


def _holder(lock_file):
    try:
        info = json.loads(Path(lock_file).read_text() or "{}")
    except (OSError, ValueError):
        info = {}
    if not info.get("pid"):
        return "another process"
    return (f"sapgo {info.get('command', '?')} (process {info['pid']} on "
            f"{info.get('host', '?')}, since {info.get('since', '?')})")


@contextlib.contextmanager
def project_lock(path, command):
    """Hold the lock of the project at ``path`` for ``command`` (a word for the message a
    contender gets). Raises :class:`ProjectLockedError` at once when another process holds
    it."""
    from filelock import FileLock, Timeout

    key = str(Path(os.path.abspath(path)))
    with _guard:
        entry = _held.get(key)
        if entry is not None:
            entry[1] += 1
    if entry is None:
        lf = lock_path(key)
        made = []   # (the folders made for a new project: removed if it is not written)
        if not lf.parent.is_dir():   # (a new project's folder: made by its writer)
            d = lf.parent
            while not d.exists():
                made.append(d)
                d = d.parent
            lf.parent.mkdir(parents=True, exist_ok=True)
        lock = FileLock(str(lf), timeout=0, thread_local=False)
        try:
            lock.acquire()
        except Timeout:
            raise ProjectLockedError(
                f"{path} is being written by {_holder(lf)}: try again when it has finished "
                f"(a run that was killed releases it by itself)") from None
        try:
            with open(lf, "r+") as f:
                f.truncate()
                f.write(json.dumps({
                    "command": command, "pid": os.getpid(), "host": socket.gethostname(),
                    "since": _dt.datetime.now().isoformat(timespec="seconds"),
                    "argv": sys.argv[:8]}))
        except OSError:   # (a full disk: the lock holds, its note is only for the message)
            pass
        entry = [lock, 1, made]
        with _guard:
            _held[key] = entry
    try:
        yield
    finally:
        with _guard:
            entry[1] -= 1
            last = entry[1] == 0
            if last:
                del _held[key]
        if last:
            with contextlib.suppress(OSError):
                os.unlink(entry[0].lock_file)
            entry[0].release()
            if not os.path.exists(key):   # (a refused command: no folder left behind)
                for d in entry[2]:
                    with contextlib.suppress(OSError):
                        d.rmdir()   # (only while empty)


def writes_project(command, target):
    """Decorator: the function holds the lock of the project named by its argument
    ``target`` (:func:`project_lock`) while it runs, with numpy's huge-page advice off
    (:func:`sapgo.paging.hugepage_advice_off`)."""
    def deco(fn):
        sig = inspect.signature(fn)

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            from .paging import hugepage_advice_off
            from .project import disk_full_error, is_disk_full

            bound = sig.bind_partial(*args, **kwargs)
            path = bound.arguments[target]
            with project_lock(path, command), hugepage_advice_off():
                try:
                    return fn(*args, **kwargs)
                except (OSError, RuntimeError) as exc:   # (the writers removed their files)
                    if is_disk_full(exc):
                        raise disk_full_error(path, exc) from None
                    raise
        return wrapper
    return deco
