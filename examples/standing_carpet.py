"""Standing cilia: surface flows in any direction
===============================================

In the usual device the cilia stand on the chip's floor (the no-slip substrate z = 0) and the
field is normal to it (+z). Cilium j's beat plane is turned about the normal by its azimuth psi_j,
and its mean thrust leans towards psi_j by its thrust angle (chi_N), so a layout (chi_N, psi) can
make a flow on a plane above the cilia (the *surface flow*) turn, circulate and come back. This
script designs a mixer (two counter-rotating vortices) on a 6 x 6 standing carpet and evaluates
the designed carpet's flow in space.

Lengths in L, velocities in L / tau, angles in radians anticlockwise from +x.

Results: ``mixer_rms`` and ``mixer_error`` (the design's rms direction residual on the plane
z = 1.5 L and its error bar, rad) and ``wall_speed`` (the largest speed on the substrate,
L/tau: zero by the no-slip condition, to rounding).
"""
import numpy as np

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.design.surface import design_surface
from ciliary_carpet.design.surface_target import surface_directions
from ciliary_carpet.design import Frame, control_points
from single_cilium.table import ThrustTable

table = ThrustTable.default()
spacing = 2.0
bases = layout.square(6, 6, spacing) - 5.0                       # centred on the origin
carpet = Carpet(bases, 60.0, table, layout.random_phases(36, seed=1), wall=0.0, geometry="standing",
                azimuth=np.zeros(36))                            # on the substrate, beat planes along +x
X = control_points(bases, Frame(np.zeros(2), np.array([0.0, -1.0]), spacing), "cells")
A, keep = surface_directions("mixer", X, (0.0, 0.0), spacing, angle=0.0, separation=5.0)
d = design_surface(carpet, X[keep], directions=A, height=1.5, threshold=0.1)
mixer_rms, mixer_error = float(d.residual_rms), float(d.residual_error)

# the designed carpet's flow in space: on the substrate (no slip) and on the target plane
on_wall = np.column_stack([X, np.zeros(len(X))])
wall_speed = float(np.abs(d.carpet.evaluate(on_wall, CycleMean(), tol=1e-3).velocity).max())
plane = d.carpet.evaluate(np.column_stack([X, np.full(len(X), 1.5)]), CycleMean(), tol=1e-3)

if __name__ == "__main__":
    print(f"mixer: rms {mixer_rms:.3g} rad +- {mixer_error:.2g}; chi_N {d.chi_N.min():.3g}..{d.chi_N.max():.3g}; "
          f"speed on the plane up to {np.linalg.norm(plane.velocity, axis=1).max():.3g} L/tau, on the wall "
          f"{wall_speed:.1e}")
