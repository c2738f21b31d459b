"""A treecode for repeated Stokeslet sums over fixed points: a linear operator and its exact transpose.

The design model (:mod:`ciliary_carpet.design.model`) evaluates, hundreds of times per solve, the
velocity at P fixed control points x_k of point forces f_s at S fixed source points y_s in the
plane z = 0,

    u_k = 1/(8 pi mu) sum_s G(x_k, y_s) f_s,                          (A f)

and the adjoint sum g_s = sum_k G(y_s, x_k) w_k (A^T w for a reciprocal G, G_ij(x, y) =
G_ji(y, x): the free Stokeslet, Blake's tensor and their regularised versions, the wall's
included, :attr:`~ciliary_carpet.stokes.kernel.Kernel.symmetric`), with only the forces changing.
Direct, both cost P S kernel evaluations; at 10,000 cilia (S = 30,000 carriers) 3e8 per sum.

Barnes-Hut in the plane: the sources are sorted into a quadtree (cells of at most ``leaf``
sources, contiguous after sorting). A cell of centre c (its sources' centroid) and radius r (the
largest |y_s - c|) is *far* from x_k when |x_k - c| >= r / theta; its sources are then replaced
by six carriers at c + (r/2) u_m (u_m: the centre and a regular pentagon) whose forces
reproduce the cell's force, first and second moments about c exactly (the carriers of
:mod:`ciliary_carpet.carpet.carpet`; a fixed linear map W of the source forces). Otherwise the cell is
opened, down to the leaves, which are summed directly. By Taylor's theorem the error of one far
cell is O((r/R)^3) of its monopole; ``theta`` sets it (measured in the tests and in
benchmarks/bench_design.py: relative velocity error about 1e-4 at the default 0.3 on lattices
of 1,000 and 10,000 cilia).

The interaction lists are built once per geometry (vectorised level by level); both sums are
then one ranged sum of the backend each (any backend, as
:func:`~ciliary_carpet.stokes.dispatch.stokeslet_velocity_ranges` runs it), their fixed points
and lists checked once, at construction, and kept in the backend's layout (coordinate rows):
each sum then checks and converts only its forces (checked and copied every time, the points
took a quarter of a design's ranged sums at 10^4 cilia). The adjoint uses the same lists
transposed: each leaf and each far cell gathers the control points that see it into a
contiguous block, so that A^T is the exact transpose of the approximate A (what L-BFGS-B needs:
its gradient is that of the objective it minimises).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ciliary_carpet.stokes.backend import Backend, validated, validated_ranges
from ciliary_carpet.stokes.dispatch import Auto, ranged_backend
from ciliary_carpet.stokes.kernel import Kernel

__all__ = ["Treecode", "THETA", "LEAF", "QUADRUPOLE", "QUADRUPOLE_INV"]

THETA = 0.3
"""Default opening angle: a cell is far when its radius is at most THETA times its distance."""
LEAF = 48
"""Default largest number of sources in a leaf cell."""

QUADRUPOLE = np.array([[0.0, 0.0]] + [[math.cos(2 * math.pi * m / 5 + math.pi / 2),
                                       math.sin(2 * math.pi * m / 5 + math.pi / 2)] for m in range(5)])
"""Positions of the quadrupole carriers for unit delta: the centre and a regular pentagon (a vertex
at 90 degrees). Six point forces there reproduce a cluster's force, first and second moments
about its centre: the treecode's far cells and the carpet's quadrupole level of detail
(:mod:`ciliary_carpet.carpet.carriers`) use this one stencil."""
QUADRUPOLE_INV = np.linalg.inv(np.stack([np.ones(6), QUADRUPOLE[:, 0], QUADRUPOLE[:, 1], QUADRUPOLE[:, 0] ** 2,
                                         QUADRUPOLE[:, 0] * QUADRUPOLE[:, 1], QUADRUPOLE[:, 1] ** 2]))
"""Inverse of the quadrupole carriers' moment matrix (rows: the monomials 1, x, y, x^2, xy, y^2)."""


@dataclass(frozen=True)
class _Tree:
    order: np.ndarray  # (S,) sorted position -> source index
    start: np.ndarray  # (C,) first sorted source of each cell
    end: np.ndarray  # (C,)
    centre: np.ndarray  # (C, 2)
    radius: np.ndarray  # (C,)
    children: np.ndarray  # (C, 4) cell indices or -1


def _build(y: np.ndarray, leaf: int) -> _Tree:
    """Quadtree over ``y`` (S, 2): Morton order at depth 20, then cells split top-down."""
    lo = y.min(axis=0)
    size = float(max(np.ptp(y, axis=0).max(), 1e-300))
    depth = 20
    q = np.minimum(((y - lo) / size * (1 << depth)).astype(np.int64), (1 << depth) - 1)
    code = np.zeros(len(y), np.int64)
    for b in range(depth):
        code |= ((q[:, 0] >> b) & 1) << (2 * b) | ((q[:, 1] >> b) & 1) << (2 * b + 1)
    order = np.argsort(code, kind="stable")
    code = code[order]
    ys = y[order]
    start, end, level, prefix, children = [0], [len(y)], [0], [0], []
    i = 0
    while i < len(start):
        ch = [-1, -1, -1, -1]
        lvl = level[i]
        if end[i] - start[i] > leaf and lvl < depth:
            shift = 2 * (depth - lvl - 1)
            cuts = np.searchsorted(code[start[i]:end[i]], [((prefix[i] << 2) + d) << shift for d in range(5)]) + start[i]
            for d in range(4):
                if cuts[d + 1] > cuts[d]:
                    ch[d] = len(start)
                    start.append(int(cuts[d]))
                    end.append(int(cuts[d + 1]))
                    level.append(lvl + 1)
                    prefix.append((prefix[i] << 2) | d)
        children.append(ch)
        i += 1
    start, end = np.array(start), np.array(end)
    cid = np.repeat(np.arange(len(start)), end - start)
    idx = np.concatenate([np.arange(a, b) for a, b in zip(start, end)])
    cnt = (end - start).astype(float)
    centre = np.stack([np.bincount(cid, ys[idx, 0]), np.bincount(cid, ys[idx, 1])], axis=1) / cnt[:, None]
    d = np.linalg.norm(ys[idx] - centre[cid], axis=1)
    radius = np.zeros(len(start))
    np.maximum.at(radius, cid, d)
    return _Tree(order=order, start=start, end=end, centre=centre, radius=radius, children=np.array(children))


class Treecode:
    """The operator A of P targets and S sources in the plane z = 0 (module docstring), built once.

    Parameters
    ----------
    targets : (P, 3) control points x_k (z = 0).
    sources : (S, 3) source points y_s (z = 0).
    kernel : a reciprocal Green's function (:mod:`ciliary_carpet.stokes.kernel`: every kernel there,
        singular or regularised, free or with the wall; one whose ``symmetric`` is False is refused).
    mu : viscosity.
    backend : the backend of the sums.
    theta : opening angle in (0, 1) (:data:`THETA`); ``leaf``: leaf size (:data:`LEAF`).

    :meth:`apply` (S, 3) forces -> (P, 3) velocities; :meth:`adjoint` (P, 3) weights -> (S, 3),
    its exact transpose. ``work``: the kernel evaluations per sum (``pairs``) against P S.
    """

    def __init__(self, targets: np.ndarray, sources: np.ndarray, kernel: Kernel, mu: float,
                 backend: Backend | None = None, theta: float = THETA, leaf: int = LEAF):
        if not (0.0 < float(theta) < 1.0):
            raise ValueError(f"theta must be in (0, 1), got {theta!r}")
        if int(leaf) < 1:
            raise ValueError(f"leaf must be a positive integer, got {leaf!r}")
        if not kernel.symmetric:
            raise ValueError(f"the treecode's adjoint needs a symmetric kernel, not {type(kernel).__name__}")
        x = np.ascontiguousarray(targets, dtype=float)
        y = np.ascontiguousarray(sources, dtype=float)
        self.kernel, self.mu, self.backend = kernel, float(mu), backend
        P, S = x.shape[0], y.shape[0]
        tr = _build(y[:, :2], int(leaf))
        self._order = tr.order
        C = len(tr.start)
        # the cells' carriers and the map W from the (sorted) source forces to their forces
        delta = 0.5 * np.maximum(tr.radius, 1e-12)
        cpos = tr.centre[:, None, :] + delta[:, None, None] * QUADRUPOLE[None]
        cid = np.repeat(np.arange(C), tr.end - tr.start)
        col = np.concatenate([np.arange(a, b) for a, b in zip(tr.start, tr.end)])
        h = (y[tr.order][col, :2] - tr.centre[cid]) / delta[cid, None]
        mono = np.stack([np.ones(len(col)), h[:, 0], h[:, 1], h[:, 0] ** 2, h[:, 0] * h[:, 1], h[:, 1] ** 2])
        wv = QUADRUPOLE_INV @ mono  # (6, nnz): carrier m of cell cid gets wv[m] times the source's force
        self._W = sp.csr_matrix((wv.T.ravel(), (((6 * cid)[:, None] + np.arange(6)).ravel(), np.repeat(col, 6))),
                                shape=(6 * C, S))
        self._pts = np.concatenate([y[tr.order], np.column_stack([cpos.reshape(-1, 2), np.zeros(6 * C)])])
        # interaction lists, level by level: (target, cell) pairs
        near_k, near_c, far_k, far_c = [], [], [], []
        k = np.arange(P)
        c = np.zeros(P, np.int64)
        leafy = np.all(tr.children < 0, axis=1)
        while k.size:
            R = np.hypot(x[k, 0] - tr.centre[c, 0], x[k, 1] - tr.centre[c, 1])
            far = tr.radius[c] <= theta * R
            far_k.append(k[far])
            far_c.append(c[far])
            op = ~far
            lf = op & leafy[c]
            near_k.append(k[lf])
            near_c.append(c[lf])
            ex = op & ~leafy[c]
            ch = tr.children[c[ex]]
            kk = np.repeat(k[ex], 4)
            cc = ch.ravel()
            keep = cc >= 0
            k, c = kk[keep], cc[keep]
        nk, nc = np.concatenate(near_k), np.concatenate(near_c)
        fk, fc = np.concatenate(far_k), np.concatenate(far_c)
        # forward: per target, its near leaves' source ranges and its far cells' carrier blocks
        rk = np.concatenate([nk, fk])
        rg = np.concatenate([np.stack([tr.start[nc], tr.end[nc]], 1), np.stack([S + 6 * fc, S + 6 * fc + 6], 1)])
        o = np.argsort(rk, kind="stable")
        self._ranges = np.ascontiguousarray(rg[o], dtype=np.int64)
        self._ptr = np.concatenate([[0], np.cumsum(np.bincount(rk, minlength=P))]).astype(np.int64)
        self._x = x
        # adjoint: per leaf and per far cell the targets that see it, gathered into one block
        blk_owner = np.concatenate([nc, C + fc])  # leaves 0..C-1 (near), carrier blocks C..2C-1 (far)
        blk_k = np.concatenate([nk, fk])
        o = np.argsort(blk_owner, kind="stable")
        self._gather = blk_k[o]
        cnt = np.bincount(blk_owner, minlength=2 * C)
        off = np.concatenate([[0], np.cumsum(cnt)])
        # one range per adjoint target point: sorted sources (their leaf's block) and carriers
        leaf_of = np.full(S, -1, np.int64)
        for i in np.nonzero(leafy)[0]:
            leaf_of[tr.start[i]:tr.end[i]] = i
        car_owner = C + np.repeat(np.arange(C), 6)
        owner = np.concatenate([leaf_of, car_owner])
        self._adj_ranges = np.ascontiguousarray(np.stack([off[owner], off[owner + 1]], 1), dtype=np.int64)
        self._adj_ptr = np.arange(S + 6 * C + 1, dtype=np.int64)
        self._adj_src = np.ascontiguousarray(x[self._gather])
        self.work = {"pairs": int(np.sum(self._ranges[:, 1] - self._ranges[:, 0])), "direct_pairs": P * S,
                     "cells": C, "near_pairs": int(nk.size), "far_pairs": int(fk.size)}
        # the fixed points and lists of both sums, checked once and kept as (3, K) rows (an (K, 3)
        # view of them reaches the backend without a copy)
        fwd = validated(kernel, self._x, self._pts, np.zeros_like(self._pts), mu)[:2]
        adj = validated(kernel, self._pts, self._adj_src, np.zeros_like(self._adj_src), mu)[:2]
        self._ptr, self._ranges = validated_ranges(self._ptr, self._ranges, P, self._pts.shape[0])
        self._adj_ptr, self._adj_ranges = validated_ranges(self._adj_ptr, self._adj_ranges, self._pts.shape[0],
                                                           self._adj_src.shape[0])
        self._fwd = tuple(np.ascontiguousarray(a.T).T for a in fwd)
        self._adj = tuple(np.ascontiguousarray(a.T).T for a in adj)
        self._backend = ranged_backend(backend if backend is not None else Auto())

    def _sum(self, points: tuple, forces: np.ndarray, ptr: np.ndarray, ranges: np.ndarray) -> np.ndarray:
        """The ranged sum of ``forces`` over the checked ``points`` (targets, sources) and lists."""
        if not np.all(np.isfinite(forces)):
            raise ValueError("forces contains NaN or inf")
        if ranges.shape[0] == 0 or points[1].shape[0] == 0:
            return np.zeros((points[0].shape[0], 3))
        return self._backend.ranged(self.kernel, points[0], points[1], forces, ptr, ranges, self.mu)

    def apply(self, forces: np.ndarray) -> np.ndarray:
        """(P, 3) velocities at the targets of ``forces`` (S, 3) at the sources."""
        f = np.asarray(forces, dtype=float)
        if f.shape != (self._order.size, 3):
            raise ValueError(f"forces must have shape ({self._order.size}, 3), got {f.shape}")
        f = f[self._order]
        return self._sum(self._fwd, np.concatenate([f, self._W @ f]), self._ptr, self._ranges)

    def adjoint(self, weights: np.ndarray) -> np.ndarray:
        """(S, 3): the transpose of :meth:`apply` applied to ``weights`` (P, 3)."""
        w = np.asarray(weights, dtype=float)
        if w.shape != (self._x.shape[0], 3):
            raise ValueError(f"weights must have shape ({self._x.shape[0]}, 3), got {w.shape}")
        g = self._sum(self._adj, np.ascontiguousarray(w[self._gather]), self._adj_ptr, self._adj_ranges)
        S = self._order.size
        out = np.empty((S, 3))
        out[self._order] = g[:S] + self._W.T @ g[S:]
        return out
