"""The pictures a user puts in a paper: colour ranges that show the data, one normalisation per
shared colour bar, error estimates drawn, and every label inside the canvas (issue 42, item 4)."""
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import xarray as xr  # noqa: E402

from ciliary_carpet.output import figures  # noqa: E402
from single_cilium.figures import frequency_norm, plot_stability_map, plot_thrust_curve  # noqa: E402
from single_cilium.table import ThrustTable  # noqa: E402

DESIGNS = Path(__file__).parent.parent / "designs"


def texts_outside(fig) -> list[str]:
    """What of ``fig`` is drawn beyond its canvas by more than a pixel: each axes (its title, tick
    labels, axis labels, legend) and each figure-level legend or text, named by its title or text.
    Measured as matplotlib's tight bounding box measures (only what is drawn: tick labels outside
    the view are not)."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    W, H = fig.bbox.width, fig.bbox.height
    out = []
    parts = [(ax, ax.get_title() or ax.get_ylabel() or "axes") for ax in fig.axes]
    parts += [(lg, " ".join(t.get_text() for t in lg.get_texts())) for lg in fig.legends]
    parts += [(t, t.get_text()) for t in fig.texts if t.get_text().strip()]
    if fig._suptitle is not None:
        parts.append((fig._suptitle, fig._suptitle.get_text()))
    for artist, name in parts:
        bb = artist.get_tightbbox(r) if hasattr(artist, "get_tightbbox") else artist.get_window_extent(r)
        if bb is not None and (bb.x0 < -1 or bb.y0 < -1 or bb.x1 > W + 1 or bb.y1 > H + 1):
            out.append(name)
    return out


def test_texts_outside_sees_a_cut_label():
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.set_title("fits")
    fig.tight_layout()
    assert texts_outside(fig) == []
    ax.legend(handles=[plt.Line2D([], [], label="cut off below")], loc="upper center", bbox_to_anchor=(0.5, -0.9))
    assert texts_outside(fig) == ["fits"]
    plt.close(fig)


@pytest.mark.parametrize("chi, lo, hi, diverging", [
    ([85.1, 90.0, 95.7], 85.1, 95.7, False),      # one sign: exactly its range
    ([-95.7, -85.1, np.nan], -95.7, -85.1, False),  # NaN ignored
    ([-20.0, 5.0, 60.0], -60.0, 60.0, True),      # both signs: symmetric about 0
])
def test_chi_N_colours_show_the_layouts_range(chi, lo, hi, diverging):
    cmap, norm = figures.chi_N_colours(np.array(chi))
    assert (norm.vmin, norm.vmax) == pytest.approx((lo, hi))
    assert (cmap.name == "coolwarm") == diverging
    # the extremes of a one-sign layout are told apart (the old +-cutoff scale made them one shade)
    f = np.array(chi)[np.isfinite(chi)]
    assert np.abs(np.subtract(cmap(norm(f.min()))[:3], cmap(norm(f.max()))[:3])).max() > 0.3


def test_chi_N_colours_of_one_value_are_not_degenerate():
    _, norm = figures.chi_N_colours(np.full(4, 50.0))
    assert norm.vmin < 50.0 < norm.vmax


@pytest.fixture(scope="module")
def designed():
    from ciliary_carpet.scenes.assembly import design
    from ciliary_carpet.scenes.scene import load_scene

    scene = load_scene(DESIGNS / "uniform_deflection.toml").reduced()
    d, carpet = design(scene)
    return scene, carpet, d


@pytest.fixture
def drawn(monkeypatch):
    """The figures the render functions make, kept open instead of saved."""
    got = []
    monkeypatch.setattr(figures, "_savefig", lambda fig, path: got.append(fig))
    yield got
    for f in got:
        plt.close(f)


def test_design_picture_colours_and_labels(designed, drawn, tmp_path):
    scene, carpet, d = designed
    figures.design_picture(tmp_path / "design.png", scene.name, carpet, d)
    (fig,) = drawn
    assert texts_outside(fig) == []
    chi = carpet.chi_N
    for coll in fig.findobj(matplotlib.collections.PathCollection):
        if coll.get_array() is not None and coll.get_array().size == chi.size and coll.norm.vmin > -1e300:
            if np.allclose(np.asarray(coll.get_array()), chi):
                assert (coll.norm.vmin, coll.norm.vmax) == pytest.approx((chi.min(), chi.max()))


def test_preview_colours_and_labels(designed, drawn, tmp_path):
    scene, carpet, d = designed
    figures.preview(tmp_path / "preview.png", scene.name, carpet, None, None, d)
    (fig,) = drawn
    assert texts_outside(fig) == []
    chi = carpet.chi_N
    (coll,) = [c for c in fig.findobj(matplotlib.collections.PathCollection)
               if c.get_array() is not None and np.allclose(np.asarray(c.get_array()), chi)]
    cmap, norm = figures.chi_N_colours(chi)
    assert (coll.norm.vmin, coll.norm.vmax) == pytest.approx((norm.vmin, norm.vmax))


def _map(f):
    f = np.asarray(f, dtype=float)
    return xr.Dataset({"regime": (("chi_E", "eta"), np.where(np.isfinite(f), 1, 0)),
                       "frequency": (("chi_E", "eta"), f)},
                      coords={"chi_E": [100.0, 200.0], "eta": [0.5, 1.0]}, attrs={"chi_N": 0.0})


def test_stability_maps_under_one_colour_bar_share_their_colours():
    a, b = _map([[1.0, 2.0], [np.nan, 2.5]]), _map([[3.0, 4.0], [5.0, np.nan]])
    norm = frequency_norm([a, b])
    assert (norm.vmin, norm.vmax) == (1.0, 5.0)
    fig, axs = plt.subplots(1, 2, layout="constrained")
    ma = plot_stability_map(a, axs[0], norm=norm)
    mb = plot_stability_map(b, axs[1], norm=norm)
    fig.colorbar(mb, ax=axs)
    # equal values, equal colours: 2.0 on the left panel maps where 2.0 would on the right
    assert ma.norm(2.0) == mb.norm(2.0) == pytest.approx(0.25)
    assert texts_outside(fig) == []
    plt.close(fig)


def test_thrust_curve_draws_its_error_estimates():
    table = ThrustTable.default()
    fig = plot_thrust_curve(table, n=120)
    assert texts_outside(fig) == []
    top, bottom = fig.axes[0], fig.axes[1]
    (band,) = top.collections  # the |Fbar| band: +-(the rows' error + the interpolation error)
    half = np.ptp(band.get_paths()[0].vertices[:, 1]) / 2
    assert half > 0
    # the error panel's curves are the estimates themselves, on a log axis, all positive
    assert bottom.get_yscale() == "log"
    e = np.concatenate([ln.get_ydata() for ln in bottom.get_lines()])
    assert np.all(e > 0) and e.max() >= float(np.nanmax(table.ds.thrust_norm_error.values))
    plt.close(fig)


def test_single_cilium_thrust_curve_command(tmp_path, capsys):
    from single_cilium.cli import main

    png = tmp_path / "thrust.png"
    assert main(["thrust-curve", "--png", str(png), "--points", "60", "--dpi", "80", "--json"]) == 0
    assert png.stat().st_size > 10_000
    out = capsys.readouterr().out
    assert '"chi_N_cutoff": 162.77' in out and '"thrust_norm_error_max"' in out
    assert main(["thrust-curve", "--png", str(png)]) == 2  # an existing figure is kept without --overwrite
    assert "--overwrite" in capsys.readouterr().err
