"""Cilia that feel the flow: a coupled carpet
===========================================

Each cilium beats in the flow all the others make; ``coupling = "mean"`` (the default of every
scene) solves for that flow self-consistently: damped Newton steps on the others' mean flow at
every cilium's force centre. Each cilium's cycle is read from a thrust table over the background
flow (chi_N x U_par x U_perp): for the shipped field (chi_E = 200, eta = 1) the one that ships
with the package, ``ThrustTable.default(flow=True)``; another field builds its own
(``single-cilium table ... --U-par=-1.5:1.5:7 --U-perp=-1.5:1.5:7``, minutes on 2 cores).

Velocities in L / tau, at each cilium's force centre.

Results: ``residual`` (the Newton residual of the coupled flow, relative to the largest flow),
``speed_ratio`` (the median coupled speed over the uncoupled one at the cilia: below 1, the cilia
push against the flow they make), ``steps`` (Newton steps taken) and ``coupled_speed`` (the median
coupled speed, L/tau).
"""
from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet
from single_cilium.table import ThrustTable

flow_table = ThrustTable.default(flow=True)    # the shipped table over the background flow
bases = layout.square(5, 5, 2.0)
carpet = Carpet(bases, 92.0, flow_table, layout.random_phases(25, seed=0), coupling="mean")
solution = carpet.coupled                      # the coupled flow at every cilium and how it was solved
residual = float(solution.residual)
steps = int(solution.iterations)
change = solution.change()
coupled_speed = change["median_speed_coupled"]
speed_ratio = coupled_speed / change["median_speed_uncoupled"]

if __name__ == "__main__":
    print(f"coupled in {steps} Newton steps to a residual of {residual:.1e}; the coupled speed at the cilia is "
          f"{coupled_speed:.3f} L/tau, {speed_ratio:.2f} of the uncoupled one")
