"""BLAS and LAPACK called from numba kernels, without copies or Python in between.

SciPy exports the Fortran BLAS/LAPACK it was built with (OpenBLAS in the wheels) as C function
pointers in ``scipy.linalg.cython_blas`` / ``cython_lapack``. Their addresses are handed to the
kernels **as an argument** (``FNS``, a named tuple of integers) and called through
:func:`_call`: the kernels are compiled for an integer, not for the address, so numba can
still cache them (``cache=True``), and one kernel call runs a whole sequence of BLAS-3 updates
with submatrices given by offset and leading dimension, exactly as Fortran code would. (ctypes
function objects, numba's own way, cost about 2.5 microseconds each at every kernel call, to
convert: 24 microseconds a front for the nine routines, 5 % of the 100 x 100 block's
factorisation.)

Conventions of the wrappers below: matrices are 1-D float64 views starting at the first
element (``a[offset:]``) with a Fortran leading dimension; characters are passed as their
``ord``. Routines with an ``info`` return it.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import get_cython_function_address, intrinsic

_LAPACK = ("dpotrf", "dtrtri", "dlauum")
_NAMES = ("dgemm", "dsyrk", "dtrsm", "dtrmm", "dgemv", "dtrsv", "dpotrf", "dtrtri", "dlauum")


def _address(name):
    module = "scipy.linalg.cython_lapack" if name in _LAPACK else "scipy.linalg.cython_blas"
    return int(get_cython_function_address(module, name))


Routines = namedtuple("Routines", _NAMES)

#: The routines' addresses, in the order the kernels unpack them.
FNS = Routines(*(_address(name) for name in _NAMES))


@intrinsic
def _call(typingctx, fn, args):
    """Call the Fortran routine at address ``fn`` (an integer) with the data pointers of the
    arrays in the tuple ``args`` (its arguments, all passed by reference)."""
    if not isinstance(fn, types.Integer) or not isinstance(args, types.BaseTuple) or \
            not all(isinstance(a, types.Array) for a in args):
        return None
    n = len(args)

    def codegen(context, builder, signature, llargs):
        addr, tup = llargs
        i8p = ir.IntType(8).as_pointer()
        f = builder.inttoptr(addr, ir.FunctionType(ir.VoidType(), [i8p] * n).as_pointer())
        ptrs = []
        for j, ty in enumerate(args):
            ary = context.make_array(ty)(context, builder, builder.extract_value(tup, j))
            ptrs.append(builder.bitcast(ary.data, i8p))
        builder.call(f, ptrs)
        return context.get_dummy_value()

    return types.void(fn, args), codegen


N, T, L, U, R = ord("N"), ord("T"), ord("L"), ord("U"), ord("R")


_CONTROLLER = []


class _Limits:
    """:func:`blas_limits`' context manager: each BLAS library's thread count set on entry
    where it differs, and put back on exit."""

    __slots__ = ("libs", "threads", "saved")

    def __init__(self, libs, threads):
        self.libs, self.threads, self.saved = libs, threads, []

    def __enter__(self):
        for lib in self.libs:
            n = lib.get_num_threads()
            if n != self.threads:
                lib.set_num_threads(self.threads)
                self.saved.append((lib, n))
        return self

    def __exit__(self, *exc):
        for lib, n in reversed(self.saved):
            lib.set_num_threads(n)
        self.saved = []
        return False


def blas_limits(threads=1):
    """Context manager limiting the BLAS libraries' own threads (the kernels bring theirs).

    The libraries are looked up once per process (that look-up costs about a millisecond);
    entering and leaving then calls each library's get and set functions alone
    (threadpoolctl's ``limit`` took 38 microseconds a use, 11 ms of a run of 10 000 photos).
    """
    if not _CONTROLLER:
        from threadpoolctl import ThreadpoolController

        _CONTROLLER.append(ThreadpoolController().select(user_api="blas").lib_controllers)
    return _Limits(_CONTROLLER[0], max(1, int(threads)))


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
    _call(fn, (ch[0:], ch[1:], iv[0:], iv[1:], iv[2:], dv[0:],
               a, iv[3:], b, iv[4:], dv[1:], c, iv[5:]))


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
    _call(fn, (ch[0:], ch[1:], iv[0:], iv[1:], dv[0:], a,
               iv[2:], dv[1:], c, iv[3:]))


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
    _call(fn, (ch[0:], ch[1:], ch[2:], ch[3:], iv[0:], iv[1:],
               dv[0:], a, iv[2:], b, iv[3:]))


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
    _call(fn, (ch[0:], iv[0:], iv[1:], dv[0:], a, iv[2:],
               x, iv[3:], dv[1:], y, iv[3:]))


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
    _call(fn, (ch[0:], ch[1:], ch[2:], iv[0:], a, iv[1:],
               x, iv[2:]))


@njit(cache=True, nogil=True)
def potrf(fn, uplo, n, a, lda):
    """Cholesky factor in place; returns LAPACK's ``info``."""
    iv = np.empty(3, np.int32)
    iv[0] = n
    iv[1] = lda
    iv[2] = 0
    ch = np.empty(1, np.uint8)
    ch[0] = uplo
    _call(fn, (ch[0:], iv[0:], a, iv[1:], iv[2:]))
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
    _call(fn, (ch[0:], ch[1:], iv[0:], a, iv[1:], iv[2:]))
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
    _call(fn, (ch[0:], iv[0:], a, iv[1:], iv[2:]))
    return iv[2]
