"""The rigorous bounds of the levels of detail, and the distances at which each order will do.

A cilium's flow at a point is summed at the cheapest order of its point-force carriers
(:mod:`~ciliary_carpet.carpet.carriers`: monopole, dipole, quadrupole) whose error bound meets the
tolerance. Their moment systems are invertible. By Taylor's theorem, for a target at distance R > a from c
the order-k carriers (matching the moments below order k) err by the order-k term they miss
plus a remainder:

    monopole:    8 pi mu |u - u_resolved| <= C1 nu(D) / R^2 + C2 Q2 / (2 (R - a)^3)
    dipole:      8 pi mu |u - u_resolved| <= C2 nu(T - T_rep) / (2 R^3) + C3 (Q3 + Q3_rep) / (6 (R - a)^4)
    quadrupole:  8 pi mu |u - u_resolved| <= C3 (Q3 + Q3_rep) / (6 (R - a)^4)

with Ck the supremum of |(h.grad)^k G f| over unit in-plane h, f at unit distance (times R^(k+1)
with a wall; :attr:`Kernel.c1 <ciliary_carpet.stokes.kernel.Kernel.c1>`, ``c2``, ``c3``: 2, 4, 16
free and 4, 16, 64 with a wall; sampled maxima 2, 4, 12.3 free, 1.98 for C1 and 12.9 for C3 with
a wall, tests/test_carpet.py), T_rep and Q3_rep = delta^3 sum_m |f_m| the carriers' own second
and third moments, and nu the sum of the singular values of D (of the symmetric matrices
T[:, :, c], summed over c, for the second moment): the missed term is taken exactly, only the
remainder by absolute values. A pair is summed at the cheapest order whose bound is at most
``LOD_SLACK * tol * S_j / (8 pi mu R)``, S_j the cilium's force scale, so that at every point

    |u - u_resolved| <= LOD_SLACK * tol * sum_j S_j / (8 pi mu |x - c_j|)

rigorously (the ``error_bound`` of a :class:`~.sums.FlowSample`: the pairs' bounds at the
current moments summed, :meth:`Carriers.error_bound`).

:class:`Bounds` holds the bounds' coefficients per cilium for one kind of flow and turns a
tolerance into the distances R1, R2, R3 beyond which each order will do
(:meth:`Bounds.thresholds`): :attr:`Carriers.over_cycle` for the flow at any instant (the
exact terms' maxima over the cycle's phase samples times :data:`PHASE_MARGIN`, S_j the r.m.s. of
|F_j(t)|; the reported bound uses the moments at the current phase), :attr:`Carriers.of_mean`
for the cycle-mean flow (the cycle means, S_j = |Fbar_j|). ``tol`` is relative to the sum of the
cilia's far-field magnitudes (for a carpet whose cilia push roughly the same way, relative to
|u| itself). Measured: the error on carpets of 10 x 10, 30 x 30 and 100 x 100 cilia stays below
``0.2 * tol`` times that sum (0.16, 0.15 and 0.05 at most over tol 1e-2 to 1e-4 in free space,
0.01 or less with a wall; tested on 10 x 10; ``benchmarks/bench_calibration.py`` for every size,
benchmarks/results/bench_calibration.md: the worst-case alignments and signs that the bound adds
up do not occur, see :data:`LOD_SLACK`). Small carpets average less: 3 x 3 cilia reach 0.73 tol (free space, tol
1e-3) and a lone cilium 4.4 tol (tol 1e-2; 2.1 at 1e-3, 0.7 at 1e-4), the rigorous bound holding.
Where the far cilia are monopoles (tol 1e-2 on a few hundred cilia) their errors add up more:
a 22 x 22 carpet of random curvatures reached 0.49 tol (both signs) and 0.80 tol (one sign) of
that sum at 80 points over and beside it (three instants; 0.10-0.17 at tol 1e-3, 0.04 at 1e-4),
the rigorous bound holding (neighbouring cilia's first moments are alike, so the monopoles'
missed dipole terms do not cancel).

Groups of far cilia (:class:`~ciliary_carpet.carpet.plan.FarGroups`). On a planar carpet
whose far cilia are dipoles (large carpets), the flow at an instant also sums groups of about
four neighbouring far cilia at six quadrupole carriers of their own, about the group's centre C
(its radius a: every carrier of its cilia within a of C), where a target is far enough. The
group's carriers reproduce F, D and T about C of its cilia's dipole carriers (point forces), so
at a distance R from C they differ from them by at most C3 (Q3 + Q3_rep) / (6 (R - a)^4)
(Taylor's theorem as above, Q3 = sum_i |f_i| |y_i - C|^3 over the cilia's carriers, Q3_rep the
group carriers' own, each bounded over the whole cycle by the carriers' largest forces), and the
cilia's dipole carriers differ from their resolved lines by their own dipole bounds at R - d_j
(d_j = |c_j - C|). A group is summed as one where the sum of the two stays within the sum of its
cilia's budgets LOD_SLACK tol S_j / (8 pi mu (R + d_j)) <= that of each cilium at its own
distance, so the guarantee above holds unchanged. Measured on the 100 x 100 carpet (tol 1e-3 and
1e-4, 60 points over and beside it): a group of four is summed as one from about 45 L on, the
sums read 56-60 % of the sources, and the error against the resolved sum stays 0.013-0.019 tol
of the far-field sum (0.011-0.018 without groups). Not for a reported bound (``Carpet.evaluate``
reports the cilia's own bounds), the cycle-mean flow (quadrupoles far) or a standing carpet.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

__all__ = ["Bounds", "LOD_SLACK", "LOD_SLACK_STANDING", "PHASE_MARGIN", "smallest_root", "tier_bound"]


PHASE_MARGIN = 1.25
"""The exact terms of the cheap orders' bounds (nu(D), nu(T - T_rep)) are maximised over the
table's phase samples to choose the orders for every time; this factor covers the phases between
the samples (measured: the maximum over 2000 random phases exceeds the samples' by at most
0.4 %, tests/test_carpet.py). The reported error bound uses the moments at the current phase."""
LOD_SLACK = 8.0
"""Calibration of the levels of detail: a pair is summed at an order when its Taylor bound is at
most ``LOD_SLACK * tol * S_j / (8 pi mu R)`` (module docstring). The bound adds worst-case
magnitudes: every pair's remainder at its worst alignment, and all pairs with the same sign; in
fact the force density changes sign along the filament (the third moment cancels in part) and
the cilia's errors add with mixed signs. Measured (tests/test_carpet.py, 10 x 10 carpets with
and without wall, tol 1e-2 to 1e-4, four times and the mean flow, points 0.05 L from the swept
regions and beyond): with 8 the error stays below 0.16 tol sum_j S_j / (8 pi mu |x - c_j|) (free
space, the dipole order at tol 1e-2; 0.07 with quadrupoles at 1e-3 and 1e-4; 0.01 with a wall),
while the near pairs fall 3-fold (benchmarks/bench_flow.py, levels). The same on every carpet size
(benchmarks/bench_calibration.py, random curvatures, free space / wall at 0.5 L, at most over tol
1e-2, 1e-3, 1e-4): 30 x 30 0.15 / 0.004, 100 x 100 0.05 / 0.001; small carpets average less (3 x 3
0.73, a lone cilium 4.4), and where the far cilia are monopoles (up to 0.8 on a 22 x 22 carpet at
tol 1e-2: module docstring). The rigorous bound is still what ``error_bound`` reports, and it held
at every point of every size."""


LOD_SLACK_STANDING = 64.0
"""The calibration :data:`LOD_SLACK` of a standing carpet's levels of detail (vertical beat planes
over the substrate; the wall's Taylor constants for any direction, :meth:`Kernel.taylor_constants
<ciliary_carpet.stokes.kernel.Kernel.taylor_constants>`). Chosen by the same rule, the error at
most about 0.2 tol sum_j S_j / (8 pi mu |x - c_j|): with :data:`LOD_SLACK` (8) a standing carpet's
errors stayed below 0.004 (mean flow) and 0.012 (instant) of that on 10 x 10 random cilia (random
chi_N, psi, points at heights 0-4 L, tol 1e-2 to 1e-4): the any-direction constants and the
wall's faster decay leave its bounds 16-50 times looser than a planar carpet's, and it resolved
3-4 times more pairs for nothing. With 64: at most 0.037 (mean) and 0.17 (instant) on 10 x 10,
0.011 and 0.19 on 30 x 30, 0.10 and 1.01 on 3 x 3 (small carpets average less, as planar ones:
0.73 at 3 x 3); the resolved pairs fall 3-fold (tests/test_standing.py). The rigorous bound is
still what ``error_bound`` reports."""




@njit(cache=True, nogil=True, parallel=True)
def tier_bound(targets, centre, radius, R1, R2, R3, a1, b1, a2, b2, b3, out):  # pragma: no cover - compiled
    """out[i] = sum over the cilia j summed cheaply for targets[i] (M, 3) of the Taylor bound of
    their order (times 8 pi mu; module docstring), R the distance from the force centre c_j
    (``centre`` (N, 3), in space), d = R - a_j:

    * R >= R1[j] (monopole): a1_j / R^2 + b1_j / d^3;
    * R2[j] <= R < R1[j] (dipole): a2_j / R^3 + b2_j / d^4;
    * R3[j] <= R < R2[j] (quadrupole): b3_j / d^4;

    the same rule as :func:`_traverse`. Closer cilia are resolved (exact); a cilium with
    R1[j] < 0 makes no flow."""
    n = centre.shape[0]
    for i in prange(targets.shape[0]):
        x = targets[i, 0]
        y = targets[i, 1]
        z = targets[i, 2]
        acc = 0.0
        for j in range(n):
            if R1[j] < 0.0:
                continue
            dx = x - centre[j, 0]
            dy = y - centre[j, 1]
            dz = z - centre[j, 2]
            R = math.sqrt(dx * dx + dy * dy + dz * dz)
            d = R - radius[j]
            if R >= R1[j]:
                acc += a1[j] / (R * R) + b1[j] / (d * d * d)
            elif R >= R2[j]:
                acc += a2[j] / (R * R * R) + b2[j] / (d * d * d * d)
            elif R >= R3[j]:
                acc += b3[j] / (d * d * d * d)
        out[i] = acc


def smallest_root(f, lo: np.ndarray, hi: np.ndarray, live) -> np.ndarray:
    """Per element the end of a bracket [lo, hi] of the crossing of ``f`` (positive below it, at most
    zero beyond; decreasing in the sense that matters): ``hi`` doubled while f(hi) > 0 where
    ``live(hi)`` (at most 200 times), then 60 bisections keeping f(hi) <= 0. The distances of the
    levels of detail (:meth:`Bounds.thresholds`) and of the groups of far cilia
    (:func:`~.plan._far_groups`)."""
    for _ in range(200):
        grow = (f(hi) > 0) & live(hi)
        if not np.any(grow):
            break
        hi = np.where(grow, 2 * hi, hi)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        pos = f(mid) > 0
        lo = np.where(pos, mid, lo)
        hi = np.where(pos, hi, mid)
    return hi


@dataclass(frozen=True, eq=False)
class Bounds:
    """Per cilium (N,) the force scale ``S`` and the coefficients (times 8 pi mu) of the Taylor
    bounds that choose its order at a distance R (module docstring): ``a1`` = C1 nu(D),
    ``b1`` = C2 Q2 / 2, ``a2`` = C2 nu(T - T_rep) / 2, ``b2`` = C3 (Q3 + q3) / 6,
    ``b3`` = C3 (Q3 + q6) / 6; ``Q3`` the third moment the reported bound adds to the carriers'
    own, ``radius`` the swept radii a_j, and ``slack`` the calibration the orders are chosen with
    (:data:`LOD_SLACK` for a planar carpet, :data:`LOD_SLACK_STANDING` for a standing one)."""

    S: np.ndarray
    a1: np.ndarray
    b1: np.ndarray
    a2: np.ndarray
    b2: np.ndarray
    b3: np.ndarray
    Q3: np.ndarray
    radius: np.ndarray
    slack: float = LOD_SLACK

    def thresholds(self, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per cilium the distances R1, R2, R3 from its force centre beyond which its monopole,
        dipole and quadrupole carriers meet the tolerance: the smallest R > a_j with
        R (A / R^p + B / (R - a)^(p + 1)) <= slack tol S (the left side decreases in R),
        by bisection. -1 for a cilium that makes no flow, inf for one whose S is 0 while it makes
        a flow (always resolved)."""
        a = self.radius
        S = self.S
        target = self.slack * tol * S
        makes_flow = self.b3 > 0  # Q3 > 0: some force on the fluid
        out = []
        for A, p, B in ((self.a1, 2, self.b1), (self.a2, 3, self.b2), (np.zeros_like(a), 3, self.b3)):
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                g = lambda R: R * (A / R ** p + B / (R - a) ** (p + 1)) - target  # noqa: E731,B023
                hi = smallest_root(g, a.copy(), a + 1.0, lambda h: S > 0)
            R = hi * (1 + 1e-12) + 1e-12
            out.append(np.where(S > 0, np.minimum(R, 1e300), np.where(makes_flow, np.inf, -1.0)))
        return tuple(out)
