"""The band solver's former place: everything is in :mod:`sapgo.solve.band` now.

Kept so that code written against ``sapgo.bandsolve`` (``cholesky_banded``,
``cho_solve_banded``, ``BandSolver``, ``PivotError``, ...) still imports unchanged.
"""

from .solve.band import *  # noqa: F401,F403
