"""Matplotlib figures of the toolkit's results (imported lazily: matplotlib is only needed here)."""
from __future__ import annotations

import numpy as np
import xarray as xr

__all__ = ["plot_stability_map"]


def plot_stability_map(ds: xr.Dataset, ax=None, boundary=None, title: str | None = None):
    """Draw a :func:`~single_cilium.stability.stability_map` Dataset on ``ax``.

    Flutter points are coloured by frequency ``beta / 2 pi``; stable points are light grey,
    divergence dark grey, coiled (not computed) hatched white. ``boundary`` (a
    :class:`~single_cilium.stability.FlutterBoundary`) is drawn over the grid. Axes: eta
    horizontally, chi_E vertically, as in the published maps. Returns the colour mappable.
    """
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    if ax is None:
        _, ax = plt.subplots(figsize=(5, 4))
    eta, chi_E = ds.eta.values, ds.chi_E.values
    regime = ds.regime.values
    background = np.where(regime == 0, 0.0, np.where(regime == 2, 1.0, np.nan))
    ax.pcolormesh(eta, chi_E, background, cmap=ListedColormap(["0.9", "0.5"]), vmin=0, vmax=1,
                  shading="nearest")
    if np.any(regime == 3):
        coiled = np.where(regime == 3, 1.0, np.nan)
        ax.contourf(eta, chi_E, coiled, levels=[0.5, 1.5], colors="none", hatches=["//"])
    mappable = ax.pcolormesh(eta, chi_E, ds.frequency.values, cmap="viridis", shading="nearest")
    for br in (boundary.branches if boundary is not None else []):
        ax.plot(br[:, 0], br[:, 1], "r-", lw=1.5)
    ax.set_xlabel(r"$\eta$")
    ax.set_ylabel(r"$\chi_E$")
    ax.set_title(title if title is not None else rf"$\chi_N$ = {ds.attrs['chi_N']:.4g}")
    return mappable
