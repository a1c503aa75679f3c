"""Exceptions sapgo raises for problems a user can fix.

Every error a user can cause (a wrong file, bad values, a block that cannot be adjusted) is a
:class:`SapgoError` with a one-line message that says what is wrong and where. The command line
prints that line and exits non-zero; it never shows a traceback for these.
"""


class SapgoError(Exception):
    """Base class of every error sapgo reports to a user."""


class ProjectFormatError(SapgoError):
    """The file is not a sapgo project, has another schema version, or is malformed."""


class DataError(SapgoError):
    """The project's data are invalid (NaN, infinite, out-of-range values, bad references)."""


class DatumDefectError(SapgoError):
    """The block lacks the control (points or station priors) to fix its datum."""


class SingularNormalsError(SapgoError):
    """The reduced normal equations are not positive definite at a station."""


class UndeterminedPointError(SingularNormalsError):
    """A pass point's rays are (nearly) parallel at the current values: ``args`` are the
    message and the point's record number (the adjustment sets it aside and goes on)."""

    def __str__(self):
        return str(self.args[0])

    @property
    def record(self):
        return int(self.args[1])


class ClosedProjectError(SapgoError):
    """A project was used after it was closed."""


class ParameterError(SapgoError, ValueError):
    """An option or parameter is out of range."""


class DiskFullError(SapgoError):
    """The disk (or the project's folder's filesystem) is full, or would be: nothing was
    changed and the temporaries are gone."""
