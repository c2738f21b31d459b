"""The levels of detail: point-force carriers of each cilium's moments and their rigorous bounds.

Per (cilium, evaluation point) pair the flow is summed at the cheapest representation whose
error bound meets the tolerance (DESIGN.md "flow fidelity"). Around the force centre c_j of
cilium j (every filament point lies within the radius a_j of it; :class:`~.cycles.CycleData`),
with h = r - c, its moments F = int f ds (2,), D = int h f^T ds (2, 2), T = int h h f ds
(2, 2, 2) and Qk = int |h|^k |f| ds are carried by point forces at fixed positions about c_j, at
one of three orders:

* the *monopole*: F at c_j;
* the *dipole*: three forces at c_j + delta_j u_m, u_m the unit vectors of an equilateral triangle
  (:data:`DIPOLE` at 90, 210 and 330 degrees, :func:`triangle`), delta_j = a_j / 2, reproducing F
  and D: f_m = F / 3 + 2 / (3 delta) D^T u_m, from the inverse of their moment matrix
  (:func:`dipole_forces`, the one implementation, which the design model uses too, with its own
  triangle at 0, 120 and 240 degrees, :data:`DESIGN_DIPOLE`);
* the *quadrupole*: six forces, one at c_j and five on a regular pentagon of radius delta_j
  (:data:`~ciliary_carpet.stokes.treecode.QUADRUPOLE`, a vertex at 90 degrees; the treecode's stencil), reproducing F, D and T.

Their moment systems are invertible. By Taylor's theorem, for a target at distance R > a from c
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

rigorously (the ``error_bound`` of a :class:`~.carpet.FlowSample`: the pairs' bounds at the
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

Groups of far cilia (:class:`~ciliary_carpet.carpet.traversal.FarGroups`). On a planar carpet
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

Shapes: per cilium arrays (N,); carrier forces (N, 3, 2) and (N, 6, 2) in each cilium's 2D frame
(:mod:`~ciliary_carpet.carpet.geometry`), mapped into space when stacked. A standing carpet's
frames are vertical: its bounds take the kernel's constants for any direction (larger with a
wall: :meth:`Kernel.taylor_constants <ciliary_carpet.stokes.kernel.Kernel.taylor_constants>`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit, prange

from ciliary_carpet.carpet.cycles import CycleData
from ciliary_carpet.stokes import QUADRUPOLE, QUADRUPOLE_INV, Kernel

__all__ = ["Bounds", "CarrierForces", "Carriers", "DIPOLE", "DESIGN_DIPOLE", "HARMONIC_TAIL", "InstantCarriers",
           "InstantForces", "LOD_SLACK", "LOD_SLACK_STANDING", "MomentRows", "PHASE_MARGIN",
           "dipole_forces", "smallest_root", "triangle"]

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


def triangle(angle: float) -> np.ndarray:
    """(3, 2) the unit vectors at ``angle``, ``angle + 2 pi / 3`` and ``angle + 4 pi / 3``
    (radians, anticlockwise from +x): the positions of dipole carriers for unit delta."""
    return np.array([[math.cos(2 * math.pi * m / 3 + angle), math.sin(2 * math.pi * m / 3 + angle)]
                     for m in range(3)])


DIPOLE = triangle(math.pi / 2)
"""Positions of the carpet's dipole carriers for unit delta: an equilateral triangle with a vertex
at 90 degrees (90, 210, 330), the vertex the pentagon of :data:`~ciliary_carpet.stokes.treecode.QUADRUPOLE` has too. Any
orientation reproduces F and D exactly; the orientation sets the carriers' own second moment
T_rep, hence what the dipole order misses (its bound uses nu(T - T_rep))."""
DESIGN_DIPOLE = np.array([[1.0, 0.0], [-0.5, math.sqrt(3) / 2], [-0.5, -math.sqrt(3) / 2]])
"""Positions of the design model's dipole carriers for unit delta (:mod:`ciliary_carpet.design.model`):
the triangle at 0, 120 and 240 degrees. The same carriers (:func:`dipole_forces`), another
orientation: the design model's flow is its own approximation (corrected by the full flow
between passes), and its designs were calibrated with this one. Measured on the five bundled
scenes (reduced): the carpet's orientation would move the designed layouts' flows by up to 3 %
(path-line velocities; the pattern a carpet can hold, e.g. 24.4 against 23.0 degrees for
vortex_turn), so the design keeps its own."""


def dipole_forces(F: np.ndarray, D: np.ndarray, delta: np.ndarray, unit: np.ndarray = DIPOLE) -> np.ndarray:
    """(K, 3, 2) the forces of the dipole carriers at c + delta u_m that reproduce the moments
    F (K, 2) and D (K, 2, 2) about c of K cilia with carrier scales ``delta`` (K,):
    f_m = F / 3 + 2 / (3 delta) D^T u_m, from the inverse of the carriers' moment matrix (rows 1,
    x, y). ``unit`` (3, 2): the u_m, an equilateral triangle: the carpet's :data:`DIPOLE` (default)
    or the design model's :data:`DESIGN_DIPOLE`. Linear in (F, D): the derivatives of F and D
    give the carriers' derivatives. The one implementation of the dipole carriers, for the
    carpet's levels of detail and the design model (one compiled pass over the cilia: every
    evaluation of a carpet's flow makes them for all its cilia)."""
    unit = np.asarray(unit, dtype=float)
    inv = DIPOLE_INV if unit is DIPOLE else np.linalg.inv(np.stack([np.ones(3), unit[:, 0], unit[:, 1]]))
    F = np.ascontiguousarray(F, dtype=float)
    D = np.ascontiguousarray(D, dtype=float)
    d = np.ascontiguousarray(np.broadcast_to(np.asarray(delta, dtype=float), (F.shape[0],)))
    out = np.empty((F.shape[0], 3, 2))
    _dipole_forces(F, D, d, inv, out)
    return out


@njit(cache=True, nogil=True)
def _dipole_forces(F, D, delta, inv, out):  # pragma: no cover - compiled
    """out[j, m] = inv[m, 0] F[j] + inv[m, 1] D[j, 0] / delta[j] + inv[m, 2] D[j, 1] / delta[j]
    (:func:`dipole_forces`, in the order numpy's broadcast took)."""
    for j in range(F.shape[0]):
        d = delta[j]
        for m in range(3):
            for k in range(2):
                out[j, m, k] = inv[m, 0] * F[j, k] + inv[m, 1] * (D[j, 0, k] / d) + inv[m, 2] * (D[j, 1, k] / d)


@njit(cache=True, inline="always")
def _solve_carriers(inv, b, fk):  # pragma: no cover - compiled
    """fk (n, 2) = inv (n, n) @ b[:n] (the carriers' forces from their scaled moments); returns
    sum_m |fk_m|."""
    acc = 0.0
    for m in range(inv.shape[0]):
        gx = 0.0
        gy = 0.0
        for q in range(inv.shape[1]):
            gx += inv[m, q] * b[q, 0]
            gy += inv[m, q] * b[q, 1]
        fk[m, 0] = gx
        fk[m, 1] = gy
        acc += math.sqrt(gx * gx + gy * gy)
    return acc


@njit(cache=True, nogil=True)
def _carrier_sets(F, D, T, delta, u3, f3, inv6, f6, nu1, nu2, q3, q6):  # pragma: no cover - compiled
    """Per cilium j the bound terms of the cheap orders about c_j (module docstring), for its
    moments F (N, 2), D (N, 2, 2), T (N, 2, 2, 2) and its dipole carriers' forces f3 (N, 3, 2) at
    c_j + delta_j u3_m (:func:`dipole_forces`):

    * q3 (N,) = delta^3 sum |f3_m|, the dipole carriers' third moment, and nu2 (N,) =
      nu(T - T_rep), T_rep their second moment;
    * f6 (N, 6, 2): the quadrupole carriers' forces at c_j + delta_j u_m (``inv6``: the inverse
      of their moment matrix), reproducing F, D and T; q6 (N,) = delta^3 sum |f6_m|;
    * nu1 (N,) = nu(D), the sum of D's singular values.

    nu of a second moment M (2, 2, 2), symmetric in its first two indices, is
    sum_c (|lambda_1| + |lambda_2|) of the symmetric matrices M[:, :, c]: with M = sum of
    |lambda| u u^T e_c terms, |(grad^2 G) : M| <= C2 nu(M) / R^3 (and |(grad G) : D| <= C1 nu(D) / R^2)."""
    b = np.empty((6, 2))
    for j in range(F.shape[0]):
        d = delta[j]
        d2 = d * d
        for k in range(2):
            b[0, k] = F[j, k]
            b[1, k] = D[j, 0, k] / d
            b[2, k] = D[j, 1, k] / d
            b[3, k] = T[j, 0, 0, k] / d2
            b[4, k] = T[j, 0, 1, k] / d2
            b[5, k] = T[j, 1, 1, k] / d2
        q6[j] = d2 * d * _solve_carriers(inv6, b, f6[j])
        acc = 0.0
        for m in range(3):
            acc += math.sqrt(f3[j, m, 0] * f3[j, m, 0] + f3[j, m, 1] * f3[j, m, 1])
        q3[j] = d2 * d * acc
        nu = 0.0
        for c in range(2):
            # the symmetric part of T[:, :, c] minus the carriers' second moment
            sxx = T[j, 0, 0, c]
            sxy = 0.5 * (T[j, 0, 1, c] + T[j, 1, 0, c])
            syy = T[j, 1, 1, c]
            for m in range(3):
                fm = f3[j, m, c] * d2
                sxx -= u3[m, 0] * u3[m, 0] * fm
                sxy -= u3[m, 0] * u3[m, 1] * fm
                syy -= u3[m, 1] * u3[m, 1] * fm
            tr = sxx + syy
            det = sxx * syy - sxy * sxy
            nu += abs(tr) if det >= 0.0 else math.sqrt(tr * tr - 4.0 * det)
        nu2[j] = nu
        fro = D[j, 0, 0] ** 2 + D[j, 0, 1] ** 2 + D[j, 1, 0] ** 2 + D[j, 1, 1] ** 2
        det = D[j, 0, 0] * D[j, 1, 1] - D[j, 0, 1] * D[j, 1, 0]
        nu1[j] = math.sqrt(fro + 2.0 * abs(det))


@njit(cache=True, nogil=True)
def _stack(F, f3, f6, js, axes, out):  # pragma: no cover - compiled
    """out (10 n, 3) = F[js], then f3[js] (3 per cilium), then f6[js] (6 per cilium), n = len(js),
    each mapped into space by its cilium's axes (N, 3, 2) (:meth:`Carriers.stacked`)."""
    n = js.shape[0]
    for q in range(n):
        j = js[q]
        for k in range(3):
            a0 = axes[j, k, 0]
            a1 = axes[j, k, 1]
            out[q, k] = a0 * F[j, 0] + a1 * F[j, 1]
            for m in range(3):
                out[n + 3 * q + m, k] = a0 * f3[j, m, 0] + a1 * f3[j, m, 1]
            for m in range(6):
                out[4 * n + 6 * q + m, k] = a0 * f6[j, m, 0] + a1 * f6[j, m, 1]


LANES = 32
"""Cilia side by side in :func:`_stacked_at` (a block, one parallel task): every loop over them is
a vector loop (:class:`MomentRows` holds their coefficients lane by lane). Eight were too few for
the compiler to vectorise the loops (each runs with a check that its arrays do not overlap);
measured on a step's five instants, one thread: 10^4 cilia 5.6 ms with 8, 4.1 ms with 32, 4.0 ms
with 64; 900 cilia 0.71, 0.55 and 0.57 ms (a lazily made quadrupole costs its whole block)."""
_TWO_PI = 2.0 * math.pi
_SIN = (-1.0 / 6, 1.0 / 120, -1.0 / 5040, 1.0 / 362880, -1.0 / 39916800, 1.0 / 6227020800, -1.0 / 1307674368000)
_COS = (-0.5, 1.0 / 24, -1.0 / 720, 1.0 / 40320, -1.0 / 3628800, 1.0 / 479001600, -1.0 / 87178291200,
        1.0 / 20922789888000)
DIPOLE_INV = np.linalg.inv(np.stack([np.ones(3), DIPOLE[:, 0], DIPOLE[:, 1]]))
"""The inverse of the moment matrix (rows 1, x, y) of the carpet's dipole carriers :data:`DIPOLE`."""


_ROWS = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 12, 13])
"""The rows of the moments' interpolant (:attr:`CycleData.moment_coef
<ciliary_carpet.carpet.cycles.CycleData.moment_coef>`) the carriers use: F (2), D (4), then
T[0, 0], T[0, 1], T[1, 1] (x and y each; T[1, 0] = T[0, 1]). The monopole and the dipoles need
the first six."""
MONO_DIPOLE, QUADRUPOLES, ALL_ORDERS = 0, 1, 2
"""What :func:`_stacked_at` makes: the monopole and dipole carriers, the quadrupoles, or all."""
HARMONIC_TAIL = 1e-3
"""A carpet's carriers at an instant drop the harmonics of the moments' interpolant whose sum,
over the phase, stays below this fraction of the tolerance times the moment's own scale
(:meth:`Carriers.harmonics`; 12-13 of 21 harmonics at tol 1e-4, 9 at 1e-2, for the shipped table).
What that changes is a small part of the levels of detail's own error (at most 0.2 tol of sum_j
S_j / (8 pi mu R_j), :data:`LOD_SLACK`): measured at tol 1e-2 to 1e-4, at most 0.14 times this
fraction of tol of that sum on a random 10 x 10 carpet (tests/test_carpet.py), 0.038 and 0.011
on the designed uniform_deflection carpet at 30 x 30 and 100 x 100 (60 points each)."""


@njit(cache=True, fastmath={"reassoc", "contract", "nsz", "arcp"}, inline="always")
def _sincos_2pi(x, c, s):  # pragma: no cover - compiled
    """c[l] = cos(2 pi x[l]), s[l] = sin(2 pi x[l]) (x a phase in [0, 1)), as one vector loop: x less
    its nearest quarter q / 4 (exact) times 2 pi, |r| <= pi / 4, Taylor polynomials to r^15 and
    r^16 (truncation below 1e-16), the quadrant by exchanging and negating. Within 1e-15 of
    ``np.cos``, ``np.sin`` (tests/test_carpet.py); a call of the library's sincos per cilium
    and instant cost as much as the whole sum of its moments."""
    for ll in range(x.shape[0]):
        q = math.floor(4.0 * x[ll] + 0.5)
        r = _TWO_PI * (x[ll] - 0.25 * q)
        r2 = r * r
        sp = r * (1.0 + r2 * (_SIN[0] + r2 * (_SIN[1] + r2 * (_SIN[2] + r2 * (_SIN[3] + r2 * (
            _SIN[4] + r2 * (_SIN[5] + r2 * _SIN[6])))))))
        cp = 1.0 + r2 * (_COS[0] + r2 * (_COS[1] + r2 * (_COS[2] + r2 * (_COS[3] + r2 * (
            _COS[4] + r2 * (_COS[5] + r2 * (_COS[6] + r2 * _COS[7])))))))
        k = int(q) & 3
        a = sp if k & 1 else cp
        b = cp if k & 1 else sp
        c[ll] = -a if (k == 1 or k == 2) else a
        s[ll] = -b if k >= 2 else b


@njit(cache=True, nogil=True, parallel=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
def _stacked_at(coef, ph, delta, inv3, inv6, axes, js, blocks, want, kc, what, out):  # pragma: no cover - compiled
    """The carriers' forces in space of cilia js (n,) at each of T sets of phases ``ph`` (T, N), in
    the order of :meth:`Carriers.positions` of ``js``, as coordinate rows (out (T, 3, 10 n); only
    the rows of the cilia ``want`` (n,) bool and of ``what`` are written: :data:`MONO_DIPOLE`,
    :data:`QUADRUPOLES` or :data:`ALL_ORDERS`): per block of :data:`LANES` cilia (``blocks``, in
    parallel; cilium js[b LANES + l] in lane l of block b) and time their moments F, D (and T)
    from the first ``kc`` harmonics of their trigonometric interpolant (coef (nb, 14, 2 kc - 1,
    LANES), ``delta`` (nb, LANES), ``axes`` (nb, 3, 2, LANES): :class:`MomentRows`; :data:`_ROWS`),
    the dipole carriers' forces f3 = inv3 (F, D_0 / delta, D_1 / delta) (:func:`dipole_forces`),
    the quadrupole carriers' f6 = inv6 (F, D / delta, T / delta^2) (:func:`_carrier_sets`), each
    mapped into space by the cilium's axes (:func:`_stack`). One pass for what
    :meth:`Carriers.forces` and :meth:`Carriers.stacked` do in four, without the bound terms
    (which only a reported bound needs): the T times share one read of the coefficients, the
    monopoles and dipoles read 6 of the 12 rows, and the basis (:func:`_sincos_2pi`, then the
    angle-addition recurrence) and the sums run over the lanes as vectors. Each cilium's and
    time's numbers are those of any other block, time or order asked with it, to the bit."""
    nk = coef.shape[2]
    n = js.shape[0]
    nt = ph.shape[0]
    nrow = 6 if what == 0 else 14
    for i in prange(blocks.shape[0]):  # scratch once per block
        blk = blocks[i]
        base = blk * LANES
        b = np.empty((nt, nk, LANES))  # b[t, k]: 1, cos k, then sin k of each lane's phase
        m = np.empty((nt, 14, LANES))
        x = np.empty(LANES)
        r = np.empty((6, 2))
        for tt in range(nt):
            bt = b[tt]
            for ll in range(LANES):
                x[ll] = ph[tt, js[min(base + ll, n - 1)]]  # lanes past the last cilium: any phase
            b0 = bt[0]
            for ll in range(LANES):
                b0[ll] = 1.0
            if kc > 1:
                c1 = bt[1]
                s1 = bt[kc]
                _sincos_2pi(x, c1, s1)
                for k in range(2, kc):
                    cp = bt[k - 1]
                    sp = bt[kc + k - 2]
                    cn = bt[k]
                    sn = bt[kc + k - 1]
                    for ll in range(LANES):
                        cn[ll] = cp[ll] * c1[ll] - sp[ll] * s1[ll]
                        sn[ll] = sp[ll] * c1[ll] + cp[ll] * s1[ll]
        cb = coef[blk]
        for p in range(nrow):  # the rows of _ROWS
            if p == 10 or p == 11:
                continue
            cr = cb[p]
            for tt in range(nt):
                bt = b[tt]
                acc = m[tt, p]
                c0 = cr[0]
                b0 = bt[0]
                for ll in range(LANES):
                    acc[ll] = c0[ll] * b0[ll]
                for k in range(1, kc):
                    ck = cr[k]
                    bk = bt[k]
                    cs = cr[kc - 1 + k]
                    bs = bt[kc - 1 + k]
                    for ll in range(LANES):
                        acc[ll] += ck[ll] * bk[ll] + cs[ll] * bs[ll]
        for ll in range(LANES):
            q = base + ll
            if q >= n:
                break
            if not want[q]:
                continue
            d = delta[blk, ll]
            d2 = d * d
            a00 = axes[blk, 0, 0, ll]
            a01 = axes[blk, 0, 1, ll]
            a10 = axes[blk, 1, 0, ll]
            a11 = axes[blk, 1, 1, ll]
            a20 = axes[blk, 2, 0, ll]
            a21 = axes[blk, 2, 1, ll]
            for tt in range(nt):
                # rhs rows: F, D[0] / d, D[1] / d, T[0, 0] / d^2, T[0, 1] / d^2, T[1, 1] / d^2 (x and y each)
                for k in range(2):
                    r[0, k] = m[tt, k, ll]
                    r[1, k] = m[tt, 2 + k, ll] / d
                    r[2, k] = m[tt, 4 + k, ll] / d
                if what != 1:
                    out[tt, 0, q] = a00 * r[0, 0] + a01 * r[0, 1]
                    out[tt, 1, q] = a10 * r[0, 0] + a11 * r[0, 1]
                    out[tt, 2, q] = a20 * r[0, 0] + a21 * r[0, 1]
                    for mm in range(3):
                        gx = inv3[mm, 0] * r[0, 0] + inv3[mm, 1] * r[1, 0] + inv3[mm, 2] * r[2, 0]
                        gy = inv3[mm, 0] * r[0, 1] + inv3[mm, 1] * r[1, 1] + inv3[mm, 2] * r[2, 1]
                        out[tt, 0, n + 3 * q + mm] = a00 * gx + a01 * gy
                        out[tt, 1, n + 3 * q + mm] = a10 * gx + a11 * gy
                        out[tt, 2, n + 3 * q + mm] = a20 * gx + a21 * gy
                if what == 0:
                    continue
                for k in range(2):
                    r[3, k] = m[tt, 6 + k, ll] / d2
                    r[4, k] = m[tt, 8 + k, ll] / d2
                    r[5, k] = m[tt, 12 + k, ll] / d2
                for mm in range(6):
                    gx = 0.0
                    gy = 0.0
                    for w6 in range(6):
                        gx += inv6[mm, w6] * r[w6, 0]
                        gy += inv6[mm, w6] * r[w6, 1]
                    out[tt, 0, 4 * n + 6 * q + mm] = a00 * gx + a01 * gy
                    out[tt, 1, 4 * n + 6 * q + mm] = a10 * gx + a11 * gy
                    out[tt, 2, 4 * n + 6 * q + mm] = a20 * gx + a21 * gy


@njit(cache=True, nogil=True, parallel=True, fastmath={"contract", "nsz", "arcp"})
def _group_forces(out, n, pos, start, centre, delta, inv6):  # pragma: no cover - compiled
    """Rows 10 n + 6 g + m of out (T, 3, 10 n + 6 G): the six quadrupole carriers of group g of
    far cilia (:class:`~.traversal.FarGroups`: the sorted cilia start[g] ... start[g + 1], its
    centre (G, 3) and scale ``delta`` (G,)) at each instant, in the plane, reproducing F, D and T
    about the centre of its cilia's dipole carriers (rows n + 3 q + m, at ``pos`` (3, 10 n)):
    the forces f = inv6 (F, D_x / delta, D_y / delta, T_xx / delta^2, T_xy / delta^2,
    T_yy / delta^2) of :func:`_carrier_sets`. The rows' weights are made once for all instants,
    the sums run over each instant's contiguous rows (no square roots: the solve of
    :func:`_carrier_sets` also sums the forces' norms; timings in benchmarks/results/bench_large.md).
    The sums run in their written order (no ``reassoc``), so that the copy numba compiles in a
    process and the copy it loads from its cache give the same numbers: a render's results do not
    depend on numba's cache."""
    nt = out.shape[0]
    for g in prange(centre.shape[0]):
        d = delta[g]
        cx = centre[g, 0]
        cy = centre[g, 1]
        r0 = n + 3 * start[g]
        nr = 3 * (start[g + 1] - start[g])
        w = np.empty((5, nr))  # the rows' weights 1, hx, hy, hx^2, hx hy, hy^2 (after 1): the same at every instant
        for i in range(nr):
            hx = (pos[0, r0 + i] - cx) / d
            hy = (pos[1, r0 + i] - cy) / d
            w[0, i] = hx
            w[1, i] = hy
            w[2, i] = hx * hx
            w[3, i] = hx * hy
            w[4, i] = hy * hy
        b = np.empty((6, 2))
        for tt in range(nt):
            for c in range(2):
                fr = out[tt, c, r0:r0 + nr]
                s0 = 0.0
                s1 = 0.0
                s2 = 0.0
                s3 = 0.0
                s4 = 0.0
                s5 = 0.0
                for i in range(nr):
                    f = fr[i]
                    s0 += f
                    s1 += w[0, i] * f
                    s2 += w[1, i] * f
                    s3 += w[2, i] * f
                    s4 += w[3, i] * f
                    s5 += w[4, i] * f
                b[0, c] = s0
                b[1, c] = s1
                b[2, c] = s2
                b[3, c] = s3
                b[4, c] = s4
                b[5, c] = s5
            for mm in range(6):
                gx = 0.0
                gy = 0.0
                for q in range(6):
                    gx += inv6[mm, q] * b[q, 0]
                    gy += inv6[mm, q] * b[q, 1]
                out[tt, 0, 10 * n + 6 * g + mm] = gx
                out[tt, 1, 10 * n + 6 * g + mm] = gy
                out[tt, 2, 10 * n + 6 * g + mm] = 0.0


@njit(cache=True)
def _missing_quadrupoles(ranges, n, done):  # pragma: no cover - compiled
    """The cilia (positions in a plan's order, ascending) whose quadrupole carriers the source
    ``ranges`` (R, 2) read (rows 4 n + 6 q ...) and that are not ``done`` yet; marks them done."""
    need = np.zeros(n, np.bool_)
    cnt = 0
    for r in range(ranges.shape[0]):
        lo = ranges[r, 0]
        if lo < 4 * n or lo >= 10 * n or ranges[r, 1] <= lo:  # (rows from 10 n on: groups' carriers)
            continue
        for q in range((lo - 4 * n) // 6, (ranges[r, 1] - 4 * n) // 6):
            if not done[q] and not need[q]:
                need[q] = True
                cnt += 1
    out = np.empty(cnt, np.int64)
    k = 0
    for q in range(n):
        if need[q]:
            out[k] = q
            done[q] = True
            k += 1
    return out


@njit(cache=True, nogil=True, parallel=True)
def _tier_bound(targets, centre, radius, R1, R2, R3, a1, b1, a2, b2, b3, out):  # pragma: no cover - compiled
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
    (:func:`~.traversal._far_groups`)."""
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
class CarrierForces:
    """The cheap orders' carriers of K cilia for given moments: the dipole and quadrupole forces
    f3 (K, 3, 2), f6 (K, 6, 2) (the monopole is F itself) and the bound terms (K,) nu1 = nu(D),
    nu2 = nu(T - T_rep), q3 and q6 (the dipole's and quadrupole's delta^3 sum |f_m|) of
    :func:`_carrier_sets`."""

    f3: np.ndarray
    f6: np.ndarray
    nu1: np.ndarray
    nu2: np.ndarray
    q3: np.ndarray
    q6: np.ndarray


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


@dataclass(frozen=True, eq=False)
class MomentRows:
    """What :func:`_stacked_at` reads of cilia ``js``, in that order (the order a sum reads their
    carriers), in blocks of :data:`LANES` (cilium js[b LANES + l] in lane l of block b, the lanes
    past the last cilium zero): ``coef`` (nb, 14, 2 kc - 1, LANES) the moments' interpolant cut to
    its first ``kc`` harmonics (cosines 0 ... kc - 1, then sines 1 ... kc - 1), ``delta`` (nb,
    LANES) the carriers' scales (1 past the last cilium), ``axes`` (nb, 3, 2, LANES) the frames'
    axes in space. Every instant reads all of them: contiguous in the order of the sum, 10^4
    cilia take 1.5 times less than read from the full arrays (:meth:`Carriers.rows`), and lane by
    lane every loop of the pass runs over vectors."""

    js: np.ndarray
    kc: int
    coef: np.ndarray
    delta: np.ndarray
    axes: np.ndarray


class Carriers:
    """The level-of-detail carriers of a carpet's cilia and their rigorous bounds (module
    docstring), for the cycle data ``cycles`` and the Green's function ``kernel`` (its Taylor
    constants c1, c2, c3). ``delta`` (N,): the carriers' scale a_j / 2."""

    def __init__(self, cycles: CycleData, kernel: Kernel):
        self.cycles, self.kernel = cycles, kernel
        self.delta = 0.5 * np.maximum(cycles.radius, 1e-12)
        self.constants = kernel.taylor_constants(cycles.embedding.in_plane)
        self.slack = LOD_SLACK if self.constants == (kernel.c1, kernel.c2, kernel.c3) else LOD_SLACK_STANDING
        """The calibration the orders are chosen with: :data:`LOD_SLACK_STANDING` for frames out of
        the plane of a wall (a standing carpet on its substrate), :data:`LOD_SLACK` otherwise (free
        space, where a standing carpet is a planar one turned)."""
        """(c1, c2, c3): the kernel's Taylor constants for the directions the cilia's frames take
        (in the plane of a wall, or any: :meth:`Kernel.taylor_constants
        <ciliary_carpet.stokes.kernel.Kernel.taylor_constants>`)."""

    _ROWS_KEPT = 4
    """Plans whose :class:`MomentRows` a carpet keeps (:meth:`rows`)."""

    def rows(self, js: np.ndarray, kc: int) -> MomentRows:
        """The :class:`MomentRows` of cilia ``js`` (a plan's order) with ``kc`` harmonics, made once
        per array ``js`` (kept for the last few; not pickled)."""
        cache = self.__dict__.setdefault("_rows", {})
        hit = cache.get((id(js), kc))
        if hit is not None and hit.js is js:
            return hit
        c = self.cycles
        K = (c.moment_coef.shape[2] + 1) // 2
        kc = int(min(max(kc, 1), K))
        idx = np.asarray(js, dtype=np.int64)
        cols = np.r_[np.arange(kc), K + np.arange(kc - 1)]
        nb = -(-idx.size // LANES)
        coef = np.zeros((nb * LANES, 14, cols.size))
        coef[:idx.size] = c.moment_coef[idx][:, :, cols]
        delta = np.ones(nb * LANES)
        delta[:idx.size] = self.delta[idx]
        axes = np.zeros((nb * LANES, 3, 2))
        axes[:idx.size] = c.embedding.axes[idx]
        rows = MomentRows(js=js, kc=kc,
                          coef=np.ascontiguousarray(coef.reshape(nb, LANES, 14, cols.size).transpose(0, 2, 3, 1)),
                          delta=np.ascontiguousarray(delta.reshape(nb, LANES)),
                          axes=np.ascontiguousarray(axes.reshape(nb, LANES, 3, 2).transpose(0, 2, 3, 1)))
        if len(cache) >= self._ROWS_KEPT:
            cache.clear()
        cache[(id(js), kc)] = rows
        return rows

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_rows", None)
        return state

    def forces(self, F: np.ndarray, D: np.ndarray, T: np.ndarray, delta: np.ndarray | None = None) -> CarrierForces:
        """The carriers for moments F (K, 2), D (K, 2, 2), T (K, 2, 2, 2) of cilia of carrier scale
        ``delta`` (K,) (default: every cilium's, K = N)."""
        d = np.ascontiguousarray(self.delta if delta is None else delta, dtype=float)
        k = F.shape[0]
        f3 = np.ascontiguousarray(dipole_forces(F, D, d))
        out = CarrierForces(f3=f3, f6=np.empty((k, 6, 2)), nu1=np.empty(k), nu2=np.empty(k), q3=np.empty(k),
                            q6=np.empty(k))
        _carrier_sets(np.ascontiguousarray(F, dtype=float), np.ascontiguousarray(D, dtype=float),
                      np.ascontiguousarray(T, dtype=float), d, DIPOLE, f3, QUADRUPOLE_INV, out.f6, out.nu1,
                      out.nu2, out.q3, out.q6)
        return out

    @cached_property
    def over_cycle(self) -> Bounds:
        """The bounds of the flow at any instant: the exact terms' maxima over the cycle's phase
        samples times :data:`PHASE_MARGIN`, the remainders' maxima, S the r.m.s. of |F(t)|."""
        c = self.cycles
        n, n_p = c.n, c.n_phase
        car = self.forces(c.F.reshape(-1, 2), c.D.reshape(-1, 2, 2), c.T.reshape(-1, 2, 2, 2),
                          np.repeat(self.delta, n_p))
        nu1, nu2 = (getattr(car, q).reshape(n, n_p).max(axis=1) for q in ("nu1", "nu2"))
        Q3 = c.Q_max
        q3, q6 = ((c.Q + getattr(car, q).reshape(n, n_p)).max(axis=1) - Q3 for q in ("q3", "q6"))
        Q2 = c.Q2.max(axis=1)
        S = c.F_rms * c.flutter
        return self._bounds(S, nu1, nu2, q3, q6, Q2, Q3, PHASE_MARGIN)

    @cached_property
    def dipole_force_max(self) -> np.ndarray:
        """(N, 3) the largest force of each dipole carrier over the cycle's phase samples, times
        :data:`PHASE_MARGIN` (the phases between them): what bounds a group of far cilia
        (:class:`~.traversal.FarGroups`)."""
        c = self.cycles
        n, n_p = c.n, c.n_phase
        f3 = dipole_forces(c.F.reshape(-1, 2), c.D.reshape(-1, 2, 2), np.repeat(self.delta, n_p))
        return PHASE_MARGIN * np.sqrt((f3 ** 2).sum(-1)).reshape(n, n_p, 3).max(axis=1)

    @cached_property
    def of_mean(self) -> Bounds:
        """The bounds of the cycle-mean flow: those of the cycle means, S = |Fbar|."""
        c = self.cycles
        car = self.forces(c.F_mean, c.D_mean, c.T_mean)
        S = np.sqrt((c.F_mean ** 2).sum(-1)) * c.flutter
        return self._bounds(S, car.nu1, car.nu2, car.q3, car.q6, c.Q2_mean, c.Q_mean, 1.0)

    def _bounds(self, S, nu1, nu2, q3, q6, Q2, Q3, margin) -> Bounds:
        c1, c2, c3 = self.constants
        return Bounds(S=S, a1=margin * c1 * nu1, b1=0.5 * c2 * Q2, a2=margin * 0.5 * c2 * nu2,
                      b2=c3 / 6.0 * (Q3 + q3), b3=c3 / 6.0 * (Q3 + q6), Q3=Q3, radius=self.cycles.radius,
                      slack=self.slack)

    def positions(self, js: np.ndarray) -> np.ndarray:
        """(10 len(js), 3) the carriers' positions in space of cilia ``js`` in the order a ranged
        sum reads them: the monopoles (at c_j), then the dipoles' three, then the quadrupoles' six
        per cilium (placed in each cilium's 2D frame, then embedded:
        :class:`~ciliary_carpet.carpet.geometry.Embedding`)."""
        js = np.asarray(js, dtype=np.int64)
        cen, dl = self.cycles.centre[js], self.delta[js][:, None, None]
        emb = self.cycles.embedding
        parts = [cen[:, None], cen[:, None] + dl * DIPOLE[None], cen[:, None] + dl * QUADRUPOLE[None]]
        return np.concatenate([emb.points(q, js).reshape(-1, 3) for q in parts])

    def stacked(self, F: np.ndarray, car: CarrierForces, js: np.ndarray) -> np.ndarray:
        """(10 len(js), 3) the carriers' forces in space of cilia ``js`` in the order of
        :meth:`positions` (one compiled gather: every evaluation of a carpet's flow stacks all its
        cilia's)."""
        js = np.ascontiguousarray(js, dtype=np.int64)
        out = np.empty((10 * js.size, 3))
        _stack(np.ascontiguousarray(F, dtype=float), car.f3, car.f6, js, self.cycles.embedding.axes, out)
        return out

    def stacked_at(self, phases: np.ndarray, js: np.ndarray, kc: int | None = None) -> np.ndarray:
        """The carriers' forces in space of cilia ``js`` at the phases ``phases`` (N,) of one
        instant, (10 len(js), 3), or (T, N) of T instants, (T, 10 len(js), 3): :meth:`stacked` of
        :meth:`forces` of the moments there, in one compiled pass (:func:`_stacked_at`; equal to
        rounding; T instants at once cost little more than one), from the first ``kc`` harmonics
        of the moments' interpolant (default all; :meth:`harmonics`). What an evaluation without
        a reported bound needs (:class:`InstantCarriers` makes the quadrupoles on demand)."""
        return InstantCarriers(self, phases, js, kc, eager=True).forces

    @cached_property
    def _tails(self) -> np.ndarray:
        """(K + 1,) for k' = 0 ... K the largest over cilia and moments of the sum of the
        amplitudes of harmonics k' and up of the moments' interpolant (a bound of what dropping
        them changes at any phase), relative to the moment's scale: S_j for F, S_j a_j for D,
        S_j a_j^2 for T (S_j the r.m.s. force, a_j the swept radius); cilia that make no flow
        left out."""
        c = self.cycles
        co = np.abs(c.moment_coef[:, _ROWS])  # (N, 12, 2K - 1)
        K = (co.shape[2] + 1) // 2
        amp = co[:, :, :K].copy()
        amp[:, :, 1:] += co[:, :, K:]
        tail = np.concatenate([np.cumsum(amp[:, :, ::-1], axis=2)[:, :, ::-1], np.zeros(amp.shape[:2] + (1,))],
                              axis=2)  # (N, 12, K + 1): tail[..., k'] = sum_{k >= k'}
        S = c.F_rms * c.flutter
        a = c.radius
        scale = np.concatenate([np.repeat(S[:, None], 2, 1), np.repeat((S * a)[:, None], 4, 1),
                                np.repeat((S * a * a)[:, None], 6, 1)], axis=1)
        live = S > 0
        if not np.any(live):
            return np.zeros(K + 1)
        return (tail[live] / scale[live][:, :, None]).max(axis=(0, 1))

    def harmonics(self, tol: float) -> int:
        """The harmonics of the moments' interpolant an instant's carriers keep at ``tol``: the
        fewest whose dropped tail (:attr:`_tails`) stays below :data:`HARMONIC_TAIL` tol of
        each moment's scale, so that the velocity changes by at most about that fraction of the
        tolerance (every harmonic for tol = 0)."""
        t = self._tails
        ok = np.nonzero(t <= HARMONIC_TAIL * float(tol))[0]
        return int(ok[0]) if ok.size else t.size - 1

    def error_bound(self, targets: np.ndarray, thresholds: tuple, bounds: Bounds, car: CarrierForces,
                    mu: float) -> np.ndarray:
        """(M,) the rigorous bound of |u - u_resolved| at ``targets`` (M, 3): per target the
        Taylor bounds of the cilia summed cheaply at the orders the ``thresholds`` (R1, R2, R3)
        give them (:func:`_tier_bound`), at the current moments (``car``)."""
        c1, c2, c3 = self.constants
        k3 = c3 / 6.0
        Q3 = bounds.Q3
        out = np.zeros(targets.shape[0])
        R1, R2, R3 = thresholds
        _tier_bound(targets, self.cycles.centre3, self.cycles.radius, R1, R2, R3, c1 * car.nu1, bounds.b1,
                    0.5 * c2 * car.nu2, k3 * (Q3 + car.q3), k3 * (Q3 + car.q6), out)
        return out / (8 * math.pi * mu)


class InstantCarriers:
    """The carriers' forces in space of a plan's cilia ``js`` at T instants (their phases ``ph``
    (T, N), or (N,) for one), from the first ``kc`` harmonics (default all), as coordinate rows
    (T, 3, 10 n) in the order of :meth:`Carriers.positions` (into ``out`` when given and of that
    shape: a buffer no longer used, as a carpet recycles): the monopoles and dipoles of every
    cilium made at once (:func:`_stacked_at`, one read of their coefficients for the T instants),
    the quadrupoles too when ``eager``, else on demand (:meth:`complete`: the cilia whose
    quadrupoles an evaluation reads, made for the T instants together). A carpet whose far cilia
    are dipoles (100 x 100: 10^4 cilia, about a quarter of them near a tracer) reads 6 of the 12
    rows for most of them. ``groups`` (a plan's :class:`~.traversal.FarGroups` and its carriers'
    positions (3, 10 n)): the groups' six carriers each, after the cilia's (rows 10 n + 6 g ...),
    made with the monopoles and dipoles (:func:`_group_forces`). ``dtype``: the forces' type
    (float32 for sums in fp32: computed in fp64, rounded as they are stored)."""

    def __init__(self, carriers: Carriers, ph: np.ndarray, js: np.ndarray, kc: int | None = None,
                 eager: bool = False, out: np.ndarray | None = None, groups=None, dtype=np.float64):
        ph = np.asarray(ph, dtype=float)
        self.many = ph.ndim == 2
        self.ph = np.ascontiguousarray(ph if self.many else ph[None])
        self.js = np.ascontiguousarray(js, dtype=np.int64)
        self.carriers = carriers
        K = (carriers.cycles.moment_coef.shape[2] + 1) // 2
        self.kc = K if kc is None else int(min(max(kc, 1), K))
        self.rows = carriers.rows(js, self.kc)
        n = self.js.size
        G = 0 if groups is None else groups[0].n
        shape = (self.ph.shape[0], 3, 10 * n + 6 * G)
        reuse = out is not None and out.shape == shape and out.dtype == dtype
        self.out = out if reuse else np.empty(shape, dtype)  # a spare: no fresh pages
        self.done = np.full(n, bool(eager))
        self._make(np.arange(n, dtype=np.int64), ALL_ORDERS if eager else MONO_DIPOLE)
        if G:  # the groups' carriers, from their cilia's dipole carriers
            g, pos = groups
            _group_forces(self.out, n, pos, g.start, g.centre, g.delta, QUADRUPOLE_INV)

    def _make(self, sel: np.ndarray, what: int) -> None:
        """Make the carriers ``what`` of the cilia ``sel`` (positions in :attr:`js`) at every instant."""
        r = self.rows
        n = self.js.size
        if sel.size == n:
            blocks, want = np.arange(-(-n // LANES), dtype=np.int64), np.ones(n, np.bool_)
        else:
            blocks = np.unique(sel // LANES)
            want = np.zeros(n, np.bool_)
            want[sel] = True
        _stacked_at(r.coef, self.ph, r.delta, DIPOLE_INV, QUADRUPOLE_INV, r.axes, self.js, blocks, want, self.kc,
                    what, self.out)

    @property
    def forces(self) -> np.ndarray:
        """(T, 10 n, 3), or (10 n, 3) for one instant: views of the coordinate rows (complete only
        when made eagerly, or after :meth:`complete` of every quadrupole)."""
        f = self.out.transpose(0, 2, 1)
        return f if self.many else f[0]

    def complete(self, ranges: np.ndarray) -> None:
        """Make the quadrupoles that the source ``ranges`` (R, 2) of a ranged sum read and that
        are not made yet, at every instant."""
        if self.done.all():
            return
        need = _missing_quadrupoles(ranges, self.js.size, self.done)
        if need.size:
            self._make(need, QUADRUPOLES)

    def at(self, i: int) -> "InstantForces":
        """The forces at instant ``i``, for a ranged sum (:func:`~.traversal.flow_sum`)."""
        return InstantForces(self, i)


@dataclass(frozen=True, eq=False)
class InstantForces:
    """The carriers' forces of one instant of an :class:`InstantCarriers`: :meth:`for_ranges`
    gives the (10 n, 3) forces with every quadrupole the ranges read made."""

    group: InstantCarriers
    i: int

    def for_ranges(self, ranges: np.ndarray) -> np.ndarray:
        self.group.complete(ranges)
        return self.group.out[self.i].T
