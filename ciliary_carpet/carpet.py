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
Stokeslet of blob size ``blob`` (the filament radius; :mod:`ciliary_carpet.kernel`), so that the
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
tolerance is expected to meet it is used. Around the force centre c_j (the centroid of the cilium's swept samples;
every filament point lies within the radius a_j of it), with h = r - c, the moments
F = int f ds, D = int h f^T ds, T = int h h f ds (second moments) and Q3 = int |h|^3 |f| ds:

* ``point``: F(t), D(t) and T(t) at the current phase, carried by six point forces, one at c and
  five at c + delta u_m (u_m at 72 degree steps, delta = a/2), whose forces solve the 6 x 6
  moment system, so that they reproduce F, D and T exactly;
* ``mean``: the same with the cycle means (the steady, time-averaged flow only);
* ``resolved``: the full line distribution (for the mean flow: averaged over the phase samples).

Both cheap levels share the monopole, dipole and quadrupole with the resolved sum, so by
Taylor's theorem with remainder their error for a target at distance R > a from c is at most

    |u_level - u_resolved| <= C3 (Q3 + Q3_rep) / (6 * 8 pi mu (R - a)^4),

with Q3_rep = sum_m delta^3 |f_m| the third moment of the carrier and C3 the supremum of
|(h.grad)^3 G f| over unit in-plane h, f at unit distance (:attr:`Kernel.c3
<ciliary_carpet.kernel.Kernel.c3>`; sampled in the tests: 12.3 free, 12.9 times R^4 with a wall;
the constants 16 and 64 leave a margin). A pair is
summed cheaply when this bound is at most ``LOD_SLACK * tol * S_j / (8 pi mu R)``, where S_j is
the cilium's force scale (|Fbar_j| for the mean flow, the r.m.s. of |F_j(t)| over the cycle for
the instantaneous flow) and :data:`LOD_SLACK` = 8 a calibration, so that at every point

    |u - u_resolved| <= LOD_SLACK * tol * sum_j S_j / (8 pi mu |x - c_j|)

rigorously (the ``error_bound`` of the result: the pairs' bounds summed), while the measured error
stays below ``0.09 * tol`` times the same sum (tested; the worst-case alignments and signs that
the bound adds up do not occur, see :data:`LOD_SLACK`): ``tol`` is relative to the sum of the
cilia's far-field magnitudes (for a carpet whose cilia push roughly the same way, relative to |u|
itself). Measured on 10 x 10 and 30 x 30 carpets: see the tests and benchmarks/bench_flow.py.
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

from .kernel import C2_FREE, C2_WALL, C3_FREE, C3_WALL, Kernel, Wall, make_kernel
from .stokeslet import Auto, Backend, stokeslet_velocity

logger = logging.getLogger(__name__)

__all__ = ["Carpet", "Scales", "FlowSample", "C2_FREE", "C2_WALL", "C3_FREE", "C3_WALL", "LEVELS", "BLOB",
           "LOD_SLACK"]

LEVELS = ("mean", "point", "resolved")
_AUTO = Auto()
"""The evaluator of a carpet made without ``backend``."""
_CHUNK_SOURCES = 1 << 19
"""The resolved near-field sources of a flow evaluation are made and summed in chunks of cilia
of at most this many sources (3 MB per coordinate array): :meth:`Carpet._sum`."""
_UNIT = np.array([[0.0, 0.0]] + [[math.cos(2 * math.pi * m / 5 + math.pi / 2), math.sin(2 * math.pi * m / 5 + math.pi / 2)]
                                 for m in range(5)])
"""Carrier positions of the cheap levels for unit delta: the centre and a regular pentagon."""
_UNIT_INV = np.linalg.inv(np.stack([np.ones(6), _UNIT[:, 0], _UNIT[:, 1], _UNIT[:, 0] ** 2,
                                    _UNIT[:, 0] * _UNIT[:, 1], _UNIT[:, 1] ** 2]))
"""Inverse of the carrier's moment matrix (rows: the monomials 1, x, y, x^2, xy, y^2)."""
LOD_SLACK = 8.0
"""Calibration of the levels of detail: a pair is summed cheaply when its Taylor bound is at most
``LOD_SLACK * tol * S_j / (8 pi mu R)`` (module docstring). The bound adds worst-case magnitudes:
every pair's third-order term at its worst alignment, and all pairs with the same sign; in fact
the force density changes sign along the filament (the third moment cancels in part) and the
cilia's errors add with mixed signs. Measured (tests/test_carpet.py, 10 x 10 carpets with and
without wall, tol 1e-2 to 1e-4, four times and the mean flow, points 0.05 L from the swept
regions and beyond): with 8 the error stays below 0.09 tol sum_j S_j / (8 pi mu |x - c_j|) (free
space; 0.011 with a wall), i.e. an 11-fold margin left, while the near pairs fall 3-fold
(benchmarks/bench_flow.py, levels). The rigorous bound is still what ``error_bound`` reports."""
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
    the (point, source) interactions summed (the cost: each is one kernel evaluation), and
    ``ranges``, the source blocks of the sparse sum (per point one sweep over the carriers, and
    one block per near pair)."""

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


@njit(cache=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
def _moments_at(coef_t, ph, out):  # pragma: no cover - compiled
    """out[j, p] = a_0 + sum_{k=1}^{K-1} a_k cos(2 pi k ph_j) + b_k sin(2 pi k ph_j), the
    trigonometric interpolant of every cilium j at its phase ph[j], with coef_t[j, p] (2K-1,)
    holding a_0..a_{K-1} then b_1..b_{K-1} (the moments' coefficients stored transposed, so that
    each output is one contiguous dot product, which vectorises: the reordered sum differs by
    rounding only). The basis by the angle-addition recurrence (rounding grows like k eps: below
    1e-13 for the K <= 64 used)."""
    nk = coef_t.shape[2]
    K = (nk + 1) // 2
    cs = np.empty(K)
    sn = np.empty(K)
    b = np.empty(nk)
    for j in range(coef_t.shape[0]):
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
                F, D, T, Q):  # pragma: no cover - compiled
    """Per cilium j (parallel over j) of one chunk: rotate its cycle samples x, y, fx, fy
    (n, n_p, n_s) by ``rot`` into the lab frame, then

    * coef[j] (2K-1, n_s, 4): the trigonometric interpolant's coefficients in phase,
      a_k = mk_k / n_p sum_p v_p cos(2 pi k p / n_p), b_k = mk_k / n_p sum_p v_p sin(...)
      (``cos_p``, ``sin_p`` (n_p, K) hold the cosines and sines; v = x, y, fx, fy);
    * mom_coef[j] (2Km-1, 14): the coefficients (cos k = 0..Km-1, then sin k = 1..Km-1) of
      F (2), D (4) and T (8) of the interpolant about c_j = base + mean of the shape (its k = 0
      term), sampled at n_m = 2 Km phases (``cos_m``, ``sin_m`` (n_m, Km)): products of up
      to three functions of K harmonics hold 3 (K - 1) + 1 <= Km, so the samples alias nothing;
    * from the raw samples: centre[j] (the centroid of the swept samples, plus the base),
      radius[j], and per table phase F[j] (n_p, 2), D[j] (n_p, 2, 2), T[j] (n_p, 2, 2, 2) and
      Q[j] (n_p,) = sum_s w_s |h|^3 |f| about the centroid (Simpson weights ``w``)."""
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
                Q[j, p] += r * r * r * math.sqrt(v[p, 4 * s + 2] ** 2 + v[p, 4 * s + 3] ** 2) * w[s]
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

@njit(cache=True, parallel=True)
def _lod_bound(targets, centre, radius, q, active, near_ptr, near_j, out):  # pragma: no cover - compiled
    """out[i] = sum_j q_j / (R_ij - a_j)^4 over the active cilia j not listed for point i in
    ``near_j[near_ptr[i]:near_ptr[i + 1]]`` (ascending), R_ij the distance of targets[i] (M, 3)
    from the force centre c_j (in the plane z = 0): the levels of detail's Taylor bound."""
    n = centre.shape[0]
    for i in prange(targets.shape[0]):
        x = targets[i, 0]
        y = targets[i, 1]
        z2 = targets[i, 2] * targets[i, 2]
        k = near_ptr[i]
        end = near_ptr[i + 1]
        acc = 0.0
        for j in range(n):
            if k < end and near_j[k] == j:
                k += 1
                continue
            if active[j]:
                dx = x - centre[j, 0]
                dy = y - centre[j, 1]
                d = math.sqrt(dx * dx + dy * dy + z2) - radius[j]
                acc += q[j] / (d * d * d * d)
        out[i] = acc


@njit(cache=True, parallel=True)
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


@njit(cache=True, inline="always")
def _near_of(i, targets, cx, cy, r, order, cell_ptr, x0, y0, h, nx, ny, reach, out, k):  # pragma: no cover
    """The cilia near targets[i] (see :func:`_near_pairs`) written to out[k:] when ``out`` is
    not empty; returns the end of i's list (k plus their number)."""
    fill = out.shape[0] > 0
    x = targets[i, 0]
    y = targets[i, 1]
    z2 = targets[i, 2] * targets[i, 2]
    ix = int(math.floor((x - x0) / h))
    iy = int(math.floor((y - y0) / h))
    for gx in range(max(ix - reach, 0), min(ix + reach + 1, nx)):
        for gy in range(max(iy - reach, 0), min(iy + reach + 1, ny)):
            c = gx * ny + gy
            for q in range(cell_ptr[c], cell_ptr[c + 1]):
                j = order[q]
                dx = x - cx[j]
                dy = y - cy[j]
                if dx * dx + dy * dy + z2 <= r[j] * r[j]:
                    if fill:
                        out[k] = j
                    k += 1
    return k


@njit(cache=True, parallel=True)
def _near_pairs(targets, cx, cy, r, order, cell_ptr, x0, y0, h, nx, ny, reach, ptr, out):  # pragma: no cover
    """Near pairs (target i, cilium j) with |targets[i] - (cx_j, cy_j, 0)| <= r_j, the cilia
    binned on a grid of cells of side h >= max r / reach (origin x0, y0; nx x ny cells; cilia of
    cell c: order[cell_ptr[c]:cell_ptr[c + 1]]), so that the (2 reach + 1)^2 cells around a
    target's hold every cilium near it. Pass 1 (``out`` empty): ptr[i + 1] = the number of i's
    pairs; pass 2 (``ptr`` the CSR offsets, ``out`` of size ptr[-1]): out[ptr[i]:ptr[i + 1]]
    holds i's cilia in ascending order (indices into cx, cy, r). The caller allocates every
    array: a compiled function that returns new arrays turns a Ctrl-C that lands while they are
    boxed into a SystemError."""
    m = targets.shape[0]
    if out.shape[0] == 0:
        for i in prange(m):
            ptr[i + 1] = _near_of(i, targets, cx, cy, r, order, cell_ptr, x0, y0, h, nx, ny, reach, out, 0)
        return
    for i in prange(m):
        k0 = ptr[i]
        k = _near_of(i, targets, cx, cy, r, order, cell_ptr, x0, y0, h, nx, ny, reach, out, k0)
        for a in range(k0 + 1, k):  # insertion sort: a handful of cilia per target
            v = out[a]
            b = a - 1
            while b >= k0 and out[b] > v:
                out[b + 1] = out[b]
                b -= 1
            out[b + 1] = v


@njit(cache=True)
def _carrier_forces(F, D, T, delta, inv, fk, q_rep):  # pragma: no cover - compiled
    """Forces fk (N, 6, 2) of the six carriers at c_j + delta_j u_m reproducing F (N, 2),
    D (N, 2, 2) and T (N, 2, 2, 2) of each cilium about c_j (``inv``: the inverse moment matrix
    :data:`_UNIT_INV`), and their third moments q_rep (N,) = delta^3 sum_m |fk_m|."""
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
        acc = 0.0
        for m in range(6):
            gx = 0.0
            gy = 0.0
            for q in range(6):
                gx += inv[m, q] * b[q, 0]
                gy += inv[m, q] * b[q, 1]
            fk[j, m, 0] = gx
            fk[j, m, 1] = gy
            acc += math.sqrt(gx * gx + gy * gy)
        q_rep[j] = d2 * d * acc


@njit(cache=True, parallel=True)
def _near_ranges(near_ptr, near_j, pidx, chunk, slot, k, off, blk, n_car, gaps, ranges):  # pragma: no cover
    """Source ranges of each target i for chunk ``k`` of the near blocks (CSR by
    ``near_ptr``/``near_j``: i's near cilia, ascending). With ``gaps`` (chunk 0: ranges
    ``2 near_ptr[i] + i`` ... ``2 near_ptr[i + 1] + i + 1``) the carriers of every present cilium
    that is not near i (present cilium p's six at rows 6p ... 6p + 6: the runs between i's near
    cilia), interleaved with the near cilia's resolved blocks (rows off + slot[j] blk ... + blk);
    without (ranges near_ptr[i] ... near_ptr[i + 1]) the blocks only. A near cilium of another
    chunk gets an empty range."""
    for i in prange(near_ptr.shape[0] - 1):
        a = near_ptr[i]
        b = near_ptr[i + 1]
        r = 2 * a + i if gaps else a
        prev = 0
        for q in range(a, b):
            j = near_j[q]
            if gaps:
                p = pidx[j]
                ranges[r, 0] = 6 * prev
                ranges[r, 1] = 6 * p
                r += 1
                prev = p + 1
            if chunk[j] == k:
                ranges[r, 0] = off + slot[j] * blk
                ranges[r, 1] = off + (slot[j] + 1) * blk
            else:
                ranges[r, 0] = 0
                ranges[r, 1] = 0
            r += 1
        if gaps:
            ranges[r, 0] = 6 * prev
            ranges[r, 1] = n_car


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
    bases : (N, 2) base points in the plane z = 0 (units of L); see :mod:`ciliary_carpet.layout`.
    chi_N : (N,) signed natural curvatures, each within the table's range.
    table : the ThrustTable of the field (chi_E, eta).
    phases : (N,) phases at t = 0 in [0, 1) (default all 0); see :mod:`ciliary_carpet.layout`.
    direction : field direction, radians anticlockwise from +y (the scene rotates with it).
    mu : fluid viscosity in model units (B tau / L^4); 1 by default.
    wall : distance h > 0 of a no-slip wall z = -h below the plane, or None (free space).
    scales : optional :class:`Scales` for output in SI units.
    backend : evaluator of the sums (:mod:`ciliary_carpet.stokeslet`); default Auto.
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
        coef = np.empty((n, 2 * K - 1, n_s, 4))
        mom_coef = np.empty((n, 2 * Km - 1, 14))
        centre, radius = np.empty((n, 2)), np.empty(n)
        F, D, T2, Q = np.empty((n, n_p, 2)), np.empty((n, n_p, 2, 2)), np.empty((n, n_p, 2, 2, 2)), np.empty((n, n_p))
        for lo in range(0, n, 128):  # in chunks: the full cycle data of a large carpet would not fit
            sl = slice(lo, min(n, lo + 128))
            cyc = t.cycles(self.chi_N[sl])  # raises TableError for chi_N outside the table
            fl[sl] = cyc["flutter"]
            for i in np.nonzero(~cyc["flutter"])[0]:  # still filaments: equilibrium shape, no force
                x, y = equilibrium_shape(CiliumParams(t.chi_E, t.eta, float(self.chi_N[lo + i])), s)
                cyc["x"][i], cyc["y"][i] = x[None], y[None]
            _cycle_data(cyc["x"], cyc["y"], cyc["fx"], cyc["fy"], rot, self.bases[sl], w, np.cos(arg), np.sin(arg),
                        mk, np.cos(arg_m), np.sin(arg_m), coef[sl], mom_coef[sl], centre[sl], radius[sl], F[sl], D[sl],
                        T2[sl], Q[sl])
        period = np.full(n, np.nan)
        if np.any(fl):
            period[fl] = t.scalar("period", self.chi_N[fl])
        return dict(flutter=fl, n_s=n_s, n_phase=n_p, s=s, w=w, coef=coef, k=np.arange(K),
                    period=period, rate=np.where(fl, 1.0 / np.where(fl, period, 1.0), 0.0),
                    centre=centre, radius=radius, F=F, D=D, Q=Q, F_rms=np.sqrt((F ** 2).sum(-1).mean(axis=1)),
                    F_mean=F.mean(axis=1), D_mean=D.mean(axis=1), Q_mean=Q.mean(axis=1), hulls={}, radii={},
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

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shapes and forces of all cilia at time t.

        Returns positions (N, n_s, 2) (lab frame), force per length on the fluid (N, n_s, 2),
        and the phases (N,)."""
        c = self._c
        ph = self.phase_at(t)
        arg = 2.0 * math.pi * ph[:, None] * c["k"][None, :]
        basis = np.concatenate([np.cos(arg), np.sin(arg[:, 1:])], axis=1)  # (N, 2K-1)
        vals = np.einsum("jk,jksq->jsq", basis, c["coef"], optimize=True)
        return vals[..., :2] + self.bases[:, None, :], vals[..., 2:], ph

    def cycle_samples(self, js) -> tuple[np.ndarray, np.ndarray]:
        """Positions and forces per length of cilia ``js`` at the table's phase samples:
        (len(js), n_phase, n_s, 2) each, lab frame."""
        c = self._c
        js = np.asarray(js, dtype=np.int64)
        ph = np.arange(c["n_phase"]) / c["n_phase"]
        arg = 2.0 * math.pi * ph[:, None] * c["k"][None, :]
        basis = np.concatenate([np.cos(arg), np.sin(arg[:, 1:])], axis=1)  # (phase, 2K-1)
        vals = np.einsum("pk,jksq->jpsq", basis, c["coef"][js], optimize=True)
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
    def _carriers(self, F: np.ndarray, D: np.ndarray, T: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Six point forces per cilium reproducing F (N, 2), D (N, 2, 2) and T (N, 2, 2, 2) about
        c_j: positions (N, 6, 2) (fixed: c_j + delta_j u_m, delta_j = a_j / 2), forces (N, 6, 2)
        and their third moments Q3_rep (N,)."""
        pos = self._carrier_positions()
        fk, q_rep = np.empty((F.shape[0], 6, 2)), np.empty(F.shape[0])
        _carrier_forces(np.ascontiguousarray(F, dtype=float), np.ascontiguousarray(D, dtype=float),
                        np.ascontiguousarray(T, dtype=float), self._c["delta"], _UNIT_INV, fk, q_rep)
        return pos, fk, q_rep

    def _carrier_positions(self) -> np.ndarray:
        """(N, 6, 2) the carriers' fixed positions c_j + delta_j u_m, delta_j = a_j / 2 (made once)."""
        c = self._c
        if "cpos" not in c:
            c["delta"] = 0.5 * np.maximum(c["radius"], 1e-12)
            c["cpos"] = c["centre"][:, None, :] + c["delta"][:, None, None] * _UNIT[None]
        return c["cpos"]

    def _near_radius(self, Q: np.ndarray, S: np.ndarray, tol: float) -> np.ndarray:
        """Per cilium the distance R* beyond which the cheap level's bound
        C3 Q R / (6 (R - a)^4) <= LOD_SLACK tol S holds (inf when S = 0 but Q > 0)."""
        a = self._c["radius"]
        k = self.kernel.c3 * Q / (6.0 * LOD_SLACK)
        with np.errstate(divide="ignore", invalid="ignore"):
            g = lambda R: k * R - tol * S * (R - a) ** 4  # noqa: E731 -- decreasing past its root
            lo = a.copy()
            hi = a + 1.0
            for _ in range(200):
                grow = g(hi) > 0
                if not np.any(grow & (S > 0)):
                    break
                hi = np.where(grow & (S > 0), 2 * hi, hi)
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                pos = g(mid) > 0
                lo = np.where(pos, mid, lo)
                hi = np.where(pos, hi, mid)
        R = hi * (1 + 1e-12) + 1e-12
        R = np.where(S > 0, R, np.where(Q > 0, np.inf, a))
        return R

    def _near_radii(self, tol: float, level: str) -> np.ndarray:
        """:meth:`_near_radius` for the ``point`` level (second moments maximised over the cycle's
        phase samples, so that one radius serves every time) or the ``mean`` level; memoised per
        tolerance."""
        key = (level, tol)
        cache = self._c["radii"]
        if key not in cache:
            c = self._c
            if level == "mean":
                Qt = c["Q_mean"] + self._carriers(c["F_mean"], c["D_mean"], c["T_mean"])[2]
                S = np.sqrt((c["F_mean"] ** 2).sum(-1)) * c["flutter"]
            else:
                Qt = np.max([c["Q"][:, p] + self._carriers(c["F"][:, p], c["D"][:, p], c["T"][:, p])[2]
                             for p in range(c["n_phase"])], axis=0)
                S = c["F_rms"] * c["flutter"]
            R = self._near_radius(Qt, S, tol) if tol > 0 else np.full(self.n, np.inf)
            if len(cache) > 32:
                cache.clear()
            cache[key] = np.where((S > 0) | (Qt > 0), R, -1.0)
        return cache[key]

    def _grid(self, js: np.ndarray, r: np.ndarray) -> tuple:
        """Cilia ``js`` binned on a grid of cells of side at least max ``r`` / 2 (for
        :func:`_near_pairs`: each target searches the 5 x 5 cells around its own)."""
        cen = self._c["centre"][js]
        reach = 2
        h = float(min(r.max(), 1e300)) / reach
        lo = cen.min(axis=0) - h
        span = cen.max(axis=0) + h - lo
        nx, ny = (int(min(max(1, math.ceil(v / h)), 4096)) for v in span)
        h = float(max(span[0] / nx, span[1] / ny, h))  # at most 4096 cells a side
        g = np.minimum((np.floor((cen - lo) / h)).astype(np.int64), [nx - 1, ny - 1])
        cell = g[:, 0] * ny + g[:, 1]
        order = np.argsort(cell, kind="stable")
        ptr = np.searchsorted(cell[order], np.arange(nx * ny + 1)).astype(np.int64)
        cx, cy = np.ascontiguousarray(cen[:, 0]), np.ascontiguousarray(cen[:, 1])
        return (cx, cy, np.ascontiguousarray(np.minimum(r, 1e300)), order, ptr, float(lo[0]), float(lo[1]), h, nx,
                ny, reach)

    def _pairs(self, targets: np.ndarray, js: np.ndarray, r: np.ndarray, grid: tuple | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """Near pairs (point i, cilium j) with |x_i - c_j| <= r (cilia ``js``, radii ``r``) as CSR:
        ``ptr`` (M + 1,) and the cilia (ascending per point), by a compiled search over the cells
        of :meth:`_grid` (``grid``: its result, when cached)."""
        grid = self._grid(js, r) if grid is None else grid
        ptr = np.zeros(targets.shape[0] + 1, np.int64)
        _near_pairs(targets, *grid, ptr, np.zeros(0, np.int64))
        np.cumsum(ptr, out=ptr)
        out = np.empty(int(ptr[-1]), np.int64)
        if out.size:
            _near_pairs(targets, *grid, ptr, out)
        return ptr, js[out]

    def _plan(self, tol: float, level: str, active: np.ndarray) -> dict:
        """What an evaluation at (tol, level) reuses: the near radii, the cilia that carry carriers
        (active, or with a finite near radius) and their index among them, the carriers'
        positions and the grid of the near-pair search; memoised with the radii."""
        key = ("plan", level, tol)
        cache = self._c["radii"]
        if key not in cache:
            rstar = self._near_radii(tol, level)
            present = active | (rstar > 0)
            pj = np.nonzero(present)[0]
            pidx = np.full(self.n, -1, np.int64)
            pidx[pj] = np.arange(pj.size)
            cpos = self._carrier_positions()
            cand = np.nonzero(rstar > 0)[0]
            cache[key] = dict(rstar=rstar, present=present, pidx=pidx, cand=cand, n_car=6 * pj.size,
                              carr_src=_pad(cpos[present].reshape(-1, 2)),
                              grid=self._grid(cand, rstar[cand]) if cand.size else None)
        return cache[key]

    def _sum(self, targets: np.ndarray, ph: np.ndarray | None, F: np.ndarray, D: np.ndarray, T: np.ndarray,
             Q: np.ndarray, S: np.ndarray, tol: float, error: bool, cheap_level: str) -> FlowSample:
        """Per point: the carriers of every cilium not near it, and the resolved sources of its
        near cilia (one ranged sum per chunk of near cilia; see :func:`_near_ranges`). The resolved sources of a
        cilium: its line distribution at its phase ``ph[j]`` ((N,): the instantaneous flow), or at
        every phase sample of the table with weight 1 / n_phase (``ph=None``: the mean flow)."""
        c = self._c
        n = self.n
        active = S > 0
        _, cf, q_rep = self._carriers(F, D, T)
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

        n_res_src = (c["n_phase"] if ph is None else 1) * c["n_s"]
        m = targets.shape[0]
        kernel = self.kernel
        evaluator = self.backend if self.backend is not None else _AUTO
        if tol == 0:  # the resolved sum itself: every source of every active cilium, in chunks
            js = np.nonzero(active)[0]
            u = np.zeros((m, 3))
            per = max(1, _CHUNK_SOURCES // n_res_src)
            for lo in range(0, js.size, per):
                jc = js[lo:lo + per]
                bsrc, bfrc = np.empty((len(jc) * n_res_src, 3)), np.empty((len(jc) * n_res_src, 3))
                blocks(jc, bsrc, bfrc)
                u += stokeslet_velocity(targets, bsrc, bfrc, self.mu, kernel=kernel, backend=self.backend)
            return FlowSample(velocity=u, error_bound=np.zeros(m), pairs={cheap_level: 0, "resolved": m * js.size},
                              tol=tol, work=dict(sources=m * js.size * n_res_src, ranges=0))
        plan = self._plan(tol, cheap_level, active)
        present = plan["present"]
        n_car = plan["n_car"]
        u = np.zeros((m, 3))
        work = dict(sources=0, ranges=0)
        near_ptr, near_j = np.zeros(m + 1, np.int64), np.zeros(0, np.int64)
        if plan["cand"].size and m:
            near_ptr, near_j = self._pairs(targets, plan["cand"], plan["rstar"][plan["cand"]], plan["grid"])
        n_near = near_j.size
        if not n_car or not m:
            return FlowSample(velocity=u, error_bound=np.zeros(m), pairs={cheap_level: 0, "resolved": 0}, tol=tol,
                              work=work)
        # Per point one list of source ranges: the carriers of the cilia that are not near it (the
        # runs between its near cilia) and the resolved block of each near cilium (long ranges
        # vectorise in the kernel). The blocks are made and summed in chunks of cilia of at most
        # _CHUNK_SOURCES sources (the resolved mean flow has 4160 per cilium: a whole carpet's
        # would take hundreds of MB, and fresh memory costs more than the sum); the first chunk
        # carries the carriers too, so that an instantaneous flow (65 sources per cilium: one
        # chunk) is one ranged sum, one parallel region.
        blk = n_res_src
        used = np.zeros(n, bool)
        used[near_j] = True
        js = np.nonzero(used)[0]
        per = max(1, _CHUNK_SOURCES // blk)
        local = np.zeros(n, np.int64)
        local[js] = np.arange(js.size)
        slot, chunk = local % per, local // per
        n_chunks = max(1, -(-js.size // per))
        for k in range(n_chunks):
            jc = js[k * per:(k + 1) * per]
            off = n_car if k == 0 else 0
            src, frc = np.empty((off + jc.size * blk, 3)), np.empty((off + jc.size * blk, 3))
            if k == 0:
                src[:n_car] = plan["carr_src"]
                frc[:n_car, :2] = cf[present].reshape(-1, 2)
                frc[:n_car, 2] = 0.0
                ptr = 2 * near_ptr + np.arange(m + 1)
            else:
                ptr = near_ptr
            if jc.size:
                blocks(jc, src[off:], frc[off:])
            ranges = np.empty((int(ptr[-1]), 2), np.int64)
            _near_ranges(near_ptr, near_j, plan["pidx"], chunk, slot, k, off, blk, n_car, k == 0, ranges)
            # the evaluator directly: every array here is made and checked by this method (the
            # public front door's validation of them cost a fifth of a 100-tracer evaluation)
            u += evaluator.ranged(kernel, targets, src, frc, ptr, ranges, self.mu)
        # every point: the carriers of each present cilium not near it, the block of each near one
        work["sources"] = m * n_car + n_near * (blk - 6)
        work["ranges"] = m + n_near
        bound = np.zeros(m)
        if error and np.any(active):
            # per point, over the active cilia not summed resolved (near pairs listed by point)
            _lod_bound(targets, c["centre"], c["radius"], kernel.c3 * (Q + q_rep) / 6.0, active, near_ptr,
                       near_j, bound)
            bound /= 8 * math.pi * self.mu
        n_pairs = m * int(active.sum())
        n_res = int(np.sum(active[near_j])) if n_near else 0
        pairs = {cheap_level: n_pairs - n_res, "resolved": n_res}
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

        if "S_point" not in c:
            c["S_point"] = c["F_rms"] * c["flutter"]
        return self._sum(x, ph, F, D, T, c["Q_max"], c["S_point"], tol, error, "point")

    def velocity(self, points, t: float, tol: float = 1e-3) -> np.ndarray:
        """(M, 3) fluid velocity at ``points`` at time ``t`` (see :meth:`evaluate`)."""
        return self.evaluate(points, t, tol, error=False).velocity

    def evaluate_mean(self, points, tol: float = 1e-3, error: bool = True) -> FlowSample:
        """The time-averaged (steady) velocity: each cilium's flow averaged over its own cycle,
        levels ``mean`` and ``resolved`` (the phase samples' average) chosen per pair."""
        x = self._targets(points)
        tol = self._tol(tol)
        c = self._c

        S = np.sqrt((c["F_mean"] ** 2).sum(-1)) * c["flutter"]
        return self._sum(x, None, c["F_mean"], c["D_mean"], c["T_mean"], c["Q_mean"], S, tol, error, "mean")

    def mean_velocity(self, points, tol: float = 1e-3) -> np.ndarray:
        """(M, 3) time-averaged fluid velocity (see :meth:`evaluate_mean`)."""
        return self.evaluate_mean(points, tol, error=False).velocity

    def pathlines(self, seeds, t_span, **kwargs):
        """Path lines of tracers from ``seeds`` over ``t_span``: see
        :func:`ciliary_carpet.pathlines.pathlines` for the keywords and the result."""
        from .pathlines import pathlines

        return pathlines(self, seeds, t_span, **kwargs)
