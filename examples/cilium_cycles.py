"""Limit cycles of one cilium
==========================

The limit cycles at chi_N in {8, 16, 24}*2pi (chi_E = 200, eta = 1).

For each cycle: filament snapshots over one period with the clamp force F (force on the fluid)
as arrows, the tip orbit (its enclosed area measures the non-reciprocity), and ``|F(t)|`` and its
angle over a period with the means. The mean thrust is much smaller than ``|F(t)|``, and its angle
(phi_Fbar - pi) lies a little above the equilibrium's theta_lim.
Run as a script it writes cilium_cycles.png (CILIA_EXAMPLE_QUICK=1 for a coarse, fast run).
"""
import os

import numpy as np

import single_cilium as sc

QUICK = os.environ.get("CILIA_EXAMPLE_QUICK") == "1"
SETTINGS = dict(degree=6, n_phase=32, error_estimate=False) if QUICK else dict(degree=8, n_phase=64)

cycles = {k: sc.limit_cycle(sc.CiliumParams(200.0, 1.0, k * 2 * np.pi), **SETTINGS) for k in (8, 16, 24)}
summary = {k: (c.period, c.thrust_norm, c.thrust_angle, c.theta_lim, c.tip_area) for k, c in cycles.items()}

if __name__ == "__main__":
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 3, figsize=(13, 11))
    for row, (k, c) in zip(axes, cycles.items()):
        d = c.data
        ax = row[0]
        for j in range(0, d.sizes["phase"], max(1, d.sizes["phase"] // 8)):
            ax.plot(d.x[j], d.y[j], lw=0.8)
            ax.arrow(0, 0, 0.5 * float(d.Fx[j]), 0.5 * float(d.Fy[j]), width=0.004, color="k", alpha=0.4)
        ax.arrow(0, 0, 0.5 * c.thrust_x, 0.5 * c.thrust_y, width=0.01, color="r")
        ax.set(aspect="equal", xlabel="x [L]", ylabel="y [L]",
               title=rf"$\chi_N$ = {k}$\cdot 2\pi$: shapes, F/2 (black), mean (red)")
        tip_x, tip_y = np.append(d.x[:, -1], d.x[0, -1]), np.append(d.y[:, -1], d.y[0, -1])  # closed orbit
        row[1].plot(tip_x, tip_y)
        row[1].set(aspect="equal", xlabel="x [L]", ylabel="y [L]", title=f"tip orbit, area {c.tip_area:.2e} L$^2$")
        t = np.append(d.phase, 1.0) * c.period
        Fx, Fy = np.append(d.Fx, d.Fx[0]), np.append(d.Fy, d.Fy[0])
        Fn = np.hypot(Fx, Fy)
        # the instantaneous thrust angle in the convention of thrust_angle (phi_F - pi), unwrapped and
        # shifted by whole turns to lie about the mean's angle
        ang = np.unwrap(np.arctan2(-Fx, Fy) - np.pi)
        ang -= 2 * np.pi * np.round((np.mean(ang) - c.thrust_angle) / (2 * np.pi))
        row[2].plot(t, Fn, label="|F(t)|")
        row[2].axhline(c.thrust_norm, color="C0", ls="--", label="|mean F|")
        r2 = row[2].twinx()
        r2.plot(t, ang, color="C1")
        r2.axhline(c.thrust_angle, color="C1", ls="--")
        r2.axhline(c.theta_lim, color="k", ls=":")
        r2.set_ylabel("angle [rad]")
        row[2].set(xlabel="t [tau]", ylabel="|F| [B/L$^2$]",
                   title="|F| (blue), angle (orange), means dashed,\ntheta_lim (dotted)")
    if QUICK:  # say so on the picture: the gallery shows this coarse run
        fig.suptitle("quick mode: degree 6, 32 phases, no error estimates (run without CILIA_EXAMPLE_QUICK for "
                     "the converged cycles)", fontsize=9)
    fig.tight_layout()
    fig.savefig("cilium_cycles.png", dpi=110)
    for k, v in summary.items():
        print(k, "period %.7f  |Fbar| %.7f  angle %.7f  theta_lim %.7f  area %.3e" % v)
