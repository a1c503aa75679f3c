"""Plots of an adjusted project (``sapgo adjust --plots DIR``, ``sapgo report --plots DIR``;
the ``plot`` extra, matplotlib).

- ``layout.png``: photo centres and points by kind (control, check, pass; rejected marked);
- ``residuals_camera_<id>.png``: image residual vectors over each camera's format, the mean
  vector per cell of a grid (systematic errors show as a pattern) and, for small blocks, every
  vector;
- ``checkpoints.png``: check-point errors, horizontal as vectors and vertical as colour;
- ``matrix.png``: the pattern of the reduced normal matrix in the stations' logical order:
  non-zero blocks, the fill-in inside the envelope and the band (as Figure 1 of seeds/002
  and Figure 12 of seeds/000).

Everything is read in chunks; large blocks are drawn from a bounded sample of points and
a binned image of the matrix, so memory stays bounded.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .errors import DataError
from .normals import control_rotations
from .project import (
    CHUNK_RECORDS,
    KIND_CHECK,
    KIND_CONTROL,
    KIND_HORIZONTAL,
    KIND_PASS,
    KIND_VERTICAL,
    STATUS_ACTIVE,
    STATUS_REJECTED,
    Project,
)

#: At most this many points are drawn in the layout (a regular sample beyond).
MAX_POINTS_DRAWN = 200_000
#: Beyond this many check points their errors are drawn as means over square cells.
MAX_CHECK_DRAWN = 5_000
#: At most this many single residual vectors are drawn per camera.
MAX_VECTORS_DRAWN = 5_000
#: Cells of the residual grid along the longer side of the format.
GRID_CELLS = 12
#: The matrix pattern is binned into at most this many rows and columns.
MATRIX_BINS = 1000


def check_matplotlib():
    """Raise a clear error when matplotlib is not installed."""
    try:
        import matplotlib
    except ImportError as exc:
        raise DataError("plots need matplotlib: pip install 'sapgo[plot]'") from exc
    return matplotlib


def _pyplot():
    matplotlib = check_matplotlib()
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_plots(project_path, out_dir, chunk=CHUNK_RECORDS):
    """Write the plots of an adjusted project into ``out_dir`` (created); returns the paths."""
    plt = _pyplot()
    out_dir = Path(out_dir)
    with Project(project_path) as p:
        if not p.has_solution or p.file["solution"].attrs.get("state") != "adjusted":
            raise DataError(f"{project_path}: the project has no adjusted solution: run "
                            f"'sapgo adjust' first")
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DataError(f"{out_dir}: cannot create the directory ({exc.strerror})") from exc
        report = json.loads(p.file["solution/report"][()])
        paths = [_layout(plt, p, out_dir, chunk, report)]
        paths += _residuals(plt, p, out_dir, chunk)
        paths.append(_checkpoints(plt, p, out_dir, chunk, report))
        paths.append(_matrix(plt, p, out_dir, chunk))
    return [str(x) for x in paths if x is not None]


def _figure(plt, extent, width=10.0):
    """A figure whose axes follow the block's aspect ratio (``extent``: dx, dy)."""
    dx, dy = max(float(extent[0]), 1e-9), max(float(extent[1]), 1e-9)
    height = min(max(width * dy / dx, 3.0), 14.0)
    return plt.subplots(figsize=(width, height + 1.2))


def _save(plt, fig, path):
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def _layout(plt, p, out_dir, chunk, report):
    st = p.read("stations")
    eo = st["eo"] + p.solution("station_corr")
    act = st["status"] == STATUS_ACTIVE
    step = max(1, p.n_points // MAX_POINTS_DRAWN)
    groups = {"pass": [], "control": [], "check": [], "rejected": []}
    for a, b in p.chunks("points", chunk):
        pts = p.read("points", a, b)
        xyz = pts["xyz"] + p.solution("point_corr", a, b)
        ob_status = p.read_field("observations", "status", int(pts["obs_start"][0]),
                                 int(pts["obs_start"][-1] + pts["n_obs"][-1]))
        owner = np.repeat(np.arange(len(pts)), pts["n_obs"])
        rejected = np.bincount(owner, weights=ob_status == STATUS_REJECTED,
                               minlength=len(pts)) > 0
        kind = pts["kind"]
        live = pts["status"] == STATUS_ACTIVE
        ctrl = np.isin(kind, (KIND_CONTROL, KIND_HORIZONTAL, KIND_VERTICAL))
        groups["control"].append(xyz[live & ctrl & ~rejected, :2])
        groups["check"].append(xyz[live & (kind == KIND_CHECK) & ~rejected, :2][::step])
        groups["rejected"].append(xyz[rejected, :2])
        sel = live & (kind == KIND_PASS) & ~rejected
        groups["pass"].append(xyz[sel, :2][::step])
    fig, ax = _figure(plt, np.ptp(eo[act, 3:5], axis=0) if act.any() else (1, 1))
    style = {"pass": dict(s=2, c="0.6", marker="."),
             "control": dict(s=40, c="tab:red", marker="^"),
             "check": dict(s=20, c="tab:blue", marker="s"),
             "rejected": dict(s=40, c="k", marker="x")}
    for name, parts in groups.items():
        xy = np.concatenate(parts) if parts else np.zeros((0, 2))
        if len(xy):
            label = name + (f" (every {step}th)" if name in ("pass", "check") and step > 1
                            else "")
            label += " (with rejected rays)" if name == "rejected" else ""
            ax.scatter(xy[:, 0], xy[:, 1], label=f"{label}: {len(xy)}", **style[name])
    ax.scatter(eo[act, 3], eo[act, 4], s=8, c="tab:green", marker="o",
               label=f"photo centres: {int(act.sum())}")
    ax.set_aspect("equal")
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m]")
    ax.set_title(f"{Path(p.path).name}: block layout (frame: "
                 f"{(report.get('frame') or {}).get('kind', 'local')})")
    ax.legend(loc="upper right", fontsize=8, markerscale=1.5)
    return _save(plt, fig, out_dir / "layout.png")


def _residuals(plt, p, out_dir, chunk):
    cams = p.cameras()
    st_cam = p.read_field("stations", "camera")
    n_cam = len(cams)
    half = np.stack([cams["format_x"], cams["format_y"]], axis=1) / 2.0
    cells = [(GRID_CELLS, max(1, int(round(GRID_CELLS * h[1] / max(h[0], 1e-9)))))
             for h in half]
    sums = [np.zeros((cx, cy, 3)) for cx, cy in cells]
    sample = [[] for _ in range(n_cam)]
    n_obs = np.zeros(n_cam, np.int64)
    for a, b in p.chunks("observations", chunk):
        ob = p.read("observations", a, b)
        n_obs += np.bincount(st_cam[ob["station"]], minlength=n_cam)
    step = np.maximum(1, n_obs // MAX_VECTORS_DRAWN)
    for a, b in p.chunks("observations", chunk):
        ob = p.read("observations", a, b)
        res = 1000.0 * p.solution("residuals", a, b)
        cam = st_cam[ob["station"]]
        act = ob["status"] == STATUS_ACTIVE
        for c in range(n_cam):
            m = act & (cam == c)
            if not m.any():
                continue
            x, y, v = ob["x"][m], ob["y"][m], res[m]
            cx, cy = cells[c]
            ix = np.clip(((x + half[c, 0]) / (2 * half[c, 0]) * cx).astype(int), 0, cx - 1)
            iy = np.clip(((y + half[c, 1]) / (2 * half[c, 1]) * cy).astype(int), 0, cy - 1)
            np.add.at(sums[c], (ix, iy), np.column_stack([v, np.ones(len(v))]))
            idx = np.flatnonzero(m)
            keep = idx[(a + idx) % step[c] == 0]
            sample[c].append(np.column_stack([ob["x"][keep], ob["y"][keep], res[keep]]))
    paths = []
    for c in range(n_cam):
        if not n_obs[c]:
            continue
        cx, cy = cells[c]
        s = sums[c]
        cnt = np.maximum(s[:, :, 2], 1)
        mean = s[:, :, :2] / cnt[:, :, None]
        gx = (np.arange(cx) + 0.5) / cx * 2 * half[c, 0] - half[c, 0]
        gy = (np.arange(cy) + 0.5) / cy * 2 * half[c, 1] - half[c, 1]
        GX, GY = np.meshgrid(gx, gy, indexing="ij")
        fig, ax = plt.subplots(figsize=(8, 8 * half[c, 1] / max(half[c, 0], 1e-9)))
        pts = np.concatenate(sample[c]) if sample[c] else np.zeros((0, 4))
        rms = float(np.sqrt(np.mean(pts[:, 2:] ** 2))) if len(pts) else 1.0
        scale_um = max(rms, 1e-3)
        # arrows: scale_um of residual drawn as a tenth of the format's half width
        k = 0.1 * half[c, 0] / scale_um
        if len(pts):
            ax.quiver(pts[:, 0], pts[:, 1], pts[:, 2] * k, pts[:, 3] * k, angles="xy",
                      scale_units="xy", scale=1, color="0.7", width=0.002,
                      label=f"residuals ({len(pts)} of {int(n_obs[c])})")
        has = s[:, :, 2] > 0
        ax.quiver(GX[has], GY[has], mean[:, :, 0][has] * k * 5, mean[:, :, 1][has] * k * 5,
                  angles="xy", scale_units="xy", scale=1, color="tab:red", width=0.004,
                  label="mean per cell (x5)")
        ax.plot([-half[c, 0], -half[c, 0] + scale_um * k], [-half[c, 1] * 1.05] * 2, "k-",
                lw=2)
        ax.text(-half[c, 0], -half[c, 1] * 1.1, f"{scale_um:.1f} um", va="top", fontsize=8)
        ax.set_xlim(-half[c, 0] * 1.1, half[c, 0] * 1.1)
        ax.set_ylim(-half[c, 1] * 1.2, half[c, 1] * 1.1)
        ax.set_aspect("equal")
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
        ax.set_title(f"camera {int(cams['id'][c])}: image residuals (RMS {rms:.2f} um)")
        ax.legend(loc="upper right", fontsize=8)
        paths.append(_save(plt, fig, out_dir / f"residuals_camera_{int(cams['id'][c])}.png"))
    return paths


def _checkpoints(plt, p, out_dir, chunk, report):
    frame = p.frame()
    xy, d = [], []
    for a, b in p.chunks("points", chunk):
        pts = p.read("points", a, b)
        m = (pts["kind"] == KIND_CHECK) & (pts["status"] == STATUS_ACTIVE)
        if not m.any():
            continue
        xyz = (pts["xyz"] + p.solution("point_corr", a, b))[m]
        rot = control_rotations(pts["kind"][m], pts["control"][m], frame)
        xy.append(xyz[:, :2])
        d.append(np.einsum("nij,nj->ni", rot, xyz - pts["control"][m]))
    if not xy:
        return None
    xy, d = np.concatenate(xy), np.concatenate(d)
    ext = np.ptp(xy, axis=0)
    fig, ax = _figure(plt, ext)
    h = np.hypot(d[:, 0], d[:, 1])
    ref = float(np.sqrt(np.mean(h ** 2))) or 1.0
    n_all = len(xy)
    what = "points"
    if n_all > MAX_CHECK_DRAWN:  # many check points: mean errors per square cell
        cell = float(np.sqrt(max(ext[0], 1.0) * max(ext[1], 1.0) / MAX_CHECK_DRAWN))
        ij = np.floor((xy - xy.min(axis=0)) / cell).astype(np.int64)
        key, inv = np.unique(ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1],
                             return_inverse=True)
        cnt = np.bincount(inv)
        xy = np.column_stack([np.bincount(inv, xy[:, k]) / cnt for k in range(2)])
        d = np.column_stack([np.bincount(inv, d[:, k]) / cnt for k in range(3)])
        what = f"cells of {cell:.0f} m, means"
    spacing = float(np.sqrt(max(ext[0], 1.0) * max(ext[1], 1.0) / len(xy)))
    k = 0.8 * spacing / ref  # the RMS error drawn as 0.8 of the mean spacing
    lim = float(np.abs(d[:, 2]).max()) or 1.0
    sc = ax.scatter(xy[:, 0], xy[:, 1], c=d[:, 2], cmap="coolwarm", vmin=-lim, vmax=lim,
                    s=25 if what == "points" else 12)
    ax.quiver(xy[:, 0], xy[:, 1], d[:, 0] * k, d[:, 1] * k, angles="xy", scale_units="xy",
              scale=1, width=0.002)
    fig.colorbar(sc, ax=ax, label="dZ (adjusted - known) [m]", orientation="horizontal",
                 fraction=0.05, pad=0.2)
    c = report.get("check_points") or {}
    ax.set_title(f"check points ({n_all}; {what}): dXY as vectors (RMS {ref:.3f} m = 0.8 "
                 f"spacings), dZ as colour"
                 + (f" (sZ {c['sz']:.3f} m)" if c.get("sz") is not None else ""), fontsize=9)
    ax.set_aspect("equal")
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m]")
    return _save(plt, fig, out_dir / "checkpoints.png")


def station_pairs(p, chunk=CHUNK_RECORDS):
    """Yield arrays (k x 2) of the station pairs (logical indices, first <= second) that
    share a point, chunk by chunk: the non-zero 6 x 6 blocks of the reduced normals."""
    for a, b in p.chunks("points", chunk):
        pts = p.read("points", a, b)
        live = pts["status"] == STATUS_ACTIVE
        o0 = int(pts["obs_start"][0])
        ob = p.read("observations", o0, int(pts["obs_start"][-1] + pts["n_obs"][-1]))
        owner = np.repeat(np.arange(len(pts)), pts["n_obs"])
        keep = live[owner] & (ob["status"] == STATUS_ACTIVE)
        s, own = ob["station"][keep], owner[keep]
        out = [np.column_stack([s, s])]
        for d in range(1, int(pts["n_obs"].max()) if len(pts) else 1):
            same = own[:-d] == own[d:]
            s1, s2 = s[:-d][same], s[d:][same]
            out.append(np.column_stack([np.minimum(s1, s2), np.maximum(s1, s2)]))
        yield np.concatenate(out)


def matrix_pattern(p, bins=None, chunk=CHUNK_RECORDS):
    """The pattern of the reduced normal matrix in ``bins`` x ``bins`` cells of stations
    (default one per station): 2 where a 6 x 6 block is non-zero, 1 inside the envelope (the
    fill-in: zero in the matrix, filled in by the Cholesky factorisation), 0 outside. Also
    returns the band width in stations."""
    n = p.n_stations
    bins = min(n, bins or n)
    img = np.zeros((bins, bins), np.int8)
    first = np.arange(bins)  # per column: the first row of the envelope (upper triangle)
    bw = 0
    for pairs in station_pairs(p, chunk):
        if len(pairs):
            bw = max(bw, int((pairs[:, 1] - pairs[:, 0]).max()) + 1)
            i, j = pairs[:, 0] * bins // n, pairs[:, 1] * bins // n
            img[i, j] = 2
            img[j, i] = 2
            np.minimum.at(first, j, i)
    r = np.arange(bins)[:, None]
    env = (r >= first[None, :]) & (r <= np.arange(bins)[None, :])
    env = env | env.T
    img[(img == 0) & env] = 1
    return img, bw


def _matrix(plt, p, out_dir, chunk):
    from matplotlib.colors import ListedColormap

    n = p.n_stations
    img, bw = matrix_pattern(p, MATRIX_BINS, chunk)
    bins = len(img)
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.imshow(img, cmap=ListedColormap(["white", "#f4b183", "black"]), vmin=0, vmax=2,
              interpolation="nearest", extent=(0, n, n, 0))
    ax.plot([0, n], [bw, n + bw], "r--", lw=0.8, label=f"band: {bw} stations")
    ax.plot([bw, n + bw], [0, n], "r--", lw=0.8)
    ax.plot([], [], "s", color="black", label="non-zero 6x6 blocks")
    ax.plot([], [], "s", color="#f4b183", label="fill-in inside the envelope")
    ax.set_xlim(0, n)
    ax.set_ylim(n, 0)
    ax.set_xlabel("station (logical order)")
    ax.set_ylabel("station (logical order)")
    ax.set_title(f"reduced normal matrix ({n} stations"
                 + (f", {bins} x {bins} cells" if bins < n else "") + ")")
    ax.legend(loc="upper right", fontsize=8)
    return _save(plt, fig, out_dir / "matrix.png")
