"""The ranged sums of an evaluation: which carriers or sources each target sums, and the sums.

Given the thresholds R1, R2, R3 of every cilium (:meth:`~.bounds.Bounds.thresholds`), each
target x (M, 3) sums cilium j at the cheapest order its distance |x - c_j| reaches: its monopole
carrier (R >= R1), its three dipole carriers (R >= R2), its six quadrupole carriers (R >= R3), or
its resolved line sources (closer; :class:`~.blocks.ResolvedSources`). All of it is two sparse
"ranged" sums of the evaluator (:meth:`Backend.ranged <ciliary_carpet.stokes.backend.Backend.ranged>`):
one over the carriers of every cilium (monopoles, then dipoles, then quadrupoles, cilia sorted
by grid cell: :meth:`~.carriers.Carriers.positions`), read where they lie, one over the
resolved blocks; each target reads a list of row ranges of them (CSR: ``ptr`` (M + 1,),
``ranges`` (R, 2)).

:class:`Plan` is what an evaluation at one tolerance reuses: the thresholds, a grid of the force
centres and the order ``far`` of the cilia beyond the (2 reach + 1)^2 cells around a target,
which are not looked at one by one but taken as runs between those cells (:func:`_traverse`).
The far order is the one with the least estimated cost per target (:func:`_far_order`:
classifying a cilium costs about :data:`_CLASSIFY` kernel evaluations, so small carpets keep
quadrupoles and large ones take monopoles or dipoles; at tol 1e-3 the thresholds are about
80, 7 and 3 L for the instantaneous flow), unless the flow fixes it (the cycle-mean flow keeps
quadrupoles: its resolved blocks dominate its cost, and bounds that each sit near their budget
would loosen its error bars, the design's residuals', for a saving of about 2 %). Measured on
10 x 10 and 30 x 30 carpets: see tests/test_carpet.py and benchmarks/bench_flow.py.

On a planar carpet whose far cilia are dipoles, the plan also has :class:`FarGroups`: the cilia
of each cell sorted by sub-cells of about two spacings, and the far cilia of an instant's flow
taken group by group, a group at its own six quadrupole carriers where the target is past its
distance of acceptance (the bound: :mod:`~.carriers`, "groups of far cilia"), else its cilia at
the far order. On 100 x 100 cilia at tol 1e-4 the sums then read 60 % of the sources.

:func:`flow_sum` makes and runs the sum (targets in parts when their ranges would take more than
:data:`_MAX_ROWS` rows; the resolved blocks in chunks of at most :data:`_CHUNK_SOURCES` sources),
:func:`dense_sum` the resolved sum of every source (tol = 0). Both return a :class:`Summed`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit, prange

from ciliary_carpet.carpet.blocks import ResolvedSources
from ciliary_carpet.carpet.bounds import smallest_root
from ciliary_carpet.carpet.carriers import Carriers
from ciliary_carpet.stokes import Direct, Kernel, fp32_sources, in_fp32, ranged_evaluator, ranged_fp32
from ciliary_carpet.stokes import stokeslet_velocity

__all__ = ["FarGroups", "Plan", "Summed", "make_plan", "flow_sum", "dense_sum"]

_FP32 = Direct("fp32")  # what in_fp32 gives where the far sums may run in fp32

_CLASSIFY = 5.0
"""Cost of classifying one cilium for one target (:func:`_traverse`) in kernel evaluations
(measured: about 3 ns against 0.55 ns per evaluation on 2 cores); used to choose the order of
the far cilia (:func:`_far_order`)."""
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
class Plan:
    """What an evaluation at one tolerance reuses (module docstring): ``thresholds`` (R1, R2, R3)
    (N,) each, the cheaper orders' made infinite where the far order replaces them; ``order``
    (n_p,) the cilia chosen per target (finite thresholds), sorted by grid cell; ``always`` the
    cilia resolved for every target (no finite threshold); ``carriers`` (10 n_p, 3) their
    carriers' positions (:meth:`Carriers.positions <.carriers.Carriers.positions>`); ``far`` the
    order of the cilia beyond the cells around a target (0 monopole, 1 dipole, 2 quadrupole);
    ``traverse`` the arguments of :func:`_traverse` after the targets (the sorted centres in
    space and squared thresholds, the grid: cell pointers, origin, cell side, cells per side, reach)."""

    thresholds: tuple
    order: np.ndarray
    always: np.ndarray
    carriers: np.ndarray
    far: int
    traverse: tuple
    groups: "FarGroups | None" = None

    @cached_property
    def carriers_soa(self) -> np.ndarray:
        """(3, 10 n_p) :attr:`carriers` as coordinate rows (the layout the sums read)."""
        return np.ascontiguousarray(self.carriers.T)

    @cached_property
    def grouped_soa(self) -> np.ndarray:
        """(3, 10 n_p + 6 G) :attr:`carriers_soa` and the carriers of the :attr:`groups` after them."""
        g = self.groups
        return np.ascontiguousarray(np.concatenate([self.carriers, g.carriers]).T)

    def rounded(self, kernel: Kernel, grouped: bool) -> tuple[np.ndarray, np.ndarray]:
        """``(shift, positions)``: :attr:`carriers_soa` (or :attr:`grouped_soa`) shifted by
        ``-shift`` (the centre of their bounding box; heights above ``kernel``'s wall) and rounded
        to fp32 (3, K), made once per plan for the sums in fp32
        (:func:`~ciliary_carpet.stokes.direct.ranged_fp32`)."""
        key = (grouped, kernel.z_origin)
        got = self._rounded.get(key)
        if got is None:
            got = self._rounded[key] = fp32_sources(kernel, (self.grouped_soa if grouped else self.carriers_soa).T)
        return got

    @cached_property
    def _rounded(self) -> dict:
        return {}

    def groups_args(self, grouped: bool) -> tuple:
        """The arguments of :func:`_lists` that describe the groups of far cilia (none unless
        ``grouped`` and the plan has them)."""
        g = self.groups
        if not grouped or g is None:
            return _NO_GROUPS
        return (g.start, g.of, g.centre[:, 0].copy(), g.centre[:, 1].copy(), g.centre[:, 2].copy(), g.R2, g.cell,
                g.cell_ptr, g.all2, g.none2)

    @property
    def grid(self) -> tuple:
        """The arguments of :func:`_upper` that describe the grid (cell_ptr, x0, y0, h, nx, ny, reach)."""
        return self.traverse[7:14]


_NO_GROUPS = (np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0),
              np.zeros(0, np.int64), np.zeros(1, np.int64), np.zeros(0), np.zeros(0))
GROUP_MIN = 3
"""Cilia a group of far cilia needs to be summed as one (:class:`FarGroups`): its six carriers
replace three dipole carriers per cilium."""
GROUP_DELTA = 0.125
"""A group's carriers lie this fraction of its radius from its centre (:class:`FarGroups`). Their
own third moment, which the group's bound adds, shrinks with it (delta^3 sum |f_m| ~ delta T):
on the 100 x 100 carpet at tol 1e-4 a group of four cilia is summed as one from 45 L on, from
59 L at a half (the cilia's own carriers' fraction); its forces grow as 1 / delta^2, which costs
nothing measurable in rounding at these distances (R >> a)."""


@dataclass(frozen=True, eq=False)
class FarGroups:
    """Groups of a planar carpet's far cilia, each summed at six quadrupole carriers of its own
    where a target is far enough (module docstring of :mod:`~.carriers`, "groups").

    The cilia of a plan whose far cilia are dipoles are sorted by sub-cell (``sub`` x ``sub`` per
    grid cell): group g holds the sorted cilia start[g] ... start[g + 1] (``start`` (G + 1,);
    ``of`` (n_p,) the group of each); ``centre`` (G, 3) the centroid of its force centres (in the
    carpet's plane), ``delta`` (G,) its carriers' scale (half its radius ``a``: every carrier of
    its cilia lies within ``a`` of the centre), ``carriers`` (6 G, 3) their positions (the
    pentagon and centre of :data:`~ciliary_carpet.stokes.QUADRUPOLE`), and ``R2`` (G,) the square
    of the distance beyond which a target sums it as one (inf for groups of fewer than
    :data:`GROUP_MIN` cilia): the smallest R at which the group's Taylor remainder about its
    centre (its cilia's dipole carriers against its own six: C3 (Q3 + Q3_rep) / (6 (R - a)^4),
    both third moments bounded over the whole cycle) plus its cilia's own dipole bounds at
    R - d_j stays within the sum of their budgets, slack tol S_j / (R + d_j). Per grid cell of the
    plan (``cell`` (G,) each group's, ``cell_ptr`` the groups of each cell): ``all2`` the square of
    the distance from the cell's centre beyond which every group of the cell is past its
    distance (inf where one never is), ``none2`` that below which none is."""

    start: np.ndarray
    of: np.ndarray
    centre: np.ndarray
    delta: np.ndarray
    radius: np.ndarray
    carriers: np.ndarray
    R2: np.ndarray
    cell: np.ndarray
    cell_ptr: np.ndarray
    all2: np.ndarray
    none2: np.ndarray

    @property
    def n(self) -> int:
        return self.centre.shape[0]


def _far_groups(carriers: Carriers, sj: np.ndarray, key: np.ndarray, tol: float, cell: np.ndarray, grid: tuple
                ) -> FarGroups | None:
    """The :class:`FarGroups` of the sorted cilia ``sj`` (plan order), group g the run of equal
    ``key`` (sorted), for a plan at ``tol`` whose far cilia are dipoles (:class:`FarGroups` for
    the bound), ``cell`` (n_p,) the grid cell of each sorted cilium, ``grid`` (x0, y0, h, nx, ny)
    the plan's grid. None when no group could ever be summed as one."""
    from ciliary_carpet.stokes import QUADRUPOLE, QUADRUPOLE_INV

    n_p = sj.size
    cut = np.flatnonzero(np.diff(key)) + 1
    start = np.concatenate([[0], cut, [n_p]]).astype(np.int64)
    G = start.size - 1
    size = np.diff(start)
    if not np.any(size >= GROUP_MIN):
        return None
    of = np.repeat(np.arange(G, dtype=np.int64), size)
    cyc = carriers.cycles
    cen3 = cyc.centre3[sj]
    cen = np.zeros((G, 3))
    for k in range(3):
        cen[:, k] = np.bincount(of, weights=cen3[:, k], minlength=G) / size
    # the dipole carriers of every cilium (positions in space; largest force over the cycle)
    pos = carriers.positions(sj)[n_p:4 * n_p].reshape(n_p, 3, 3)
    fmax = carriers.dipole_force_max[sj]  # (n_p, 3)
    h = pos[:, :, :2] - cen[of][:, None, :2]  # (n_p, 3, 2) in the plane
    hn = np.sqrt((h ** 2).sum(-1))
    a = np.maximum(np.maximum.reduceat(hn.max(axis=1), start[:-1]), 1e-12)
    delta = GROUP_DELTA * a
    Q3 = np.bincount(of, weights=(fmax * hn ** 3).sum(axis=1), minlength=G)
    # the group's own carriers: |g_m| <= sqrt(2) sum_k |INV6[m, k]| B_k, B_k the moments' bounds
    dl = delta[of][:, None]
    mono = np.stack([np.ones_like(hn), np.abs(h[..., 0]) / dl, np.abs(h[..., 1]) / dl, h[..., 0] ** 2 / dl ** 2,
                     np.abs(h[..., 0] * h[..., 1]) / dl ** 2, h[..., 1] ** 2 / dl ** 2], axis=-1)  # (n_p, 3, 6)
    B = np.stack([np.bincount(of, weights=(mono[..., k] * fmax).sum(axis=1), minlength=G) for k in range(6)], axis=1)
    Qrep = delta ** 3 * math.sqrt(2.0) * (B @ np.abs(QUADRUPOLE_INV).T).sum(axis=1)
    # the smallest R where the group's remainder and its cilia's dipole bounds fit their budgets
    b = carriers.over_cycle
    k3 = carriers.constants[2] / 6.0
    js = sj
    d = np.sqrt(((cen3[:, :2] - cen[of][:, :2]) ** 2).sum(-1))
    S, a2, b2, aj = b.S[js], b.a2[js], b.b2[js], b.radius[js]
    target = b.slack * tol

    def excess(R):
        Rj = R[of]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            own = np.where(Rj - d - aj > 0, a2 / (Rj - d) ** 3 + b2 / (Rj - d - aj) ** 4, np.inf)
            lhs = k3 * (Q3 + Qrep) / (R - a) ** 4 + np.bincount(of, weights=own, minlength=G)
        budget = target * np.bincount(of, weights=S / (Rj + d), minlength=G)
        return np.where(R > a, lhs - budget, np.inf)

    lo = a + np.maximum.reduceat(d + aj, start[:-1])
    hi = smallest_root(excess, lo, 2.0 * lo + 1.0, lambda h: h < 1e12)
    R = hi * (1 + 1e-12) + 1e-12
    ok = (size >= GROUP_MIN) & (hi < 1e12) & (b.S[js].sum() > 0)
    R2 = np.where(ok, R ** 2, np.inf)
    if not np.any(np.isfinite(R2)):
        return None
    car = cen[:, None, :] + np.concatenate([delta[:, None, None] * QUADRUPOLE[None], np.zeros((G, 6, 1))], axis=2)
    # per cell: the distances from its centre beyond which all its groups, below which none, are taken
    x0, y0, h, nx, ny = grid
    gc = cell[start[:-1]].astype(np.int64)
    cell_ptr = np.searchsorted(gc, np.arange(nx * ny + 1)).astype(np.int64)
    cc = np.column_stack([x0 + (gc // ny + 0.5) * h, y0 + (gc % ny + 0.5) * h])
    off = np.sqrt(((cen[:, :2] - cc) ** 2).sum(-1)) * (1 + 1e-12) + 1e-12
    Rg = np.sqrt(R2)
    occupied = np.flatnonzero(np.diff(cell_ptr))
    all2 = np.full(nx * ny, np.inf)
    none2 = np.zeros(nx * ny)
    if occupied.size:
        all2[occupied] = np.maximum.reduceat(Rg + off, cell_ptr[occupied]) ** 2
        none2[occupied] = np.maximum(np.minimum.reduceat(Rg - off, cell_ptr[occupied]), 0.0) ** 2
    return FarGroups(start=start, of=of, centre=cen, delta=delta, radius=a, carriers=car.reshape(-1, 3),
                     R2=np.ascontiguousarray(R2), cell=gc, cell_ptr=cell_ptr, all2=all2, none2=none2)


def _far_order(cen: np.ndarray, R: tuple) -> int:
    """The order (0 monopole, 1 dipole, 2 quadrupole) of the cilia beyond the cells around a
    target with the least estimated cost per target, cells of side max R_f / 2 for order f
    (R = (R1, R2, R3) of the cilia at centres ``cen``): the cilia of the 5 x 5 cells are
    classified one by one (:data:`_CLASSIFY` kernel evaluations' worth each) and get their
    cheapest order, the others cost 1, 3 or 6 evaluations. Cilia spread evenly over their
    bounding box, the cells' box as a disc of radius 1.4 max R_f, median thresholds; the
    resolved cilia cost the same for every f and are left out."""
    n = cen.shape[0]
    ext = np.ptp(cen, axis=0) + 2.0
    rho = n / float(ext[0] * ext[1])
    med = [float(np.median(r)) for r in R]

    def within(r):
        return min(float(n), rho * math.pi * min(r, 1e150) ** 2)

    cost = []
    for f, (Rf, sf) in enumerate(zip(R, (1.0, 3.0, 6.0))):
        rn = 1.4 * float(min(Rf.max(), 1e150))
        n_in = within(rn)
        edges = [min(r, rn) for r in med[f:]][::-1] + [rn]  # R3 <= ... <= rn
        price = (6.0, 3.0, 1.0)[:len(edges) - 1]  # inside: costlier orders closer in
        inside = sum(p * (within(b) - within(a)) for p, a, b in zip(price, edges[:-1], edges[1:]))
        cost.append(_CLASSIFY * n_in + inside + sf * (n - n_in))
    return int(np.argmin(cost))


def make_plan(thresholds: tuple, carriers: Carriers, far: int | None = None, tol: float | None = None) -> Plan:
    """The :class:`Plan` of the ``thresholds`` (R1, R2, R3) (N,) of the cilia of ``carriers``: the
    far order ``far`` (or the cheapest, :func:`_far_order`), a grid of the centres of the cilia
    chosen per target with cells of side max R_far / 2 (at most 4096 a side), the cheaper orders'
    thresholds made infinite for them, and their carriers' positions in grid order. Given the
    ``tol`` of the thresholds (those of the flow at an instant, :attr:`Carriers.over_cycle
    <.carriers.Carriers.over_cycle>`), a planar carpet whose far cilia are dipoles also gets
    :class:`FarGroups`: sub-cells of about two spacings a side, the cilia sorted by them."""
    R1, R2, R3 = thresholds
    centre3 = carriers.cycles.centre3
    centre = centre3[:, :2]
    js = np.nonzero(np.isfinite(R3) & (R3 >= 0))[0]
    always = np.nonzero(np.isinf(R3))[0].astype(np.int64)
    reach = 2
    f = 0
    if js.size:
        cen = centre[js]
        # Far cilia (beyond reach h) at one order f, cells of side max R_f / 2; the cheaper
        # orders' thresholds made infinite.
        f = far if far is not None else _far_order(cen, (R1[js], R2[js], R3[js]))
        R1 = np.where(R1 >= 0, np.inf, R1) if f >= 1 else R1  # the far cilia are summed at order f
        R2 = np.where(R2 >= 0, np.inf, R2) if f >= 2 else R2
        h = float(min((R1, R2, R3)[f][js].max(), 1e300)) / reach
        lo = cen.min(axis=0) - h
        span = cen.max(axis=0) + h - lo
        nx, ny = (int(min(max(1, math.ceil(v / h)), 4096)) for v in span)
        h = float(max(span[0] / nx, span[1] / ny, h))  # at most 4096 cells a side
        ext = np.ptp(cen, axis=0) + 2.0
        spacing = math.sqrt(float(ext[0] * ext[1]) / js.size)
        sub = max(1, int(round(h / (2.0 * spacing))))  # sub-cells of about two spacings (a cell when smaller)
        grouped = (tol is not None and f == 1 and h >= 1.5 * spacing and carriers.cycles.embedding.in_plane
                   and np.ptp(centre3[js, 2]) == 0.0)
        if grouped:
            sc = np.minimum(np.floor((cen - lo) / (h / sub)).astype(np.int64), [nx * sub - 1, ny * sub - 1])
            g = sc // sub
            cell = g[:, 0] * ny + g[:, 1]
            key = (cell * sub + sc[:, 0] % sub) * sub + sc[:, 1] % sub
        else:
            g = np.minimum(np.floor((cen - lo) / h).astype(np.int64), [nx - 1, ny - 1])
            cell = g[:, 0] * ny + g[:, 1]
            key = cell
        order = np.argsort(key, kind="stable")
        cell_ptr = np.searchsorted(cell[order], np.arange(nx * ny + 1)).astype(np.int64)
        x0, y0 = float(lo[0]), float(lo[1])
    else:
        order, cell_ptr, x0, y0, h, nx, ny = np.zeros(0, np.int64), np.zeros(2, np.int64), 0.0, 0.0, 1.0, 1, 1
        grouped, key = False, None
    sj = js[order].astype(np.int64)
    cen = centre3[sj]
    groups = _far_groups(carriers, sj, key[order], tol, cell[order], (x0, y0, h, nx, ny)) if grouped else None
    return Plan(thresholds=(R1, R2, R3), order=sj, always=always, carriers=carriers.positions(sj), far=f,
                traverse=(np.ascontiguousarray(cen[:, 0]), np.ascontiguousarray(cen[:, 1]),
                          np.ascontiguousarray(cen[:, 2]), R1[sj] ** 2, R2[sj] ** 2, R3[sj] ** 2, sj, cell_ptr, x0, y0,
                          h, nx, ny, reach, f, always), groups=groups)


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
             kernel: Kernel, evaluator, mu: float, grouped: bool = False, precision: str = "fp64") -> Summed:
    """Per target (M, 3) the ranged sums (module docstring): every cilium of the ``n`` at the
    order the ``plan`` gives it at its distance, its carriers with ``forces`` (10 n_p, 3) (in the
    order of ``plan.carriers``; or an :class:`~.instants.InstantForces`, whose quadrupoles the
    ranges read are made first), or its resolved ``sources``; ``evaluator`` runs the sums. With
    ``grouped`` (and a plan with :class:`FarGroups`) the far cilia go by groups, the forces then
    holding the groups' carriers after the cilia's (10 n_p + 6 G rows). The sources are laid
    out as coordinate rows (3, K) and handed over as their (K, 3) transposes: the direct sums
    read that layout without a copy. With ``precision="fp32"`` the carriers' sum runs in fp32 on
    the CPU where ``evaluator``'s would run on it in fp64
    (:func:`~ciliary_carpet.stokes.evaluator.in_fp32`), over the plan's carriers rounded once
    (:meth:`Plan.rounded`)."""
    evaluator = ranged_evaluator(evaluator)  # one without ranged sums (the FMM) has them run on Direct
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
        return Summed.joined([flow_sum(t, plan, forces, sources, n, kernel, evaluator, mu, grouped, precision)
                              for t in np.split(targets, cut)])
    # The carriers: one ranged sum over the plan's carriers as they are (coordinate rows, no
    # copy; the resolved cilia's ranges left empty), their forces made where the sum reads
    # quadrupoles not made yet (InstantForces).
    if not isinstance(forces, np.ndarray):
        forces = forces.for_ranges(ranges)
    u = np.zeros((m, 3))
    if n_car and ptr[-1]:
        # the evaluator directly: every array here is made and checked by this function
        if precision == "fp32" and in_fp32(evaluator) == _FP32:
            shift, pos32 = plan.rounded(kernel, grouped)
            u += ranged_fp32(kernel, targets, pos32, shift, forces, ptr, ranges, mu)
        else:
            pos = plan.grouped_soa if grouped else plan.carriers_soa
            u += evaluator.ranged(kernel, targets, pos.T, forces, ptr, ranges, mu)
    # The resolved blocks are made and summed in chunks of cilia of at most _CHUNK_SOURCES
    # sources (the resolved mean flow has 4160 per cilium: a whole carpet's would take hundreds
    # of MB, and fresh memory costs more than the sum); an instantaneous flow's (65 sources per
    # cilium) are one chunk; those of an instant said ahead are where they are kept (no copy).
    used = _used(res_j, n)
    kept = sources.located(used) if used.size else None
    if kept is not None:
        src, frc, slot = kept
        u += evaluator.ranged(kernel, targets, src, frc, rptr, _kept_ranges(res_j, slot, blk), mu)
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
            u += evaluator.ranged(kernel, targets, src.T, frc.T, rptr, rng, mu)
    cnt = counts.sum(axis=0)
    return Summed(velocity=u, orders=cnt[:3], resolved=int(res_j.size), ranges=int(ptr[-1]),
                  sources=int(cnt[0] + 3 * cnt[1] + 6 * cnt[2] + 6 * cnt[3] + res_j.size * blk), grouped=int(cnt[3]))
