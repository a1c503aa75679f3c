"""sapgo: out-of-core bundle block adjustment after the 1974 SAPGO program.

Python entry points (each command of the ``sapgo`` tool calls one of these)::

    from sapgo import generate_block, import_text, order_project, adjust, Options, open_project

    generate_block("p3.h5", preset="sapgo-p-3")
    import_text("block.h5", cameras=["cameras.txt"], photos=["photos.txt"],
                measurements=["image.txt"], control=["control.txt"])
    summary = adjust("p3.h5", Options(max_iterations=6))
    print(summary.full_report())
"""

__version__ = "0.1.0"

from . import kernelcache as _kernelcache  # noqa: E402

_kernelcache.configure(__version__)   # (before any module defines a kernel)

from .errors import (  # noqa: E402
    DataError,
    DatumDefectError,
    ProjectFormatError,
    SapgoError,
    SingularNormalsError,
)
from .project import Project, open_project  # noqa: E402
from .ordering import order_project  # noqa: E402
from .generate import generate_block, PRESETS  # noqa: E402
from .adjust import Options, Summary, adjust  # noqa: E402
from .ingest import import_text  # noqa: E402
from .formats import export_text  # noqa: E402

__all__ = [
    "__version__",
    "DataError",
    "DatumDefectError",
    "Options",
    "PRESETS",
    "Project",
    "ProjectFormatError",
    "SapgoError",
    "SingularNormalsError",
    "Summary",
    "adjust",
    "export_text",
    "generate_block",
    "import_text",
    "open_project",
    "order_project",
]
