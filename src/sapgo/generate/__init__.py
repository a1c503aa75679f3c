"""Synthetic blocks with known truth: the SAPGO-P presets and parameterised blocks."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

from .. import paging
from ..errors import ParameterError
from ..lock import writes_project
import numpy as np

from ..project import TRUTH_BLUNDER_DTYPE, ProjectWriter, append_history
from .apollo import SCENES as _APOLLO
from .mfl import SCENES as _MFL
from .sapgo_p import BlockSpec, write_block
from .scene import write_scene

#: SAPGO-P data sets 1-4 (seeds/002, Table 2).
PRESETS = {
    "sapgo-p-1": dict(strips=4, photos_per_strip=25, pattern=9, control_points=16),
    "sapgo-p-2": dict(strips=4, photos_per_strip=25, pattern=25, control_points=32),
    "sapgo-p-3": dict(strips=5, photos_per_strip=100, pattern=9, control_points=48),
    "sapgo-p-4": dict(strips=12, photos_per_strip=42, pattern=9, control_points=44),
}


#: Generated scenes: SAPGO-MFL (Table 5) and SAPGO-L Apollo 15 (Table 6).
SCENES = {**_MFL, **_APOLLO}

#: Every preset name (the SAPGO-P blocks and the generated scenes of SAPGO-MFL/-L).
ALL_PRESETS = sorted(PRESETS) + sorted(SCENES)


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


@writes_project("generate", "path")
def generate_block(path, preset=None, progress=None, force=False, **overrides):
    """Generate a block into a new project file at ``path``; returns a summary dict.

    The records are streamed into the file a column block at a time (memory does not grow
    with the block beyond per-photo vectors); the file appears at ``path`` only when complete.
    ``progress``: True, False or None (a progress bar when stderr is a terminal). An
    existing ``path`` is refused unless ``force``.
    """
    from tqdm import tqdm

    from ..project import new_project_path

    new_project_path(path, force)
    if preset in SCENES:
        return _generate_scene(path, preset, **overrides)
    if any(overrides.get(k) is not None for k in FLIGHT_DESIGN):
        return _generate_flight(path, preset, **overrides)
    spec = block_spec(preset, **overrides)
    creator = {"command": "generate", "preset": preset, "spec": dataclasses.asdict(spec)}
    enabled = sys.stderr.isatty() if progress is None else progress
    with ProjectWriter(Path(path), {"creator": json.dumps(creator),
                                    "history": append_history("[]", creator)},
                       truth=True, sizes={"cameras": 1, "stations": spec.n_photos,
                                          "truth/stations": spec.n_photos}) as w, \
            tqdm(total=spec.n_cols, desc="generate", unit="col", leave=False,
                 disable=not enabled, dynamic_ncols=True) as bar, \
            paging.paged(Path(path).resolve().parent, spec.n_photos > paging.PAGE_STATIONS):
        counts = write_block(spec, w, progress=bar.update)
        counts["blunders"] = plant_blunders(w, spec.blunders, spec.blunder_size, spec.seed)
        w.finish()
    return {
        "path": str(path),
        "preset": preset,
        "photos": counts["photos"],
        "strips": spec.strips,
        "points": counts["points"],
        "control_points": counts["control"],
        "check_points": counts["points"] - counts["control"],
        "observations": counts["observations"],
        "blunders": counts["blunders"],
    }


#: The parameters of an irregular flight design (any of them makes a flight-design block).
FLIGHT_DESIGN = ("shift", "lengths", "starts", "scales")


def _generate_flight(path, preset, strips=None, photos_per_strip=None, forelap=None,
                     sidelap=None, control_points=None, sigma_image=None, terrain_relief=None,
                     seed=None, shift=None, lengths=None, starts=None, scales=None,
                     **overrides):
    """A block of an irregular flight design (:func:`sapgo.generate.flight.flight_scene`):
    shifted strips, strips of their own lengths, starts and scales."""
    from .flight import flight_scene

    unused = {k for k, v in overrides.items() if v is not None}
    if preset is not None or unused:
        given = sorted(unused | ({"preset"} if preset is not None else set()))
        raise ParameterError(f"an irregular flight design (shift, strip lengths, starts, "
                             f"scales) takes strips, photos per strip, forelap, sidelap, "
                             f"control points, sigma image, terrain relief and seed, not "
                             f"{', '.join(given)}")
    d = BlockSpec()
    lists = [v for v in (lengths, starts, scales) if v is not None]
    if strips is None:  # (the strips of the per-strip lists, else the default)
        strips = len(lists[0]) if lists else d.strips
    if photos_per_strip is None:
        photos_per_strip = max(lengths) if lengths else d.photos_per_strip
    design = dict(strips=strips, photos_per_strip=photos_per_strip,
                  forelap=d.forelap if forelap is None else forelap,
                  sidelap=d.sidelap if sidelap is None else sidelap, shift=shift or 0.0,
                  lengths=lengths, starts=starts, scales=scales)
    scene = flight_scene(**design, control_points=control_points,
                         sigma_image=d.sigma_image if sigma_image is None else sigma_image,
                         relief=30.0 if terrain_relief is None else terrain_relief,
                         seed=1 if seed is None else seed)
    return _write_scene_file(path, scene, None, {"command": "generate",
                                                 "flight_design": design, "seed": scene.seed})


def _generate_scene(path, preset, seed=None, **overrides):
    """A scene preset (SAPGO-MFL/-L); only ``seed`` may be overridden."""
    unused = {k for k, v in overrides.items() if v is not None}
    if unused:
        raise ParameterError(f"preset {preset} takes no block parameters but --seed "
                             f"(given: {', '.join(sorted(unused))})")
    seed = 1 if seed is None else seed
    scene = SCENES[preset](seed)
    return _write_scene_file(path, scene, preset,
                             {"command": "generate", "preset": preset, "seed": seed})


def _write_scene_file(path, scene, preset, creator):
    """Write a scene into a new project at ``path`` (``creator`` recorded); the summary."""
    with ProjectWriter(Path(path), {"creator": json.dumps(creator),
                                    "history": append_history("[]", creator)},
                       truth=True) as w:
        counts = write_scene(scene, w)
        w.finish()
    return {"path": str(path), "preset": preset, "photos": counts["photos"],
            "strips": counts["strips"], "points": counts["points"],
            "control_points": counts["control"],
            "check_points": 0, "observations": counts["observations"],
            "cameras": counts["cameras"]}


def plant_blunders(writer, n, size, seed):
    """Move ``n`` observations (chosen at random, one per point at most) by ``size[0]`` to
    ``size[1]`` mm in a random direction, in the file being written; the planted blunders go
    to ``/truth/blunders`` (photo and point ids, dx, dy). Returns ``n``."""
    if n <= 0:
        return 0
    f = writer.file
    obs, pts, st = f["observations"], f["points"], f["stations"]
    n_obs = obs.shape[0]
    if n > n_obs // 10:
        raise ParameterError(f"{n} blunders in {n_obs} observations: at most one in ten")
    rng = np.random.default_rng([seed, 91])
    picked, used = [], set()
    while len(picked) < n:
        i = int(rng.integers(n_obs))
        point = int(obs[i]["point"])
        if point not in used:
            used.add(point)
            picked.append(i)
    picked.sort()
    rec = np.zeros(n, TRUTH_BLUNDER_DTYPE)
    for k, i in enumerate(picked):
        o = obs[i]
        size_mm = rng.uniform(size[0], size[1])
        angle = rng.uniform(0.0, 2.0 * np.pi)
        dx, dy = size_mm * np.cos(angle), size_mm * np.sin(angle)
        o["x"] += dx
        o["y"] += dy
        obs[i] = o
        rec[k] = (int(st[int(o["station"])]["id"]), int(pts[int(o["point"])]["id"]), dx, dy)
    writer.append("truth/blunders", rec)
    return n
