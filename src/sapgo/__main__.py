"""``python -m sapgo``: the ``sapgo`` command (:func:`sapgo.cli.main`)."""

import sys

from .cli import main

sys.exit(main())
