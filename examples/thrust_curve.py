"""The thrust curve
================

The design curve: thrust magnitude and angle against chi_N under one field (chi_E = 200,
eta = 1), from the shipped lookup table, with the equilibrium's theta_lim. Curvature tilts the
thrust: the angle follows theta_lim (a little above it) and the magnitude falls to zero at the
flutter cutoff. Run as a script it writes thrust_curve.png, each curve with its error estimate
(``single-cilium thrust-curve --png thrust_curve.png`` draws the same figure).
"""
import numpy as np

from single_cilium.table import ThrustTable

table = ThrustTable.default()
cutoff = float(table.ds.attrs["chi_N_cutoff"])
chi_N = np.linspace(0.0, cutoff, 200)
rows = [table.at(c) for c in chi_N]
thrust_norm = np.array([float(r.thrust_norm) for r in rows])
thrust_angle = np.array([float(r.thrust_angle) if c < cutoff else np.nan for r, c in zip(rows, chi_N)])
theta_lim = np.array([float(r.theta_lim) for r in rows])

if __name__ == "__main__":
    from single_cilium.figures import plot_thrust_curve

    fig = plot_thrust_curve(table)  # with the error bands, and the error estimates in a panel below
    fig.savefig("thrust_curve.png", dpi=150)
