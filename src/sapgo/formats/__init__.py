"""Exchange formats of a block's input records (the plain-text files of ``sapgo import``).

:mod:`sapgo.formats.text` defines the four whitespace-separated text formats (cameras, photos,
image measurements, control), parses them chunk by chunk and writes a project's input records
in them (:func:`export_text`); :func:`export_adjusted` writes an adjusted block in the user's
coordinate system. The formats are documented field by field in
``docs/formats.md``.
"""

from .text import ANGLE_UNITS, export_adjusted, export_text

__all__ = ["ANGLE_UNITS", "export_adjusted", "export_text"]
