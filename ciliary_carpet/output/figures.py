"""The render's pictures: ``design.png`` and ``preview.png`` (matplotlib, Agg), written atomically
with the usual permissions."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from cilia_runtime.files import usual_mode

from ciliary_carpet.carpet.carpet import Carpet

__all__ = ["chi_N_colours", "design_picture", "preview", "standing_preview"]

ARROWS_MAX = 400
"""Most control points whose arrows ``design.png`` draws (an even subset beyond it): more arrows
than that overlap into a mass at the figure's size."""


def chi_N_colours(chi_N: np.ndarray):
    """The colour map and normalisation that show a layout's curvatures ``chi_N`` (any shape).

    A layout of one sign (every ``chi_N >= 0``, or every ``chi_N <= 0``) gets a sequential map
    (viridis, dark at the low end so that no cilium fades into the background) over exactly its range, so that a design of 85..96 shows its variation instead of one shade
    of a +-cutoff scale; a layout of both signs gets a diverging map symmetric about 0 (blue
    negative, red positive: the sign is the side a cilium's thrust leans to). A layout of one
    value gets a range of +-1 about it (or +-1e-9 relative), so the map is never degenerate.
    Returns ``(cmap, norm)`` for matplotlib.
    """
    import matplotlib
    import matplotlib.pyplot as plt

    c = np.asarray(chi_N, dtype=float)
    c = c[np.isfinite(c)]
    lo, hi = (float(c.min()), float(c.max())) if c.size else (0.0, 0.0)
    if lo < 0 < hi:
        lim = max(-lo, hi)
        return plt.get_cmap("coolwarm"), matplotlib.colors.Normalize(-lim, lim)
    if hi - lo <= 1e-9 * max(1.0, abs(hi)):
        pad = max(1.0, 1e-9 * abs(hi))
        lo, hi = lo - pad, hi + pad
    return plt.get_cmap("viridis"), matplotlib.colors.Normalize(lo, hi)


def _spacing(points: np.ndarray) -> float:
    """The median distance from each of ``points`` (n, 2) to its nearest neighbour (1 for one
    point)."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return 1.0
    d, _ = cKDTree(points).query(points, k=2)
    d = d[:, 1][d[:, 1] > 0]
    return float(np.median(d)) if d.size else 1.0


def _savefig(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".png", dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110)
        os.chmod(tmp, usual_mode())  # mkstemp creates 0600; the usual permissions, like the other files
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        Path(tmp).unlink(missing_ok=True)


def design_picture(path: Path, name: str, carpet: Carpet, d) -> None:
    """Three panels: target (grey) and achieved (blue) flow directions at the control points
    (at most :data:`ARROWS_MAX` of them, an even subset beyond) over the layout coloured by
    chi_N; the residual per control point; the layout coloured by chi_N (over its own range,
    :func:`chi_N_colours`) with the cilia of weak push (``d.near_cutoff``) ringed. ``d`` is the
    :class:`~ciliary_carpet.design.result.Design`; ``name`` (the scene's) begins the title. Every
    label lies inside the canvas."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    X, b = d.control, carpet.bases
    lim = float(carpet.table.in_still_fluid().flutter_range[1])
    cmap, norm = chi_N_colours(carpet.chi_N)
    fig, axs = plt.subplots(1, 3, figsize=(17, 6.6), layout="constrained")
    shown = np.arange(len(X))
    if len(X) > ARROWS_MAX:  # an even subset: every k-th control point
        shown = shown[:: -(-len(X) // ARROWS_MAX)]
    scale = 0.8 * _spacing(X[shown])

    def arrows(ax, v, **kw):
        v = v[shown]
        n = np.maximum(np.linalg.norm(v, axis=1), 1e-300)[:, None]
        vv = v / n * scale
        xs = X[shown]
        return ax.quiver(xs[:, 0] - 0.5 * vv[:, 0], xs[:, 1] - 0.5 * vv[:, 1], vv[:, 0], vv[:, 1], angles="xy",
                         scale_units="xy", scale=1, **kw)

    ax = axs[0]
    ax.scatter(b[:, 0], b[:, 1], c=carpet.chi_N, cmap=cmap, norm=norm, s=14, zorder=1)
    arrows(ax, d.target, color="0.6", width=0.009, zorder=2, label="target")
    arrows(ax, d.achieved, color="tab:blue", width=0.0035, zorder=3, label="achieved")
    ax.legend(loc="lower left", fontsize=8, framealpha=0.9)
    sub = "" if len(shown) == len(X) else f" ({len(shown)} of {len(X)} shown)"
    ax.set_title(f"mean-flow direction at the control points{sub}\ntarget (grey) vs achieved (blue), "
                 f"over the cilia (chi_N)", fontsize=10)
    ax = axs[1]
    unit = "rad" if d.kind == "angle" else "relative"
    sc = ax.scatter(X[:, 0], X[:, 1], c=d.residual, cmap="magma_r", vmin=0, s=40, marker="s")
    ax.scatter(b[:, 0], b[:, 1], c="0.7", s=6)
    fig.colorbar(sc, ax=ax, label=f"residual [{unit}]", shrink=0.85)
    ax.set_title(f"residual per control point\nrms {d.residual_rms:.3g} {unit} (model error at most "
                 f"{d.residual_error:.1g}), worst {d.residual.max():.3g}", fontsize=10)
    ax = axs[2]
    sc = ax.scatter(b[:, 0], b[:, 1], c=carpet.chi_N, cmap=cmap, norm=norm, s=40)
    nc = list(d.near_cutoff)
    if nc:
        ax.scatter(b[nc, 0], b[nc, 1], facecolors="none", edgecolors="k", s=110, lw=1.2,
                   label=f"{len(nc)} with a weak push (the design's near_cutoff)")
        ax.legend(loc="lower left", fontsize=8, framealpha=0.9)
    fig.colorbar(sc, ax=ax, label=f"chi_N (flutter for |chi_N| < {lim:.5g})", shrink=0.85)
    ax.set_title(f"layout: chi_N from {carpet.chi_N.min():.4g} to {carpet.chi_N.max():.4g}", fontsize=10)
    if getattr(d, "azimuth", None) is not None:  # a standing carpet: each cilium's pumping direction
        e = np.column_stack([np.cos(d.azimuth), np.sin(d.azimuth)]) * np.sign(carpet.chi_N)[:, None]
        sp = _spacing(b)
        ax.quiver(b[:, 0], b[:, 1], e[:, 0], e[:, 1], angles="xy", scale_units="xy", scale=1.4 / sp, width=0.004,
                  color="k", zorder=3)
        ax.set_title(f"layout: chi_N from {carpet.chi_N.min():.4g} to {carpet.chi_N.max():.4g}; arrows: the "
                     "beat planes'\nazimuths psi, where each cilium's thrust leans (standing)", fontsize=10)
    for ax in axs:
        ax.set_aspect("equal")
        ax.set_xlabel("x / L")
        ax.set_ylabel("y / L")
    fig.suptitle(f"{name}: design ({d.kind} target, {len(X)} control points; without the design, each "
                 f"cilium curved for the target on its own: rms {d.local_rms:.3g} {unit})", fontsize=11)
    _savefig(fig, path)


def _streamlines(ax, mean_field, bars: list, label: str, lw: float, arrowsize: float) -> None:
    """Draw the in-plane streamlines of ``mean_field`` (a MeanField on a plane) coloured by their
    speed, and append their colour bar (with ``label``) to ``bars``."""
    import matplotlib

    shape, pts, u = mean_field.grid.shape, mean_field.points, mean_field.velocity
    X = pts[:, 0].reshape(shape[1], shape[0])
    Y = pts[:, 1].reshape(shape[1], shape[0])
    U = np.nan_to_num(u[:, 0]).reshape(X.shape)
    W = np.nan_to_num(u[:, 1]).reshape(X.shape)
    sp = np.hypot(U, W)
    norm = matplotlib.colors.Normalize(0.0, float(sp.max()) if sp.max() > 0 else 1.0)
    ax.streamplot(X, Y, U, W, color=sp, cmap="Blues", norm=norm, density=1.4, linewidth=lw, arrowsize=arrowsize)
    bars.append((matplotlib.cm.ScalarMappable(norm=norm, cmap="Blues"), label))


PREVIEW_POINTS = 400
"""Most samples of one tracer the preview draws (evenly strided, its end point kept)."""


def _pathlines_from_above(ax, pl, bars: list, label: str) -> None:
    """Draw the path lines ``pl`` projected on the plane (x, y), coloured by time, and their end
    points; append their colour bar (with ``label``) to ``bars``. Nothing without path lines."""
    from matplotlib.collections import LineCollection

    if pl is None or not len(pl.points):
        return
    # at most PREVIEW_POINTS samples a tracer (its last kept): a picture shows no more, and
    # matplotlib makes a path per segment (a million of them took 6 s)
    keep = [np.unique(np.append(np.arange(0, len(p), max(1, -(-len(p) // PREVIEW_POINTS))), len(p) - 1))
            for p in pl.points]
    pts = [p[k] for p, k in zip(pl.points, keep)]
    tms = [t[k] for t, k in zip(pl.times, keep)]
    segs = [np.stack([p[:-1, :2], p[1:, :2]], axis=1) for p in pts if len(p) > 1]
    if segs:
        tt = np.concatenate([0.5 * (t[:-1] + t[1:]) for p, t in zip(pts, tms) if len(p) > 1])
        lc = LineCollection(np.concatenate(segs), cmap="autumn", lw=0.6, alpha=0.85)
        lc.set_array(tt)
        ax.add_collection(lc)
        bars.append((lc, label))
    e = pl.end_points
    ax.plot(e[:, 0], e[:, 1], ".", color="k", ms=2)


def preview(path: Path, name: str, carpet: Carpet, mean_field, pl, d) -> None:
    """The render at a glance: the mean flow's streamlines (coloured by mean speed), the path
    lines (coloured by time, their end points in black) and the cilia at t = 0 with their bases
    (coloured by chi_N); a colour bar for each colour. In the model's units (L, tau).

    ``mean_field`` is the render's :class:`~ciliary_carpet.output.contract.MeanField`, ``pl`` its
    path lines and ``d`` its design, each None when the render has none; ``name`` (the scene's)
    begins the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    fig = plt.figure(figsize=(9.6, 6.5))
    ax = fig.add_axes([0.08, 0.09, 0.62, 0.83])
    bars = []
    if mean_field is not None:
        _streamlines(ax, mean_field, bars, "streamlines: mean speed [L/tau]", 0.6, 0.7)
    _pathlines_from_above(ax, pl, bars, "path lines: time [tau]")
    pos, _, _ = carpet.state(0.0)
    cmap, norm = chi_N_colours(carpet.chi_N)
    # the cilia as one collection, drawn as lines are (zorder 2, projecting caps, round joins): one
    # artist per cilium takes seconds at 10^4 cilia
    ax.add_collection(LineCollection(pos[:, :, :2], colors=cmap(norm(carpet.chi_N)), lw=1.2,
                                     capstyle="projecting", joinstyle="round", zorder=2))
    sc = ax.scatter(carpet.bases[:, 0], carpet.bases[:, 1], c=carpet.chi_N, cmap=cmap, norm=norm,
                    s=12, zorder=3, edgecolors="k", linewidths=0.3)
    bars.insert(0, (sc, "cilia: chi_N"))
    for k, (m, label) in enumerate(bars):  # a colour bar for each colour, side by side at the right
        cb = fig.colorbar(m, cax=fig.add_axes([0.735 + 0.09 * k, 0.17, 0.016, 0.67]))
        cb.set_label(label, fontsize=9)
        cb.ax.tick_params(labelsize=8)
    title = name
    if d is not None:
        unit = f"{np.degrees(d.residual_rms):.2g} deg" if d.kind == "angle" else f"{d.residual_rms:.1%}"
        title += f"  (design: {unit} rms off the target)"
    ax.set_title(title)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x / L")
    ax.set_ylabel("y / L")
    _savefig(fig, path)


def standing_preview(path: Path, name: str, height: float, carpet: Carpet, mean_field, pl) -> None:
    """A standing carpet at a glance, a plan view (looking down -z): the mean flow in the target
    plane z = h (streamlines of its in-plane velocity, coloured by that speed), the path lines
    projected on the plane (coloured by time, their end points in black), and the cilia's
    footprints: each cilium's swept region over its beat projected on the substrate (its
    positions at the table's phase samples, a band along its beat plane) coloured by chi_N, with
    its base. A colour bar for each colour. In the model's units (L, tau).

    ``mean_field`` is the render's :class:`~ciliary_carpet.output.contract.MeanField` on the
    target plane and ``pl`` its path lines (3D), each None when the render has none; ``name`` (the
    scene's) begins the title, ``height`` is the target plane's h [L] (the mean field's own height
    when there is one)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    fig = plt.figure(figsize=(9.6, 6.5))
    ax = fig.add_axes([0.08, 0.09, 0.62, 0.83])
    bars = []
    h = float(height)
    if mean_field is not None:
        h = float(mean_field.points[0, 2])
        _streamlines(ax, mean_field, bars, f"streamlines: mean speed at z = {h:.3g} L [L/tau]", 0.7, 0.9)
    _pathlines_from_above(ax, pl, bars, "path lines (seen from above): time [tau]")
    cmap, norm = chi_N_colours(carpet.chi_N)
    ends = np.empty((carpet.n, 2, 2))
    for lo in range(0, carpet.n, 256):  # the footprints: the swept samples of each cilium, seen from above
        js = np.arange(lo, min(lo + 256, carpet.n))
        xs, _ = carpet.cycle_samples(js)  # (m, n_phase, n_s, 2) in each beat plane
        xyz = carpet.embedding.points(xs.reshape(js.size, -1, 2), js)  # (m, n_phase n_s, 3)
        e = np.stack([np.cos(carpet.azimuth[js]), np.sin(carpet.azimuth[js])], axis=1)  # (m, 2) along each plane
        along = np.einsum("kpa,ka->kp", xyz[:, :, :2] - carpet.bases[js][:, None], e)
        ends[js] = carpet.bases[js][:, None] + np.stack([along.min(axis=1), along.max(axis=1)], axis=1)[:, :, None] \
            * e[:, None]
    ax.add_collection(LineCollection(ends, colors=cmap(norm(carpet.chi_N)), lw=2.4, capstyle="round",
                                     alpha=0.9, zorder=2))
    sc = ax.scatter(carpet.bases[:, 0], carpet.bases[:, 1], c=carpet.chi_N, cmap=cmap, norm=norm,
                    s=10, zorder=3, edgecolors="k", linewidths=0.3)
    bars.insert(0, (sc, "cilia footprints: chi_N"))
    for k, (m, label) in enumerate(bars):
        cb = fig.colorbar(m, cax=fig.add_axes([0.735 + 0.09 * k, 0.17, 0.016, 0.67]))
        cb.set_label(label, fontsize=9)
        cb.ax.tick_params(labelsize=8)
    psi = np.round(np.degrees(carpet.azimuth), 9)
    az = f"azimuth {psi.min():.3g} deg" if np.ptp(psi) < 1e-9 else f"azimuths {psi.min():.3g}..{psi.max():.3g} deg"
    ax.set_title(f"{name}: standing cilia ({az}), mean flow at z = {h:.3g} L, seen from above", fontsize=10)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x / L")
    ax.set_ylabel("y / L")
    _savefig(fig, path)
