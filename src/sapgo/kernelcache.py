"""Where numba keeps sapgo's compiled kernels: a folder keyed on the installed version and
on the source of every module that defines kernels.

numba's own cache (``cache=True``, in ``__pycache__`` beside each module) notices a change
of the module that holds a kernel, not of the modules whose kernels it calls: after an
upgrade a caller could run a stale compiled copy of a changed callee. Keying the whole
cache on the kernels' sources makes any change of any of them a fresh compilation (once),
and an upgrade leaves the older keys' folders to be removed here (all but the newest few).

The folder: ``$SAPGO_CACHE_DIR`` or ``$XDG_CACHE_HOME/sapgo`` (``~/.cache/sapgo``), then
``numba-<version>-<hash>``. ``NUMBA_CACHE_DIR`` set by the user is respected as it is.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

#: Whether this process found no compiled kernels for its key (the first run after an
#: install or an upgrade: the command line says it compiles them, once).
FIRST_RUN = False
#: Key folders kept (the one in use and the most recently made others).
KEEP = 3
#: The folder in use (None: the user's ``NUMBA_CACHE_DIR``, or no writable folder).
CACHE_DIR = None


def kernel_key(version):
    """``<version>-<12 hex digits>``: the hash of the sources of the modules that define
    kernels (``njit``)."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        text = path.read_bytes()
        if b"njit(" in text or b"@njit" in text:
            h.update(path.relative_to(root).as_posix().encode())
            h.update(text)
    return f"{version}-{h.hexdigest()[:12]}"


def configure(version):
    """Point numba's cache at the folder of this installation's key (before any kernel is
    defined); remove the folders of other keys. Sets :data:`FIRST_RUN`."""
    global FIRST_RUN, CACHE_DIR
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    base = os.environ.get("SAPGO_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
        "sapgo")
    base = Path(base)
    folder = base / f"numba-{kernel_key(version)}"
    try:
        FIRST_RUN = not folder.is_dir()
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:   # no writable cache folder: numba's default beside the modules
        FIRST_RUN = False
        return
    others = sorted((p for p in base.glob("numba-*") if p != folder),
                    key=lambda p: p.stat().st_mtime, reverse=True)
    for old in others[KEEP - 1:]:   # (the newest few stay: other installations in use)
        shutil.rmtree(old, ignore_errors=True)
    import numba.core.config

    os.environ["NUMBA_CACHE_DIR"] = str(folder)   # (Dask workers and subprocesses)
    numba.core.config.CACHE_DIR = str(folder)
    CACHE_DIR = folder
