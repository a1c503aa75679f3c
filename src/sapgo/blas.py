"""BLAS and LAPACK called from numba kernels, without copies or Python in between.

SciPy exports the Fortran BLAS/LAPACK it was built with (OpenBLAS in the wheels) as C function
pointers in ``scipy.linalg.cython_blas`` / ``cython_lapack``. Each routine is wrapped in a ctypes
function type and handed to the kernels **as an argument** (``FNS``): the kernels are compiled
for the pointer's type, not its address, so numba can still cache them (``cache=True``), and
one kernel call runs a whole sequence of BLAS-3 updates with submatrices given by offset and
leading dimension, exactly as Fortran code would.

Conventions of the wrappers below: matrices are 1-D float64 views starting at the first
element (``a[offset:]``) with a Fortran leading dimension; characters are passed as their
``ord``. Routines with an ``info`` return it.
"""

from __future__ import annotations

import ctypes
from collections import namedtuple

import numpy as np
from numba import njit
from numba.extending import get_cython_function_address

_VP = ctypes.c_void_p
_NARGS = {"dgemm": 13, "dsyrk": 10, "dtrsm": 11, "dtrmm": 11, "dgemv": 11, "dtrsv": 8,
          "dpotrf": 5, "dtrtri": 6, "dlauum": 5}


def _pointer(name):
    module = "scipy.linalg.cython_lapack" if name in ("dpotrf", "dtrtri", "dlauum") else \
        "scipy.linalg.cython_blas"
    proto = ctypes.CFUNCTYPE(None, *([_VP] * _NARGS[name]))
    return proto(get_cython_function_address(module, name))


Routines = namedtuple("Routines", list(_NARGS))

#: The routines, in the order the kernels unpack them.
FNS = Routines(*(_pointer(name) for name in _NARGS))

N, T, L, U, R = ord("N"), ord("T"), ord("L"), ord("U"), ord("R")


_CONTROLLER = []


def blas_limits(threads=1):
    """Context manager limiting the BLAS libraries' own threads (the kernels bring theirs).

    The libraries are looked up once per process (that look-up costs about a millisecond).
    """
    if not _CONTROLLER:
        from threadpoolctl import ThreadpoolController

        _CONTROLLER.append(ThreadpoolController())
    return _CONTROLLER[0].limit(limits=threads, user_api="blas")


@njit(cache=True, nogil=True)
def gemm(fn, ta, tb, m, n, k, alpha, a, lda, b, ldb, beta, c, ldc):
    """``c <- alpha op(a) op(b) + beta c`` (``c`` m x n)."""
    iv = np.empty(6, np.int32)
    iv[0] = m
    iv[1] = n
    iv[2] = k
    iv[3] = lda
    iv[4] = ldb
    iv[5] = ldc
    dv = np.empty(2)
    dv[0] = alpha
    dv[1] = beta
    ch = np.empty(2, np.uint8)
    ch[0] = ta
    ch[1] = tb
    fn(ch[0:].ctypes, ch[1:].ctypes, iv[0:].ctypes, iv[1:].ctypes, iv[2:].ctypes, dv[0:].ctypes,
       a.ctypes, iv[3:].ctypes, b.ctypes, iv[4:].ctypes, dv[1:].ctypes, c.ctypes, iv[5:].ctypes)


@njit(cache=True, nogil=True)
def syrk(fn, uplo, trans, n, k, alpha, a, lda, beta, c, ldc):
    """``c <- alpha a a' + beta c`` on the ``uplo`` triangle of ``c`` (n x n)."""
    iv = np.empty(4, np.int32)
    iv[0] = n
    iv[1] = k
    iv[2] = lda
    iv[3] = ldc
    dv = np.empty(2)
    dv[0] = alpha
    dv[1] = beta
    ch = np.empty(2, np.uint8)
    ch[0] = uplo
    ch[1] = trans
    fn(ch[0:].ctypes, ch[1:].ctypes, iv[0:].ctypes, iv[1:].ctypes, dv[0:].ctypes, a.ctypes,
       iv[2:].ctypes, dv[1:].ctypes, c.ctypes, iv[3:].ctypes)


@njit(cache=True, nogil=True)
def _triangular3(fn, side, uplo, ta, diag, m, n, alpha, a, lda, b, ldb):
    """The common call of dtrsm and dtrmm (same arguments)."""
    iv = np.empty(4, np.int32)
    iv[0] = m
    iv[1] = n
    iv[2] = lda
    iv[3] = ldb
    dv = np.empty(1)
    dv[0] = alpha
    ch = np.empty(4, np.uint8)
    ch[0] = side
    ch[1] = uplo
    ch[2] = ta
    ch[3] = diag
    fn(ch[0:].ctypes, ch[1:].ctypes, ch[2:].ctypes, ch[3:].ctypes, iv[0:].ctypes, iv[1:].ctypes,
       dv[0:].ctypes, a.ctypes, iv[2:].ctypes, b.ctypes, iv[3:].ctypes)


@njit(cache=True, nogil=True)
def trsm(fn, side, uplo, ta, diag, m, n, alpha, a, lda, b, ldb):
    """``b <- alpha op(a)^-1 b`` (side L) or ``alpha b op(a)^-1`` (side R); ``b`` m x n."""
    _triangular3(fn, side, uplo, ta, diag, m, n, alpha, a, lda, b, ldb)


@njit(cache=True, nogil=True)
def trmm(fn, side, uplo, ta, diag, m, n, alpha, a, lda, b, ldb):
    """``b <- alpha op(a) b`` (side L) or ``alpha b op(a)`` (side R); ``b`` m x n."""
    _triangular3(fn, side, uplo, ta, diag, m, n, alpha, a, lda, b, ldb)


@njit(cache=True, nogil=True)
def gemv(fn, ta, m, n, alpha, a, lda, x, beta, y):
    """``y <- alpha op(a) x + beta y`` (``a`` m x n, unit strides)."""
    iv = np.empty(4, np.int32)
    iv[0] = m
    iv[1] = n
    iv[2] = lda
    iv[3] = 1
    dv = np.empty(2)
    dv[0] = alpha
    dv[1] = beta
    ch = np.empty(1, np.uint8)
    ch[0] = ta
    fn(ch[0:].ctypes, iv[0:].ctypes, iv[1:].ctypes, dv[0:].ctypes, a.ctypes, iv[2:].ctypes,
       x.ctypes, iv[3:].ctypes, dv[1:].ctypes, y.ctypes, iv[3:].ctypes)


@njit(cache=True, nogil=True)
def trsv(fn, uplo, ta, diag, n, a, lda, x):
    """``x <- op(a)^-1 x`` (``a`` triangular n x n, unit stride)."""
    iv = np.empty(3, np.int32)
    iv[0] = n
    iv[1] = lda
    iv[2] = 1
    ch = np.empty(3, np.uint8)
    ch[0] = uplo
    ch[1] = ta
    ch[2] = diag
    fn(ch[0:].ctypes, ch[1:].ctypes, ch[2:].ctypes, iv[0:].ctypes, a.ctypes, iv[1:].ctypes,
       x.ctypes, iv[2:].ctypes)


@njit(cache=True, nogil=True)
def potrf(fn, uplo, n, a, lda):
    """Cholesky factor in place; returns LAPACK's ``info``."""
    iv = np.empty(3, np.int32)
    iv[0] = n
    iv[1] = lda
    iv[2] = 0
    ch = np.empty(1, np.uint8)
    ch[0] = uplo
    fn(ch[0:].ctypes, iv[0:].ctypes, a.ctypes, iv[1:].ctypes, iv[2:].ctypes)
    return iv[2]


@njit(cache=True, nogil=True)
def trtri(fn, uplo, diag, n, a, lda):
    """Inverse of a triangular matrix in place; returns LAPACK's ``info``."""
    iv = np.empty(3, np.int32)
    iv[0] = n
    iv[1] = lda
    iv[2] = 0
    ch = np.empty(2, np.uint8)
    ch[0] = uplo
    ch[1] = diag
    fn(ch[0:].ctypes, ch[1:].ctypes, iv[0:].ctypes, a.ctypes, iv[1:].ctypes, iv[2:].ctypes)
    return iv[2]


@njit(cache=True, nogil=True)
def lauum(fn, uplo, n, a, lda):
    """``L'L`` (``uplo`` L) or ``UU'`` of a triangular matrix, in place on its triangle;
    returns LAPACK's ``info``."""
    iv = np.empty(3, np.int32)
    iv[0] = n
    iv[1] = lda
    iv[2] = 0
    ch = np.empty(1, np.uint8)
    ch[0] = uplo
    fn(ch[0:].ctypes, iv[0:].ctypes, a.ctypes, iv[1:].ctypes, iv[2:].ctypes)
    return iv[2]
