"""Stability maps
==============

The two stability studies of the published work, with Hopf boundaries traced by continuation.

(a) chi_E in [-50, 150], eta in [0.1, 2.5], for chi_N = 0 and chi_N = 0.01*2pi side by side: for
    chi_E < 0 the tiny natural curvature removes flutter (the equilibrium folds over; see the
    docstring of single_cilium.stability), for chi_E > 0 it changes nothing.
(b) chi_E in [90, 300], eta in [0.1, 2.5], for chi_N in {0, 8, 16, 24}*2pi: raising chi_N raises
    the critical chi_E and lowers the flutter frequency.

Flutter points are coloured by the frequency beta/2pi; red curves are the boundaries. The grids
are 106 x 49 as published (set CILIA_EXAMPLE_QUICK=1 for a coarse 12 x 7 run).
Run as a script it writes stability_maps_a.png and stability_maps_b.png.
"""
import os

import numpy as np

from single_cilium.stability import flutter_boundary, stability_map

QUICK = os.environ.get("CILIA_EXAMPLE_QUICK") == "1"
N_CHI_E, N_ETA = (12, 7) if QUICK else (106, 49)
TWO_PI = 2 * np.pi
ETA = np.linspace(0.1, 2.5, N_ETA)

study_a = {}
for chi_N in (0.0, 0.01 * TWO_PI):
    grid = stability_map(chi_N, chi_E=np.linspace(-50, 150, N_CHI_E), eta=ETA)
    study_a[chi_N] = (grid, flutter_boundary(chi_N, chi_E=(-50, 150), eta=(0.1, 2.5)))

study_b = {}
for k in (0, 8, 16, 24):
    grid = stability_map(k * TWO_PI, chi_E=np.linspace(90, 300, N_CHI_E), eta=ETA)
    study_b[k] = (grid, flutter_boundary(k * TWO_PI, chi_E=(90, 300), eta=(0.1, 2.5)))

# headline numbers: flutter fraction of each grid, and the lowest critical chi_E of study (b)
flutter_fraction_a = {c: float((g.regime == 1).mean()) for c, (g, _) in study_a.items()}
lowest_critical_chi_E_b = {k: float(min(br[:, 1].min() for br in b.branches)) if b.branches else np.nan
                           for k, (_, b) in study_b.items()}

if __name__ == "__main__":
    import matplotlib.pyplot as plt

    from single_cilium.figures import frequency_norm, plot_stability_map

    # one colour bar per figure, so one normalisation for all its panels
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True, layout="constrained")
    norm = frequency_norm([g for g, _ in study_a.values()])
    for ax, (chi_N, (grid, bnd)) in zip(axes, study_a.items()):
        m = plot_stability_map(grid, ax, bnd, title=rf"$\chi_N$ = {chi_N / TWO_PI:g} $\cdot 2\pi$", norm=norm)
    fig.colorbar(m, ax=axes, label=r"flutter frequency $\beta/2\pi$  [$1/\tau$]")
    if QUICK:  # say so on the picture: the gallery shows this coarse run
        fig.suptitle(f"quick mode: a coarse {N_CHI_E} x {N_ETA} grid (published: 106 x 49)", fontsize=9)
    fig.savefig("stability_maps_a.png", dpi=150)
    fig, axes = plt.subplots(1, 4, figsize=(16, 4), sharey=True, layout="constrained")
    norm = frequency_norm([g for g, _ in study_b.values()])
    for ax, (k, (grid, bnd)) in zip(axes, study_b.items()):
        m = plot_stability_map(grid, ax, bnd, title=rf"$\chi_N$ = {k} $\cdot 2\pi$", norm=norm)
    fig.colorbar(m, ax=axes, label=r"flutter frequency $\beta/2\pi$  [$1/\tau$]")
    if QUICK:
        fig.suptitle(f"quick mode: a coarse {N_CHI_E} x {N_ETA} grid (published: 106 x 49)", fontsize=9)
    fig.savefig("stability_maps_b.png", dpi=150)
    print("flutter fraction (a):", flutter_fraction_a)
    print("lowest critical chi_E (b):", lowest_critical_chi_E_b)
