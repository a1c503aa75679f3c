"""Per-station vectors of a very large block, memory-mapped from scratch files.

The passes of an adjustment stream points, observations and factor rows from direct-access
files (:mod:`sapgo.rawfile`); what stays in core is a few vectors a station: the
orientations, the step, the orientations before it, the variances of the precision pass.
At 48 bytes each, these are 480 MB apiece for 10 000 000 photos. The numba kernels read
them at random by station number (though always within the band of the points they work
on), so they cannot be streamed like records.

Above :data:`PAGE_STATIONS` stations (``Options.page_stations``) the run allocates them
here instead: each is a ``MAP_SHARED`` map of an unlinked file in the work directory, and a
janitor thread returns every map's pages to the page cache every :data:`RELEASE_SECONDS`
(``madvise(MADV_DONTNEED)``: a shared map's data stay in the page cache, and the next touch
maps the same page again, without a read while the kernel keeps it). The process holds
only the pages touched since the last release -- in a pass over the stations, the band it
is working on -- and the kernel keeps, writes back or drops the rest as memory allows.
Below the threshold (every block up to a few million photos) the same calls give ordinary
arrays.

Use::

    with paging.paged(work_dir, enabled):
        eo = paging.zeros((n, 6))          # a mapped array while paged, else np.zeros
"""

from __future__ import annotations

import contextlib
import mmap
import os
import tempfile
import threading
import weakref

import numpy as np

#: Blocks of more stations than this keep their per-station vectors in mapped files
#: (``sapgo adjust --page-stations``).
PAGE_STATIONS = 2_000_000

#: The janitor returns the maps' pages to the page cache this often (seconds).
RELEASE_SECONDS = 0.1

#: Arrays smaller than this stay in core even while paged.
MIN_PAGED_BYTES = 1 << 20


class Pager:
    """Mapped arrays in ``directory`` and the janitor thread that releases their pages."""

    def __init__(self, directory, interval=RELEASE_SECONDS, min_bytes=MIN_PAGED_BYTES):
        self.directory = os.fspath(directory)
        self.min_bytes = min_bytes
        self.interval = interval
        self._maps = weakref.WeakSet()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = None
        self.released = 0   # janitor rounds (for the tests)

    def zeros(self, shape, dtype=np.float64):
        """A zero-filled array of ``shape``, mapped from an unlinked file whose blocks are
        allocated first (``posix_fallocate``): a full disk is an ``OSError`` naming the
        directory here, never a SIGBUS at the first write through the map."""
        dtype = np.dtype(dtype)
        shape = tuple(int(s) for s in np.atleast_1d(shape)) if not isinstance(shape, int) \
            else (int(shape),)
        nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if nbytes < max(1, self.min_bytes):
            return np.zeros(shape, dtype)
        with tempfile.TemporaryFile(dir=self.directory, prefix="paged.") as f:
            try:
                os.posix_fallocate(f.fileno(), 0, nbytes)
            except OSError as exc:
                raise OSError(exc.errno, f"{exc.strerror} (a {nbytes / 2**20:.0f} MiB scratch "
                                         f"vector of the run)", self.directory) from None
            mm = mmap.mmap(f.fileno(), nbytes)   # (the map keeps the file; it may close)
        with self._lock:
            self._maps.add(mm)
        return np.frombuffer(mm, dtype).reshape(shape)

    def release(self):
        """Return every map's pages to the page cache."""
        with self._lock:
            maps = list(self._maps)
        for mm in maps:
            try:
                mm.madvise(mmap.MADV_DONTNEED)
            except (ValueError, OSError):   # closed meanwhile
                pass
        self.released += 1

    def _run(self):
        while not self._stop.wait(self.interval):
            self.release()

    def start(self):
        self._thread = threading.Thread(target=self._run, name="sapgo-pager", daemon=True)
        self._thread.start()

    def stop(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None


_active: Pager | None = None


def _advice_switch():
    """numpy's switch of its transparent-huge-page advice (``_set_madvise_hugepage``:
    private, in numpy since 1.20; it returns the setting it replaces), or None."""
    import importlib

    for name in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            mod = importlib.import_module(name)
        except ImportError:
            continue
        switch = getattr(mod, "_set_madvise_hugepage", None)
        if switch is not None:
            return switch
    return None


_advice_lock = threading.Lock()
_advice_depth = 0        # (how many blocks of hugepage_advice_off are open, in any thread)
_advice_before = None    # (numpy's setting when the first of them opened)


@contextlib.contextmanager
def hugepage_advice_off():
    """numpy's transparent-huge-page advice off until the block exits, then numpy's setting
    back (every command that writes a project runs in one: :func:`sapgo.lock.writes_project`).

    numpy asks the kernel for huge pages (``madvise(MADV_HUGEPAGE)``) on every array of
    4 MiB or more. Where the kernel defragments memory for such requests (``defrag``
    ``madvise``, common), a run right after other work on the machine slowed down 1.5
    times: a 1 000-photo block's run 0.161-0.171 s with the advice on against 0.104-0.113 s
    off (``python benchmarks/interference.py``, benchmarks/README.md). Off, runs alone took
    as long at 10 000 and 100 000 photos and on the squares, within the machine's
    run-to-run differences (the same script's ``--alone``). A value the environment gives numpy (``NUMPY_MADVISE_HUGEPAGE``, read when
    numpy loads) is the user's choice: sapgo then leaves numpy's setting alone. (Dask
    workers are processes of their own and keep theirs.)

    numpy's setting is one for the process: the blocks are counted, the first to open
    turns the advice off and the last to close puts back what the first found, so that
    commands running at once in threads of one process (which may end in any order) leave
    numpy as they found it.
    """
    global _advice_depth, _advice_before
    switch = None if "NUMPY_MADVISE_HUGEPAGE" in os.environ else _advice_switch()
    if switch is None:
        yield
        return
    with _advice_lock:
        if _advice_depth == 0:
            _advice_before = switch(False)
        _advice_depth += 1
    try:
        yield
    finally:
        with _advice_lock:
            _advice_depth -= 1
            if _advice_depth == 0:
                switch(_advice_before)
                _advice_before = None


@contextlib.contextmanager
def paged(directory, enabled=True, min_bytes=MIN_PAGED_BYTES):
    """Per-station vectors allocated by :func:`zeros`, :func:`empty` and :func:`copy` are
    mapped from files in ``directory`` (when ``enabled``) until the block exits; those of
    fewer than ``min_bytes`` stay in core."""
    global _active
    if not enabled or _active is not None:
        yield _active
        return
    pager = Pager(directory, min_bytes=min_bytes)
    pager.start()
    _active = pager
    try:
        yield pager
    finally:
        _active = None
        pager.stop()


def active():
    """Is a run's paging on?"""
    return _active is not None


def zeros(shape, dtype=np.float64):
    """``np.zeros``, mapped from a scratch file while :func:`paged`."""
    if _active is None:
        return np.zeros(shape, dtype)
    return _active.zeros(shape, dtype)


def empty(shape, dtype=np.float64):
    """``np.empty`` (zero-filled when mapped)."""
    if _active is None:
        return np.empty(shape, dtype)
    return _active.zeros(shape, dtype)


#: Rows a chunked copy or read moves at a time.
CHUNK_ROWS = 1 << 16


def copy(a, dtype=None):
    """A copy of ``a`` (an array or anything sliced by rows: an HDF5 dataset, a
    :class:`~sapgo.rawfile.RawArray`), made a chunk of rows at a time."""
    dtype = np.dtype(dtype or a.dtype)
    out = empty(a.shape, dtype)
    for i in range(0, len(out), CHUNK_ROWS):
        out[i:i + CHUNK_ROWS] = a[i:i + CHUNK_ROWS]
    return out


def field(p, table, name, dtype=None):
    """A field of a project's records (``p.read_field(table, name)``), read a chunk at a
    time into a (possibly mapped) array."""
    first = p.read_field(table, name, 0, 0)
    n = int(p.file[table].shape[0])
    out = empty((n,) + first.shape[1:], dtype or first.dtype)
    for a, b in p.chunks(table):
        out[a:b] = p.read_field(table, name, a, b)
    return out


def release():
    """While paged, return every map's pages to the page cache now."""
    if _active is not None:
        _active.release()


def rows(n, step=CHUNK_ROWS):
    """``(a, b)`` row ranges of ``n`` rows; while paged, the maps' pages are released after
    each (a pass at memory speed outruns the janitor)."""
    for a in range(0, n, step):
        yield a, min(n, a + step)
        release()


def save_npy(f, a):
    """``np.save(f, a)`` of a C-contiguous array, a chunk of rows at a time."""
    fmt = np.lib.format
    fmt.write_array_header_1_0(f, fmt.header_data_from_array_1_0(a))
    for i, j in rows(len(a)):
        f.write(np.ascontiguousarray(a[i:j]).tobytes())


def npy_header(path):
    """``(shape, dtype, data offset)`` of an ``.npy`` file (ValueError when it is not one,
    or is cut short)."""
    fmt = np.lib.format
    with open(path, "rb") as f:
        version = fmt.read_magic(f)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, fortran, dtype = read(f)
        offset = f.tell()
        size = os.fstat(f.fileno()).st_size
    if fortran or dtype.hasobject:
        raise ValueError(f"{path}: not a C-ordered numeric array")
    if size != offset + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize:
        raise ValueError(f"{path}: {size} bytes, not those of {shape} {dtype}")
    return shape, dtype, offset


def load_npy(path):
    """``np.load(path)`` read a chunk of rows at a time into a (possibly mapped) array."""
    shape, dtype, offset = npy_header(path)
    out = empty(shape, dtype)
    flat = out.reshape(len(out), -1) if len(shape) else out.reshape(1)
    with open(path, "rb") as f:
        f.seek(offset)
        for i, j in rows(len(flat)):
            f.readinto(memoryview(flat[i:j]).cast("B"))
    return out


def assign(dst, src):
    """``dst[:] = src``, a chunk of rows at a time."""
    for a, b in rows(len(dst)):
        dst[a:b] = src[a:b]


def take(a, idx):
    """``a[idx]`` (rows of ``a`` at the indices ``idx``), gathered a chunk at a time into a
    (possibly mapped) array."""
    out = empty((len(idx),) + a.shape[1:], a.dtype)
    for i, j in rows(len(idx)):
        out[i:j] = a[idx[i:j]]
    return out


def arange(n, dtype=np.int64):
    """``np.arange(n)``, a chunk at a time into a (possibly mapped) array."""
    out = empty(n, dtype)
    for a, b in rows(n):
        out[a:b] = np.arange(a, b)
    return out


def inverse(perm, n=None):
    """``pos`` with ``pos[perm] = arange(len(perm))``, a chunk at a time."""
    out = empty(len(perm) if n is None else n, np.int64)
    for a, b in rows(len(perm)):
        out[perm[a:b]] = np.arange(a, b)
    return out


def nonzero(mask):
    """``np.flatnonzero(mask)`` into a (possibly mapped) array, a chunk at a time."""
    count = sum(int(np.count_nonzero(mask[a:b])) for a, b in rows(len(mask)))
    out = empty(count, np.int64)
    at = 0
    for a, b in rows(len(mask)):
        k = a + np.flatnonzero(mask[a:b])
        out[at:at + len(k)] = k
        at += len(k)
    return out


def records(p, table):
    """A table's records (``p.read(table)``), read a chunk at a time into a (possibly
    mapped) array."""
    first = p.read(table, 0, 0)
    out = empty(int(p.file[table].shape[0]), first.dtype)
    for a, b in p.chunks(table):
        out[a:b] = p.read(table, a, b)
    return out
