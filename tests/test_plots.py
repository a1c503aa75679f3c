"""Plots stay legible: long blocks in panels of bounded aspect, legends and keys outside the
data, arrows inside the axes with their scales stated, a lunar block in longitude and
latitude, labelled axes (issue 19, item 12)."""

import numpy as np
import pytest
from conftest import read_records

import sapgo
from sapgo.project import KIND_CHECK, KIND_PASS, Project, write_project

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import matplotlib.pyplot as plt

    plt.close("all")


@pytest.fixture(scope="module")
def strip(tmp_path_factory):
    """A long single strip (100 photos, about 20 times longer than wide), adjusted."""
    path = tmp_path_factory.mktemp("plots") / "strip.h5"
    sapgo.generate_block(path, strips=1, photos_per_strip=100, control_points=6)
    sapgo.adjust(path, sapgo.Options(progress=False))
    return path


@pytest.fixture(scope="module")
def lunar(tmp_path_factory):
    """Two Apollo 15 revolutions (selenocentric, 200 deg of longitude), every fourth pass
    point made a check point at its true position, adjusted."""
    from sapgo.generate import apollo

    path = tmp_path_factory.mktemp("plots") / "lunar.h5"
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(apollo.APOLLO15, 1, ([85, 85], 300, 200.0))
        sapgo.generate_block(path, preset="apollo15-1")
    with Project(path) as p:
        attrs = p.frame().to_attrs()
    rec = read_records(path)
    pt = rec["points"]
    pick = np.flatnonzero(pt["kind"] == KIND_PASS)[::4]
    pt["kind"][pick] = KIND_CHECK
    pt["control"][pick] = rec["truth"]["points"]["xyz"][pick]
    pt["control_sigma"][pick] = 1.0
    path.unlink()
    write_project(path, rec["cameras"], rec["stations"], pt, rec["observations"],
                  rec["station_priors"], rec["truth"], attrs=attrs)
    sapgo.adjust(path, sapgo.Options(progress=False))
    return path


def figures_of(path):
    from sapgo.plots import figures

    with Project(path) as p:
        return dict(figures(p))


def plan_axes(fig):
    return [ax for ax in fig.axes if ax.get_label() != "colour bar"]


def inches(ax):
    """Width and height of the axes' data area [inches]."""
    bb = ax.get_position()
    w, h = ax.figure.get_size_inches()
    return bb.width * w, bb.height * h


def overlaps(a, b):
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_a_long_strip_is_drawn_in_panels_of_bounded_aspect(strip):
    from sapgo.plots import MAX_PANEL_RATIO

    figs = figures_of(strip)
    with Project(strip) as p:
        x = (p.read("stations")["eo"][:, 3] + p.solution("station_corr")[:, 3]) / 1000.0
    for name in ("layout.png", "checkpoints.png"):
        fig = figs[name]
        axes = plan_axes(fig)
        w, h = fig.get_size_inches()
        assert len(axes) > 1 and h >= 5.0 and w / h <= 2.0, name  # not a sliver
        lo = min(ax.get_xlim()[0] for ax in axes)
        hi = max(ax.get_xlim()[1] for ax in axes)
        assert lo <= x.min() and hi >= x.max()  # the panels hold the whole strip (km)
        for ax in axes:
            aw, ah = inches(ax)
            assert ah >= 2.0 and aw / ah <= MAX_PANEL_RATIO + 1e-6
            # one scale in x and y, or the short axis says how much larger it is drawn
            ratio = (np.ptp(ax.get_xlim()) / aw) / (np.ptp(ax.get_ylim()) / ah)
            assert ratio > 1.0 - 1e-6
            if ratio > 1.0 + 1e-6:
                assert f"drawn at {ratio:.3g}x the scale of X" in ax.get_ylabel()
        assert axes[-1].get_xlabel() == "X [km]" and axes[0].get_ylabel().startswith("Y [km]")


def test_legends_and_keys_lie_outside_the_data(strip):
    figs = figures_of(strip)
    for name, fig in figs.items():
        fig.canvas.draw()
        r = fig.canvas.get_renderer()
        boxes = [ax.get_window_extent(r) for ax in plan_axes(fig)]
        legends = fig.legends + [ax.get_legend() for ax in fig.axes if ax.get_legend()]
        texts = [t for t in fig.texts if t is not fig._suptitle]
        assert legends or texts, name
        for artist in legends + texts:
            bb = artist.get_window_extent(r)
            assert not any(overlaps(bb, b) for b in boxes), name


def test_the_layout_draws_control_over_small_light_check_points(strip):
    fig = figures_of(strip)["layout.png"]
    drawn = {c.get_gid(): c for ax in plan_axes(fig) for c in ax.collections}
    check, control = drawn["check"], drawn["control"]
    assert control.get_zorder() > max(c.get_zorder() for c in drawn.values()
                                       if c is not control)
    assert check.get_sizes().max() < control.get_sizes().min()
    assert check.get_alpha() < 1.0
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert any(t.startswith("control points") for t in labels)
    assert any(t.startswith("check points") for t in labels)


def test_residual_arrows_stay_inside_the_axes_with_their_scales(strip, monkeypatch):
    from matplotlib.quiver import Quiver, QuiverKey

    import sapgo.plots

    monkeypatch.setattr(sapgo.plots, "MAX_VECTORS_DRAWN", 100)
    with Project(strip) as p:
        n_obs = p.n_observations
    fig = figures_of(strip)["residuals_camera_1.png"]
    ax = plan_axes(fig)[0]
    quivers = [c for c in ax.collections if isinstance(c, Quiver)]
    assert len(quivers) == 2
    sample, means = quivers
    assert 50 < len(sample.X) <= 130 < n_obs  # a thin random sample
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    for q in quivers:
        tx, ty = q.X + q.U / q.scale, q.Y + q.V / q.scale
        assert (tx >= x0).all() and (tx <= x1).all() and (ty >= y0).all() and (ty <= y1).all()
    # the largest mean arrow is drawn at most half a grid cell long: it stays in its cell
    cell = np.ptp(np.unique(means.X))[()] / (len(np.unique(means.X)) - 1)
    assert (np.hypot(means.U, means.V) / means.scale).max() <= 0.5 * cell + 1e-9
    keys = [a for a in ax.artists if isinstance(a, QuiverKey)]
    assert len(keys) == 2
    texts = " ".join(t.get_text() for t in fig.texts)
    assert f"{keys[0].U:g} µm: single residuals" in texts
    assert f"{keys[1].U:g} µm: mean per cell" in texts
    assert ax.get_xlabel() == "x [mm]" and ax.get_ylabel() == "y [mm]"


def test_check_point_arrows_have_a_reference_arrow_and_stay_inside(strip):
    from matplotlib.quiver import Quiver, QuiverKey

    fig = figures_of(strip)["checkpoints.png"]
    fig.canvas.draw()
    keys = [a for ax in fig.axes for a in ax.artists if isinstance(a, QuiverKey)]
    assert len(keys) == 1
    assert any(t.get_text().startswith(f"{keys[0].U:g} m horizontal error")
               for t in fig.texts)
    n = 0
    for ax in plan_axes(fig):
        bb = ax.get_window_extent()
        for q in (c for c in ax.collections if isinstance(c, Quiver)):
            tail = ax.transData.transform(np.column_stack([q.X, q.Y]))
            tip = tail + np.column_stack([q.U, q.V]) / q.scale * fig.dpi  # scale: m per inch
            assert ((tip[:, 0] >= bb.x0) & (tip[:, 0] <= bb.x1) & (tip[:, 1] >= bb.y0)
                    & (tip[:, 1] <= bb.y1)).all()
            n += len(q.X)
    assert n >= 294  # every check point, once or twice where panels overlap
    cbar = [ax for ax in fig.axes if ax.get_label() == "colour bar"]
    assert len(cbar) == 1 and cbar[0].get_ylabel() == "dZ (adjusted - known) [m]"


def test_a_lunar_block_is_drawn_in_longitude_and_latitude(lunar):
    with Project(lunar) as p:
        xyz = p.read("stations")["eo"][:, 3:6] + p.solution("station_corr")[:, 3:6]
    lon = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    lat = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    assert np.ptp(lon) > 150.0  # the block spans most of a hemisphere
    figs = figures_of(lunar)
    for name in ("layout.png", "checkpoints.png"):
        axes = plan_axes(figs[name])
        assert axes[-1].get_xlabel().startswith("longitude [°]"), name
        for ax in axes:
            assert ax.get_ylabel().startswith("latitude [°]"), name
            (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
            assert -180.0 <= x0 < x1 <= 180.0 and -90.0 <= y0 < y1 <= 90.0
            ticks = [t for t in ax.get_xticks() if x0 <= t <= x1]
            assert ticks and all(-180.0 <= t <= 180.0 for t in ticks)
            ticks = [t for t in ax.get_yticks() if y0 <= t <= y1]
            assert ticks and all(-90.0 <= t <= 90.0 for t in ticks)
        lo = min(ax.get_xlim()[0] for ax in axes)
        hi = max(ax.get_xlim()[1] for ax in axes)
        if name == "layout.png":  # the photo centres drawn where they are
            assert lo <= lon.min() and hi >= lon.max() and hi - lo < np.ptp(lon) + 60.0
            centres = np.concatenate([c.get_offsets() for ax in axes for c in ax.collections
                                      if c.get_gid() == "photo centres"])
            assert np.ptp(centres[:, 1]) == pytest.approx(np.ptp(lat), abs=1e-6)
    cbar = [ax for ax in figs["checkpoints.png"].axes if ax.get_label() == "colour bar"]
    assert cbar[0].get_ylabel() == "d up (adjusted - known) [m]"


@pytest.mark.parametrize("lo, hi, aspect, panels, side_by_side, exaggerated", [
    ((0, 0), (10, 10), 1.0, 1, False, False),       # a square block
    ((0, 0), (100, 10), 1.0, 3, False, False),      # 10:1: three panels of 3.3:1, stacked
    ((0, 0), (1000, 10), 1.0, 4, False, True),      # 100:1: four panels, Y drawn larger
    ((0, 0), (10, 200), 1.0, 4, True, True),        # a tall block: panels side by side
    ((-60, -20), (60, 20), 1.5, 1, False, False),   # degrees at 48 deg latitude: 2:1
])
def test_plan_axes_cut_long_blocks_and_keep_one_scale(lo, hi, aspect, panels, side_by_side,
                                                       exaggerated):
    from sapgo.plots import MAX_PANEL_RATIO, _plan_axes, _pyplot

    view = _plan_axes(_pyplot(), lo, hi, aspect)
    assert len(view.axes) == panels
    lefts = {round(ax.get_position().x0, 6) for ax in view.axes}
    assert (len(lefts) == panels) == side_by_side or panels == 1
    for ax in view.axes:
        aw, ah = inches(ax)
        assert max(aw / ah, ah / aw) <= MAX_PANEL_RATIO + 1e-6
        ratio = (np.ptp(ax.get_xlim()) / aw) / (np.ptp(ax.get_ylim()) * aspect / ah)
        assert (max(ratio, 1 / ratio) > 1.0 + 1e-6) == exaggerated
        assert max(ratio, 1 / ratio) == pytest.approx(view.exaggeration)
    xs = sorted(ax.get_xlim() for ax in view.axes)
    ys = sorted(ax.get_ylim() for ax in view.axes)
    assert xs[0][0] <= lo[0] and xs[-1][1] >= hi[0] and ys[0][0] <= lo[1]
    assert ys[-1][1] >= hi[1]


def test_the_plan_plot_has_labelled_axes_and_the_legend_outside(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    from sapgo.plan import design_network, write_pattern

    saved = []
    savefig = Figure.savefig

    def keep(fig, *args, **kwargs):
        out = savefig(fig, *args, **kwargs)
        r = fig.canvas.get_renderer()  # (the figure is closed after saving)
        saved.append((fig, fig.legends[0].get_window_extent(r),
                      fig.axes[0].get_window_extent(r)))
        return out

    monkeypatch.setattr(Figure, "savefig", keep)
    write_pattern(design_network(3, 8), tmp_path / "m.png", "across_strip")
    assert (tmp_path / "m.png").stat().st_size > 0
    fig, legend, data = saved[0]
    ax = fig.axes[0]
    assert ax.get_xlabel() == "photo number in the across_strip order (column of M)"
    assert ax.get_ylabel() == "photo number (row of M)"
    assert not overlaps(legend, data)
