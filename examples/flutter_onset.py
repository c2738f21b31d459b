"""Flutter onset
=============

The flutter onset of the published cilium (chi_E = 200, eta = 1, chi_N = 16*2pi).

A small perturbation of the equilibrium grows into an oscillation: the clamp force F(t) (the force
the filament exerts on the fluid) oscillates with a growing amplitude. The script measures the
oscillation period from the zero crossings of F_x and the growth of its envelope, and (run as a
script) plots F(t) and the tip orbit over the last two periods to ``flutter_onset.png``.
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
    ax1.set(xlabel="t / tau", ylabel="clamp force (B/L^2)", title=f"period {period:.4f}, growth {growth_rate:.3f}")
    ax1.legend()
    late = t > t[-1] - 2 * period
    tip_x = sim.data.x.values[:, -1] - sim.data.x.values[0, -1]
    tip_y = sim.data.y.values[:, -1] - sim.data.y.values[0, -1]
    ax2.plot(tip_x[late], tip_y[late])
    ax2.set(aspect="equal", xlabel="tip x - x_eq", ylabel="tip y - y_eq",
            title="tip orbit over the last two periods")
    fig.tight_layout()
    fig.savefig("flutter_onset.png", dpi=120)
    print(f"period {period:.6f}, growth rate {growth_rate:.4f}, error estimate {sim.error:.1e}")
