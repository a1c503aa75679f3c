"""Plots of an adjusted project (``sapgo adjust --plots DIR``, ``sapgo report --plots DIR``;
the ``plot`` extra, matplotlib).

- ``layout.png``: photo centres and points by kind (control on top, check points small and
  light under it, pass points; rejected marked);
- ``residuals_camera_<id>.png``: image residuals over each camera's format: the RMS per cell
  of a grid as colour, the mean vector per cell (systematic errors show as a pattern) and a
  thin sample of single vectors, each kind of arrow with its own scale key;
- ``checkpoints.png``: check-point errors, horizontal as vectors (with a reference arrow) and
  vertical as colour;
- ``matrix.png``: the pattern of the reduced normal matrix in the stations' logical order:
  non-zero blocks, the fill-in inside the envelope and the band (as Figure 1 of seeds/002
  and Figure 12 of seeds/000).

Plan views are drawn in the frame's X, Y (east, north in a local tangent frame) in m, or km
for blocks over 20 km, and a selenocentric block in planetocentric longitude and latitude on
the IAU 2015 Moon sphere. A block much longer than wide is cut into up to
:data:`MAX_PANELS` panels along its length; a panel still longer than
:data:`MAX_PANEL_RATIO` has its short axis drawn at a larger scale, stated in that axis's
label. Legends and scale keys sit outside the data area.

Everything is read in chunks; large blocks are drawn from a bounded sample of points and
a binned image of the matrix, so memory stays bounded.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from .errors import DataError
from .frames import MOON_RADIUS, SELENOCENTRIC, TANGENT
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
MAX_CHECK_DRAWN = 2_500
#: At most this many single residual vectors are drawn per camera (a regular sample beyond).
MAX_VECTORS_DRAWN = 600
#: Cells of the residual grid along the longer side of the format.
GRID_CELLS = 12
#: The matrix pattern is binned into at most this many rows and columns.
MATRIX_BINS = 1000
#: A plan-view panel is at most this many times longer than high at equal scales.
MAX_PANEL_RATIO = 4.0
#: A long block is cut into at most this many panels along its length.
MAX_PANELS = 4
#: The long side of a plan-view panel [inches]: along X, along Y.
PANEL_INCHES = (10.0, 9.0)
#: Plan views of blocks wider than this [m] are drawn in km.
KM_BEYOND = 20_000.0
#: The longest check-point error arrow [inches] (the axes leave this much room around).
MAX_ARROW_INCHES = 0.4

# figure margins [inches]: left (y tick labels and label), right, top (title), below a panel
# (x tick labels and label), between stacked panels, between panels side by side
_LEFT, _RIGHT, _TOP, _BELOW, _GAP_STACKED, _GAP_SIDE = 1.1, 0.3, 0.7, 0.75, 0.55, 1.1


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
        _check_adjusted(p, project_path)
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DataError(f"{out_dir}: cannot create the directory ({exc.strerror})") from exc
        paths = []
        for name, fig in figures(p, chunk):
            try:
                fig.savefig(out_dir / name, dpi=120, bbox_inches="tight")
            finally:
                plt.close(fig)
            paths.append(str(out_dir / name))
    return paths


def _check_adjusted(p, path):
    if not p.has_solution or p.file["solution"].attrs.get("state") != "adjusted":
        raise DataError(f"{path}: the project has no adjusted solution: run 'sapgo adjust' "
                        f"first")


def figures(p, chunk=CHUNK_RECORDS):
    """Yield ``(file name, figure)`` for the plots of an open, adjusted project ``p``, one
    figure at a time (the caller saves and closes each)."""
    _check_adjusted(p, p.path)
    report = json.loads(p.file["solution/report"][()])
    yield "layout.png", layout_figure(p, chunk)
    for cam_id, fig in residual_figures(p, chunk):
        yield f"residuals_camera_{cam_id}.png", fig
    fig = checkpoint_figure(p, chunk, report)
    if fig is not None:
        yield "checkpoints.png", fig
    yield "matrix.png", matrix_figure(p, chunk)


# -- plan views ---------------------------------------------------------------------------
class PlanView:
    """Plan-view coordinates of a block in its frame: ``plane(xyz)`` gives n x 2 plot
    coordinates; ``labels`` the axis labels with units, ``names`` the axes' short names and
    ``aspect`` the drawn length of a unit of y over one of x at one ground scale.

    A selenocentric block (the IAU 2015 Moon sphere, see :mod:`sapgo.frames`) is drawn in
    planetocentric longitude and latitude, longitude = atan2(Y, X), latitude =
    atan2(Z, hypot(X, Y)) (a sphere: planetocentric and planetographic agree), the longitudes
    kept within 180 deg of the stations' mean so a block across the 180 deg meridian stays
    whole; a degree of longitude is cos(latitude) of one of latitude (``aspect``). Other
    frames are drawn in their X, Y (east, north in a local tangent frame), in km for blocks
    wider than :data:`KM_BEYOND`."""

    def __init__(self, frame, station_xyz):
        xyz = np.asarray(station_xyz, np.float64).reshape(-1, 3)
        self.lunar = frame.kind == SELENOCENTRIC
        self.lon0 = 0.0
        if self.lunar:
            lon = np.arctan2(xyz[:, 1], xyz[:, 0])
            if len(xyz):
                self.lon0 = math.degrees(math.atan2(np.sin(lon).sum(), np.cos(lon).sum()))
            lat = self(xyz)[:, 1]
            mid = 0.5 * (lat.min() + lat.max()) if len(lat) else 0.0
            self.aspect = 1.0 / max(math.cos(math.radians(mid)), 0.2)
            self.scale, self.unit = 1.0, "°"
            self.names = ("longitude", "latitude")
            self.labels = ("longitude [°] (planetocentric, IAU 2015 Moon sphere)",
                           f"latitude [°] (1° = {math.radians(MOON_RADIUS) / 1000:.1f} km)")
        else:
            span = float(np.ptp(xyz[:, :2], axis=0).max()) if len(xyz) else 0.0
            self.scale, self.unit = (1000.0, "km") if span > KM_BEYOND else (1.0, "m")
            self.aspect = 1.0
            self.names = ("east", "north") if frame.kind == TANGENT else ("X", "Y")
            self.labels = tuple(f"{n} [{self.unit}]" for n in self.names)

    def __call__(self, xyz):
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        if not self.lunar:
            return xyz[:, :2] / self.scale
        lon = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
        lon = self.lon0 + (lon - self.lon0 + 180.0) % 360.0 - 180.0
        lat = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
        return np.column_stack([lon, lat])


def _plan_of(p):
    """The plan view of project ``p``, the adjusted stations' exterior orientation and
    which of them are active."""
    st = p.read("stations")
    eo = st["eo"] + p.solution("station_corr")
    act = st["status"] == STATUS_ACTIVE
    return PlanView(p.frame(), eo[act, 3:6]), eo, act


def _plan_axes(plt, lo, hi, aspect=1.0, size=None, pad=0.04, pad_inches=0.0, right=0.0,
               bottom=0.0, panels=None):
    """A figure with axes for the box ``lo``..``hi`` (plot units) at one ground scale in x and
    y (``aspect``: the drawn length of a y unit over an x unit). A box more than
    :data:`MAX_PANEL_RATIO` times longer than wide is cut into up to ``panels`` (default
    :data:`MAX_PANELS`) panels along its longer axis (stacked for a long X, side by side
    for a long Y); a panel still longer has its short axis drawn ``exaggeration`` times the
    scale of the long one.

    ``size``: the long side of a panel [inches]; ``pad``: room around the data, a fraction of
    the extent, and at least ``pad_inches``; ``right``, ``bottom``: inches kept free right
    of and below the panels (a colour bar, the legend). Returns a namespace: ``fig``,
    ``axes``, ``long`` (0: X, 1: Y), ``exaggeration``, ``inch`` (a panel's width, height),
    ``width``, ``height``, ``bottom`` and ``box`` (left, bottom, right, top of the panels in
    inches)."""
    lo, hi = np.array(lo, np.float64), np.array(hi, np.float64)
    ext = hi - lo
    for k in range(2):  # a block without extent along an axis (a single point or line)
        if not ext[k] > 0:
            d = 0.1 * float(ext.max()) if ext.max() > 0 else 1.0
            lo[k], ext[k] = lo[k] - d / 2, d
    mul = np.array([1.0, aspect])
    long = 0 if ext[0] * mul[0] >= ext[1] * mul[1] else 1
    short = 1 - long
    n = int(np.clip(np.ceil(ext[long] * mul[long] / (ext[short] * mul[short])
                            / MAX_PANEL_RATIO), 1, panels or MAX_PANELS))
    seg = ext.copy()
    seg[long] /= n
    inch_long = PANEL_INCHES[long] if size is None else size
    extra = np.zeros(2)
    for it in range(8):  # the room of pad_inches depends on the scale it changes
        span = seg * (1.0 + 2.0 * pad) + 2.0 * extra
        r = span[long] * mul[long] / (span[short] * mul[short])
        e = max(1.0, r / MAX_PANEL_RATIO)
        inch = np.zeros(2)
        inch[long], inch[short] = inch_long, inch_long * e / r
        extra = pad_inches * span / inch
    span = seg * (1.0 + 2.0 * pad) + 2.0 * extra
    below = _BELOW + (0.2 if long == 1 and e > 1.0 else 0.0)  # a two-line x label
    if long == 0:
        width = _LEFT + inch[0] + _RIGHT + right
        height = _TOP + n * inch[1] + (n - 1) * _GAP_STACKED + below + bottom
        corners = [(_LEFT, bottom + below + (n - 1 - i) * (inch[1] + _GAP_STACKED))
                   for i in range(n)]
        box = (_LEFT, bottom + below, _LEFT + inch[0], height - _TOP)
    else:
        width = _LEFT + n * inch[0] + (n - 1) * _GAP_SIDE + _RIGHT + right
        height = _TOP + inch[1] + below + bottom
        corners = [(_LEFT + i * (inch[0] + _GAP_SIDE), bottom + below) for i in range(n)]
        box = (_LEFT, bottom + below, width - _RIGHT - right, height - _TOP)
    fig = plt.figure(figsize=(width, height))
    axes = []
    for i, (x0, y0) in enumerate(corners):
        ax = fig.add_axes((x0 / width, y0 / height, inch[0] / width, inch[1] / height))
        start = lo + np.where(np.arange(2) == long, i * seg, 0.0)
        middle = start + seg / 2
        ax.set_xlim(middle[0] - span[0] / 2, middle[0] + span[0] / 2)
        ax.set_ylim(middle[1] - span[1] / 2, middle[1] + span[1] / 2)
        ax.ticklabel_format(useOffset=False, style="plain")
        axes.append(ax)
    return SimpleNamespace(fig=fig, axes=axes, long=long, exaggeration=e, inch=inch,
                           width=width, height=height, bottom=bottom, box=box)


def _label_plan(view, plane, title):
    """Axis labels with units (the exaggerated axis says so), the title, and longitudes
    written within -180..180 deg."""
    labels = list(plane.labels)
    short = 1 - view.long
    if view.exaggeration > 1.0 + 1e-9:
        labels[short] += (f"\n(drawn at {view.exaggeration:.3g}x the scale of "
                          f"{plane.names[view.long]})")
    last = len(view.axes) - 1
    for i, ax in enumerate(view.axes):
        if view.long == 1 or i == last:
            ax.set_xlabel(labels[0])
        if view.long == 0 or i == 0:
            ax.set_ylabel(labels[1])
        if plane.lunar and max(np.abs(ax.get_xlim())) > 180.0:
            from matplotlib.ticker import FuncFormatter

            ax.xaxis.set_major_formatter(
                FuncFormatter(lambda v, _: f"{(v + 180.0) % 360.0 - 180.0:g}"))
    box = view.box
    view.fig.suptitle(title, x=0.5 * (box[0] + box[2]) / view.width,
                      y=1.0 - 0.15 / view.height, va="top", fontsize=10)


def _legend_below(view, handles, ncol=None):
    """A legend under the panels, outside the data area."""
    box = view.box
    return view.fig.legend(handles=handles, loc="upper center",
                           bbox_to_anchor=(0.5 * (box[0] + box[2]) / view.width,
                                           view.bottom / view.height),
                           ncol=ncol or min(len(handles), 3), fontsize=8, frameon=False)


def _colorbar_axes(view):
    """Axes for a colour bar right of the panels, at most 6 inches high."""
    box = view.box
    h = min(box[3] - box[1], 6.0)
    y = 0.5 * (box[1] + box[3] - h)
    return view.fig.add_axes(((box[2] + 0.35) / view.width, y / view.height,
                              0.18 / view.width, h / view.height), label="colour bar")


def _inside(ax, xy):
    """Which of the points ``xy`` lie within the limits of ``ax``."""
    (x0, x1), (y0, y1) = sorted(ax.get_xlim()), sorted(ax.get_ylim())
    return (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)


def _marker_area(view, n, fraction, low, high):
    """A marker area [pt^2] that takes ``fraction`` of the mean spacing of ``n`` points
    squared over the panels, within ``low``..``high``."""
    inches2 = len(view.axes) * float(view.inch[0] * view.inch[1])
    spacing = 72.0 * math.sqrt(inches2 / max(n, 1))
    return float(np.clip(fraction * spacing ** 2, low, high))


def _nice(value):
    """The number of the form 1, 2 or 5 x 10^k nearest ``value`` (> 0)."""
    value = max(float(value), 1e-12)
    e = math.floor(math.log10(value))
    cands = [m * 10.0 ** k for k in (e, e + 1) for m in (1, 2, 5)]
    return min(cands, key=lambda c: abs(math.log(c / value)))


def _scale_key(view, q, u, inches, x, y, label, **kw):
    """A key arrow of ``u`` (data units of quiver ``q``) drawn ``inches`` long, its tail at
    ``x``, ``y`` inches from the figure's lower left corner, and its ``label`` to the right
    (a figure text, so a tight bounding box keeps it)."""
    view.axes[0].quiverkey(q, (x + inches) / view.width, y / view.height, u, "",
                           labelpos="E", coordinates="figure", **kw)
    return view.fig.text((x + inches + 0.1) / view.width, y / view.height, label,
                         va="center", ha="left", fontsize=9)


def layout_figure(p, chunk=CHUNK_RECORDS):
    """The block layout: photo centres, pass points, check points small and light, control
    on top and distinct, points with rejected rays marked; the legend below the panels."""
    from matplotlib.lines import Line2D

    plt = _pyplot()
    plane, eo, act = _plan_of(p)
    step = max(1, p.n_points // MAX_POINTS_DRAWN)
    groups = {"pass": [], "check": [], "rejected": [], "control": []}
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
        groups["control"].append(plane(xyz[live & ctrl & ~rejected]))
        groups["check"].append(plane(xyz[live & (kind == KIND_CHECK) & ~rejected][::step]))
        groups["rejected"].append(plane(xyz[rejected]))
        groups["pass"].append(plane(xyz[live & (kind == KIND_PASS) & ~rejected][::step]))
    xy = {k: np.concatenate(v) if v else np.zeros((0, 2)) for k, v in groups.items()}
    xy["photo centres"] = plane(eo[act, 3:6])
    every = np.concatenate(list(xy.values()))
    lo, hi = (every.min(axis=0), every.max(axis=0)) if len(every) else (np.zeros(2),) * 2
    view = _plan_axes(plt, lo, hi, plane.aspect, bottom=0.55)
    n = {k: len(v) for k, v in xy.items()}
    style = {  # drawn in this order, the control last and on top
        "pass": dict(marker=".", color="0.6", lw=0,
                     s=_marker_area(view, n["pass"], 0.06, 0.3, 6.0)),
        "check": dict(marker="s", color="#9ecae1", lw=0, alpha=0.7,
                      s=_marker_area(view, n["check"], 0.12, 0.8, 16.0)),
        "photo centres": dict(marker="o", color="tab:green", lw=0,
                              s=_marker_area(view, n["photo centres"], 0.12, 1.0, 14.0)),
        "rejected": dict(marker="x", color="k", lw=1.0, s=30.0),
        "control": dict(marker="^", color="tab:red", edgecolor="k", lw=0.6, s=55.0),
    }
    labels = {"pass": "pass points", "check": "check points",
              "photo centres": "photo centres", "rejected": "points with rejected rays",
              "control": "control points (full, horizontal, vertical)"}
    handles = []
    for z, (name, kw) in enumerate(style.items()):
        if not n[name]:
            continue
        for ax in view.axes:
            m = _inside(ax, xy[name])
            if m.any():
                ax.scatter(xy[name][m, 0], xy[name][m, 1], zorder=2 + z, gid=name, **kw)
        drawn = (f" (every {step}th drawn)" if name in ("pass", "check") and step > 1
                 else "")
        handles.append(Line2D([], [], ls="none", marker=kw["marker"], color=kw["color"],
                              markeredgecolor=kw.get("edgecolor", kw["color"]),
                              markersize=7 if name == "control" else 5,
                              label=f"{labels[name]}: {n[name]}{drawn}"))
    _label_plan(view, plane, f"{Path(p.path).name}: block layout (frame: {p.frame().kind})")
    _legend_below(view, handles)
    return view.fig


# -- image residuals ----------------------------------------------------------------------
def _fit_scale(k, xy, uv, xlim, ylim):
    """``k`` or less, so that every arrow ``xy + k uv`` ends within the limits."""
    for c, (a, b) in ((0, xlim), (1, ylim)):
        u = uv[:, c]
        room = np.where(u > 0, b - xy[:, c], np.where(u < 0, a - xy[:, c], np.inf))
        with np.errstate(divide="ignore", invalid="ignore"):
            ok = np.where(u != 0, room / u, np.inf)
        if len(ok):
            k = min(k, 0.98 * float(np.clip(ok, 0.0, None).min()))
    return k


def residual_figures(p, chunk=CHUNK_RECORDS):
    """Yield ``(camera id, figure)``: the image residuals over each camera's format. The RMS
    per grid cell as colour, the mean vector per cell in red, a thin sample of at most
    :data:`MAX_VECTORS_DRAWN` single vectors in grey; each kind of arrow scaled to stay
    inside the axes, its scale shown by a key arrow under the axes."""
    plt = _pyplot()
    cams = p.cameras()
    st_cam = p.read_field("stations", "camera")
    n_cam = len(cams)
    half = np.stack([cams["format_x"], cams["format_y"]], axis=1) / 2.0
    cells = [(GRID_CELLS, max(1, int(round(GRID_CELLS * h[1] / max(h[0], 1e-9)))))
             for h in half]
    sums = [np.zeros((cx, cy, 4)) for cx, cy in cells]  # vx, vy, vx^2 + vy^2, count
    sample = [[] for _ in range(n_cam)]
    n_obs = np.zeros(n_cam, np.int64)
    for a, b in p.chunks("observations", chunk):
        ob = p.read("observations", a, b)
        act = ob["status"] == STATUS_ACTIVE
        n_obs += np.bincount(st_cam[ob["station"][act]], minlength=n_cam)
    step = np.maximum(1, -(-n_obs // MAX_VECTORS_DRAWN))
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
            np.add.at(sums[c], (ix, iy),
                      np.column_stack([v, (v ** 2).sum(axis=1), np.ones(len(v))]))
            idx = np.flatnonzero(m)  # a random sample, the same for the same chunks
            keep = idx[np.random.default_rng([a, c]).random(len(idx)) * step[c] < 1.0]
            sample[c].append(np.column_stack([ob["x"][keep], ob["y"][keep], res[keep]]))
    for c in range(n_cam):
        if not n_obs[c]:
            continue
        yield int(cams["id"][c]), _residual_figure(plt, cams["id"][c], half[c], cells[c],
                                                   sums[c], sample[c], int(n_obs[c]))


def _residual_figure(plt, cam_id, half, cells, s, sample, n_obs):
    from matplotlib.patches import Rectangle

    cx, cy = cells
    cnt = s[:, :, 3]
    has = cnt > 0
    mean = s[:, :, :2] / np.maximum(cnt, 1)[:, :, None]
    rms_cell = np.sqrt(s[:, :, 2] / np.maximum(2 * cnt, 1))
    rms = float(np.sqrt(s[:, :, 2].sum() / max(2 * cnt.sum(), 1)))
    gx = (np.arange(cx) + 0.5) / cx * 2 * half[0] - half[0]
    gy = (np.arange(cy) + 0.5) / cy * 2 * half[1] - half[1]
    GX, GY = np.meshgrid(gx, gy, indexing="ij")
    view = _plan_axes(plt, -half, half, size=7.0, pad=0.06, right=1.1, bottom=0.55, panels=1)
    ax, fig = view.axes[0], view.fig
    xlim, ylim = ax.get_xlim(), ax.get_ylim()
    cell = min(2 * half[0] / cx, 2 * half[1] / cy)
    mesh = ax.pcolormesh(np.linspace(-half[0], half[0], cx + 1),
                         np.linspace(-half[1], half[1], cy + 1),
                         np.ma.masked_where(~has, rms_cell).T, cmap="Blues", vmin=0.0,
                         vmax=max(float(rms_cell.max()), 1e-6), alpha=0.5, zorder=0)
    ax.add_patch(Rectangle((-half[0], -half[1]), 2 * half[0], 2 * half[1], fill=False,
                           ec="0.4", lw=0.8, zorder=1))
    box = view.box
    cax = _colorbar_axes(view)
    fig.colorbar(mesh, cax=cax, label="RMS of the residuals per cell [µm]")
    key_y = view.bottom - 0.2
    per_mm = view.inch[0] / (xlim[1] - xlim[0])  # inches per mm of the format
    pts = np.concatenate(sample) if sample else np.zeros((0, 4))
    if len(pts):
        # single vectors: the RMS drawn as a quarter of a cell, none leaving the axes
        k = _fit_scale(0.25 * cell / max(rms, 1e-6), pts[:, :2], pts[:, 2:], xlim, ylim)
        q = ax.quiver(pts[:, 0], pts[:, 1], pts[:, 2], pts[:, 3], angles="xy",
                      scale_units="xy", scale=1.0 / k, color="0.25", alpha=0.45,
                      width=0.0015, headwidth=4, zorder=2)
        u = _nice(rms)
        _scale_key(view, q, u, u * k * per_mm, box[0], key_y,
                   f"{u:g} µm: single residuals ({len(pts)} of {n_obs} drawn)")
    big = float(np.hypot(mean[:, :, 0], mean[:, :, 1])[has].max()) if has.any() else 0.0
    # means: the largest drawn as 0.45 of a cell (it stays in its cell and in the axes)
    xy_m = np.column_stack([GX[has], GY[has]])
    uv_m = np.column_stack([mean[:, :, 0][has], mean[:, :, 1][has]])
    k = _fit_scale(0.45 * cell / max(big, 1e-6), xy_m, uv_m, xlim, ylim)
    q = ax.quiver(xy_m[:, 0], xy_m[:, 1], uv_m[:, 0], uv_m[:, 1], angles="xy",
                  scale_units="xy", scale=1.0 / k, color="tab:red", width=0.005, zorder=3,
                  label="mean per cell")
    u = _nice(big / 2 if big > 0 else 1.0)
    _scale_key(view, q, u, u * k * per_mm, 0.5 * (box[0] + box[2]) + 0.3, key_y,
               f"{u:g} µm: mean per cell", color="tab:red")
    ax.set_aspect("auto")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    fig.suptitle(f"camera {int(cam_id)}: image residuals of {n_obs} observations "
                 f"(RMS {rms:.2f} µm)", x=0.5 * (box[0] + box[2]) / view.width,
                 y=1.0 - 0.15 / view.height, va="top", fontsize=10)
    return fig


# -- check points -------------------------------------------------------------------------
def checkpoint_figure(p, chunk=CHUNK_RECORDS, report=None):
    """Check-point errors: horizontal ones as arrows (east, north; X, Y in a local frame)
    with a reference arrow of labelled length, vertical ones as colour; beyond
    :data:`MAX_CHECK_DRAWN` points, means over square cells. None without check points."""
    plt = _pyplot()
    frame = p.frame()
    plane, _, _ = _plan_of(p)
    xy, d = [], []
    for a, b in p.chunks("points", chunk):
        pts = p.read("points", a, b)
        m = (pts["kind"] == KIND_CHECK) & (pts["status"] == STATUS_ACTIVE)
        if not m.any():
            continue
        xyz = (pts["xyz"] + p.solution("point_corr", a, b))[m]
        rot = control_rotations(pts["kind"][m], pts["control"][m], frame)
        xy.append(plane(xyz))
        d.append(np.einsum("nij,nj->ni", rot, xyz - pts["control"][m]))
    if not xy:
        return None
    xy, d = np.concatenate(xy), np.concatenate(d)
    ext = np.ptp(xy, axis=0)
    h = np.hypot(d[:, 0], d[:, 1])
    ref = float(np.sqrt(np.mean(h ** 2))) or 1.0
    n_all = len(xy)
    what = ""
    if n_all > MAX_CHECK_DRAWN:  # many check points: mean errors per square cell
        area = max(ext[0], 1e-9) * max(ext[1], 1e-9) * plane.aspect
        cell = float(np.sqrt(area / MAX_CHECK_DRAWN))
        size = np.array([cell, cell / plane.aspect])
        ij = np.floor((xy - xy.min(axis=0)) / size).astype(np.int64)
        key, inv = np.unique(ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1],
                             return_inverse=True)
        inv = inv.reshape(-1)
        cnt = np.bincount(inv)
        xy = np.column_stack([np.bincount(inv, xy[:, k]) / cnt for k in range(2)])
        d = np.column_stack([np.bincount(inv, d[:, k]) / cnt for k in range(3)])
        what = f"; means over cells of {cell:.3g} {plane.unit}"
    view = _plan_axes(plt, xy.min(axis=0), xy.max(axis=0), plane.aspect,
                      pad_inches=MAX_ARROW_INCHES, right=1.3, bottom=0.45)
    # the RMS error drawn as 0.7 of the mean spacing of the points, no arrow longer than
    # MAX_ARROW_INCHES (the room the axes leave around the points)
    spacing = math.sqrt(len(view.axes) * float(view.inch[0] * view.inch[1]) / len(xy))
    rms_inches = float(np.clip(0.7 * spacing, 0.06, 0.3))
    per_inch = max(ref / rms_inches, float(np.hypot(d[:, 0], d[:, 1]).max())
                   / (0.95 * MAX_ARROW_INCHES))
    lim = float(np.abs(d[:, 2]).max()) or 1.0
    size = _marker_area(view, len(xy), 0.25, 6.0, 30.0)
    sc = key_q = None
    for ax in view.axes:
        m = _inside(ax, xy)
        sc = ax.scatter(xy[m, 0], xy[m, 1], c=d[m, 2], cmap="coolwarm", vmin=-lim, vmax=lim,
                        s=size, edgecolors="0.3", linewidths=0.3, zorder=2)
        q = ax.quiver(xy[m, 0], xy[m, 1], d[m, 0], d[m, 1], angles="uv",
                      scale_units="inches", scale=per_inch, units="inches", width=0.012,
                      headwidth=4, headlength=5, headaxislength=4.5, zorder=3)
        if key_q is None and m.any():
            key_q = q
    cax = _colorbar_axes(view)
    up = "dZ" if frame.kind == "local space rectangular" else "d up"
    view.fig.colorbar(sc, cax=cax, label=f"{up} (adjusted - known) [m]")
    u = _nice(ref)
    across = ("dX, dY" if frame.kind == "local space rectangular" else "d east, d north")
    _scale_key(view, key_q, u, u / per_inch, view.box[0], view.bottom - 0.2,
               f"{u:g} m horizontal error ({across})")
    c = (report or {}).get("check_points") or {}
    sz = f" (sZ {c['sz']:.3f} m)" if c.get("sz") is not None else ""
    _label_plan(view, plane, f"{Path(p.path).name}: check points ({n_all}{what})\n"
                             f"horizontal errors as arrows (RMS {ref:.3f} m), vertical as "
                             f"colour{sz}")
    return view.fig


# -- the reduced normal matrix ------------------------------------------------------------
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


def matrix_figure(p, chunk=CHUNK_RECORDS):
    """The pattern of the reduced normal matrix (:func:`matrix_pattern`) with its band; the
    legend below the axes."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    plt = _pyplot()
    n = p.n_stations
    img, bw = matrix_pattern(p, MATRIX_BINS, chunk)
    bins = len(img)
    view = _plan_axes(plt, (0, 0), (n, n), size=7.0, pad=0.0, bottom=0.45, panels=1)
    ax, fig = view.axes[0], view.fig
    ax.imshow(img, cmap=ListedColormap(["white", "#f4b183", "black"]), vmin=0, vmax=2,
              interpolation="nearest", extent=(0, n, n, 0), aspect="auto")
    ax.plot([0, n], [bw, n + bw], "r--", lw=0.8)
    ax.plot([bw, n + bw], [0, n], "r--", lw=0.8)
    ax.set_xlim(0, n)
    ax.set_ylim(n, 0)
    ax.set_xlabel("station (logical order)")
    ax.set_ylabel("station (logical order)")
    fig.suptitle(f"reduced normal matrix ({n} stations"
                 + (f", {bins} x {bins} cells" if bins < n else "") + ")",
                 x=0.5 * (view.box[0] + view.box[2]) / view.width,
                 y=1.0 - 0.15 / view.height, va="top", fontsize=10)
    from matplotlib.lines import Line2D

    _legend_below(view, [Patch(color="black", label="non-zero 6x6 blocks"),
                         Patch(color="#f4b183", label="fill-in inside the envelope"),
                         Line2D([], [], color="r", ls="--", lw=0.8,
                                label=f"band: {bw} stations")])
    return fig
