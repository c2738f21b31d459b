"""A carpet of cilia under one uniform field, and the Stokes flow it drives.

Model (MODEL.md section 6)
--------------------------
Every cilium j is clamped at its base point b_j in the plane z = 0 and beats on the limit cycle
of its natural curvature chi_N_j, read from the :class:`~single_cilium.table.ThrustTable` of the
field (chi_E, eta). The field points along ``direction`` (radians, anticlockwise from +y); the
whole single-filament picture (field along e2) is rotated by it. Cilium j is at phase
``phi_j(t) = phases[j] + t / T(chi_N_j)`` (mod 1): each beats at its own period, so the carpet's
flow is in general quasi-periodic, and nothing here assumes a common period. The fluid velocity
is the superposition of the filaments' line distributions of Stokeslets,

    u(x, t) = 1/(8 pi mu) sum_j int_0^1 G(x, r_j(s, t)) f_j(s, t) ds,

with f = -d the force per length on the fluid (the table's fx, fy) and G the regularised
Stokeslet of blob size ``blob`` (the filament radius; :mod:`ciliary_carpet.stokes.kernel`), so that the
velocity stays bounded on and between the filaments and tracers pass through the carpet; away
from a filament it differs from the singular Stokeslet I/|R| + R R^T/|R|^3 by O(blob^2/|R|^3). The arc length integral is
the composite Simpson rule on the table's uniform s grid; the phase dependence is the
trigonometric interpolant of the table's uniform phase samples (spectral: the cycle is smooth).
With ``wall=h`` a no-slip plane lies at z = -h (the regularised image system of Ainley et al.
2008; Blake's for ``blob=None``). The model ignores
contact and hydrodynamic interaction between filaments (each beats as if alone); a base point
inside another cilium's swept region is warned about.

Levels of detail (DESIGN.md "flow fidelity")
--------------------------------------------
Per (cilium, evaluation point) pair the cheapest representation whose error bound is under the
tolerance is used. Around the force centre c_j (the centroid of the cilium's swept samples;
every filament point lies within the radius a_j of it), with h = r - c, the moments
F = int f ds, D = int h f^T ds, T = int h h f ds (second moments) and Qk = int |h|^k |f| ds:

* ``point``: the moments at the current phase carried by point forces at fixed positions about
  c, at one of three orders: the *monopole* (F at c), the *dipole* (three forces at
  c + delta u_m, an equilateral triangle, delta = a/2, reproducing F and D) or the *quadrupole*
  (six forces, one at c and five on a regular pentagon of radius delta, reproducing F, D and T:
  their moment systems are invertible);
* ``mean``: the same with the cycle means (the steady, time-averaged flow only);
* ``resolved``: the full line distribution (for the mean flow: averaged over the phase samples).

By Taylor's theorem, for a target at distance R > a from c the order-k carriers (matching the
moments below order k) err by the order-k term they miss plus a remainder:

    monopole:    8 pi mu |u - u_resolved| <= C1 nu(D) / R^2 + C2 Q2 / (2 (R - a)^3)
    dipole:      8 pi mu |u - u_resolved| <= C2 nu(T - T_rep) / (2 R^3) + C3 (Q3 + Q3_rep) / (6 (R - a)^4)
    quadrupole:  8 pi mu |u - u_resolved| <= C3 (Q3 + Q3_rep) / (6 (R - a)^4)

with Ck the supremum of |(h.grad)^k G f| over unit in-plane h, f at unit distance (times R^(k+1)
with a wall; :attr:`Kernel.c1 <ciliary_carpet.stokes.kernel.Kernel.c1>`, ``c2``, ``c3``: 2, 4, 16 free
and 4, 16, 64 with a wall; sampled maxima 2, 4, 12.3 free, 1.98 for C1 and 12.9 for C3 with a
wall, tests/test_carpet.py), T_rep and
Q3_rep = delta^3 sum_m |f_m| the carriers' own second and third moments, and nu the sum of the
singular values of D (of the symmetric matrices T[:, :, c], summed over c, for the second
moment): the missed term is taken exactly, only the remainder by absolute values. A pair is summed
at the cheapest order whose bound is at most ``LOD_SLACK * tol * S_j / (8 pi mu R)``, where S_j is
the cilium's force scale (|Fbar_j| for the mean flow, the r.m.s. of |F_j(t)| over the cycle for
the instantaneous flow, whose orders are chosen with the bounds' maxima over the cycle) and
:data:`LOD_SLACK` = 8 a calibration, so that at every point

    |u - u_resolved| <= LOD_SLACK * tol * sum_j S_j / (8 pi mu |x - c_j|)

rigorously (the ``error_bound`` of the result: the pairs' bounds at the current moments summed),
while the measured error on carpets of 10 x 10 and 30 x 30 cilia stays below ``0.2 * tol`` times
the same sum (tested on 10 x 10; ``benchmarks/bench_calibration.py`` for every size: the worst-case
alignments and signs that the bound adds up do not occur, see :data:`LOD_SLACK`). Small carpets
average less: 3 x 3 cilia reach 0.73 tol (free space, tol 1e-3) and a lone cilium 4.4 tol (tol
1e-2; 2.1 at 1e-3, 0.7 at 1e-4), the rigorous bound holding. ``tol`` is
relative to the sum of the cilia's far-field magnitudes (for a carpet whose cilia push roughly
the same way, relative to |u| itself).

Per cilium the three bounds give distances R1, R2, R3 beyond which each order will do
(:meth:`Carpet._thresholds`; at tol 1e-3 about 80, 7 and 3 L for the instantaneous flow). One
ranged sum per evaluation (:func:`_traverse`): per target the cilia of the grid cells around it
are given their cheapest order one by one, and all the others, runs of cilia sorted by cell,
one order ``far`` whose cells the grid makes wide enough -- the monopoles, dipoles or quadrupoles,
whichever the plan estimates cheapest (:meth:`Carpet._plan`: classifying a cilium costs about
five kernel evaluations, so small carpets keep quadrupoles and large ones take monopoles or
dipoles). The mean flow keeps quadrupoles: its resolved blocks dominate its cost, and bounds
that each sit near their budget would loosen its error bars (the design's residuals'), for a
saving of about 2 %. Measured on 10 x 10 and 30 x 30 carpets: see the tests and
benchmarks/bench_flow.py.
"""
from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange
from scipy.spatial import ConvexHull, cKDTree

from single_cilium.equilibrium import equilibrium_shape
from single_cilium.params import CiliumParams
from single_cilium.table import ThrustTable

from ciliary_carpet.stokes import (C1_FREE, C1_WALL, C2_FREE, C2_WALL, C3_FREE, C3_WALL, Auto, Backend, Kernel, Wall,
                                   make_kernel, stokeslet_velocity)

logger = logging.getLogger(__name__)

__all__ = ["Carpet", "Scales", "FlowSample", "C1_FREE", "C1_WALL", "C2_FREE", "C2_WALL", "C3_FREE", "C3_WALL",
           "LEVELS", "BLOB", "PHASE_MARGIN", "LOD_SLACK"]

LEVELS = ("mean", "point", "resolved")
_AUTO = Auto()
"""The evaluator of a carpet made without ``backend``."""
_CLASSIFY = 5.0
"""Cost of classifying one cilium for one target (:func:`_traverse`) in kernel evaluations
(measured: about 3 ns against 0.55 ns per evaluation on 2 cores); used to choose the order of
the far cilia (:meth:`Carpet._plan`)."""
_MAX_ROWS = 1 << 23
"""An evaluation's targets are taken in parts when their source ranges could take more rows than
this (128 MB: :func:`_upper`)."""
_CHUNK_SOURCES = 1 << 19
"""The resolved near-field sources of a flow evaluation are made and summed in chunks of cilia
of at most this many sources (3 MB per coordinate array): :meth:`Carpet._sum`."""
_UNIT = np.array([[0.0, 0.0]] + [[math.cos(2 * math.pi * m / 5 + math.pi / 2), math.sin(2 * math.pi * m / 5 + math.pi / 2)]
                                 for m in range(5)])
"""Carrier positions of the cheap levels for unit delta: the centre and a regular pentagon."""
_UNIT_INV = np.linalg.inv(np.stack([np.ones(6), _UNIT[:, 0], _UNIT[:, 1], _UNIT[:, 0] ** 2,
                                    _UNIT[:, 0] * _UNIT[:, 1], _UNIT[:, 1] ** 2]))
"""Inverse of the carrier's moment matrix (rows: the monomials 1, x, y, x^2, xy, y^2)."""
_U3 = np.array([[math.cos(2 * math.pi * m / 3 + math.pi / 2), math.sin(2 * math.pi * m / 3 + math.pi / 2)]
                for m in range(3)])
"""Carrier positions of the dipole order for unit delta: an equilateral triangle."""
_U3_INV = np.linalg.inv(np.stack([np.ones(3), _U3[:, 0], _U3[:, 1]]))
"""Inverse of the dipole carriers' moment matrix (rows: the monomials 1, x, y)."""
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
while the near pairs fall 3-fold (benchmarks/bench_flow.py, levels). The rigorous bound is still
what ``error_bound`` reports."""
BLOB = 0.02
"""Default blob size eps of the regularised Stokeslets, in units of L: the filament radius of a
slender filament of aspect ratio L / (2 a) = 25 (scene key ``[carpet] blob``)."""


@dataclass(frozen=True)
class Scales:
    """Physical scales for output in SI units: the filament length L [m], the relaxation time
    tau [s] and the fluid viscosity [Pa s]. Positions scale by L, times by tau, velocities by
    L/tau; a force per length f (model units B/L^3) by ``viscosity * L / (tau * mu)`` where
    ``mu`` is the carpet's dimensionless viscosity."""

    length_m: float
    time_s: float
    viscosity_Pa_s: float

    def __post_init__(self) -> None:
        for k in ("length_m", "time_s", "viscosity_Pa_s"):
            v = getattr(self, k)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"Scales.{k} must be a positive finite number, got {v!r}")

    @property
    def velocity(self) -> float:
        return self.length_m / self.time_s


@dataclass(frozen=True)
class FlowSample:
    """Velocities at points with their error bound and the fidelity used.

    velocity (M, 3); error_bound (M,): the bound of the levels of detail against the resolved
    sum (zero where every pair was resolved); pairs: number of (cilium, point) pairs evaluated
    at each level; tol: the tolerance asked for; work: counters of the work done: ``sources``,
    the (point, source) interactions summed (the cost: each is one kernel evaluation),
    ``ranges``, the source ranges of the sparse sum (per point the runs of carriers and one block
    per resolved pair), and ``orders``, the cheap pairs per order (``monopole``, ``dipole``,
    ``quadrupole``)."""

    velocity: np.ndarray
    error_bound: np.ndarray
    pairs: dict
    tol: float
    work: dict = field(default_factory=dict)

    @property
    def fidelity(self) -> dict:
        """Fraction of the pairs evaluated at each level."""
        n = sum(self.pairs.values())
        return {k: (v / n if n else 0.0) for k, v in self.pairs.items()}


def _modes(table: ThrustTable, floor: float = 1e-7) -> int:
    """Number of phase harmonics (k = 0..K-1) above ``floor`` times the largest, over every row of
    the table (the table stores float32: its harmonics level off near 1e-8)."""
    fl = table.ds.flutter.values.astype(bool)
    if not np.any(fl):
        return 1
    amp = np.zeros(table.ds.sizes["phase"] // 2 + 1)
    for k in ("x", "y", "fx", "fy"):
        a = np.abs(np.fft.rfft(table.ds[k].values[fl].astype(float), axis=1)).max(axis=(0, 2))
        amp = np.maximum(amp, a / a.max())
    return int(np.nonzero(amp > floor)[0].max()) + 1


def _pad(a: np.ndarray) -> np.ndarray:
    """(..., 2) -> (..., 3) with z = 0."""
    return np.concatenate([a, np.zeros(a.shape[:-1] + (1,))], axis=-1)


@njit(cache=True, inline="always")
def _basis_row(ph, cs, sn):  # pragma: no cover - compiled
    """cs[k] = cos(2 pi k ph), sn[k] = sin(2 pi k ph), k < len(cs), by the angle-addition recurrence."""
    th = 2.0 * np.pi * ph
    c1 = np.cos(th)
    s1 = np.sin(th)
    cs[0] = 1.0
    sn[0] = 0.0
    for k in range(1, cs.shape[0]):
        cs[k] = cs[k - 1] * c1 - sn[k - 1] * s1
        sn[k] = sn[k - 1] * c1 + cs[k - 1] * s1


@njit(cache=True, parallel=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
def _moments_at(coef_t, ph, out):  # pragma: no cover - compiled
    """out[j, p] = a_0 + sum_{k=1}^{K-1} a_k cos(2 pi k ph_j) + b_k sin(2 pi k ph_j), the
    trigonometric interpolant of every cilium j (in parallel) at its phase ph[j], with
    coef_t[j, p] (2K-1,) holding a_0..a_{K-1} then b_1..b_{K-1} (the moments' coefficients stored
    transposed, so that each output is one contiguous dot product, which vectorises: the
    reordered sum differs by rounding only). The basis by the angle-addition recurrence
    (rounding grows like k eps: below 1e-13 for the K <= 64 used)."""
    nk = coef_t.shape[2]
    K = (nk + 1) // 2
    for j in prange(coef_t.shape[0]):
        cs = np.empty(K)
        sn = np.empty(K)
        b = np.empty(nk)
        _basis_row(ph[j], cs, sn)
        for k in range(K):
            b[k] = cs[k]
        for k in range(1, K):
            b[K - 1 + k] = sn[k]
        for p in range(coef_t.shape[1]):
            acc = 0.0
            for k in range(nk):
                acc += coef_t[j, p, k] * b[k]
            out[j, p] = acc


@njit(cache=True)
def _basis(ph, K, out):  # pragma: no cover - compiled
    """out[i, 0] (len(ph), 1, 2K-1): the trigonometric basis 1, cos(2 pi k ph_i), sin(2 pi k ph_i)
    (k = 1..K-1) of :func:`_moments_at` at phase ph[i]."""
    cs = np.empty(K)
    sn = np.empty(K)
    for i in range(ph.shape[0]):
        _basis_row(ph[i], cs, sn)
        for k in range(K):
            out[i, 0, k] = cs[k]
        for k in range(1, K):
            out[i, 0, K - 1 + k] = sn[k]


@njit(cache=True, parallel=True)
def _cycle_data(x, y, fx, fy, rot, bases, w, cos_p, sin_p, mk, cos_m, sin_m, coef, mom_coef, centre, radius,
                F, D, T, Q, Q2):  # pragma: no cover - compiled
    """Per cilium j (parallel over j) of one chunk: rotate its cycle samples x, y, fx, fy
    (n, n_p, n_s) by ``rot`` into the lab frame, then

    * coef[j] (2K-1, n_s, 4), float32: the trigonometric interpolant's coefficients in phase
      (rounded to single precision, the table's own: the near-field blocks made from them at
      every evaluation read half the memory),
      a_k = mk_k / n_p sum_p v_p cos(2 pi k p / n_p), b_k = mk_k / n_p sum_p v_p sin(...)
      (``cos_p``, ``sin_p`` (n_p, K) hold the cosines and sines; v = x, y, fx, fy);
    * mom_coef[j] (2Km-1, 14): the coefficients (cos k = 0..Km-1, then sin k = 1..Km-1) of
      F (2), D (4) and T (8) of the interpolant about c_j = base + mean of the shape (its k = 0
      term), sampled at n_m = 2 Km phases (``cos_m``, ``sin_m`` (n_m, Km)): products of up
      to three functions of K harmonics hold 3 (K - 1) + 1 <= Km, so the samples alias nothing;
    * from the raw samples: centre[j] (the centroid of the swept samples, plus the base),
      radius[j], and per table phase F[j] (n_p, 2), D[j] (n_p, 2, 2), T[j] (n_p, 2, 2, 2) and
      Q[j] (n_p,) = sum_s w_s |h|^3 |f| and Q2[j] (n_p,) = sum_s w_s |h|^2 |f| about the centroid
      (Simpson weights ``w``)."""
    n, n_p, n_s = x.shape
    K = cos_p.shape[1]
    n_m, Km = cos_m.shape
    R = 4 * n_s
    for j in prange(n):
        v = np.empty((n_p, R))  # (phase, (s, q)) flattened: the inner loops run over R contiguous numbers
        for p in range(n_p):
            for s in range(n_s):
                a = x[j, p, s]
                b = y[j, p, s]
                v[p, 4 * s] = rot[0, 0] * a + rot[0, 1] * b
                v[p, 4 * s + 1] = rot[1, 0] * a + rot[1, 1] * b
                a = fx[j, p, s]
                b = fy[j, p, s]
                v[p, 4 * s + 2] = rot[0, 0] * a + rot[0, 1] * b
                v[p, 4 * s + 3] = rot[1, 0] * a + rot[1, 1] * b
        # trigonometric coefficients in phase
        cf = np.zeros((2 * K - 1, R))
        for p in range(n_p):
            for k in range(K):
                c = mk[k] * cos_p[p, k] / n_p
                for r in range(R):
                    cf[k, r] += c * v[p, r]
            for k in range(1, K):
                c = mk[k] * sin_p[p, k] / n_p
                for r in range(R):
                    cf[K - 1 + k, r] += c * v[p, r]
        for k in range(2 * K - 1):  # stored in single precision, as the table's samples are: the
            for r in range(R):      # moments below are those of the rounded interpolant
                cf[k, r] = np.float32(cf[k, r])
        for k in range(2 * K - 1):
            for s in range(n_s):
                for q in range(4):
                    coef[j, k, s, q] = cf[k, 4 * s + q]
        # raw moments about the centroid of the swept samples
        cx = 0.0
        cy = 0.0
        for p in range(n_p):
            for s in range(n_s):
                cx += v[p, 4 * s + 0]
                cy += v[p, 4 * s + 1]
        cx /= n_p * n_s
        cy /= n_p * n_s
        centre[j, 0] = cx + bases[j, 0]
        centre[j, 1] = cy + bases[j, 1]
        rmax = 0.0
        for p in range(n_p):
            for a in range(2):
                F[j, p, a] = 0.0
                for b in range(2):
                    D[j, p, a, b] = 0.0
                    for c3 in range(2):
                        T[j, p, a, b, c3] = 0.0
            Q[j, p] = 0.0
            Q2[j, p] = 0.0
            for s in range(n_s):
                h0 = v[p, 4 * s + 0] - cx
                h1 = v[p, 4 * s + 1] - cy
                r = math.sqrt(h0 * h0 + h1 * h1)
                rmax = max(rmax, r)
                g0 = v[p, 4 * s + 2] * w[s]
                g1 = v[p, 4 * s + 3] * w[s]
                F[j, p, 0] += g0
                F[j, p, 1] += g1
                D[j, p, 0, 0] += h0 * g0
                D[j, p, 0, 1] += h0 * g1
                D[j, p, 1, 0] += h1 * g0
                D[j, p, 1, 1] += h1 * g1
                T[j, p, 0, 0, 0] += h0 * h0 * g0
                T[j, p, 0, 0, 1] += h0 * h0 * g1
                T[j, p, 0, 1, 0] += h0 * h1 * g0
                T[j, p, 0, 1, 1] += h0 * h1 * g1
                T[j, p, 1, 0, 0] += h1 * h0 * g0
                T[j, p, 1, 0, 1] += h1 * h0 * g1
                T[j, p, 1, 1, 0] += h1 * h1 * g0
                T[j, p, 1, 1, 1] += h1 * h1 * g1
                af = math.sqrt(v[p, 4 * s + 2] ** 2 + v[p, 4 * s + 3] ** 2) * w[s]
                Q[j, p] += r * r * r * af
                Q2[j, p] += r * r * af
        radius[j] = rmax
        # moments of the interpolant on the oversampled phase grid, then their coefficients
        mx = 0.0
        my = 0.0
        for s in range(n_s):
            mx += cf[0, 4 * s]
            my += cf[0, 4 * s + 1]
        mx /= n_s
        my /= n_s
        vm = np.empty(R)
        mom = np.empty(14)
        mc = np.zeros((2 * Km - 1, 14))
        for pm in range(n_m):
            for r in range(R):
                vm[r] = cf[0, r]
            for k in range(1, K):
                c = cos_m[pm, k]
                sn = sin_m[pm, k]
                for r in range(R):
                    vm[r] += c * cf[k, r] + sn * cf[K - 1 + k, r]
            for q in range(14):
                mom[q] = 0.0
            for s in range(n_s):
                h0 = vm[4 * s] - mx
                h1 = vm[4 * s + 1] - my
                g0 = vm[4 * s + 2] * w[s]
                g1 = vm[4 * s + 3] * w[s]
                mom[0] += g0
                mom[1] += g1
                mom[2] += h0 * g0
                mom[3] += h0 * g1
                mom[4] += h1 * g0
                mom[5] += h1 * g1
                mom[6] += h0 * h0 * g0
                mom[7] += h0 * h0 * g1
                mom[8] += h0 * h1 * g0
                mom[9] += h0 * h1 * g1
                mom[10] += h1 * h0 * g0
                mom[11] += h1 * h0 * g1
                mom[12] += h1 * h1 * g0
                mom[13] += h1 * h1 * g1
            for k in range(Km):
                c = (1.0 if k == 0 else 2.0) * cos_m[pm, k] / n_m
                for q in range(14):
                    mc[k, q] += c * mom[q]
            for k in range(1, Km):
                c = 2.0 * sin_m[pm, k] / n_m
                for q in range(14):
                    mc[Km - 1 + k, q] += c * mom[q]
        mom_coef[j] = mc

@njit(cache=True, parallel=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
def _blocks(coef, basis, wgt, bases, jc, src, frc):  # pragma: no cover - compiled
    """Source blocks of cilia ``jc``: block i (rows i * blk ... (i + 1) * blk of ``src`` and
    ``frc``, (len(jc) * blk, 3), z = 0, blk = P n_s) holds the resolved sources of cilium
    j = jc[i] -- its trigonometric interpolant (coef (N, 2K-1, n_s, 4)) at the P phases whose
    basis rows are ``basis[i]`` (len(jc), P, 2K-1), positions plus the base, forces times
    ``wgt`` (n_s,)."""
    n_s = coef.shape[2]
    nk = coef.shape[1]
    P = basis.shape[1]
    blk = P * n_s
    R = 4 * n_s
    for i in prange(jc.shape[0]):
        j = jc[i]
        o = i * blk
        cj = coef[j].reshape(nk, R)  # (k, (s, q)): the inner loop runs over R contiguous numbers
        v = np.empty(R)
        for p in range(P):
            e = basis[i, p, 0]
            for r in range(R):
                v[r] = e * cj[0, r]
            for k in range(1, nk):
                e = basis[i, p, k]
                for r in range(R):
                    v[r] += e * cj[k, r]
            for s in range(n_s):
                r = o + p * n_s + s
                src[r, 0] = v[4 * s] + bases[j, 0]
                src[r, 1] = v[4 * s + 1] + bases[j, 1]
                src[r, 2] = 0.0
                frc[r, 0] = v[4 * s + 2] * wgt[s]
                frc[r, 1] = v[4 * s + 3] * wgt[s]
                frc[r, 2] = 0.0


@njit(cache=True, parallel=True)
def _tier_bound(targets, centre, radius, R1, R2, R3, a1, b1, a2, b2, b3, out):  # pragma: no cover - compiled
    """out[i] = sum over the cilia j summed cheaply for targets[i] (M, 3) of the Taylor bound of
    their order (times 8 pi mu; module docstring), R the distance from the force centre c_j (in
    the plane z = 0), d = R - a_j:

    * R >= R1[j] (monopole): a1_j / R^2 + b1_j / d^3;
    * R2[j] <= R < R1[j] (dipole): a2_j / R^3 + b2_j / d^4;
    * R3[j] <= R < R2[j] (quadrupole): b3_j / d^4;

    the same rule as :func:`_traverse`. Closer cilia are resolved (exact); a cilium with
    R1[j] < 0 makes no flow."""
    n = centre.shape[0]
    for i in prange(targets.shape[0]):
        x = targets[i, 0]
        y = targets[i, 1]
        z2 = targets[i, 2] * targets[i, 2]
        acc = 0.0
        for j in range(n):
            if R1[j] < 0.0:
                continue
            dx = x - centre[j, 0]
            dy = y - centre[j, 1]
            R = math.sqrt(dx * dx + dy * dy + z2)
            d = R - radius[j]
            if R >= R1[j]:
                acc += a1[j] / (R * R) + b1[j] / (d * d * d)
            elif R >= R2[j]:
                acc += a2[j] / (R * R * R) + b2[j] / (d * d * d * d)
            elif R >= R3[j]:
                acc += b3[j] / (d * d * d * d)
        out[i] = acc


@njit(cache=True, inline="always")
def _close(seg, lo, hi, r, ranges, n_p, count):  # pragma: no cover - compiled
    """Write the open run [lo, hi) of order ``seg`` (0 monopole, 1 dipole, 2 quadrupole; -1 none)
    as source range r of the carrier segments (:func:`_traverse`) and count its pairs in
    count[seg]; returns the next range."""
    if seg < 0:
        return r
    base = 0 if seg == 0 else (n_p if seg == 1 else 4 * n_p)
    mult = 1 if seg == 0 else (3 if seg == 1 else 6)
    ranges[r, 0] = base + mult * lo
    ranges[r, 1] = base + mult * hi
    count[seg] += hi - lo
    return r + 1


@njit(cache=True, inline="always")
def _resolve(j, r, k, ranges, res_j, res_r):  # pragma: no cover - compiled
    """Record cilium j as resolved k, its block's range r left empty for the caller (:func:`_traverse`)."""
    res_j[k] = j
    res_r[k] = r
    ranges[r, 0] = 0
    ranges[r, 1] = 0


@njit(cache=True, inline="always")
def _window(x, y, x0, y0, h, nx, ny, reach):  # pragma: no cover - compiled
    """The columns gx0..gx1 and rows gy0..gy1 of the cells within ``reach`` of the cell of
    (x, y) (none: gx1 < gx0)."""
    ix = int(math.floor((x - x0) / h))
    iy = int(math.floor((y - y0) / h))
    gx0 = max(ix - reach, 0)
    gx1 = min(ix + reach, nx - 1)
    gy0 = max(iy - reach, 0)
    gy1 = min(iy + reach, ny - 1)
    if gx0 > gx1 or gy0 > gy1:  # the target is beside the grid: no cell is near it
        gx0 = 0
        gx1 = -1
    return gx0, gx1, gy0, gy1


@njit(cache=True, parallel=True)
def _upper(targets, cell_ptr, x0, y0, h, nx, ny, reach, n_always, uptr):  # pragma: no cover - compiled
    """uptr[i + 1] = an upper bound of target i's ranges (and resolved cilia) in
    :func:`_traverse`: the cilia of its cells, one run of far cilia before each column of cells
    and after the last, and the cilia always resolved."""
    for i in prange(targets.shape[0]):
        gx0, gx1, gy0, gy1 = _window(targets[i, 0], targets[i, 1], x0, y0, h, nx, ny, reach)
        k = gx1 - gx0 + 2 + n_always
        for gx in range(gx0, gx1 + 1):
            k += cell_ptr[gx * ny + gy1 + 1] - cell_ptr[gx * ny + gy0]
        uptr[i + 1] = k


@njit(cache=True, parallel=True)
def _traverse(targets, scx, scy, sR1, sR2, sR3, sj, cell_ptr, x0, y0, h, nx, ny, reach, far, always,
              uptr, nr, nres, counts, ranges, res_j, res_r):  # pragma: no cover - compiled
    """Per target i (M, 3) the list of source ranges of one ranged sum: each present cilium q
    (sorted by grid cell: centres scx, scy, the squares of the thresholds sR1, sR2, sR3, cilium
    index sj[q]) at the cheapest order whose bound meets the tolerance at its distance R from
    the target: its monopole carrier (row q) when R >= R1, else its three dipole carriers (rows
    n_p + 3q ...) when R >= R2, else its six quadrupole carriers (rows 4 n_p + 6q ...) when R >= R3,
    else its resolved block (an empty range, filled by the caller; the cilium and the range
    go to res_j, res_r). Consecutive cilia at the same order make one range.

    Only the cilia of the (2 reach + 1)^2 cells around the target's (origin x0, y0, nx x ny
    cells of side h; cell c holds the sorted cilia cell_ptr[c] ... cell_ptr[c + 1]) are looked
    at: every other cilium is further than reach h and is summed at the order ``far`` (0, 1 or 2),
    taken as the runs between those cells; the caller makes reach h at least the threshold of
    that order (max R1 for monopoles, max R2 for dipoles, with R1 = inf). The cilia ``always``
    (no finite threshold) are resolved for every target.

    Target i writes its ranges and resolved cilia from row uptr[i] on (:func:`_upper` bounds
    their number), and its counts: nr[i] ranges, nres[i] resolved cilia, counts[i] its pairs at
    the three cheap orders (:func:`_compact` then packs the rows)."""
    n_p = scx.shape[0]
    for i in prange(targets.shape[0]):
        x = targets[i, 0]
        y = targets[i, 1]
        z2 = targets[i, 2] * targets[i, 2]
        gx0, gx1, gy0, gy1 = _window(x, y, x0, y0, h, nx, ny, reach)
        r = uptr[i]
        k = uptr[i]
        seg = -1
        lo = 0
        hi = 0
        count = counts[i]
        count[:] = 0
        pos = 0
        for gx in range(gx0, gx1 + 2):
            if gx <= gx1:
                a = cell_ptr[gx * ny + gy0]
                b = cell_ptr[gx * ny + gy1 + 1]
            else:  # past the last column: the rest is far
                a = n_p
                b = n_p
            if a > pos:  # a run of far cilia
                if seg == far and hi == pos:
                    hi = a
                else:
                    r = _close(seg, lo, hi, r, ranges, n_p, count)
                    seg = far
                    lo = pos
                    hi = a
            for q in range(a, b):
                dx = x - scx[q]
                dy = y - scy[q]
                R2 = dx * dx + dy * dy + z2  # squared distance against squared thresholds
                if R2 >= sR1[q]:
                    t = 0
                elif R2 >= sR2[q]:
                    t = 1
                elif R2 >= sR3[q]:
                    t = 2
                else:
                    t = 3
                if t == seg and hi == q:
                    hi = q + 1
                    continue
                r = _close(seg, lo, hi, r, ranges, n_p, count)
                if t == 3:
                    seg = -1
                    _resolve(sj[q], r, k, ranges, res_j, res_r)
                    r += 1
                    k += 1
                else:
                    seg = t
                    lo = q
                    hi = q + 1
            if b > pos:
                pos = b
        r = _close(seg, lo, hi, r, ranges, n_p, count)
        for q in range(always.shape[0]):
            _resolve(always[q], r, k, ranges, res_j, res_r)
            r += 1
            k += 1
        nr[i] = r - uptr[i]
        nres[i] = k - uptr[i]


@njit(cache=True, parallel=True)
def _compact(uptr, nr, nres, ptr, rptr, ranges_u, res_j_u, res_r_u, ranges, res_j, res_r):  # pragma: no cover
    """Pack target i's rows of :func:`_traverse` (from uptr[i]) into CSR rows ptr[i] ... (ranges)
    and rptr[i] ... (resolved cilia, their range indices shifted along)."""
    for i in prange(nr.shape[0]):
        u = uptr[i]
        p = ptr[i]
        for q in range(nr[i]):
            ranges[p + q, 0] = ranges_u[u + q, 0]
            ranges[p + q, 1] = ranges_u[u + q, 1]
        rp = rptr[i]
        for q in range(nres[i]):
            res_j[rp + q] = res_j_u[u + q]
            res_r[rp + q] = res_r_u[u + q] - u + p


@njit(cache=True, parallel=True)
def _block_ranges(res_j, res_r, local, per, k, off, blk, out):  # pragma: no cover - compiled
    """The source range of each resolved pair q (cilium res_j[q]) in the sum of chunk k of the
    resolved blocks (cilia of local index l in chunk l // per, rows off + (l % per) blk ...),
    empty for another chunk's cilium: at row res_r[q] of ``out`` (the first chunk: the ranges of
    :func:`_traverse`), or at row q (``res_r`` empty: a later chunk's own ranges)."""
    direct = res_r.shape[0] == 0
    for q in prange(res_j.shape[0]):
        loc = local[res_j[q]]
        row = np.int64(q) if direct else res_r[q]
        if loc // per == k:
            out[row, 0] = off + (loc % per) * blk
            out[row, 1] = out[row, 0] + blk
        else:
            out[row, 0] = 0
            out[row, 1] = 0


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


@njit(cache=True)
def _carrier_sets(F, D, T, delta, u3, inv3, inv6, f3, f6, nu1, nu2, q3, q6):  # pragma: no cover - compiled
    """Per cilium j the carriers of the cheap orders about c_j (module docstring), for its
    moments F (N, 2), D (N, 2, 2), T (N, 2, 2, 2):

    * f3 (N, 3, 2): the dipole carriers' forces at c_j + delta_j u3_m (``inv3``: the inverse of
      their moment matrix), reproducing F and D; their third moments q3 (N,) = delta^3 sum |f3_m|
      and nu2 (N,) = nu(T - T_rep), T_rep their second moment;
    * f6 (N, 6, 2): the quadrupole carriers' forces at c_j + delta_j u_m (``inv6``:
      :data:`_UNIT_INV`), reproducing F, D and T; q6 (N,) = delta^3 sum |f6_m|;
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
        q3[j] = d2 * d * _solve_carriers(inv3, b, f3[j])
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


def _simpson(n: int) -> np.ndarray:
    if n < 3 or n % 2 == 0:
        raise ValueError(f"the table's s grid must have an odd number (>= 3) of points, got {n}")
    w = np.ones(n)
    w[1:-1:2] = 4.0
    w[2:-1:2] = 2.0
    return w / (3.0 * (n - 1))


@dataclass(frozen=True, eq=False)
class Carpet:
    """Cilia clamped at ``bases`` under one uniform field, with the flow they make.

    Parameters
    ----------
    bases : (N, 2) base points in the plane z = 0 (units of L); see :mod:`ciliary_carpet.carpet.layout`.
    chi_N : (N,) signed natural curvatures, each within the table's range.
    table : the ThrustTable of the field (chi_E, eta).
    phases : (N,) phases at t = 0 in [0, 1) (default all 0); see :mod:`ciliary_carpet.carpet.layout`.
    direction : field direction, radians anticlockwise from +y (the scene rotates with it).
    mu : fluid viscosity in model units (B tau / L^4); 1 by default.
    wall : distance h > 0 of a no-slip wall z = -h below the plane, or None (free space).
    scales : optional :class:`Scales` for output in SI units.
    backend : evaluator of the sums (:mod:`ciliary_carpet.stokes`); default Auto.
    blob : regularisation length eps of the Stokeslets (:data:`BLOB`, the filament radius), > 0
        and at most half the smallest distance between base points; None: singular Stokeslets
        (the flow is then unbounded at the filaments).

    Cilia whose chi_N does not flutter stand still in their equilibrium shape and make no flow.
    """

    bases: np.ndarray
    chi_N: np.ndarray
    table: ThrustTable
    phases: np.ndarray | None = None
    direction: float = 0.0
    mu: float = 1.0
    wall: float | None = None
    scales: Scales | None = None
    backend: Backend | None = None
    blob: float | None = BLOB
    _c: dict = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        b = np.asarray(self.bases, dtype=float)
        if b.ndim != 2 or b.shape[1] != 2 or b.shape[0] < 1:
            raise ValueError(f"bases must have shape (N, 2) with N >= 1, got {b.shape}")
        if not np.all(np.isfinite(b)):
            raise ValueError("bases contain NaN or inf")
        n = b.shape[0]
        c = np.broadcast_to(np.asarray(self.chi_N, dtype=float), (n,)).copy() if np.ndim(self.chi_N) == 0 \
            else np.asarray(self.chi_N, dtype=float)
        if c.shape != (n,):
            raise ValueError(f"chi_N must have shape ({n},) to match bases, got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("chi_N contains NaN or inf")
        p = np.zeros(n) if self.phases is None else np.asarray(self.phases, dtype=float)
        if p.shape != (n,) or not np.all(np.isfinite(p)):
            raise ValueError(f"phases must be {n} finite numbers, got shape {p.shape}")
        for k in ("direction", "mu"):
            v = getattr(self, k)
            if not isinstance(v, (int, float, np.floating)) or not math.isfinite(v):
                raise ValueError(f"{k} must be a finite number, got {v!r}")
        if self.mu <= 0:
            raise ValueError(f"mu must be positive, got {self.mu}")
        if self.wall is not None and not (math.isfinite(self.wall) and self.wall > 0):
            raise ValueError(f"wall must be a positive distance below the plane (or None), got {self.wall!r}")
        if self.blob is not None:
            try:
                e = float(self.blob)
            except (TypeError, ValueError):
                raise ValueError(f"blob must be a positive length (or None), got {self.blob!r}") from None
            if not (math.isfinite(e) and e > 0):
                raise ValueError(f"blob must be a positive length in units of L (the filament radius), got {e}")
            if n > 1:
                gap = float(cKDTree(b).query(b, k=2)[0][:, 1].min())
                if e > 0.5 * gap:
                    raise ValueError(f"blob = {e:g} is larger than half the smallest spacing of the base points "
                                     f"({gap:g} L): the blobs of neighbouring filaments would overlap")
            object.__setattr__(self, "blob", e)
        if not isinstance(self.table, ThrustTable):
            raise TypeError(f"table must be a ThrustTable, got {type(self.table).__name__}")
        object.__setattr__(self, "bases", b)
        object.__setattr__(self, "chi_N", c)
        object.__setattr__(self, "phases", np.mod(p, 1.0))
        object.__setattr__(self, "direction", float(self.direction))
        object.__setattr__(self, "mu", float(self.mu))
        object.__setattr__(self, "_c", self._prepare())
        self._warn_overlaps()

    # ------------------------------------------------------------------ precomputation
    def _prepare(self) -> dict:
        t = self.table
        n = self.n
        n_p, n_s = t.ds.sizes["phase"], t.ds.sizes["s"]
        s = t.ds.s.values
        w = _simpson(n_s)
        rot = self.rotation
        K = _modes(t)
        Km = 3 * (K - 1) + 1  # the moments are products of up to three K-band functions
        n_m = 2 * Km
        arg = 2.0 * math.pi * np.arange(n_p)[:, None] * np.arange(K)[None, :] / n_p
        arg_m = 2.0 * math.pi * np.arange(n_m)[:, None] * np.arange(Km)[None, :] / n_m
        mk = np.full(K, 2.0)
        mk[0] = 1.0
        if n_p % 2 == 0 and K - 1 == n_p // 2:
            mk[-1] = 1.0
        fl = np.zeros(n, bool)
        coef = np.empty((n, 2 * K - 1, n_s, 4), np.float32)
        mom_coef = np.empty((n, 2 * Km - 1, 14))
        centre, radius = np.empty((n, 2)), np.empty(n)
        F, D, T2, Q = np.empty((n, n_p, 2)), np.empty((n, n_p, 2, 2)), np.empty((n, n_p, 2, 2, 2)), np.empty((n, n_p))
        Q2 = np.empty((n, n_p))
        for lo in range(0, n, 128):  # in chunks: the full cycle data of a large carpet would not fit
            sl = slice(lo, min(n, lo + 128))
            cyc = t.cycles(self.chi_N[sl])  # raises TableError for chi_N outside the table
            fl[sl] = cyc["flutter"]
            for i in np.nonzero(~cyc["flutter"])[0]:  # still filaments: equilibrium shape, no force
                x, y = equilibrium_shape(CiliumParams(t.chi_E, t.eta, float(self.chi_N[lo + i])), s)
                cyc["x"][i], cyc["y"][i] = x[None], y[None]
            _cycle_data(cyc["x"], cyc["y"], cyc["fx"], cyc["fy"], rot, self.bases[sl], w, np.cos(arg), np.sin(arg),
                        mk, np.cos(arg_m), np.sin(arg_m), coef[sl], mom_coef[sl], centre[sl], radius[sl], F[sl], D[sl],
                        T2[sl], Q[sl], Q2[sl])
        period = np.full(n, np.nan)
        if np.any(fl):
            period[fl] = t.scalar("period", self.chi_N[fl])
        return dict(flutter=fl, n_s=n_s, n_phase=n_p, s=s, w=w, coef=coef, k=np.arange(K),
                    period=period, rate=np.where(fl, 1.0 / np.where(fl, period, 1.0), 0.0),
                    centre=centre, radius=radius, F=F, D=D, Q=Q, F_rms=np.sqrt((F ** 2).sum(-1).mean(axis=1)),
                    F_mean=F.mean(axis=1), D_mean=D.mean(axis=1), Q_mean=Q.mean(axis=1), hulls={}, memo={},
                    Q2=Q2, Q2_mean=Q2.mean(axis=1),
                    T=T2, T_mean=T2.mean(axis=1), mom_coef=mom_coef, k_m=np.arange(Km),
                    Q_max=Q.max(axis=1))

    def _warn_overlaps(self) -> None:
        c = self._c
        near = cKDTree(self.bases).query_ball_point(c["centre"], c["radius"])
        bad = [(i, j) for j in range(self.n) for i in near[j]
               if i != j and self.in_swept_region(self.bases[i][None], j)[0]]
        if bad:
            warnings.warn(f"{len(bad)} cilium base(s) lie inside another cilium's swept region, e.g. base "
                          f"{bad[0][0]} in cilium {bad[0][1]}'s: the model ignores contact and hydrodynamic "
                          "interaction between filaments, so such a layout is not physical; space the cilia "
                          "further apart", UserWarning, stacklevel=3)

    # ------------------------------------------------------------------ geometry and state
    @property
    def n(self) -> int:
        """Number of cilia."""
        return self.bases.shape[0]

    @property
    def rotation(self) -> np.ndarray:
        """2x2 rotation from the field frame (field along e2) to the lab frame."""
        a = self.direction
        return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])

    @property
    def periods(self) -> np.ndarray:
        """(N,) beat period of each cilium (NaN for still ones)."""
        return self._c["period"].copy()

    @property
    def flutter(self) -> np.ndarray:
        return self._c["flutter"].copy()

    @property
    def centres(self) -> np.ndarray:
        """(N, 2) force centres c_j (centroid of the swept samples)."""
        return self._c["centre"].copy()

    @property
    def radii(self) -> np.ndarray:
        """(N,) radius a_j of the swept region about c_j."""
        return self._c["radius"].copy()

    @property
    def mean_thrust(self) -> np.ndarray:
        """(N, 2) cycle-mean force on the fluid, lab frame (the table's thrust, rotated)."""
        return self._c["F_mean"].copy()

    @property
    def s(self) -> np.ndarray:
        return self._c["s"].copy()

    @property
    def kernel(self) -> Kernel:
        """The Green's function of the flow: regularised (blob) or singular, free or with the wall."""
        return make_kernel(None if self.wall is None else Wall(z=-float(self.wall)), self.blob or 0.0)

    def filament_distance(self, points, t: float) -> np.ndarray:
        """(M,) distance of ``points`` (M, 2) or (M, 3) from the nearest filament at time ``t``
        (to the sampled centre lines, the table's s grid; in-plane)."""
        p = np.asarray(points, dtype=float)[:, :2]
        pos, _, _ = self.state(t)
        return cKDTree(pos.reshape(-1, 2)).query(p)[0]

    def phase_at(self, t: float) -> np.ndarray:
        """(N,) phase of every cilium at time t, in [0, 1)."""
        return np.mod(self.phases + float(t) * self._c["rate"], 1.0)

    def state(self, t: float, js=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shapes and forces of all cilia (or of cilia ``js``) at time t.

        Returns positions (N, n_s, 2) (lab frame), force per length on the fluid (N, n_s, 2),
        and the phases (N,) (N = len(js) with ``js``)."""
        c = self._c
        ph = self.phase_at(t)
        coef, bases = c["coef"], self.bases
        if js is not None:
            js = np.asarray(js, dtype=np.int64).reshape(-1)
            ph, coef, bases = ph[js], coef[js], bases[js]
        arg = 2.0 * math.pi * ph[:, None] * c["k"][None, :]
        basis = np.concatenate([np.cos(arg), np.sin(arg[:, 1:])], axis=1)  # (N, 2K-1)
        vals = np.einsum("jk,jksq->jsq", basis, coef, dtype=float, optimize=True)
        return vals[..., :2] + bases[:, None, :], vals[..., 2:], ph

    def beat_velocity(self, t, js=None) -> np.ndarray:
        """Velocity d r_j / dt (s, t) of the filaments ``js`` (default all) at time ``t`` (a
        number, or one per cilium of ``js``): (len(js), n_s, 2), lab frame, in L / tau. The
        exact time derivative of the phase interpolant that :meth:`state` evaluates (its
        harmonics times 2 pi k / T_j); zero for still cilia."""
        c = self._c
        js = np.arange(self.n) if js is None else np.asarray(js, dtype=np.int64).reshape(-1)
        t = np.broadcast_to(np.asarray(t, dtype=float), js.shape)
        ph = np.mod(self.phases[js] + t * c["rate"][js], 1.0)
        k = c["k"]
        arg = 2.0 * math.pi * ph[:, None] * k[None, :]
        w = 2.0 * math.pi * k[None, :] * c["rate"][js][:, None]  # d(phase angle)/dt of harmonic k
        dbasis = np.concatenate([-w * np.sin(arg), (w * np.cos(arg))[:, 1:]], axis=1)  # (len(js), 2K-1)
        return np.einsum("jk,jksq->jsq", dbasis, c["coef"][js][..., :2], dtype=float, optimize=True)

    def cycle_samples(self, js) -> tuple[np.ndarray, np.ndarray]:
        """Positions and forces per length of cilia ``js`` at the table's phase samples:
        (len(js), n_phase, n_s, 2) each, lab frame."""
        c = self._c
        js = np.asarray(js, dtype=np.int64)
        ph = np.arange(c["n_phase"]) / c["n_phase"]
        arg = 2.0 * math.pi * ph[:, None] * c["k"][None, :]
        basis = np.concatenate([np.cos(arg), np.sin(arg[:, 1:])], axis=1)  # (phase, 2K-1)
        vals = np.einsum("pk,jksq->jpsq", basis, c["coef"][js], dtype=float, optimize=True)
        return vals[..., :2] + self.bases[js][:, None, None, :], vals[..., 2:]

    def in_swept_region(self, points, j: int, margin: float = 0.0) -> np.ndarray:
        """Whether points (M, 2) lie in the convex hull of cilium j's swept region grown by
        ``margin`` (conservative: the hull covers the region)."""
        p = np.asarray(points, dtype=float)[:, :2]
        hulls = self._c["hulls"]
        if j not in hulls:  # built when first asked for: most cilia never are
            try:
                hulls[j] = ConvexHull(self.cycle_samples([j])[0].reshape(-1, 2)).equations
            except Exception:  # degenerate (a straight still filament): its bounding disc is used
                hulls[j] = None
        eq = hulls[j]
        if eq is None:
            d = np.linalg.norm(p - self._c["centre"][j], axis=1)
            return d <= self._c["radius"][j] + margin
        return np.all(p @ eq[:, :2].T + eq[:, 2] <= margin, axis=1)

    # ------------------------------------------------------------------ flow
    def _delta(self) -> np.ndarray:
        """(N,) the carriers' scale delta_j = a_j / 2."""
        c = self._c
        if "delta" not in c:
            c["delta"] = 0.5 * np.maximum(c["radius"], 1e-12)
        return c["delta"]

    def _carriers(self, F: np.ndarray, D: np.ndarray, T: np.ndarray, delta: np.ndarray | None = None) -> dict:
        """The cheap orders' carriers for moments F (K, 2), D (K, 2, 2), T (K, 2, 2, 2) of cilia of
        carrier scale ``delta`` (K,) (default: every cilium's): the dipole and quadrupole forces
        f3 (K, 3, 2), f6 (K, 6, 2) and the bound terms nu1, nu2, q3, q6 (K,) of
        :func:`_carrier_sets`."""
        d = self._delta() if delta is None else delta
        k = F.shape[0]
        out = dict(f3=np.empty((k, 3, 2)), f6=np.empty((k, 6, 2)), nu1=np.empty(k), nu2=np.empty(k), q3=np.empty(k),
                   q6=np.empty(k))
        _carrier_sets(np.ascontiguousarray(F, dtype=float), np.ascontiguousarray(D, dtype=float),
                      np.ascontiguousarray(T, dtype=float), np.ascontiguousarray(d, dtype=float), _U3, _U3_INV,
                      _UNIT_INV, out["f3"], out["f6"], out["nu1"], out["nu2"], out["q3"], out["q6"])
        return out

    def _coefficients(self, level: str) -> dict:
        """Per cilium the force scale S and the bound coefficients (times 8 pi mu) that choose its
        order at a distance (module docstring): ``a1`` = C1 nu(D), ``b1`` = C2 Q2 / 2,
        ``a2`` = C2 nu(T - T_rep) / 2, ``b2`` = C3 (Q3 + q3) / 6, ``b3`` = C3 (Q3 + q6) / 6. For the
        ``point`` level their maxima over the cycle's phase samples (the exact terms times
        :data:`PHASE_MARGIN`, for the phases between the samples), S the r.m.s. of |F(t)|; for the
        ``mean`` level those of the cycle means, S = |Fbar|. Memoised."""
        c = self._c
        key = ("coef", level)
        if key not in c["memo"]:
            k = self.kernel
            n = self.n
            if level == "mean":
                car = self._carriers(c["F_mean"], c["D_mean"], c["T_mean"])
                nu1, nu2, q3, q6 = car["nu1"], car["nu2"], car["q3"], car["q6"]
                Q2, Q3 = c["Q2_mean"], c["Q_mean"]
                S = np.sqrt((c["F_mean"] ** 2).sum(-1)) * c["flutter"]
                margin = 1.0
            else:
                n_p = c["n_phase"]
                car = self._carriers(c["F"].reshape(-1, 2), c["D"].reshape(-1, 2, 2), c["T"].reshape(-1, 2, 2, 2),
                                     np.repeat(self._delta(), n_p))
                nu1, nu2 = (car[q].reshape(n, n_p).max(axis=1) for q in ("nu1", "nu2"))
                Q3 = c["Q_max"]
                q3, q6 = ((c["Q"] + car[q].reshape(n, n_p)).max(axis=1) - Q3 for q in ("q3", "q6"))
                Q2 = c["Q2"].max(axis=1)
                S = c["F_rms"] * c["flutter"]
                margin = PHASE_MARGIN
            c["memo"][key] = dict(S=S, a1=margin * k.c1 * nu1, b1=0.5 * k.c2 * Q2, a2=margin * 0.5 * k.c2 * nu2,
                                  b2=k.c3 / 6.0 * (Q3 + q3), b3=k.c3 / 6.0 * (Q3 + q6))
        return c["memo"][key]

    def _thresholds(self, tol: float, level: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per cilium the distances R1, R2, R3 from its force centre beyond which its monopole,
        dipole and quadrupole carriers meet the tolerance: the smallest R > a_j with
        R (A / R^p + B / (R - a)^(p + 1)) <= LOD_SLACK tol S (the left side decreases in R; A, B
        from :meth:`_coefficients`). -1 for a cilium that makes no flow, inf for one whose S is 0
        while it makes a flow (always resolved)."""
        co = self._coefficients(level)
        a = self._c["radius"]
        S = co["S"]
        target = LOD_SLACK * tol * S
        makes_flow = co["b3"] > 0  # Q3 > 0: some force on the fluid
        out = []
        for A, p, B in ((co["a1"], 2, co["b1"]), (co["a2"], 3, co["b2"]), (np.zeros_like(a), 3, co["b3"])):
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                g = lambda R: R * (A / R ** p + B / (R - a) ** (p + 1)) - target  # noqa: E731,B023
                lo = a.copy()
                hi = a + 1.0
                for _ in range(200):
                    grow = (g(hi) > 0) & (S > 0)
                    if not np.any(grow):
                        break
                    hi = np.where(grow, 2 * hi, hi)
                for _ in range(60):
                    mid = 0.5 * (lo + hi)
                    pos = g(mid) > 0
                    lo = np.where(pos, mid, lo)
                    hi = np.where(pos, hi, mid)
            R = hi * (1 + 1e-12) + 1e-12
            out.append(np.where(S > 0, np.minimum(R, 1e300), np.where(makes_flow, np.inf, -1.0)))
        return tuple(out)

    def _far_order(self, js: np.ndarray, R: tuple) -> int:
        """The order (0 monopole, 1 dipole, 2 quadrupole) of the cilia beyond the cells around a
        target with the least estimated cost per target, cells of side max R_f / 2 for order f
        (R = (R1, R2, R3) of the cilia ``js``): the cilia of the 5 x 5 cells are classified one by
        one (:data:`_CLASSIFY` kernel evaluations' worth each) and get their cheapest order, the
        others cost 1, 3 or 6 evaluations. Cilia spread evenly over their bounding box, the cells'
        box as a disc of radius 1.4 max R_f, median thresholds; the resolved cilia cost the same
        for every f and are left out."""
        cen = self._c["centre"][js]
        ext = np.ptp(cen, axis=0) + 2.0
        rho = js.size / float(ext[0] * ext[1])
        med = [float(np.median(r[js])) for r in R]

        def within(r):
            return min(float(js.size), rho * math.pi * min(r, 1e150) ** 2)

        cost = []
        for f, (Rf, sf) in enumerate(zip(R, (1.0, 3.0, 6.0))):
            rn = 1.4 * float(min(Rf[js].max(), 1e150))
            n_in = within(rn)
            edges = [min(r, rn) for r in med[f:]][::-1] + [rn]  # R3 <= ... <= rn
            price = (6.0, 3.0, 1.0)[:len(edges) - 1]  # inside: costlier orders closer in
            inside = sum(p * (within(b) - within(a)) for p, a, b in zip(price, edges[:-1], edges[1:]))
            cost.append(_CLASSIFY * n_in + inside + sf * (js.size - n_in))
        return int(np.argmin(cost))

    def _plan(self, tol: float, level: str) -> dict:
        """What an evaluation at (tol, level) reuses (memoised): the thresholds, the order ``far``
        of the cilia beyond the cells around a target, the cilia that are chosen per target
        (finite thresholds; ``sj``: sorted by the cells of a grid of side max R_far / 2,
        :func:`_traverse`) and those always resolved, the grid, and the carriers' fixed positions
        in that order: monopoles (at c_j), dipoles, quadrupoles."""
        key = ("plan", level, tol)
        memo = self._c["memo"]
        if key not in memo:
            if len(memo) > 32:
                memo.clear()
            c = self._c
            R1, R2, R3 = self._thresholds(tol, level)
            js = np.nonzero(np.isfinite(R3) & (R3 >= 0))[0]
            always = np.nonzero(np.isinf(R3))[0].astype(np.int64)
            reach = 2
            far = 0
            if js.size:
                cen = c["centre"][js]
                # Far cilia (beyond reach h) at one order f (:meth:`_far_order`), cells of side
                # max R_f / 2; the cheaper orders' thresholds made infinite. The mean flow (fields, the design's checks) keeps quadrupoles: its resolved blocks
                # (4160 sources a cilium) dominate its cost, the cheaper orders save about 2 % there
                # (benchmarks/bench_flow.py, levels), and their bounds, each near its budget, would
                # add up to LOD_SLACK tol: the design residuals' error bars grew from 0.01 to 0.04 rad.
                far = 2 if level == "mean" else self._far_order(js, (R1, R2, R3))
                R1 = np.where(R1 >= 0, np.inf, R1) if far >= 1 else R1  # the far cilia are summed at order f
                R2 = np.where(R2 >= 0, np.inf, R2) if far >= 2 else R2
                h = float(min((R1, R2, R3)[far][js].max(), 1e300)) / reach
                lo = cen.min(axis=0) - h
                span = cen.max(axis=0) + h - lo
                nx, ny = (int(min(max(1, math.ceil(v / h)), 4096)) for v in span)
                h = float(max(span[0] / nx, span[1] / ny, h))  # at most 4096 cells a side
                g = np.minimum(np.floor((cen - lo) / h).astype(np.int64), [nx - 1, ny - 1])
                cell = g[:, 0] * ny + g[:, 1]
                order = np.argsort(cell, kind="stable")
                cell_ptr = np.searchsorted(cell[order], np.arange(nx * ny + 1)).astype(np.int64)
                x0, y0 = float(lo[0]), float(lo[1])
            else:
                order, cell_ptr, x0, y0, h, nx, ny = np.zeros(0, np.int64), np.zeros(2, np.int64), 0.0, 0.0, 1.0, 1, 1
            sj = js[order].astype(np.int64)
            cen, dl = c["centre"][sj], self._delta()[sj][:, None, None]
            pos = np.concatenate([cen, (cen[:, None] + dl * _U3[None]).reshape(-1, 2),
                                  (cen[:, None] + dl * _UNIT[None]).reshape(-1, 2)])
            memo[key] = dict(R=(R1, R2, R3), sj=sj, always=always, carr_src=_pad(pos),
                             trav=(np.ascontiguousarray(cen[:, 0]), np.ascontiguousarray(cen[:, 1]), R1[sj] ** 2,
                                   R2[sj] ** 2, R3[sj] ** 2, sj, cell_ptr, x0, y0, h, nx, ny, reach, far, always))
        return memo[key]

    def _sum(self, targets: np.ndarray, ph: np.ndarray | None, F: np.ndarray, D: np.ndarray, T: np.ndarray,
             tol: float, error: bool, level: str) -> FlowSample:
        """Per point one ranged sum (:func:`_traverse`): every cilium at the cheapest order whose
        bound meets ``tol`` at its distance, its carriers reproducing its moments F, D, T about c_j,
        or its resolved sources. The resolved sources of a cilium: its line distribution at its
        phase ``ph[j]`` ((N,): the instantaneous flow), or at every phase sample of the table with
        weight 1 / n_phase (``ph=None``: the mean flow)."""
        c = self._c
        n = self.n
        nk = c["coef"].shape[1]
        K = (nk + 1) // 2

        def basis(phases):
            arg = 2.0 * math.pi * np.asarray(phases)[..., None] * np.arange(K)
            return np.ascontiguousarray(np.concatenate([np.cos(arg), np.sin(arg[..., 1:])], axis=-1))

        if ph is None:
            b_all = basis(np.arange(c["n_phase"]) / c["n_phase"])[None]
            wgt = c["w"] / c["n_phase"]
        else:
            wgt = c["w"]

        def blocks(jc, out_s, out_f):
            """The resolved sources and forces of cilia jc into out_s, out_f (len(jc) * blk, 3)
            (:func:`_blocks`)."""
            if ph is None:
                bs = np.ascontiguousarray(np.broadcast_to(b_all, (len(jc),) + b_all.shape[1:]))
            else:
                bs = np.empty((len(jc), 1, nk))
                _basis(ph[jc], K, bs)
            _blocks(c["coef"], bs, wgt, self.bases, np.asarray(jc, np.int64), out_s, out_f)

        blk = (c["n_phase"] if ph is None else 1) * c["n_s"]
        m = targets.shape[0]
        kernel = self.kernel
        evaluator = self.backend if self.backend is not None else _AUTO
        if tol == 0:  # the resolved sum itself: every source of every cilium that makes a flow, in chunks
            S = self._coefficients(level)["S"]
            js = np.nonzero(S > 0)[0]
            u = np.zeros((m, 3))
            per = max(1, _CHUNK_SOURCES // blk)
            for lo in range(0, js.size, per):
                jc = js[lo:lo + per]
                bsrc, bfrc = np.empty((len(jc) * blk, 3)), np.empty((len(jc) * blk, 3))
                blocks(jc, bsrc, bfrc)
                u += stokeslet_velocity(targets, bsrc, bfrc, self.mu, kernel=kernel, backend=self.backend)
            return FlowSample(velocity=u, error_bound=np.zeros(m), pairs={level: 0, "resolved": m * js.size},
                              tol=tol, work=dict(sources=m * js.size * blk, ranges=0,
                                                 orders=dict(monopole=0, dipole=0, quadrupole=0)))
        plan = self._plan(tol, level)
        sj = plan["sj"]
        n_car = 10 * sj.size
        car = self._carriers(F, D, T)
        # the ranges of every point, written into rows bounded by _upper, then packed (the
        # resolved blocks' ranges filled later); targets in parts when the bound is very large
        uptr = np.zeros(m + 1, np.int64)
        _upper(targets, *plan["trav"][6:13], plan["always"].size, uptr)
        np.cumsum(uptr, out=uptr)
        if uptr[-1] > _MAX_ROWS and m > 1:
            cut = np.searchsorted(uptr, np.arange(1, -(-int(uptr[-1]) // _MAX_ROWS)) * _MAX_ROWS)
            cut = np.unique(np.clip(cut, 1, m - 1))
            parts = [self._sum(t, ph, F, D, T, tol, error, level) for t in np.split(targets, cut)]
            return FlowSample(velocity=np.concatenate([q.velocity for q in parts]),
                              error_bound=np.concatenate([q.error_bound for q in parts]),
                              pairs={k: sum(q.pairs[k] for q in parts) for k in parts[0].pairs}, tol=tol,
                              work=dict(sources=sum(q.work["sources"] for q in parts),
                                        ranges=sum(q.work["ranges"] for q in parts),
                                        orders={k: sum(q.work["orders"][k] for q in parts)
                                                for k in parts[0].work["orders"]}))
        ranges_u, res_j_u, res_r_u = np.empty((int(uptr[-1]), 2), np.int64), np.empty(int(uptr[-1]), np.int64), \
            np.empty(int(uptr[-1]), np.int64)
        nr, nres, counts = np.empty(m, np.int64), np.empty(m, np.int64), np.empty((m, 3), np.int64)
        _traverse(targets, *plan["trav"], uptr, nr, nres, counts, ranges_u, res_j_u, res_r_u)
        ptr, rptr = np.zeros(m + 1, np.int64), np.zeros(m + 1, np.int64)
        np.cumsum(nr, out=ptr[1:])
        np.cumsum(nres, out=rptr[1:])
        ranges = np.empty((int(ptr[-1]), 2), np.int64)
        res_j, res_r = np.empty(int(rptr[-1]), np.int64), np.empty(int(rptr[-1]), np.int64)
        _compact(uptr, nr, nres, ptr, rptr, ranges_u, res_j_u, res_r_u, ranges, res_j, res_r)
        # The resolved blocks are made and summed in chunks of cilia of at most _CHUNK_SOURCES
        # sources (the resolved mean flow has 4160 per cilium: a whole carpet's would take hundreds
        # of MB, and fresh memory costs more than the sum); the first chunk carries the carriers
        # too, so that an instantaneous flow (65 sources per cilium: one chunk) is one ranged sum.
        used = np.zeros(n, bool)
        used[res_j] = True
        used = np.flatnonzero(used)
        per = max(1, _CHUNK_SOURCES // blk)
        local = np.zeros(n, np.int64)
        local[used] = np.arange(used.size)
        u = np.zeros((m, 3))
        for k in range(max(1, -(-used.size // per))):
            jc = used[k * per:(k + 1) * per]
            off = n_car if k == 0 else 0
            src, frc = np.empty((off + jc.size * blk, 3)), np.empty((off + jc.size * blk, 3))
            if k == 0:
                src[:n_car] = plan["carr_src"]
                frc[:n_car, :2] = np.concatenate([F[sj], car["f3"][sj].reshape(-1, 2), car["f6"][sj].reshape(-1, 2)])
                frc[:n_car, 2] = 0.0
                rng, p = ranges, ptr
                _block_ranges(res_j, res_r, local, per, k, off, blk, rng)
            else:
                rng, p = np.empty((res_j.size, 2), np.int64), rptr
                _block_ranges(res_j, np.zeros(0, np.int64), local, per, k, off, blk, rng)
            if jc.size:
                blocks(jc, src[off:], frc[off:])
            if src.shape[0] and rng.shape[0]:
                # the evaluator directly: every array here is made and checked by this method
                u += evaluator.ranged(kernel, targets, src, frc, p, rng, self.mu)
        cnt = counts.sum(axis=0)
        work = dict(sources=int(cnt[0] + 3 * cnt[1] + 6 * cnt[2] + res_j.size * blk), ranges=int(ptr[-1]),
                    orders=dict(monopole=int(cnt[0]), dipole=int(cnt[1]), quadrupole=int(cnt[2])))
        bound = np.zeros(m)
        if error and sj.size:
            R1, R2, R3 = plan["R"]
            co = self._coefficients(level)
            k3 = kernel.c3 / 6.0
            Q3 = c["Q_mean"] if ph is None else c["Q_max"]
            # the bound at the current moments (the thresholds used their maxima over the cycle)
            _tier_bound(targets, c["centre"], c["radius"], R1, R2, R3, kernel.c1 * car["nu1"], co["b1"],
                        0.5 * kernel.c2 * car["nu2"], k3 * (Q3 + car["q3"]), k3 * (Q3 + car["q6"]), bound)
            bound /= 8 * math.pi * self.mu
        pairs = {level: int(cnt.sum()), "resolved": int(res_j.size)}
        return FlowSample(velocity=u, error_bound=bound, pairs=pairs, tol=tol, work=work)

    def _targets(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] not in (2, 3):
            raise ValueError(f"points must have shape (M, 2) or (M, 3), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("points contain NaN or inf")
        if p.shape[1] == 2:
            p = np.concatenate([p, np.zeros((p.shape[0], 1))], axis=1)
        if self.wall is not None and np.any(p[:, 2] < -self.wall):
            raise ValueError(f"points lie below the wall at z = {-self.wall:g}")
        return np.ascontiguousarray(p)

    def _tol(self, tol) -> float:
        t = float(tol)
        if not 0 <= t < 1:
            raise ValueError(f"tol must be in [0, 1), got {tol!r}")
        return t

    def evaluate(self, points, t: float, tol: float = 1e-3, error: bool = True) -> FlowSample:
        """Fluid velocity at ``points`` (M, 2) or (M, 3) at time ``t``, levels ``point`` and
        ``resolved`` chosen per pair for tolerance ``tol`` (0 = everything resolved); see the
        module docstring for the bound. ``error`` also computes the per-point bound (O(M N))."""
        x = self._targets(points)
        tol = self._tol(tol)
        c = self._c
        ph = self.phase_at(t)
        mom = np.empty((self.n, c["mom_coef"].shape[2]))
        if "mom_coef_t" not in c:
            c["mom_coef_t"] = np.ascontiguousarray(c["mom_coef"].transpose(0, 2, 1))
        _moments_at(c["mom_coef_t"], ph, mom)
        F, D, T = mom[:, :2], mom[:, 2:6].reshape(-1, 2, 2), mom[:, 6:].reshape(-1, 2, 2, 2)
        return self._sum(x, ph, F, D, T, tol, error, "point")

    def velocity(self, points, t: float, tol: float = 1e-3) -> np.ndarray:
        """(M, 3) fluid velocity at ``points`` at time ``t`` (see :meth:`evaluate`)."""
        return self.evaluate(points, t, tol, error=False).velocity

    def evaluate_mean(self, points, tol: float = 1e-3, error: bool = True) -> FlowSample:
        """The time-averaged (steady) velocity: each cilium's flow averaged over its own cycle,
        levels ``mean`` and ``resolved`` (the phase samples' average) chosen per pair."""
        x = self._targets(points)
        tol = self._tol(tol)
        c = self._c
        return self._sum(x, None, c["F_mean"], c["D_mean"], c["T_mean"], tol, error, "mean")

    def mean_velocity(self, points, tol: float = 1e-3) -> np.ndarray:
        """(M, 3) time-averaged fluid velocity (see :meth:`evaluate_mean`)."""
        return self.evaluate_mean(points, tol, error=False).velocity

    def pathlines(self, seeds, t_span, **kwargs):
        """Path lines of tracers from ``seeds`` over ``t_span``: see
        :func:`ciliary_carpet.transport.pathlines.pathlines` for the keywords and the result."""
        from ciliary_carpet.transport.pathlines import pathlines

        return pathlines(self, seeds, t_span, **kwargs)
