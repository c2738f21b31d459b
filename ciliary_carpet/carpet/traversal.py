"""The ranged sums of an evaluation: which carriers or sources each target sums, and the sums.

Given the thresholds R1, R2, R3 of every cilium (:meth:`~.bounds.Bounds.thresholds`), each
target x (M, 3) sums cilium j at the cheapest order its distance |x - c_j| reaches: its monopole
carrier (R >= R1), its three dipole carriers (R >= R2), its six quadrupole carriers (R >= R3), or
its resolved line sources (closer; :class:`~.blocks.ResolvedSources`). All of it is two sparse
"ranged" sums of the backend (:meth:`Backend.ranged <ciliary_carpet.stokes.backend.Backend.ranged>`):
one over the carriers of every cilium (monopoles, then dipoles, then quadrupoles, cilia sorted
by grid cell: :meth:`~.carriers.Carriers.positions`), read where they lie, one over the
resolved blocks; each target reads a list of row ranges of them (CSR: ``ptr`` (M + 1,),
``ranges`` (R, 2)).

What each target reads is fixed by the :class:`~ciliary_carpet.carpet.plan.Plan` of the
evaluation's tolerance (:mod:`~ciliary_carpet.carpet.plan`): its thresholds, grid, far order and
groups of far cilia. :func:`flow_sum` makes and runs the sum (targets in parts when their ranges would take more than
:data:`_MAX_ROWS` rows; the resolved blocks in chunks of at most :data:`_CHUNK_SOURCES` sources),
:func:`dense_sum` the resolved sum of every source (tol = 0). Both return a :class:`Summed`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ciliary_carpet.carpet.blocks import ResolvedSources
from ciliary_carpet.carpet.plan import Plan
from ciliary_carpet.stokes import Direct, Kernel, in_fp32, ranged_backend, ranged_fp32
from ciliary_carpet.stokes import stokeslet_velocity

__all__ = ["Summed", "flow_sum", "dense_sum"]

_FP32 = Direct("fp32")  # what in_fp32 gives where the far sums may run in fp32

_MAX_ROWS = 1 << 23
"""An evaluation's targets are taken in parts when their source ranges could take more rows than
this (128 MB: :func:`_upper`, :func:`_lists`)."""
_CHUNK_SOURCES = 1 << 19
"""The resolved near-field sources of a flow evaluation are made and summed in chunks of cilia
of at most this many sources (3 MB per coordinate array): :func:`flow_sum`."""


@njit(cache=True, inline="always")
def _close(seg, lo, hi, r, ranges, n_p, count):  # pragma: no cover - compiled
    """Write the open run [lo, hi) of order ``seg`` (0 monopole, 1 dipole, 2 quadrupole, 3 groups
    of far cilia; -1 none) as source range r of the carrier segments (:func:`_traverse`) and
    count its pairs in count[seg]; returns the next range."""
    if seg < 0:
        return r
    base = 0 if seg == 0 else (n_p if seg == 1 else (4 * n_p if seg == 2 else 10 * n_p))
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


@njit(cache=True, inline="always")
def _upper(x, y, cell_ptr, x0, y0, h, nx, ny, reach, n_always, n_groups):  # pragma: no cover - compiled
    """An upper bound of the ranges (and resolved cilia) of a target at (x, y) in
    :func:`_traverse`: the cilia of its cells, one run of far cilia before each column of cells
    and after the last (or one range per group of far cilia, ``n_groups`` of them), and the
    cilia always resolved."""
    gx0, gx1, gy0, gy1 = _window(x, y, x0, y0, h, nx, ny, reach)
    k = gx1 - gx0 + 2 + n_always + n_groups
    for gx in range(gx0, gx1 + 1):
        k += cell_ptr[gx * ny + gy1 + 1] - cell_ptr[gx * ny + gy0]
    return k


@njit(cache=True, nogil=True)
def _traverse(targets, scx, scy, scz, sR1, sR2, sR3, sj, cell_ptr, x0, y0, h, nx, ny, reach, far, always,
              gstart, gof, gcx, gcy, gcz, gR2, gcell, gcell_ptr, call2, cnone2, uptr, nr, nres, counts, ranges, res_j,
              res_r):  # pragma: no cover - compiled
    """For each target i of ``targets`` (M, 3) the list of source ranges of one ranged sum (one
    call for all the targets: a call per target passed its two dozen arrays each time, which
    took as long as the traversal on 100 cilia): each
    present cilium q (sorted by grid cell: centres scx, scy, scz, the squares of the thresholds
    sR1, sR2, sR3, cilium index sj[q]) at the cheapest order whose bound meets the tolerance at its distance R from
    the target: its monopole carrier (row q) when R >= R1, else its three dipole carriers (rows
    n_p + 3q ...) when R >= R2, else its six quadrupole carriers (rows 4 n_p + 6q ...) when R >= R3,
    else its resolved block (an empty range, summed apart by the caller; the cilium and the range
    go to res_j, res_r). Consecutive cilia at the same order make one range.

    Only the cilia of the (2 reach + 1)^2 cells around the target's (origin x0, y0, nx x ny
    cells of side h; cell c holds the sorted cilia cell_ptr[c] ... cell_ptr[c + 1]) are looked
    at (the grid is over x, y: a distance in space is at least the one in the plane): every
    other cilium is further than reach h and is summed at the order ``far`` (0, 1 or 2),
    taken as the runs between those cells; the caller makes reach h at least the threshold of
    that order (max R1 for monopoles, max R2 for dipoles, with R1 = inf). The cilia ``always``
    (no finite threshold) are resolved for every target.

    Groups of far cilia (``gstart`` (G + 1,): group g holds the sorted cilia gstart[g] ...
    gstart[g + 1], groups tiling the cells in order; ``gof`` (n_p,) the group of each sorted
    cilium; centres ``gcx``, ``gcy``, ``gcz``; ``gR2`` the squares of their distances of
    acceptance, :func:`make_plan`): where given (G >= 1), the far cilia are taken group by
    group, a group at its six carriers (rows 10 n_p + 6 g ...) when the target is at least its
    distance away, else its cilia at the order ``far``; cell by cell first (``gcell`` (G,) the
    cell of each group, ``gcell_ptr`` the groups of each cell, ``call2`` and ``cnone2`` the
    squared distances from a cell's centre beyond which all its groups are taken as groups and
    below which none is: a group's distance plus, or minus, its centre's distance from the cell's).

    Target i writes its ranges and resolved cilia from row uptr[i] on (:func:`_upper` bounds
    their number), and its counts: nr[i] ranges, nres[i] resolved cilia, counts[i] its pairs at
    the three cheap orders and the groups (:func:`_compact` then packs the rows)."""
    n_p = scx.shape[0]
    for i in range(targets.shape[0]):
        x = targets[i, 0]
        y = targets[i, 1]
        z = targets[i, 2]
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
            if a > pos and gstart.shape[0] > 1:  # far cilia by their groups, cell by cell: a cell whose
                c = gcell[gof[pos]]                 # groups are all past (or all short of) their distances
                while c < cell_ptr.shape[0] - 1 and cell_ptr[c] < a:  # at once, else group by group
                    c0 = cell_ptr[c]
                    c1 = cell_ptr[c + 1]
                    if c1 > c0:
                        g0 = gcell_ptr[c]
                        g1 = gcell_ptr[c + 1]
                        cgx = c // ny
                        dx = x - (x0 + (cgx + 0.5) * h)
                        dy = y - (y0 + (c - cgx * ny + 0.5) * h)
                        dz = z - gcz[g0]
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 >= call2[c]:
                            if not (seg == 3 and hi == g0):
                                r = _close(seg, lo, hi, r, ranges, n_p, count)
                                seg = 3
                                lo = g0
                            hi = g1
                        elif d2 < cnone2[c]:
                            if not (seg == far and hi == c0):
                                r = _close(seg, lo, hi, r, ranges, n_p, count)
                                seg = far
                                lo = c0
                            hi = c1
                        else:
                            for g in range(g0, g1):
                                dx = x - gcx[g]
                                dy = y - gcy[g]
                                dz = z - gcz[g]
                                if dx * dx + dy * dy + dz * dz >= gR2[g]:
                                    if not (seg == 3 and hi == g):
                                        r = _close(seg, lo, hi, r, ranges, n_p, count)
                                        seg = 3
                                        lo = g
                                    hi = g + 1
                                else:
                                    if not (seg == far and hi == gstart[g]):
                                        r = _close(seg, lo, hi, r, ranges, n_p, count)
                                        seg = far
                                        lo = gstart[g]
                                    hi = gstart[g + 1]
                    c += 1
            elif a > pos:  # a run of far cilia
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
                dz = z - scz[q]
                R2 = dx * dx + dy * dy + dz * dz  # squared distance against squared thresholds
                if R2 >= sR1[q]:
                    t = 0
                elif R2 >= sR2[q]:
                    t = 1
                elif R2 >= sR3[q]:
                    t = 2
                else:
                    t = 4
                if t == seg and hi == q:
                    hi = q + 1
                    continue
                r = _close(seg, lo, hi, r, ranges, n_p, count)
                if t == 4:
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


@njit(cache=True, inline="always")
def _compact(i, uptr, nr, nres, ptr, rptr, ranges_u, res_j_u, res_r_u, ranges, res_j, res_r):  # pragma: no cover
    """Pack target i's rows of :func:`_traverse` (from uptr[i]) into CSR rows ptr[i] ... (ranges)
    and rptr[i] ... (resolved cilia, their range indices shifted along)."""
    u = uptr[i]
    p = ptr[i]
    for q in range(nr[i]):
        ranges[p + q, 0] = ranges_u[u + q, 0]
        ranges[p + q, 1] = ranges_u[u + q, 1]
    rp = rptr[i]
    for q in range(nres[i]):
        res_j[rp + q] = res_j_u[u + q]
        res_r[rp + q] = res_r_u[u + q] - u + p


@njit(cache=True, nogil=True, parallel=True)
def _block_ranges(res_j, local, per, k, blk, out):  # pragma: no cover - compiled
    """out[q] = the source range of resolved pair q (cilium res_j[q]) in the sum of chunk k of the
    resolved blocks (cilia of local index l in chunk l // per, rows (l % per) blk ...), empty
    for another chunk's cilium."""
    for q in prange(res_j.shape[0]):
        loc = local[res_j[q]]
        if loc // per == k:
            out[q, 0] = (loc % per) * blk
            out[q, 1] = out[q, 0] + blk
        else:
            out[q, 0] = 0
            out[q, 1] = 0


@njit(cache=True)
def _lists(targets, scx, scy, scz, sR1, sR2, sR3, sj, cell_ptr, x0, y0, h, nx, ny, reach, far, always,
           gstart, gof, gcx, gcy, gcz, gR2, gcell, gcell_ptr, call2, cnone2, max_rows):  # pragma: no cover
    """Every target's ranges in CSR (the arguments of :attr:`Plan.traverse` after the targets, then
    the groups of far cilia, :meth:`Plan.groups_args`):
    row bounds by :func:`_upper`, each target's rows by :func:`_traverse`, packed by
    :func:`_compact`: ``(ptr, ranges, rptr, res_j, res_r, counts, uptr)``; when the bound
    uptr[-1] of the rows exceeds ``max_rows`` (and there are several targets) only ``uptr`` is
    made, the others are empty (the caller splits the targets). Serial: a parallel region costs
    more than the lists of a few targets (35 us for a whole evaluation at one point on 30 x 30),
    and a compiled function that starts parallel regions of other compiled functions returns with
    Python's error set when a signal (Ctrl-C) arrives meanwhile (a SystemError, not the
    KeyboardInterrupt: tests/test_faults.py)."""
    m = targets.shape[0]
    uptr = np.zeros(m + 1, np.int64)
    n_always = always.shape[0]
    n_groups = gstart.shape[0] - 1 if gstart.shape[0] > 1 else 0
    for i in range(m):
        uptr[i + 1] = _upper(targets[i, 0], targets[i, 1], cell_ptr, x0, y0, h, nx, ny, reach, n_always, n_groups)
    for i in range(m):
        uptr[i + 1] += uptr[i]
    if uptr[m] > max_rows and m > 1:
        e = np.zeros(0, np.int64)
        return e, np.zeros((0, 2), np.int64), e, e, e, np.zeros((0, 4), np.int64), uptr
    rows = uptr[m]
    ranges_u = np.empty((rows, 2), np.int64)
    res_j_u = np.empty(rows, np.int64)
    res_r_u = np.empty(rows, np.int64)
    nr = np.empty(m, np.int64)
    nres = np.empty(m, np.int64)
    counts = np.empty((m, 4), np.int64)
    _traverse(targets, scx, scy, scz, sR1, sR2, sR3, sj, cell_ptr, x0, y0, h, nx, ny, reach, far, always,
              gstart, gof, gcx, gcy, gcz, gR2, gcell, gcell_ptr, call2, cnone2, uptr, nr, nres, counts, ranges_u, res_j_u,
              res_r_u)
    ptr = np.zeros(m + 1, np.int64)
    rptr = np.zeros(m + 1, np.int64)
    for i in range(m):
        ptr[i + 1] = ptr[i] + nr[i]
        rptr[i + 1] = rptr[i] + nres[i]
    ranges = np.empty((ptr[m], 2), np.int64)
    res_j = np.empty(rptr[m], np.int64)
    res_r = np.empty(rptr[m], np.int64)
    for i in range(m):
        _compact(i, uptr, nr, nres, ptr, rptr, ranges_u, res_j_u, res_r_u, ranges, res_j, res_r)
    return ptr, ranges, rptr, res_j, res_r, counts, uptr


@njit(cache=True)
def _used(res_j, n):  # pragma: no cover - compiled
    """The cilia of ``res_j`` once each, ascending (n cilia in all)."""
    seen = np.zeros(n, np.bool_)
    k = 0
    for q in range(res_j.shape[0]):
        if not seen[res_j[q]]:
            seen[res_j[q]] = True
            k += 1
    out = np.empty(k, np.int64)
    k = 0
    for j in range(n):
        if seen[j]:
            out[k] = j
            k += 1
    return out


@njit(cache=True)
def _kept_ranges(res_j, slot, blk):  # pragma: no cover - compiled
    """The source range of each resolved pair q in blocks kept at rows slot[j] blk ... of cilium
    j = res_j[q] (:class:`~.blocks.InstantBlocks`)."""
    out = np.empty((res_j.shape[0], 2), np.int64)
    for q in range(res_j.shape[0]):
        out[q, 0] = slot[res_j[q]] * blk
        out[q, 1] = out[q, 0] + blk
    return out



@dataclass(frozen=True, eq=False)
class Summed:
    """A sum's velocity (M, 3) and its work: ``orders`` (3,) the cheap pairs per order
    (monopole, dipole, quadrupole), ``resolved`` the resolved pairs, ``ranges`` the source
    ranges read, ``sources`` the (target, source) interactions summed, ``grouped`` the pairs of
    a target and a group of far cilia (:class:`FarGroups`)."""

    velocity: np.ndarray
    orders: np.ndarray
    resolved: int
    ranges: int
    sources: int
    grouped: int = 0

    @staticmethod
    def joined(parts: list) -> "Summed":
        """The parts' sums over consecutive targets as one."""
        return Summed(velocity=np.concatenate([q.velocity for q in parts]),
                      orders=sum(q.orders for q in parts), resolved=sum(q.resolved for q in parts),
                      ranges=sum(q.ranges for q in parts), sources=sum(q.sources for q in parts),
                      grouped=sum(q.grouped for q in parts))


def dense_sum(targets: np.ndarray, js: np.ndarray, sources: ResolvedSources, kernel: Kernel, backend,
              mu: float) -> Summed:
    """The resolved sum itself: every source of the cilia ``js`` at every target (M, 3), in
    chunks of cilia of at most :data:`_CHUNK_SOURCES` sources."""
    m = targets.shape[0]
    blk = sources.block
    u = np.zeros((m, 3))
    per = max(1, _CHUNK_SOURCES // blk)
    for lo in range(0, js.size, per):
        jc = js[lo:lo + per]
        bsrc, bfrc = np.empty((len(jc) * blk, 3)), np.empty((len(jc) * blk, 3))
        sources.fill(jc, bsrc, bfrc)
        u += stokeslet_velocity(targets, bsrc, bfrc, mu, kernel=kernel, backend=backend)
    return Summed(velocity=u, orders=np.zeros(3, np.int64), resolved=m * js.size, ranges=0,
                  sources=m * js.size * blk)


def flow_sum(targets: np.ndarray, plan: Plan, forces, sources: ResolvedSources, n: int,
             kernel: Kernel, backend, mu: float, grouped: bool = False, precision: str = "fp64") -> Summed:
    """Per target (M, 3) the ranged sums (module docstring): every cilium of the ``n`` at the
    order the ``plan`` gives it at its distance, its carriers with ``forces`` (10 n_p, 3) (in the
    order of ``plan.carriers``; or an :class:`~.instants.InstantForces`, whose quadrupoles the
    ranges read are made first), or its resolved ``sources``; ``backend`` runs the sums. With
    ``grouped`` (and a plan with :class:`FarGroups`) the far cilia go by groups, the forces then
    holding the groups' carriers after the cilia's (10 n_p + 6 G rows). The sources are laid
    out as coordinate rows (3, K) and handed over as their (K, 3) transposes: the direct sums
    read that layout without a copy. With ``precision="fp32"`` the carriers' sum runs in fp32 on
    the CPU where ``backend``'s would run on it in fp64
    (:func:`~ciliary_carpet.stokes.dispatch.in_fp32`), over the plan's carriers rounded once
    (:meth:`Plan.rounded`)."""
    backend = ranged_backend(backend)  # one without ranged sums (the FMM) has them run on Direct
    m = targets.shape[0]
    sj = plan.order
    n_car = 10 * sj.size
    blk = sources.block
    # the ranges of every point, written into rows bounded by _upper, then packed (the
    # resolved blocks' ranges left empty: summed apart); targets in parts when the bound is very large
    grouped = grouped and plan.groups is not None
    ptr, ranges, rptr, res_j, _, counts, uptr = _lists(targets, *plan.traverse, *plan.groups_args(grouped),
                                                       _MAX_ROWS)
    if uptr[-1] > _MAX_ROWS and m > 1:
        cut = np.searchsorted(uptr, np.arange(1, -(-int(uptr[-1]) // _MAX_ROWS)) * _MAX_ROWS)
        cut = np.unique(np.clip(cut, 1, m - 1))
        return Summed.joined([flow_sum(t, plan, forces, sources, n, kernel, backend, mu, grouped, precision)
                              for t in np.split(targets, cut)])
    # The carriers: one ranged sum over the plan's carriers as they are (coordinate rows, no
    # copy; the resolved cilia's ranges left empty), their forces made where the sum reads
    # quadrupoles not made yet (InstantForces).
    if not isinstance(forces, np.ndarray):
        forces = forces.for_ranges(ranges)
    u = np.zeros((m, 3))
    if n_car and ptr[-1]:
        # the backend directly: every array here is made and checked by this function
        if precision == "fp32" and in_fp32(backend) == _FP32:
            shift, pos32 = plan.rounded(kernel, grouped)
            u += ranged_fp32(kernel, targets, pos32, shift, forces, ptr, ranges, mu)
        else:
            pos = plan.grouped_soa if grouped else plan.carriers_soa
            u += backend.ranged(kernel, targets, pos.T, forces, ptr, ranges, mu)
    # The resolved blocks are made and summed in chunks of cilia of at most _CHUNK_SOURCES
    # sources (the resolved mean flow has 4160 per cilium: a whole carpet's would take hundreds
    # of MB, and fresh memory costs more than the sum); an instantaneous flow's (65 sources per
    # cilium) are one chunk; those of an instant said ahead are where they are kept (no copy).
    used = _used(res_j, n)
    kept = sources.located(used) if used.size else None
    if kept is not None:
        src, frc, slot = kept
        u += backend.ranged(kernel, targets, src, frc, rptr, _kept_ranges(res_j, slot, blk), mu)
    elif used.size:
        per = max(1, _CHUNK_SOURCES // blk)
        local = np.zeros(n, np.int64)
        local[used] = np.arange(used.size)
        for k in range(-(-used.size // per)):
            jc = used[k * per:(k + 1) * per]
            src, frc = np.empty((3, jc.size * blk)), np.empty((3, jc.size * blk))
            rng = np.empty((res_j.size, 2), np.int64)
            _block_ranges(res_j, local, per, k, blk, rng)
            sources.fill(jc, src.T, frc.T)
            u += backend.ranged(kernel, targets, src.T, frc.T, rptr, rng, mu)
    cnt = counts.sum(axis=0)
    return Summed(velocity=u, orders=cnt[:3], resolved=int(res_j.size), ranges=int(ptr[-1]),
                  sources=int(cnt[0] + 3 * cnt[1] + 6 * cnt[2] + 6 * cnt[3] + res_j.size * blk), grouped=int(cnt[3]))
