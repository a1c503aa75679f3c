"""The additional-parameter sets of aerial triangulation: Ebner's 12 and Gruen's 44.

A set models the systematic image errors that remain after the camera's Brown terms as a
displacement field ``(dx, dy)`` over the image, a sum of the set's terms times their
coefficients ``a1 .. aN`` (mm). Both sets are built the same way (Ebner 1976 on the 3 x 3
grid of the von Gruber points, Gruen 1978 on a 5 x 5 grid): the displacements that a grid
of ``n x n`` image points can show are the fields ``(P_i(xi) P_j(eta), 0)`` and
``(0, P_i(xi) P_j(eta))``, ``i, j < n``, with ``P_i`` the polynomials orthogonal on the
grid's ``n`` equally spaced abscissae in [-1, 1] (``xi = x / b``, ``eta = y / b``, ``b``
the camera's ``ap_base``, mm); six of those ``2 n^2`` directions are what a photo's
orientation does to a vertical photo (the shifts ``(1, 0)``, ``(0, 1)``, the scale
``(x, y)``, the rotation ``(-y, x)`` and the tilts ``(x^2, xy)``, ``(xy, y^2)``) and are
left out; the set is the ``2 n^2 - 6`` fields orthogonal to them and to each other on the
grid (docs/theory.md section 1d). On the 3 x 3 grid that construction is Ebner's set term
for term (``tests/test_apsets.py`` holds his formulas), with ``a_i = b_i b^d`` (``d`` the
degree of Ebner's term ``i``: his ``b_i`` are per mm^(d-1)). On the 5 x 5 grid it spans the
same 44 directions as Gruen's set (the orthogonal complement of the orientation's six is
one space), so the adjusted photos, points, residuals and sigma0 are Gruen's; its 44
coefficients are those of this basis (its polynomials scaled to ``P_i(1) = 1``, so that a
coefficient is about its term's largest displacement on the grid, mm), not comparable one
by one with Gruen's tables.

A camera row (:data:`sapgo.geometry.CAMERA_FIELDS`) holds its set (``ap_set``: 0 none,
:data:`EBNER`, :data:`GRUEN`), the base ``ap_base`` and the coefficients ``a1 .. a44``
(a set of 12 uses the first 12).
"""

import numpy as np
from numba import njit

NONE, EBNER, GRUEN = 0, 1, 2
#: The sets by name (the additional-parameters file, ``--calibrate ap``), their grid sizes
#: and number of terms.
AP_SETS = ("none", "ebner", "gruen")
GRID = (0, 3, 5)
N_TERMS = np.array([0, 12, 44], np.int64)
MAX_TERMS = 44
#: The default base of a camera without one: 0.4 times the larger side of its format (the
#: photo base at 60 % overlap, Ebner's b).
DEFAULT_BASE_FRACTION = 0.4


def grid_polynomials(n, edge_one=False):
    """The polynomials orthogonal on ``n`` equally spaced abscissae in [-1, 1] by
    Gram-Schmidt on the monomials, monic, or with ``edge_one`` scaled to ``P_i(1) = 1``: row
    ``i`` holds ``P_i``'s coefficients, ascending powers (``n x n``)."""
    t = np.linspace(-1.0, 1.0, n)
    v = np.vander(t, n, increasing=True)
    p = np.zeros((n, n))
    for i in range(n):
        c = np.zeros(n)
        c[i] = 1.0
        for j in range(i):
            pj = v @ p[j]
            c -= (v @ c) @ pj / (pj @ pj) * p[j]
        p[i] = c
    p[np.abs(p) < 1e-15] = 0.0
    if edge_one:
        p /= p.sum(axis=1)[:, None]   # (P_i(1): the sum of its coefficients)
    return p


def set_terms(n, edge_one=False):
    """The terms of the set on the ``n x n`` grid: rows ``(cx, ix, jx, cy, iy, jy)``, the
    term being ``(cx P_ix(xi) P_jx(eta), cy P_iy(xi) P_jy(eta))`` (a component with ``c =
    0`` is none). Order: the four that share directions with the orientation (Ebner's b1 to
    b4), then the others in pairs ``(T_ij, 0), (0, T_ji)`` by degree ``i + j`` and then
    ``i`` (Ebner's b5 to b12)."""
    v = np.vander(np.linspace(-1.0, 1.0, n), n, increasing=True)
    p = grid_polynomials(n, edge_one)

    def norm2(i, j):   # |P_i(xi) P_j(eta)|^2 over the grid
        pi, pj = v @ p[i], v @ p[j]
        return float(pi @ pi) * float(pj @ pj)

    # the tilt's (x^2, xy) is (T20 / l2, T11 / l1^2) plus a shift (l_i: P_i's leading
    # coefficient): the term beside it in the same two directions is (alpha T20, T11)
    l1, l2 = p[1, 1], p[2, 2]
    alpha = -l2 * norm2(1, 1) / (l1 * l1 * norm2(2, 0))
    rows = [(1.0, 1, 0, -1.0, 0, 1), (1.0, 0, 1, 1.0, 1, 0),
            (alpha, 2, 0, 1.0, 1, 1), (1.0, 1, 1, alpha, 0, 2)]
    left_x = {(0, 0), (1, 0), (0, 1), (2, 0), (1, 1)}
    for i, j in sorted(((i, j) for i in range(n) for j in range(n)),
                       key=lambda ij: (ij[0] + ij[1], ij[0])):
        if (i, j) not in left_x:
            rows.append((1.0, i, j, 0.0, 0, 0))
            rows.append((0.0, 0, 0, 1.0, j, i))
    out = np.array(rows, np.float64)
    assert len(out) == 2 * n * n - 6
    return out


#: The kernels' tables: ``POLY[s]`` (5 x 5) the grid polynomials of set ``s`` (zero-padded),
#: ``TERMS[s]`` (44 x 6) its terms (:func:`set_terms`).
POLY = np.zeros((3, 5, 5))
TERMS = np.zeros((3, MAX_TERMS, 6))
for _s in (EBNER, GRUEN):
    _n = GRID[_s]
    POLY[_s, :_n, :_n] = grid_polynomials(_n, _s == GRUEN)
    TERMS[_s, :N_TERMS[_s]] = set_terms(_n, _s == GRUEN)


@njit(cache=True, error_model="numpy", nogil=True)
def _poly(coef, x, val, der):
    """``P_i(x)`` and ``P_i'(x)`` of the 5 rows of ``coef`` into ``val`` and ``der``."""
    for i in range(5):
        v = 0.0
        d = 0.0
        for k in range(4, -1, -1):
            d = d * x + v
            v = v * x + coef[i, k]
        val[i] = v
        der[i] = d


@njit(cache=True, error_model="numpy", nogil=True)
def ap_displacement(u, v, s, base, a):
    """The displacement of set ``s`` (base ``base`` mm, coefficients ``a``, mm) at ``(u, v)``
    (mm from the principal point): ``(dx, dy, dxdu, dxdv, dydu, dydv)``."""
    px = np.empty(5)
    dpx = np.empty(5)
    py = np.empty(5)
    dpy = np.empty(5)
    _poly(POLY[s], u / base, px, dpx)
    _poly(POLY[s], v / base, py, dpy)
    terms = TERMS[s]
    dx = dy = j00 = j01 = j10 = j11 = 0.0
    for t in range(N_TERMS[s]):
        c = a[t]
        if c == 0.0:
            continue
        cx = terms[t, 0] * c
        if cx != 0.0:
            i, j = int(terms[t, 1]), int(terms[t, 2])
            dx += cx * px[i] * py[j]
            j00 += cx * dpx[i] * py[j]
            j01 += cx * px[i] * dpy[j]
        cy = terms[t, 3] * c
        if cy != 0.0:
            i, j = int(terms[t, 4]), int(terms[t, 5])
            dy += cy * px[i] * py[j]
            j10 += cy * dpx[i] * py[j]
            j11 += cy * px[i] * dpy[j]
    return dx, dy, j00 / base, j01 / base, j10 / base, j11 / base


@njit(cache=True, error_model="numpy", nogil=True)
def ap_partials(u, v, s, base, sign, e, col):
    """The terms of set ``s`` at ``(u, v)`` times ``sign``: ``e[0, col + t]`` and
    ``e[1, col + t]`` the x and y displacement per unit of coefficient ``t`` of the set's
    (the entries of coefficients beyond the set are left as they are: no camera has them
    to adjust)."""
    n = N_TERMS[s]
    if n == 0:
        return
    px = np.empty(5)
    dpx = np.empty(5)
    py = np.empty(5)
    dpy = np.empty(5)
    terms = TERMS[s]
    _poly(POLY[s], u / base, px, dpx)
    _poly(POLY[s], v / base, py, dpy)
    for t in range(n):
        e[0, col + t] = sign * terms[t, 0] * px[int(terms[t, 1])] * py[int(terms[t, 2])]
        e[1, col + t] = sign * terms[t, 3] * px[int(terms[t, 4])] * py[int(terms[t, 5])]
