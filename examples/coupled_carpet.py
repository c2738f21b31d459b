"""Cilia that feel the flow: a coupled carpet
===========================================

Each cilium beats in the flow all the others make; ``coupling = "mean"`` solves for that flow
self-consistently (damped Newton steps on the others' mean flow at every cilium's force centre).
It reads each cilium's cycle from a thrust table over the background flow (chi_N x U_par x U_perp).
Here that table is a coarse one built in seconds (degree 6, 32 phases, flows -1, 0, 1 in each
component): enough for a 3 x 3 carpet, whose coupled flows stay well inside it. A production
table uses the shipped discretisation (``single-cilium table ... --flow``, minutes on 2 cores).

Velocities in L / tau, at each cilium's force centre.

Results: ``residual`` (the Newton residual of the coupled flow, L/tau), ``speed_ratio`` (the
median coupled speed over the uncoupled one at the cilia: below 1, the cilia push against the
flow they make) and ``steps`` (Newton steps taken).
"""
from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet
from single_cilium.table import build_table

flow_table = build_table(200, 1, [0.0, 40.0, 80.0, 120.0, 160.0], U_par=[-1.0, 0.0, 1.0],
                         U_perp=[-1.0, 0.0, 1.0], degree=6, n_phase=32, n_s=17, error_estimate=False)
bases = layout.square(3, 3, 2.0)
carpet = Carpet(bases, 92.0, flow_table, layout.random_phases(9, seed=0), coupling="mean")
solution = carpet.coupled                      # the coupled flow at every cilium and how it was solved
residual = float(solution.residual)
steps = int(solution.iterations)
change = solution.change()
speed_ratio = change["median_speed_coupled"] / change["median_speed_uncoupled"]

if __name__ == "__main__":
    print(f"coupled in {steps} Newton steps to a residual of {residual:.1e} L/tau; the coupled speed at the "
          f"cilia is {speed_ratio:.2f} of the uncoupled one")
