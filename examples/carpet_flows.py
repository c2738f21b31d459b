"""A carpet from Python: its flow, path lines and mixing
=======================================================

A 10 x 10 hexagonal carpet under the shipped field (chi_E = 200, eta = 1), its curvatures rising
from -100 to 100 across it, the field tilted 0.3 rad from +y. The script evaluates its flow with a
rigorous error bound (at one instant and averaged over the beat), follows tracers through the
time-resolved flow and through the mean flow, and measures the mean flow's mixing (FTLE).

Units: lengths in L (the cilium's length), times in tau (the gel's relaxation time), velocities
in L / tau. Positions are (x, y, z) with the carpet in the plane z = 0.

Results: ``speed_mean`` (the largest mean speed at the probe points, L/tau) with its
``bound_mean`` (the rigorous error bound there, L/tau), ``end_points`` (the mean-flow tracers'
end points (8, 3), L) and ``mixing_number`` (the mean log-stretching of the mean flow's tracers over
the FTLE's duration, dimensionless: 0 for a translation, larger for more stretching; negative
where the in-plane flow converges, as fluid leaves the plane).
"""
import numpy as np

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean, Instant
from ciliary_carpet.output.tracers import ftle_to_vti, pathlines_to_vtp
from ciliary_carpet.transport.flow import MeanFlow, ResolvedFlow
from ciliary_carpet.transport.ftle import ftle_field
from ciliary_carpet.transport.pathlines import pathlines
from single_cilium.table import ThrustTable

table = ThrustTable.default()                                   # (chi_E, eta) = (200, 1)
bases = layout.hexagonal(10, 10, spacing=2.0)                   # (100, 2); also row, square, points
chi_N = np.linspace(-100.0, 100.0, len(bases))                  # signed natural curvatures
carpet = Carpet(bases, chi_N, table, layout.random_phases(len(bases), seed=0),
                direction=0.3, wall=None)                       # field 0.3 rad from +y; free space

# probe points 1 L above the carpet's plane (z = 1): flow sums with their rigorous error bounds
xs = np.linspace(0.0, 18.0, 7)
points = np.array([[x, y, 1.0] for x in xs for y in xs])       # (49, 3), in L
now = carpet.evaluate(points, Instant(1.2), tol=1e-3)           # .velocity (49, 3), .error_bound (49,)
mean = carpet.evaluate(points, CycleMean(), tol=1e-3)           # the beat-averaged (steady) flow
speed_mean = float(np.linalg.norm(mean.velocity, axis=1).max())
bound_mean = float(mean.error_bound.max())

# tracers released in the carpet's plane: through the time-resolved flow for a few beats, and
# through the mean flow (the long-time model) on a box that is its domain
seeds = np.column_stack([np.linspace(2.0, 16.0, 8), np.full(8, 18.0)])   # (8, 2), in L
resolved = pathlines(ResolvedFlow(carpet, tol=1e-3), seeds, (0.0, 1.0))  # 16 points per beat
mean_flow = MeanFlow.from_carpet(carpet, (-10.0, 28.0, -10.0, 28.0))
long_run = pathlines(mean_flow, seeds, (0.0, 20.0))
end_points = long_run.end_points                                 # (8, 3), z = 0

# mixing: the finite-time Lyapunov exponents of the mean flow over 5 tau
ftle = ftle_field(mean_flow, (0.0, 18.0, 0.0, 18.0), (20, 20), 5.0)
mixing_number = float(ftle.mixing_number)

if __name__ == "__main__":
    import os
    from pathlib import Path

    OUT = Path(os.environ.get("CILIA_EXAMPLE_OUT", "out/carpet_flows"))  # the folder the files go to
    OUT.mkdir(parents=True, exist_ok=True)
    print(f"mean speed up to {speed_mean:.3g} L/tau (error bound {bound_mean:.1e}); mixing number "
          f"{mixing_number:.3g}")
    pathlines_to_vtp(resolved, OUT / "pathlines.vtp")             # polylines for ParaView
    ftle_to_vti(ftle, OUT / "ftle.vti")
