"""Synthetic blocks with known truth: the SAPGO-P presets and parameterised blocks."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from ..errors import ParameterError
from ..project import append_history, write_project
from .sapgo_p import BlockSpec, make_block

#: SAPGO-P data sets 1-4 (seeds/002, Table 2).
PRESETS = {
    "sapgo-p-1": dict(strips=4, photos_per_strip=25, pattern=9, control_points=16),
    "sapgo-p-2": dict(strips=4, photos_per_strip=25, pattern=25, control_points=32),
    "sapgo-p-3": dict(strips=5, photos_per_strip=100, pattern=9, control_points=48),
    "sapgo-p-4": dict(strips=12, photos_per_strip=42, pattern=9, control_points=44),
}


def block_spec(preset=None, **overrides):
    """The :class:`BlockSpec` of a preset with ``overrides`` applied (None values ignored)."""
    params = {}
    if preset is not None:
        if preset not in PRESETS:
            raise ParameterError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
        params.update(PRESETS[preset])
    params.update({k: v for k, v in overrides.items() if v is not None})
    names = {f.name for f in dataclasses.fields(BlockSpec)}
    unknown = set(params) - names
    if unknown:
        raise ParameterError(f"unknown block parameter(s): {', '.join(sorted(unknown))}")
    return BlockSpec(**params).check()


def generate_block(path, preset=None, **overrides):
    """Generate a block into a new project file at ``path``; returns a summary dict."""
    spec = block_spec(preset, **overrides)
    rec = make_block(spec)
    creator = {"command": "generate", "preset": preset, "spec": dataclasses.asdict(spec)}
    write_project(
        Path(path), rec["cameras"], rec["stations"], rec["points"], rec["observations"],
        truth=rec["truth"],
        attrs={"creator": json.dumps(creator), "history": append_history("[]", creator)},
    )
    kinds = rec["points"]["kind"]
    return {
        "path": str(path),
        "preset": preset,
        "photos": len(rec["stations"]),
        "strips": spec.strips,
        "points": len(rec["points"]),
        "control_points": int((kinds == 1).sum()),
        "check_points": int((kinds == 4).sum()),
        "observations": len(rec["observations"]),
    }
