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


class ClosedProjectError(SapgoError):
    """A project was used after it was closed."""


class ParameterError(SapgoError, ValueError):
    """An option or parameter is out of range."""
