"""Matplotlib figures of the toolkit's results (imported lazily: matplotlib is only needed here).

Each figure is drawn for print: every panel sharing a colour bar shares its normalisation, every
curve of a computed quantity carries its error estimate, and every label lies inside the canvas
(the figures use matplotlib's constrained layout).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import xarray as xr

__all__ = ["frequency_norm", "plot_stability_map", "plot_thrust_curve"]


def frequency_norm(maps: Sequence[xr.Dataset]):
    """One colour normalisation of the flutter frequency ``beta / 2 pi`` for all of ``maps``
    (:func:`~single_cilium.stability.stability_map` Datasets): from the lowest to the highest
    frequency on any of them, so that side-by-side panels under one colour bar show equal values
    in equal colours. ``Normalize(0, 1)`` when no map has a flutter point."""
    import matplotlib

    f = np.concatenate([np.ravel(m.frequency.values) for m in maps]) if maps else np.array([])
    f = f[np.isfinite(f)]
    if not f.size:
        return matplotlib.colors.Normalize(0.0, 1.0)
    lo, hi = float(f.min()), float(f.max())
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    return matplotlib.colors.Normalize(lo, hi)


def plot_stability_map(ds: xr.Dataset, ax=None, boundary=None, title: str | None = None, norm=None):
    """Draw a :func:`~single_cilium.stability.stability_map` Dataset on ``ax``.

    Flutter points are coloured by frequency ``beta / 2 pi`` (in units of ``1 / tau``); stable
    points are light grey, divergence dark grey, coiled (not computed) hatched white.
    ``boundary`` (a :class:`~single_cilium.stability.FlutterBoundary`) is drawn over the grid.
    ``norm``: the colour normalisation of the frequency; give panels that share a colour bar the
    same one (:func:`frequency_norm`); default this map's own range. Axes: eta horizontally,
    chi_E vertically, as in the published maps. Returns the colour mappable.
    """
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    if ax is None:
        _, ax = plt.subplots(figsize=(5, 4), layout="constrained")
    eta, chi_E = ds.eta.values, ds.chi_E.values
    regime = ds.regime.values
    background = np.where(regime == 0, 0.0, np.where(regime == 2, 1.0, np.nan))
    ax.pcolormesh(eta, chi_E, background, cmap=ListedColormap(["0.9", "0.5"]), vmin=0, vmax=1,
                  shading="nearest")
    if np.any(regime == 3):
        coiled = np.where(regime == 3, 1.0, np.nan)
        ax.contourf(eta, chi_E, coiled, levels=[0.5, 1.5], colors="none", hatches=["//"])
    mappable = ax.pcolormesh(eta, chi_E, ds.frequency.values, cmap="viridis", shading="nearest",
                             norm=norm if norm is not None else frequency_norm([ds]))
    for br in (boundary.branches if boundary is not None else []):
        ax.plot(br[:, 0], br[:, 1], "r-", lw=1.5)
    ax.set_xlabel(r"$\eta$")
    ax.set_ylabel(r"$\chi_E$")
    ax.set_title(title if title is not None else rf"$\chi_N$ = {ds.attrs['chi_N']:.4g}")
    return mappable


def plot_thrust_curve(table, n: int = 400, fig=None):
    """The design curve of one field: the mean thrust ``|Fbar|`` and its angle against chi_N
    (``0 <= chi_N <`` the flutter cutoff; negative chi_N mirrors the angle), from ``table`` (a
    :class:`~single_cilium.table.ThrustTable` of one field in still fluid), with their error
    estimates.

    Top panel: ``|Fbar|`` (units ``B / L^2``, left axis) and the thrust angle (rad, right axis;
    ``thrust_angle = phi_Fbar - pi``, MODEL.md section 5) with the equilibrium's ``theta_lim``,
    each with a band of +-its error estimate (the rows' discretisation error, interpolated, plus
    the interpolation error between rows); the cutoff dashed. Bottom panel: those error
    estimates on a log scale (absolute: ``B / L^2`` and rad), so that bands too thin to see
    above are read off here. ``n`` points in chi_N. Returns the figure.
    """
    import matplotlib.pyplot as plt

    cutoff = float(table.ds.attrs["chi_N_cutoff"])
    chi = np.linspace(0.0, cutoff, n, endpoint=False)
    norm = table.scalar("thrust_norm", chi)
    angle = table.scalar("thrust_angle", chi)
    rows = table.ds.chi_N.values

    def error(name):
        own = np.interp(chi, rows, np.nan_to_num(table.ds[f"{name}_error"].values))
        return own + np.abs(table.interpolation_error(name, chi))

    e_norm, e_angle = error("thrust_norm"), error("thrust_angle")
    theta_lim = np.array([float(table.at(c).theta_lim) for c in chi])
    if fig is None:
        fig = plt.figure(figsize=(7.0, 6.2), layout="constrained")
    ax, ax_err = fig.subplots(2, 1, sharex=True, height_ratios=[2.2, 1])
    ax.fill_between(chi, norm - e_norm, norm + e_norm, color="C0", alpha=0.3, lw=0)
    ax.plot(chi, norm, "C0", label=r"$|\bar F|$ (left)")
    ax.set_ylabel(r"$|\bar F|$  [$B/L^2$]")
    ax.axvline(cutoff, color="0.4", ls="--", lw=1)
    ax.text(cutoff, 0.5, f"flutter cutoff {cutoff:.5g} ", transform=ax.get_xaxis_transform(), ha="right",
            va="center", fontsize=8, color="0.3", rotation=90)
    ax2 = ax.twinx()
    ax2.fill_between(chi, angle - e_angle, angle + e_angle, color="C1", alpha=0.3, lw=0)
    ax2.plot(chi, angle, "C1", label="thrust angle (right)")
    ax2.plot(chi, theta_lim, "k:", label=r"equilibrium $\theta_{lim}$ (right)")
    ax2.set_ylabel("angle  [rad]")
    lines = ax.get_lines()[:1] + ax2.get_lines()
    ax.legend(lines, [ln.get_label() for ln in lines], loc="center left", fontsize=8)
    ax.set_title(rf"mean thrust against $\chi_N$: $\chi_E$ = {table.ds.attrs['chi_E']:g}, "
                 rf"$\eta$ = {table.ds.attrs['eta']:g} (bands: $\pm$ error estimate)", fontsize=10)
    ax_err.semilogy(chi, np.maximum(e_norm, 1e-17), "C0", label=r"$|\bar F|$ [$B/L^2$]")
    ax_err.semilogy(chi, np.maximum(e_angle, 1e-17), "C1", label="angle [rad]")
    ax_err.set_xlabel(r"natural curvature $\chi_N$")
    ax_err.set_ylabel("error estimate")
    top = float(max(e_norm.max(), e_angle.max()))
    ax_err.set_ylim(top * 1e-3, top * 30)  # three decades below the largest, room above for the legend
    ax_err.legend(loc="upper center", fontsize=8, ncol=2)
    ax_err.set_xlim(0.0, cutoff)
    return fig
