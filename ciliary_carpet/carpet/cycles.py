"""The cilia's limit cycles in the lab frame: interpolation in phase, moments, the Simpson rule.

A carpet's cilium j beats on the limit cycle of its natural curvature chi_N_j, read from the
:class:`~single_cilium.table.ThrustTable` at the table's ``n_phase`` uniform phase samples and
``n_s`` uniform arc-length samples s, in the field frame (field along e2), rotated by the field
direction into the lab frame and placed at its base b_j. :class:`CycleData` holds, for all N
cilia of a carpet, built once:

* the trigonometric interpolant in phase of the shape r_j(s, phi) - b_j and of the force per
  length on the fluid f_j(s, phi) (``coef`` (N, 2K-1, n_s, 4), float32: the cosine coefficients
  k = 0..K-1, then the sine coefficients k = 1..K-1, of x, y, fx, fy; K the harmonics the table
  resolves), spectral because the cycle is smooth: :meth:`CycleData.state`,
  :meth:`CycleData.beat_velocity`, :meth:`CycleData.samples`, and the resolved line sources of an
  evaluation (:class:`~ciliary_carpet.carpet.blocks.ResolvedSources`);
* the force centre c_j (N, 2) (the centroid of the swept samples; every filament point lies
  within the radius a_j (N,) of it) and, about it, with h = r - c and the composite Simpson rule
  in s (:func:`simpson`), the moments at each phase sample: F = int f ds (N, n_phase, 2),
  D = int h f^T ds (N, n_phase, 2, 2), T = int h h f ds (N, n_phase, 2, 2, 2), Q = int |h|^3 |f| ds
  and Q2 = int |h|^2 |f| ds (N, n_phase); their cycle means; and the trigonometric interpolant of
  F, D, T in phase for any phase (:meth:`CycleData.moments_at`);
* the phases: phi_j(t) = phases[j] + t / T(chi_N_j) (mod 1), each cilium at its own period.

Still cilia (chi_N off the flutter branch) stand in their equilibrium shape with no force.

:class:`CycleMoments` is the same moment code (:func:`sample_moments`) as smooth functions of
chi_N: the cycle means of F and D, the centre offset and the radius of one cilium in the field
frame, interpolated by cubic splines in chi_N (the design model's, :mod:`ciliary_carpet.design.model`).

One concept over 500 lines: the cycle data and the compiled kernels that build and read it.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from scipy.spatial import ConvexHull

from single_cilium.equilibrium import equilibrium_shape
from single_cilium.params import CiliumParams
from single_cilium.table import ThrustTable

from ciliary_carpet.carpet.geometry import Embedding, planar

__all__ = ["CycleData", "harmonic_sum", "phase_basis", "sample_moments", "simpson", "trig_basis"]

_CHUNK = 128
"""Cilia whose table cycles are read and reduced at once (the full cycle data of a large carpet
would not fit in memory)."""


def simpson(n: int) -> np.ndarray:
    """(n,) weights of the composite Simpson rule on the uniform grid of n points on [0, 1]
    (n odd, >= 3): int_0^1 g(s) ds ~ sum_i w_i g(s_i). The one quadrature in arc length of the
    carpet, its design model and its omissions (the table's s grid)."""
    if n < 3 or n % 2 == 0:
        raise ValueError(f"the table's s grid must have an odd number (>= 3) of points, got {n}")
    w = np.ones(n)
    w[1:-1:2] = 4.0
    w[2:-1:2] = 2.0
    return w / (3.0 * (n - 1))


def _modes(table: ThrustTable, floor: float = 1e-7) -> int:
    """Number of phase harmonics (k = 0..K-1) above ``floor`` times the largest, over every row of
    the table (the table stores float32: its harmonics level off near 1e-8). A table stored with
    ``field_bits`` bits of mantissa (:func:`single_cilium.tablefile.compact`) is trusted to half
    its rounding, ``2**-(bits + 2)`` (3e-5 for 13 bits: the shipped flow table keeps 11 harmonics,
    as many as its full-precision original above that floor; the rest is rounding, and dropping it
    changes a 10 x 10 carpet's coupled flows by 5e-12 and its flow 0.05 L from a filament by
    1e-5). Counted once per table (a coupled solve builds a carpet per trial flow)."""
    bits = table.ds.attrs.get("field_bits")
    if bits is not None:
        floor = max(floor, 2.0 ** -(int(bits) + 2))
    key = ("_carpet_modes", floor)
    got = table.__dict__.get(key)
    if got is None:
        got = table.__dict__[key] = _count_modes(table, floor)
    return got


def _count_modes(table: ThrustTable, floor: float) -> int:
    fl = table.ds.flutter.values.astype(bool)
    if not np.any(fl):
        return 1
    amp = np.zeros(table.ds.sizes["phase"] // 2 + 1)
    for k in ("x", "y", "fx", "fy"):
        a = np.abs(np.fft.rfft(table.ds[k].values[fl].astype(float), axis=1)).max(axis=(0, 2))
        amp = np.maximum(amp, a / a.max())
    return int(np.nonzero(amp > floor)[0].max()) + 1


MOMENT_FLOOR = 1e-12
"""Harmonics of the moments' interpolant kept: up to the last whose amplitude (over every cilium)
exceeds this fraction of the largest of its moment component (:func:`_significant`)."""


def _significant(mom_coef: np.ndarray, Km: int) -> np.ndarray:
    """``mom_coef`` (N, 2Km-1, 14) (a_0..a_{Km-1}, then b_1..b_{Km-1}) cut to its harmonics
    0..K'-1, K' the last harmonic above :data:`MOMENT_FLOOR` of its component's largest, plus one.
    The moments are products of up to three K-band functions, so Km = 3 (K - 1) + 1 bounds their
    band; their amplitudes fall far faster (measured on the shipped table: below 1e-12 from
    k = 22 of Km = 40, rounding from k = 24): what is dropped is below rounding of the sources'
    own interpolant (float32), and every evaluation of a carpet's flow reads these coefficients
    for every cilium (the memory they take is its cost: 1.8 times less here)."""
    amp = np.abs(mom_coef[:, :Km])
    amp[:, 1:] = np.hypot(mom_coef[:, 1:Km], mom_coef[:, Km:])
    rel = amp.max(axis=0) / np.maximum(amp.max(axis=(0, 1)), 1e-300)  # (Km, 14)
    keep = np.nonzero((rel > MOMENT_FLOOR).any(axis=1))[0]
    k = int(keep.max()) + 1 if keep.size else 1
    return np.concatenate([mom_coef[:, :k], mom_coef[:, Km:Km + k - 1]], axis=1)


def trig_basis(phases, K: int) -> np.ndarray:
    """(..., 2K-1) the basis 1, cos(2 pi k phi), sin(2 pi k phi) (k = 1..K-1) of the interpolant
    at ``phases`` (...,)."""
    arg = 2.0 * math.pi * np.asarray(phases)[..., None] * np.arange(K)
    return np.ascontiguousarray(np.concatenate([np.cos(arg), np.sin(arg[..., 1:])], axis=-1))


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


@njit(cache=True, nogil=True, parallel=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
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


@njit(cache=True, nogil=True)
def phase_basis(ph, K, out):  # pragma: no cover - compiled
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



@njit(cache=True, inline="always")
def _rotated(x, y, fx, fy, rot, j, v):  # pragma: no cover - compiled
    """v (n_p, 4 n_s) = the cycle samples of cilium j, x, y, fx, fy (n, n_p, n_s), rotated by
    ``rot`` into the lab frame, flattened per phase as (s, q) with q = x, y, fx, fy: the inner
    loops of the callers run over 4 n_s contiguous numbers."""
    for p in range(x.shape[1]):
        for s in range(x.shape[2]):
            a = x[j, p, s]
            b = y[j, p, s]
            v[p, 4 * s] = rot[0, 0] * a + rot[0, 1] * b
            v[p, 4 * s + 1] = rot[1, 0] * a + rot[1, 1] * b
            a = fx[j, p, s]
            b = fy[j, p, s]
            v[p, 4 * s + 2] = rot[0, 0] * a + rot[0, 1] * b
            v[p, 4 * s + 3] = rot[1, 0] * a + rot[1, 1] * b


@njit(cache=True, nogil=True, parallel=True)
def sample_moments(x, y, fx, fy, rot, bases, w, centre, radius, F, D, T, Q, Q2):  # pragma: no cover - compiled
    """Per cilium j (parallel over j) the moments of its cycle samples x, y, fx, fy (n, n_p, n_s),
    rotated by ``rot`` into the lab frame: centre[j] (2,) the centroid of the swept samples plus
    bases[j], radius[j] the largest distance of a sample from it, and per phase sample p, with
    h = r - c and the Simpson weights ``w`` (n_s,), F[j, p] = sum_s w_s f (2,),
    D[j, p] = sum_s w_s h f^T (2, 2), T[j, p] = sum_s w_s h h f (2, 2, 2),
    Q[j, p] = sum_s w_s |h|^3 |f| and Q2[j, p] = sum_s w_s |h|^2 |f|."""
    n, n_p, n_s = x.shape
    for j in prange(n):
        v = np.empty((n_p, 4 * n_s))
        _rotated(x, y, fx, fy, rot, j, v)
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


@njit(cache=True, nogil=True, parallel=True)
def _interpolant(x, y, fx, fy, rot, w, cos_p, sin_p, mk, cos_m, sin_m, coef, mom_coef):  # pragma: no cover - compiled
    """Per cilium j (parallel over j) the trigonometric interpolant in phase of its cycle samples
    x, y, fx, fy (n, n_p, n_s), rotated by ``rot`` into the lab frame:

    * coef[j] (2K-1, n_s, 4), float32: its coefficients (rounded to single precision, the
      table's own: the near-field blocks made from them at every evaluation read half the memory),
      a_k = mk_k / n_p sum_p v_p cos(2 pi k p / n_p), b_k = mk_k / n_p sum_p v_p sin(...)
      (``cos_p``, ``sin_p`` (n_p, K) hold the cosines and sines; v = x, y, fx, fy);
    * mom_coef[j] (2Km-1, 14): the coefficients (cos k = 0..Km-1, then sin k = 1..Km-1) of
      F (2), D (4) and T (8) of the interpolant about c_j = base + mean of the shape (its k = 0
      term), with the Simpson weights ``w``, sampled at n_m = 2 Km phases (``cos_m``, ``sin_m``
      (n_m, Km)): products of up to three functions of K harmonics hold 3 (K - 1) + 1 <= Km, so
      the samples alias nothing."""
    n, n_p, n_s = x.shape
    K = cos_p.shape[1]
    n_m, Km = cos_m.shape
    R = 4 * n_s
    for j in prange(n):
        v = np.empty((n_p, R))  # (phase, (s, q)) flattened: the inner loops run over R contiguous numbers
        _rotated(x, y, fx, fy, rot, j, v)
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


@njit(cache=True, fastmath={"reassoc", "contract", "nsz", "arcp"}, inline="always")
def harmonic_sum(cj, b, v):  # pragma: no cover - compiled
    """v[p] (P, R) = sum_k b[p, k] cj[k] of a cilium's coefficients cj (2K-1, R) (float32, summed
    in float64) at the P basis rows b (P, 2K-1): two harmonics and two rows per pass over R (each
    coefficient read feeds four products)."""
    nk = cj.shape[0]
    R = cj.shape[1]
    P = b.shape[0]
    c0 = cj[0]
    for p in range(P):
        e = b[p, 0]
        vp = v[p]
        for r in range(R):
            vp[r] = e * c0[r]
    k = 1
    while k < nk:
        k1 = k + 1 if k + 1 < nk else k
        w = 1.0 if k1 > k else 0.0  # an odd count: the last harmonic alone
        c0 = cj[k]
        c1 = cj[k1]
        p = 0
        while p + 1 < P:
            a0 = b[p, k]
            a1 = w * b[p, k1]
            b0 = b[p + 1, k]
            b1 = w * b[p + 1, k1]
            va = v[p]
            vb = v[p + 1]
            for r in range(R):
                x0 = c0[r]
                x1 = c1[r]
                va[r] += a0 * x0 + a1 * x1
                vb[r] += b0 * x0 + b1 * x1
            p += 2
        if p < P:
            a0 = b[p, k]
            a1 = w * b[p, k1]
            va = v[p]
            for r in range(R):
                va[r] += a0 * c0[r] + a1 * c1[r]
        k += 2


@njit(cache=True, nogil=True, parallel=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
def _state(coef, basis, js, out):  # pragma: no cover - compiled
    """out[i] (n_s, 4) = sum_k basis[i, k] coef[js[i], k] (float32 coefficients read as they are,
    summed in float64; numpy's matmul would first copy every cilium's coefficients to float64)."""
    nk = coef.shape[1]
    R = 4 * coef.shape[2]
    for i in prange(js.shape[0]):
        cj = coef[js[i]].reshape(nk, R)  # the inner loop over R contiguous numbers
        o = out[i].reshape(R)
        e = basis[i, 0]
        for r in range(R):
            o[r] = e * cj[0, r]
        for k in range(1, nk):
            e = basis[i, k]
            for r in range(R):
                o[r] += e * cj[k, r]


class CycleData:
    """The limit cycles of a carpet's cilia in the lab frame and their moments (module
    docstring), built once per carpet.

    Parameters
    ----------
    table : the ThrustTable of the field (chi_E, eta).
    chi_N : (N,) signed natural curvatures, each within the table's range (TableError otherwise).
    bases : (N, 2) base points; phases : (N,) phases at t = 0 in [0, 1).
    rotation : (2, 2) from the field frame (field along e2) to the lab frame.
    background : (N, 2) or None, the uniform flow each cilium beats in (lab frame, L / tau; the
        table is read at U = rotation^T background, i.e. ``U_par`` along the field e2 and
        ``U_perp`` along e1: :mod:`single_cilium.flowtable`); None: still fluid. A table over
        the flow is needed for a non-zero flow. A cilium that does not flutter in its flow keeps
        the equilibrium shape of still fluid (the table stores no steady shape in a flow) with
        the steady state's force in the flow (the table's).
    embedding : the map of each cilium's 2D frame (where ``bases``, ``rotation`` and every 2D
        array here live) into space (:mod:`~ciliary_carpet.carpet.geometry`); default planar.

    Attributes
    ----------
    Arrays over the N cilia first; read them, do not write them.
    flutter (N,) bool: the cilium beats; period (N,): its beat period (NaN for still ones);
    rate (N,): 1 / period (0 for still ones); s (n_s,), weights (n_s,): the arc-length grid and
    its Simpson weights; n_s, n_phase: the table's samples; coef (N, 2K-1, n_s, 4): the
    interpolant's coefficients (float32); centre (N, 2), radius (N,): force centres c_j and swept
    radii a_j; F, D, T, Q, Q2: the moments per phase sample (N, n_phase, ...), with their cycle
    means F_mean, D_mean, T_mean, Q_mean, Q2_mean, the r.m.s. F_rms (N,) of |F| over the cycle
    and Q_max (N,) the largest Q; moment_coef (N, 14, 2Km-1): the coefficients in phase of
    (F, D, T) flattened to 14 numbers (:meth:`moments_at`).
    """

    def __init__(self, table: ThrustTable, chi_N: np.ndarray, bases: np.ndarray, phases: np.ndarray,
                 rotation: np.ndarray, background: np.ndarray | None = None, embedding: Embedding | None = None):
        n = bases.shape[0]
        embedding = planar(n) if embedding is None else embedding
        flow = {}
        if background is not None:  # the field-frame components (U_perp along e1, U_par along e2)
            u = np.asarray(background, dtype=float) @ rotation
            flow = {"U_perp": u[:, 0], "U_par": u[:, 1]}
        n_p, n_s = table.ds.sizes["phase"], table.ds.sizes["s"]
        s = table.ds.s.values
        w = simpson(n_s)
        K = _modes(table)
        Km = 3 * (K - 1) + 1  # the moments are products of up to three K-band functions
        n_m = 2 * Km
        arg = 2.0 * math.pi * np.arange(n_p)[:, None] * np.arange(K)[None, :] / n_p
        arg_m = 2.0 * math.pi * np.arange(n_m)[:, None] * np.arange(Km)[None, :] / n_m
        mk = np.full(K, 2.0)
        mk[0] = 1.0
        if n_p % 2 == 0 and K - 1 == n_p // 2:
            mk[-1] = 1.0
        trig = (np.cos(arg), np.sin(arg), mk, np.cos(arg_m), np.sin(arg_m))
        fl = np.zeros(n, bool)
        coef = np.empty((n, 2 * K - 1, n_s, 4), np.float32)
        mom_coef = np.empty((n, 2 * Km - 1, 14))
        centre, radius = np.empty((n, 2)), np.empty(n)
        F, D, T, Q = np.empty((n, n_p, 2)), np.empty((n, n_p, 2, 2)), np.empty((n, n_p, 2, 2, 2)), np.empty((n, n_p))
        Q2 = np.empty((n, n_p))
        for lo in range(0, n, _CHUNK):
            sl = slice(lo, min(n, lo + _CHUNK))
            cyc = table.cycles(chi_N[sl], **{k: v[sl] for k, v in flow.items()})  # TableError outside the table
            fl[sl] = cyc["flutter"]
            for i in np.nonzero(~cyc["flutter"])[0]:  # still filaments: equilibrium shape, no force
                x, y = equilibrium_shape(CiliumParams(table.chi_E, table.eta, float(chi_N[lo + i])), s)
                cyc["x"][i], cyc["y"][i] = x[None], y[None]
            xyf = (cyc["x"], cyc["y"], cyc["fx"], cyc["fy"], rotation)
            _interpolant(*xyf, w, *trig, coef[sl], mom_coef[sl])
            sample_moments(*xyf, bases[sl], w, centre[sl], radius[sl], F[sl], D[sl], T[sl], Q[sl], Q2[sl])
        period = np.full(n, np.nan)
        if np.any(fl):
            period[fl] = table.scalar("period", chi_N[fl], **{k: v[fl] for k, v in flow.items()})
        self.bases, self.phases, self.embedding = bases, phases, embedding
        self.flutter, self.period = fl, period
        self.rate = np.where(fl, 1.0 / np.where(fl, period, 1.0), 0.0)
        self.s, self.weights, self.n_s, self.n_phase = s, w, n_s, n_p
        self.coef, self.harmonics = coef, K
        self.centre, self.radius = centre, radius
        self.F, self.D, self.T, self.Q, self.Q2 = F, D, T, Q, Q2
        self.F_mean, self.D_mean, self.T_mean = F.mean(axis=1), D.mean(axis=1), T.mean(axis=1)
        self.Q_mean, self.Q2_mean, self.Q_max = Q.mean(axis=1), Q2.mean(axis=1), Q.max(axis=1)
        self.F_rms = np.sqrt((F ** 2).sum(-1).mean(axis=1))
        self.moment_coef = np.ascontiguousarray(_significant(mom_coef, Km).transpose(0, 2, 1))
        self._hulls: dict = {}

    @property
    def n(self) -> int:
        """Number of cilia."""
        return self.coef.shape[0]

    @property
    def centre3(self) -> np.ndarray:
        """(N, 3) the force centres in space (:attr:`embedding` of :attr:`centre`)."""
        if getattr(self, "_centre3", None) is None:
            self._centre3 = np.ascontiguousarray(self.embedding.points(self.centre))
        return self._centre3

    def phase_at(self, t, js=None) -> np.ndarray:
        """(N,) phase of every cilium (or of cilia ``js``) at time t, in [0, 1); (T, N) at T times
        ``t`` (T,). ``x - floor(x)`` is ``np.mod(x, 1)`` to the bit (both exact up to one rounding of
        the same number)."""
        t = np.asarray(t, dtype=float)
        p, r = (self.phases, self.rate) if js is None else (self.phases[js], self.rate[js])
        x = p + t[..., None] * r if t.ndim else p + float(t) * r
        x -= np.floor(x)
        return x

    def moments_at(self, phases: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """F (N, 2), D (N, 2, 2), T (N, 2, 2, 2) of every cilium at its phase ``phases`` (N,),
        from the interpolant of the moments (:func:`_moments_at`)."""
        mom = np.empty((self.n, self.moment_coef.shape[1]))
        _moments_at(self.moment_coef, phases, mom)
        return mom[:, :2], mom[:, 2:6].reshape(-1, 2, 2), mom[:, 6:].reshape(-1, 2, 2, 2)

    def state(self, t: float, js=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (N, n_s, 2) (lab frame), force per length on the fluid (N, n_s, 2) and phases
        (N,) of all cilia (or of cilia ``js``: N = len(js)) at time t."""
        js = np.arange(self.n) if js is None else np.asarray(js, dtype=np.int64).reshape(-1)
        ph = self.phase_at(t, js)
        basis = trig_basis(ph, self.harmonics)  # (N, 2K-1)
        vals = np.empty((js.size,) + self.coef.shape[2:])
        _state(self.coef, basis, js, vals)
        return vals[..., :2] + self.bases[js][:, None, :], vals[..., 2:], ph

    def beat_velocity(self, t, js=None) -> np.ndarray:
        """(len(js), n_s, 2) velocity d r_j / dt of the filaments ``js`` (default all) at time
        ``t`` (a number, or one per cilium of ``js``), lab frame: the exact time derivative of the
        interpolant :meth:`state` evaluates (its harmonics times 2 pi k / T_j); zero for still
        cilia."""
        js = np.arange(self.n) if js is None else np.asarray(js, dtype=np.int64).reshape(-1)
        t = np.broadcast_to(np.asarray(t, dtype=float), js.shape)
        ph = np.mod(self.phases[js] + t * self.rate[js], 1.0)
        k = np.arange(self.harmonics)
        arg = 2.0 * math.pi * ph[:, None] * k[None, :]
        w = 2.0 * math.pi * k[None, :] * self.rate[js][:, None]  # d(phase angle)/dt of harmonic k
        dbasis = np.concatenate([-w * np.sin(arg), (w * np.cos(arg))[:, 1:]], axis=1)  # (len(js), 2K-1)
        return np.einsum("jk,jksq->jsq", dbasis, self.coef[js][..., :2], dtype=float, optimize=True)

    def samples(self, js) -> tuple[np.ndarray, np.ndarray]:
        """Positions and forces per length of cilia ``js`` at the table's phase samples:
        (len(js), n_phase, n_s, 2) each, lab frame."""
        js = np.asarray(js, dtype=np.int64)
        basis = trig_basis(np.arange(self.n_phase) / self.n_phase, self.harmonics)  # (phase, 2K-1)
        vals = np.einsum("pk,jksq->jpsq", basis, self.coef[js], dtype=float, optimize=True)
        return vals[..., :2] + self.bases[js][:, None, None, :], vals[..., 2:]

    def in_swept_region(self, points, j: int, margin: float = 0.0) -> np.ndarray:
        """Whether points (M, 2) lie in the convex hull of cilium j's swept region grown by
        ``margin`` (conservative: the hull covers the region)."""
        p = np.asarray(points, dtype=float)[:, :2]
        if j not in self._hulls:  # built when first asked for: most cilia never are
            try:
                self._hulls[j] = ConvexHull(self.samples([j])[0].reshape(-1, 2)).equations
            except Exception:  # degenerate (a straight still filament): its bounding disc is used
                self._hulls[j] = None
        eq = self._hulls[j]
        if eq is None:
            d = np.linalg.norm(p - self.centre[j], axis=1)
            return d <= self.radius[j] + margin
        return np.all(p @ eq[:, :2].T + eq[:, 2] <= margin, axis=1)
