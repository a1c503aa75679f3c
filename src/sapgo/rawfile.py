"""Direct-access binary record files: SAPGO's DEFINE FILE units, with explicit reads and writes.

A :class:`RawArray` is a file of fixed-size records (a numpy dtype and a row shape) addressed by
record number. Rows are read and written with ``os.pread`` / ``os.pwrite``, never memory-mapped:
the pages live in the operating system's cache, not in the process, so the process's resident
memory stays bounded by what it asks for (a memory map would count every touched page). Data
written by a process survive its being killed (the kernel owns the page cache), which is what
the checkpoints of :mod:`sapgo.adjust` rely on.

Slicing follows numpy for contiguous row ranges: ``a[i:j]`` reads rows, ``a[i:j] = x`` writes
them, so a RawArray can stand in for an HDF5 dataset in the streaming passes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def _row_range(key, n):
    """``(start, stop)`` of the rows ``key`` (an integer or a contiguous slice) of ``n``."""
    if isinstance(key, slice):
        start, stop, step = key.indices(n)
        if step != 1:
            raise IndexError("RawArray supports contiguous row ranges only")
        return start, max(start, stop)
    if isinstance(key, (int, np.integer)):
        i = int(key) + (n if key < 0 else 0)
        if not 0 <= i < n:
            raise IndexError(f"row {key} out of range for {n} rows")
        return i, i + 1
    raise IndexError("RawArray supports integer rows and contiguous row ranges only")


class RawArray:
    """A file of ``shape[0]`` records of ``dtype`` with row shape ``shape[1:]``."""

    def __init__(self, path, shape, dtype="<f8", mode="r+"):
        self.path = Path(path)
        self._layout(shape, dtype)
        size = self.shape[0] * self.row_bytes
        if mode == "w":
            flags = os.O_RDWR | os.O_CREAT | os.O_TRUNC
        elif mode == "r+":
            flags = os.O_RDWR
        elif mode == "r":
            flags = os.O_RDONLY
        else:
            raise ValueError("mode must be 'r', 'r+' or 'w'")
        self._fd = os.open(self.path, flags, 0o644)
        if mode == "w":
            os.ftruncate(self._fd, size)  # a sparse file: unwritten rows read as zeros
        elif os.fstat(self._fd).st_size != size:
            actual = os.fstat(self._fd).st_size
            os.close(self._fd)
            self._fd = None
            raise ValueError(f"{self.path}: {actual} bytes, expected {size} for shape "
                             f"{self.shape} of {self.dtype}")

    def _layout(self, shape, dtype):
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)
        self.row_shape = self.shape[1:]
        self.row_bytes = int(np.prod(self.row_shape, dtype=np.int64)) * self.dtype.itemsize

    def _rows_to_write(self, start, data):
        """``data`` as rows of this array's type, checked to fit from row ``start``."""
        data = np.ascontiguousarray(data, dtype=self.dtype)
        n = data.shape[0] if data.ndim else 1
        if start < 0 or start + n > self.shape[0]:
            raise IndexError(f"rows {start}:{start + n} out of range for {self.shape[0]} rows")
        return data, n

    @classmethod
    def create(cls, path, shape, dtype="<f8"):
        return cls(path, shape, dtype, "w")

    def __len__(self):
        return self.shape[0]

    @property
    def ndim(self):
        return len(self.shape)

    def _range(self, key):
        return _row_range(key, self.shape[0])

    def read(self, start, stop, out=None):
        """Rows ``start:stop`` into ``out`` (a new array when None)."""
        n = stop - start
        if out is None:
            out = np.empty((n,) + self.row_shape, self.dtype)
        buf = memoryview(out.reshape(-1).view(np.uint8))
        want = n * self.row_bytes
        off = start * self.row_bytes
        got = 0
        while got < want:
            k = os.preadv(self._fd, [buf[got:]], off + got)
            if k <= 0:
                raise OSError(f"{self.path}: short read at byte {off + got}")
            got += k
        return out

    def write(self, start, data):
        data, _ = self._rows_to_write(start, data)
        buf = memoryview(data.reshape(-1).view(np.uint8))
        off = start * self.row_bytes
        done = 0
        while done < len(buf):
            done += os.pwrite(self._fd, buf[done:], off + done)

    def __getitem__(self, key):
        a, b = self._range(key)
        out = self.read(a, b)
        return out[0] if isinstance(key, (int, np.integer)) else out

    def __setitem__(self, key, value):
        a, b = self._range(key)
        value = np.asarray(value, dtype=self.dtype)
        self.write(a, np.broadcast_to(value, (b - a,) + self.row_shape))

    def fill(self, value=0.0, chunk_bytes=8 << 20):
        step = max(1, chunk_bytes // max(1, self.row_bytes))
        block = np.full((min(step, self.shape[0]),) + self.row_shape, value, self.dtype)
        for a in range(0, self.shape[0], step):
            b = min(self.shape[0], a + step)
            self.write(a, block[: b - a])

    def flush(self):
        os.fsync(self._fd)

    def close(self):
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        if getattr(self, "_fd", None) is not None:
            os.close(self._fd)
            self._fd = None


class CoreArray(RawArray):
    """A :class:`RawArray` held in memory (a run without work files,
    :class:`sapgo.work.Work`): the same reads and writes, copies in and out as the file's
    are, so that a pass cannot tell them apart; nothing survives the process."""

    def __init__(self, shape, dtype="<f8"):   # (no file: the base's fields, an array)
        self.path = None
        self._layout(shape, dtype)
        self._fd = None
        self.data = np.zeros(self.shape, self.dtype)

    def read(self, start, stop, out=None):
        if out is None:
            return self.data[start:stop].copy()
        out[...] = self.data[start:stop]
        return out

    def write(self, start, data):
        data, n = self._rows_to_write(start, data)
        self.data[start:start + n] = data.reshape((n,) + self.row_shape)

    def flush(self):
        pass
