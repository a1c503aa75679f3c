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

import os as _os

#: How long OpenBLAS's threads spin for more work after a call before they sleep: 2^20
#: cycles (about 0.4 ms) instead of OpenBLAS's 2^28 (about 0.1 s). Between the tree's BLAS
#: calls and the numba kernels running on both threads after them, spinning threads took a
#: core from the kernels: the point update ran at half speed (100 x 100 block: update 0.034
#: -0.047 s an iteration against 0.016-0.019, time to solution 2.06-2.19 s against
#: 1.90-1.95 s, 3 interleaved rounds; strips and the 200 x 200 block unchanged). OpenBLAS
#: reads it when it is loaded: effective when sapgo is imported before numpy and SciPy (the
#: ``sapgo`` command always is); a value the environment sets already is kept.
#: Whether sapgo set it (benchmarks give other tools OpenBLAS's own default, 28, then).
BLAS_TIMEOUT_SET = "OPENBLAS_THREAD_TIMEOUT" not in _os.environ
_os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "20")

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
