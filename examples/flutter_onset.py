"""Flutter onset
=============

The flutter onset of the published cilium (chi_E = 200, eta = 1, chi_N = 16*2pi).

A small perturbation of the equilibrium grows into an oscillation: the clamp force F(t) (the force
the filament exerts on the fluid) oscillates with a growing amplitude. The script measures the
oscillation period from the zero crossings of F_x and the growth of its envelope, and (run as a
script) plots F(t) and the tip's phase portrait (its displacement against its rate: a growing
spiral) to ``flutter_onset.png``.
"""
import numpy as np

import single_cilium as sc

params = sc.CiliumParams(chi_E=200.0, eta=1.0, chi_N=16 * 2 * np.pi)
sim = sc.simulate(params, t_end=3.0, n_out=1501, amplitude=1e-4)

t = sim.data.time.values
Fx = sim.data.Fx.values
late = t > 1.0
up = np.nonzero((Fx[:-1] < 0) & (Fx[1:] >= 0) & late[:-1])[0]
# linear interpolation of the upward zero crossings
crossings = t[up] - Fx[up] * (t[up + 1] - t[up]) / (Fx[up + 1] - Fx[up])
period = float(np.mean(np.diff(crossings)))
amp = [np.max(np.abs(Fx[(t >= a) & (t < b)])) for a, b in zip(crossings[:-1], crossings[1:])]
growth_rate = float(np.mean(np.diff(np.log(amp))) / period)

if __name__ == "__main__":
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    ax1.plot(t, sim.data.Fx, label="$F_x$")
    ax1.plot(t, sim.data.Fy, label="$F_y$")
    ax1.set(xlabel="t / tau", ylabel="clamp force  [B/L$^2$]", title=f"period {period:.4f}, growth {growth_rate:.3f}")
    ax1.legend()
    # the tip moves along a line at this amplitude (the growing mode's x and y are in phase), so
    # the panel shows that displacement q against its rate dq/dt: an outward spiral, one turn a period
    tip = np.column_stack([sim.data.x.values[:, -1], sim.data.y.values[:, -1]])
    tip = tip - tip[0]
    direction = np.linalg.svd(tip[t > 1.0], full_matrices=False)[2][0]
    q = tip @ direction
    q = q - q[t > 1.0].mean()
    qdot = np.gradient(q, t)
    eq, ev = (int(np.floor(np.log10(np.abs(v[t > 1.0]).max()))) for v in (q, qdot))
    ax2.plot(q[t > 1.0] / 10.0 ** eq, qdot[t > 1.0] / 10.0 ** ev, lw=0.9)
    ax2.set(xlabel=f"tip displacement q along its line of motion  [$10^{{{eq}}}$ L]",
            ylabel=f"dq/dt  [$10^{{{ev}}}$ L/tau]", title="tip: phase portrait for t > 1 (a growing spiral)")
    fig.tight_layout()
    fig.savefig("flutter_onset.png", dpi=150)
    print(f"period {period:.6f}, growth rate {growth_rate:.4f}, error estimate {sim.error:.1e}")
