"""The carriers of many cilia at an instant, made in one compiled pass from the moments' interpolant.

The flow at an instant t needs every cilium's carrier forces (:mod:`~ciliary_carpet.carpet.carriers`)
at its phase phi_j(t): the moments F, D, T from the first ``kc`` harmonics of their trigonometric
interpolant (:attr:`CycleData.moment_coef <ciliary_carpet.carpet.cycles.CycleData.moment_coef>`),
solved for the dipole and quadrupole carriers and mapped into space by each cilium's frame. An
integrator asks for a few instants at a time (the stages of a step): :class:`InstantCarriers`
makes them together from one read of the coefficients (:func:`stacked_at`, lanes of
:data:`LANES` cilia as vectors, :class:`MomentRows`), the monopoles and dipoles at once and the
quadrupoles when a sum reads them, and the quadrupole carriers of groups of far cilia
(:class:`~ciliary_carpet.carpet.plan.FarGroups`; their bound in
:mod:`~ciliary_carpet.carpet.bounds`). The numbers are those of
:meth:`Carriers.forces <ciliary_carpet.carpet.carriers.Carriers.forces>` and
:meth:`Carriers.stacked <ciliary_carpet.carpet.carriers.Carriers.stacked>` to rounding.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ciliary_carpet.carpet.carriers import DIPOLE_INV, Carriers
from ciliary_carpet.stokes import QUADRUPOLE_INV

__all__ = ["InstantCarriers", "InstantForces", "LANES", "MomentRows", "moment_rows", "stacked_at", "stacked_forces"]


LANES = 32
"""Cilia side by side in :func:`stacked_at` (a block, one parallel task): every loop over them is
a vector loop (:class:`MomentRows` holds their coefficients lane by lane; a lazily made quadrupole
costs its whole block). The choice of 32 is measured in benchmarks/results/bench_evaluation.md."""
_TWO_PI = 2.0 * math.pi
_SIN = (-1.0 / 6, 1.0 / 120, -1.0 / 5040, 1.0 / 362880, -1.0 / 39916800, 1.0 / 6227020800, -1.0 / 1307674368000)
_COS = (-0.5, 1.0 / 24, -1.0 / 720, 1.0 / 40320, -1.0 / 3628800, 1.0 / 479001600, -1.0 / 87178291200,
        1.0 / 20922789888000)
MONO_DIPOLE, QUADRUPOLES, ALL_ORDERS = 0, 1, 2
"""What :func:`stacked_at` makes: the monopole and dipole carriers, the quadrupoles, or all."""


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
def stacked_at(coef, ph, delta, inv3, inv6, axes, js, blocks, want, kc, what, out):  # pragma: no cover - compiled
    """The carriers' forces in space of cilia js (n,) at each of T sets of phases ``ph`` (T, N), in
    the order of :meth:`Carriers.positions` of ``js``, as coordinate rows (out (T, 3, 10 n); only
    the rows of the cilia ``want`` (n,) bool and of ``what`` are written: :data:`MONO_DIPOLE`,
    :data:`QUADRUPOLES` or :data:`ALL_ORDERS`): per block of :data:`LANES` cilia (``blocks``, in
    parallel; cilium js[b LANES + l] in lane l of block b) and time their moments F, D (and T)
    from the first ``kc`` harmonics of their trigonometric interpolant (coef (nb, 14, 2 kc - 1,
    LANES), ``delta`` (nb, LANES), ``axes`` (nb, 3, 2, LANES): :class:`MomentRows`; :data:`~ciliary_carpet.carpet.carriers.MOMENT_ROWS`),
    the dipole carriers' forces f3 = inv3 (F, D_0 / delta, D_1 / delta) (:func:`~ciliary_carpet.carpet.carriers.dipole_forces`),
    the quadrupole carriers' f6 = inv6 (F, D / delta, T / delta^2) (:meth:`Carriers.forces
    <ciliary_carpet.carpet.carriers.Carriers.forces>`), each mapped into space by the cilium's axes
    (:meth:`Carriers.stacked <ciliary_carpet.carpet.carriers.Carriers.stacked>`). One pass for what
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
        for p in range(nrow):  # the rows of MOMENT_ROWS
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
    far cilia (:class:`~.plan.FarGroups`: the sorted cilia start[g] ... start[g + 1], its
    centre (G, 3) and scale ``delta`` (G,)) at each instant, in the plane, reproducing F, D and T
    about the centre of its cilia's dipole carriers (rows n + 3 q + m, at ``pos`` (3, 10 n)):
    the forces f = inv6 (F, D_x / delta, D_y / delta, T_xx / delta^2, T_xy / delta^2,
    T_yy / delta^2) of :meth:`Carriers.forces <ciliary_carpet.carpet.carriers.Carriers.forces>`. The rows' weights are made once for all instants,
    the sums run over each instant's contiguous rows (no square roots: the solve of
    :meth:`Carriers.forces <ciliary_carpet.carpet.carriers.Carriers.forces>` also sums the forces' norms; timings in benchmarks/results/bench_large.md).
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


@dataclass(frozen=True, eq=False)
class MomentRows:
    """What :func:`stacked_at` reads of cilia ``js``, in that order (the order a sum reads their
    carriers), in blocks of :data:`LANES` (cilium js[b LANES + l] in lane l of block b, the lanes
    past the last cilium zero): ``coef`` (nb, 14, 2 kc - 1, LANES) the moments' interpolant cut to
    its first ``kc`` harmonics (cosines 0 ... kc - 1, then sines 1 ... kc - 1), ``delta`` (nb,
    LANES) the carriers' scales (1 past the last cilium), ``axes`` (nb, 3, 2, LANES) the frames'
    axes in space. Every instant reads all of them: contiguous in the order of the sum, 10^4
    cilia take 1.5 times less than read from the full arrays (:func:`moment_rows`), and lane by
    lane every loop of the pass runs over vectors."""

    js: np.ndarray
    kc: int
    coef: np.ndarray
    delta: np.ndarray
    axes: np.ndarray


def moment_rows(carriers: Carriers, js: np.ndarray, kc: int) -> MomentRows:
    """The :class:`MomentRows` of cilia ``js`` (a plan's order) with ``kc`` harmonics (1 to all)."""
    c = carriers.cycles
    K = (c.moment_coef.shape[2] + 1) // 2
    kc = int(min(max(kc, 1), K))
    idx = np.asarray(js, dtype=np.int64)
    cols = np.r_[np.arange(kc), K + np.arange(kc - 1)]
    nb = -(-idx.size // LANES)
    coef = np.zeros((nb * LANES, 14, cols.size))
    coef[:idx.size] = c.moment_coef[idx][:, :, cols]
    delta = np.ones(nb * LANES)
    delta[:idx.size] = carriers.delta[idx]
    axes = np.zeros((nb * LANES, 3, 2))
    axes[:idx.size] = c.embedding.axes[idx]
    return MomentRows(js=js, kc=kc,
                      coef=np.ascontiguousarray(coef.reshape(nb, LANES, 14, cols.size).transpose(0, 2, 3, 1)),
                      delta=np.ascontiguousarray(delta.reshape(nb, LANES)),
                      axes=np.ascontiguousarray(axes.reshape(nb, LANES, 3, 2).transpose(0, 2, 3, 1)))


def stacked_forces(carriers: Carriers, phases: np.ndarray, js: np.ndarray, kc: int | None = None) -> np.ndarray:
    """The carriers' forces in space of cilia ``js`` at the phases ``phases`` (N,) of one
    instant, (10 len(js), 3), or (T, N) of T instants, (T, 10 len(js), 3): :meth:`Carriers.stacked
    <ciliary_carpet.carpet.carriers.Carriers.stacked>` of :meth:`Carriers.forces
    <ciliary_carpet.carpet.carriers.Carriers.forces>` of the moments there, in one compiled pass
    (:func:`stacked_at`; equal to rounding; T instants at once cost little more than one), from
    the first ``kc`` harmonics of the moments' interpolant (default all;
    :meth:`Carriers.harmonics <ciliary_carpet.carpet.carriers.Carriers.harmonics>`)."""
    return InstantCarriers(carriers, phases, js, kc, eager=True).forces


class InstantCarriers:
    """The carriers' forces in space of a plan's cilia ``js`` at T instants (their phases ``ph``
    (T, N), or (N,) for one), from the first ``kc`` harmonics (default all), as coordinate rows
    (T, 3, 10 n) in the order of :meth:`Carriers.positions` (into ``out`` when given and of that
    shape: a buffer no longer used, as a carpet recycles): the monopoles and dipoles of every
    cilium made at once (:func:`stacked_at`, one read of their coefficients for the T instants),
    the quadrupoles too when ``eager``, else on demand (:meth:`complete`: the cilia whose
    quadrupoles an evaluation reads, made for the T instants together). A carpet whose far cilia
    are dipoles (100 x 100: 10^4 cilia, about a quarter of them near a tracer) reads 6 of the 12
    rows for most of them. ``groups`` (a plan's :class:`~.plan.FarGroups` and its carriers'
    positions (3, 10 n)): the groups' six carriers each, after the cilia's (rows 10 n + 6 g ...),
    made with the monopoles and dipoles (:func:`_group_forces`). ``dtype``: the forces' type
    (float32 for sums in fp32: computed in fp64, rounded as they are stored). ``rows``: the
    :class:`MomentRows` of ``js`` with these harmonics, when the caller keeps them (made here
    otherwise)."""

    def __init__(self, carriers: Carriers, ph: np.ndarray, js: np.ndarray, kc: int | None = None,
                 eager: bool = False, out: np.ndarray | None = None, groups=None, dtype=np.float64,
                 rows: MomentRows | None = None):
        ph = np.asarray(ph, dtype=float)
        self.many = ph.ndim == 2
        self.ph = np.ascontiguousarray(ph if self.many else ph[None])
        self.js = np.ascontiguousarray(js, dtype=np.int64)
        self.carriers = carriers
        K = (carriers.cycles.moment_coef.shape[2] + 1) // 2
        self.kc = K if kc is None else int(min(max(kc, 1), K))
        self.rows = rows if rows is not None and rows.js is js and rows.kc == self.kc else moment_rows(carriers, js, self.kc)
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
        stacked_at(r.coef, self.ph, r.delta, DIPOLE_INV, QUADRUPOLE_INV, r.axes, self.js, blocks, want, self.kc,
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
