"""The plan of an evaluation at one tolerance: the orders of the cilia, the grid, the far order.

:class:`Plan` is what an evaluation at one tolerance reuses: the thresholds, a grid of the force
centres and the order ``far`` of the cilia beyond the (2 reach + 1)^2 cells around a target,
which are not looked at one by one but taken as runs between those cells (:func:`~ciliary_carpet.carpet.traversal._traverse`).
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
distance of acceptance (the bound: :mod:`~.bounds`, "groups of far cilia"), else its cilia at
the far order. On 100 x 100 cilia at tol 1e-4 the sums then read 60 % of the sources.

The sums that follow a plan are :mod:`~ciliary_carpet.carpet.traversal`'s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ciliary_carpet.carpet.bounds import smallest_root
from ciliary_carpet.carpet.carriers import Carriers
from ciliary_carpet.stokes import Kernel, fp32_sources

__all__ = ["FarGroups", "Plan", "make_plan", "GROUP_DELTA", "GROUP_MIN"]

_CLASSIFY = 5.0
"""Cost of classifying one cilium for one target (:func:`~ciliary_carpet.carpet.traversal._traverse`) in kernel evaluations
(measured: about 3 ns against 0.55 ns per evaluation on 2 cores); used to choose the order of
the far cilia (:func:`_far_order`)."""


@dataclass(frozen=True, eq=False)
class Plan:
    """What an evaluation at one tolerance reuses (module docstring): ``thresholds`` (R1, R2, R3)
    (N,) each, the cheaper orders' made infinite where the far order replaces them; ``order``
    (n_p,) the cilia chosen per target (finite thresholds), sorted by grid cell; ``always`` the
    cilia resolved for every target (no finite threshold); ``carriers`` (10 n_p, 3) their
    carriers' positions (:meth:`Carriers.positions <.carriers.Carriers.positions>`); ``far`` the
    order of the cilia beyond the cells around a target (0 monopole, 1 dipole, 2 quadrupole);
    ``traverse`` the arguments of :func:`~ciliary_carpet.carpet.traversal._traverse` after the targets (the sorted centres in
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
        """The arguments of :func:`~ciliary_carpet.carpet.traversal._lists` that describe the groups of far cilia (none unless
        ``grouped`` and the plan has them)."""
        g = self.groups
        if not grouped or g is None:
            return _NO_GROUPS
        return (g.start, g.of, g.centre[:, 0].copy(), g.centre[:, 1].copy(), g.centre[:, 2].copy(), g.R2, g.cell,
                g.cell_ptr, g.all2, g.none2)

    @property
    def grid(self) -> tuple:
        """The arguments of :func:`~ciliary_carpet.carpet.traversal._upper` that describe the grid (cell_ptr, x0, y0, h, nx, ny, reach)."""
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
    where a target is far enough (module docstring of :mod:`~.bounds`, "groups").

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
