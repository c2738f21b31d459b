"""The resolved line sources of an evaluation, and the blocks of them an evaluation keeps.

Where a (cilium, point) pair is too close for the levels of detail, the flow sums the cilium's
resolved line: its n_s arc-length samples r_j(s_i, phi) with weights w_i f_j(s_i, phi) (the
composite Simpson rule, :func:`~ciliary_carpet.carpet.cycles.simpson`) at its phase of an instant,
or at every phase sample weighted 1 / n_phase for the cycle mean. :class:`ResolvedSources` makes
those blocks, in space (each cilium's 2D frame embedded), from the trigonometric interpolant of
:class:`~ciliary_carpet.carpet.cycles.CycleData` (one compiled pass per chunk of cilia).
:class:`MeanBlocks` and :class:`InstantBlocks` keep blocks made once for the next evaluations:
the cycle mean's do not change, and a few prepared instants' are made together. What they keep
never changes a number: a kept block equals the one made afresh, to the bit.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from ciliary_carpet.carpet.cycles import CycleData, harmonic_sum, phase_basis, trig_basis

__all__ = ["InstantBlocks", "MeanBlocks", "ResolvedSources", "INSTANT_BLOCKS_BYTES", "MEAN_BLOCKS_BYTES"]


@njit(cache=True, nogil=True, parallel=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
def _blocks(coef, basis, wgt, bases, origin, axes, jc, src, frc):  # pragma: no cover - compiled
    """Source blocks of cilia ``jc``: block i (rows i * blk ... (i + 1) * blk of ``src`` and
    ``frc``, (len(jc) * blk, 3), blk = P n_s) holds the resolved sources of cilium
    j = jc[i] -- its trigonometric interpolant (coef (N, 2K-1, n_s, 4)) at the P phases whose
    basis rows are ``basis[i]`` (len(jc), P, 2K-1), positions plus the base, forces times
    ``wgt`` (n_s,) -- embedded in 3D: position origin[j] + axes[j] @ p, force axes[j] @ f
    (:class:`Embedding`)."""
    n_s = coef.shape[2]
    nk = coef.shape[1]
    P = basis.shape[1]
    blk = P * n_s
    R = 4 * n_s
    for i in prange(jc.shape[0]):
        j = jc[i]
        o = i * blk
        v = np.empty((P, R))
        harmonic_sum(coef[j].reshape(nk, R), basis[i], v)  # (k, (s, q)): R contiguous numbers
        for p in range(P):
            for s in range(n_s):
                r = o + p * n_s + s
                px = v[p, 4 * s] + bases[j, 0]
                py = v[p, 4 * s + 1] + bases[j, 1]
                fx = v[p, 4 * s + 2] * wgt[s]
                fy = v[p, 4 * s + 3] * wgt[s]
                for q in range(3):
                    src[r, q] = origin[j, q] + axes[j, q, 0] * px + axes[j, q, 1] * py
                    frc[r, q] = axes[j, q, 0] * fx + axes[j, q, 1] * fy


@njit(cache=True, nogil=True, parallel=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
def _instant_blocks(coef, basis, wgt, bases, origin, axes, jc, slots, src, frc):  # pragma: no cover - compiled
    """The resolved sources of cilia ``jc`` at P instants at once: cilium j = jc[i] at instant p
    (its basis row ``basis[i, p]``, (len(jc), P, 2K-1)) into columns slots[i] n_s ... of
    ``src[p]``, ``frc[p]`` ((P, 3, K): coordinate rows), the numbers of :func:`_blocks` (the same
    sums in the same order), its coefficients read once for the P instants."""
    n_s = coef.shape[2]
    nk = coef.shape[1]
    P = basis.shape[1]
    R = 4 * n_s
    for i in prange(jc.shape[0]):
        j = jc[i]
        v = np.empty((P, R))
        harmonic_sum(coef[j].reshape(nk, R), basis[i], v)
        o = slots[i] * n_s
        for p in range(P):
            for s in range(n_s):
                px = v[p, 4 * s] + bases[j, 0]
                py = v[p, 4 * s + 1] + bases[j, 1]
                fx = v[p, 4 * s + 2] * wgt[s]
                fy = v[p, 4 * s + 3] * wgt[s]
                for q in range(3):
                    src[p, q, o + s] = origin[j, q] + axes[j, q, 0] * px + axes[j, q, 1] * py
                    frc[p, q, o + s] = axes[j, q, 0] * fx + axes[j, q, 1] * fy




@njit(cache=True, nogil=True, parallel=True)
def _copy_blocks(loc, src_c, frc_c, src, frc):  # pragma: no cover - compiled
    """Block i (rows i blk ...) of ``src``, ``frc`` (K, 3) from block loc[i] of the kept blocks
    src_c, frc_c (capacity, blk, 3), where loc[i] >= 0."""
    blk = src_c.shape[1]
    for i in prange(loc.shape[0]):
        b = loc[i]
        if b < 0:
            continue
        for s in range(blk):
            for q in range(3):
                src[i * blk + s, q] = src_c[b, s, q]
                frc[i * blk + s, q] = frc_c[b, s, q]


@njit(cache=True, nogil=True, parallel=True)
def _keep_blocks(rows, slots, src, frc, src_c, frc_c):  # pragma: no cover - compiled
    """Block rows[m] of ``src``, ``frc`` (K, 3) into slot slots[m] of the kept blocks (capacity, blk, 3)."""
    blk = src_c.shape[1]
    for m in prange(rows.shape[0]):
        i = rows[m]
        b = slots[m]
        for s in range(blk):
            for q in range(3):
                src_c[b, s, q] = src[i * blk + s, q]
                frc_c[b, s, q] = frc[i * blk + s, q]


@njit(cache=True, nogil=True, parallel=True)
def _scatter_blocks(rows, src_m, frc_m, src, frc):  # pragma: no cover - compiled
    """Block m of src_m, frc_m (len(rows) blk, 3) into block rows[m] of ``src``, ``frc`` (K, 3)."""
    blk = src_m.shape[0] // max(rows.shape[0], 1)
    for m in prange(rows.shape[0]):
        i = rows[m]
        for s in range(blk):
            for q in range(3):
                src[i * blk + s, q] = src_m[m * blk + s, q]
                frc[i * blk + s, q] = frc_m[m * blk + s, q]


MEAN_BLOCKS_BYTES = 256 * 2 ** 20
"""Memory a carpet may keep resolved cycle-mean blocks in (:class:`MeanBlocks`)."""


class MeanBlocks:
    """The resolved blocks of the cycle-mean flow (every phase sample of a cilium's line, 4160
    sources for the shipped table) of the cilia evaluated so far, kept for the next evaluations:
    they do not change, and making one reads its cilium's coefficients for every phase sample
    (63 % of a standing carpet's mean flow at 100 points). The first cilia asked for are kept,
    up to :data:`MEAN_BLOCKS_BYTES` (1300 cilia of the shipped table); the others are made
    each time."""

    def __init__(self, cycles: CycleData, budget: int = MEAN_BLOCKS_BYTES):
        self.block = cycles.n_phase * cycles.n_s
        self.capacity = int(min(cycles.n, budget // (48 * self.block)))
        self.index = np.full(cycles.n, -1, np.int64)
        self.count = 0
        self.src = self.frc = None

    def copy(self, jc: np.ndarray, src: np.ndarray, frc: np.ndarray) -> np.ndarray:
        """Copy the kept blocks of cilia ``jc`` into their rows of ``src``, ``frc``; returns the
        indices into ``jc`` of those not kept."""
        loc = self.index[jc]
        if self.count:
            _copy_blocks(loc, self.src, self.frc, src, frc)
        return np.flatnonzero(loc < 0)

    def keep(self, jc: np.ndarray, rows: np.ndarray, src: np.ndarray, frc: np.ndarray) -> None:
        """Keep the blocks of cilia ``jc[rows]`` (made in ``src``, ``frc``) while there is room."""
        rows = rows[:self.capacity - self.count]
        if not rows.size:
            return
        if self.src is None:  # the pages are taken as the slots fill
            self.src = np.empty((self.capacity, self.block, 3))
            self.frc = np.empty((self.capacity, self.block, 3))
        slots = np.arange(self.count, self.count + rows.size, dtype=np.int64)
        _keep_blocks(rows, slots, src, frc, self.src, self.frc)
        self.index[jc[rows]] = slots
        self.count += rows.size


INSTANT_BLOCKS_BYTES = 256 * 2 ** 20
"""Memory the resolved blocks of a few prepared instants may take (:class:`InstantBlocks`)."""


class InstantBlocks:
    """The resolved blocks of the cilia at a few instants (an integrator step's stages, said
    ahead by :meth:`Carpet.prepare <ciliary_carpet.carpet.carpet.Carpet.prepare>`): a cilium's
    block is made at all of them the first time an evaluation at one of them needs it, in one read
    of its coefficients (:func:`_instant_blocks`; one instant at a time reads them once per
    instant, and reading them is most of the cost), and kept until :meth:`reset` names other
    instants. The numbers are those of :meth:`ResolvedSources.fill`. At most
    :data:`INSTANT_BLOCKS_BYTES` are kept: an evaluation that needs more cilia makes its own."""

    def __init__(self, cycles: CycleData, budget: int = INSTANT_BLOCKS_BYTES):
        self.cycles = cycles
        self.times = np.zeros(0)
        self._index: dict = {}
        self.budget = int(budget)
        self.slot = np.full(cycles.n, -1, np.int64)
        self.cilia = np.zeros(0, np.int64)
        self.count = 0
        self.src = self.frc = None  # (P, 3, capacity n_s)

    def reset(self, times: np.ndarray) -> None:
        """Keep the blocks of the instants ``times`` (unique, finite) from now on: the blocks kept
        are forgotten (their memory reused) unless the times are the same."""
        times = np.asarray(times, dtype=float).ravel()
        if times.shape == self.times.shape and np.array_equal(times, self.times):
            return
        self.slot[self.cilia[:self.count]] = -1
        self.count = 0
        self.times = times.copy()
        self._index = {float(t): i for i, t in enumerate(self.times)}
        if self.src is not None and self.src.shape[0] != times.size:
            self.src = self.frc = None

    def index(self, t: float) -> int | None:
        """The instant ``t``'s index among the kept instants (None: not one of them)."""
        return self._index.get(t)

    def located(self, p: int, jc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The sources and forces of instant ``p`` as (K, 3) views of coordinate rows, and the
        slots (N,) of the blocks in them (cilium j's block: rows slot[j] n_s ...), the blocks of
        cilia ``jc`` made at every kept instant where missing; None when they would take more
        than the budget."""
        c = self.cycles
        n_s = c.n_s
        miss = jc[self.slot[jc] < 0]
        need = self.count + miss.size
        P = self.times.size
        if need * n_s * P * 48 > self.budget:
            return None
        if miss.size:
            if self.src is None or need * n_s > self.src.shape[2]:
                cap = max(64, 2 * need) * n_s
                src, frc = np.empty((P, 3, cap)), np.empty((P, 3, cap))
                if self.src is not None and self.count:
                    src[:, :, :self.count * n_s] = self.src[:, :, :self.count * n_s]
                    frc[:, :, :self.count * n_s] = self.frc[:, :, :self.count * n_s]
                self.src, self.frc = src, frc
            slots = np.arange(self.count, need, dtype=np.int64)
            if self.cilia.size < need:
                self.cilia = np.concatenate([self.cilia[:self.count], np.empty(max(need, 2 * self.cilia.size) -
                                                                                 self.count, np.int64)])
            self.cilia[self.count:need] = miss
            self.slot[miss] = slots
            self.count = need
            bs = np.empty((miss.size * P, 1, c.coef.shape[1]))
            phase_basis(c.phase_at(self.times, miss).T.ravel(), c.harmonics, bs)
            e = c.embedding
            _instant_blocks(c.coef, bs.reshape(miss.size, P, -1), c.weights, c.bases, e.origin, e.axes, miss, slots,
                            self.src, self.frc)
        return self.src[p].T, self.frc[p].T, self.slot


class ResolvedSources:
    """The resolved line sources of the cilia for one evaluation: cilium j's line distribution at
    its phase ``phases[j]`` ((N,): the flow at an instant), or at every phase sample of the table
    with weight 1 / n_phase (``phases`` None: the cycle-mean flow, its blocks taken from and kept
    in ``kept`` where given, :class:`MeanBlocks`), or at time ``t`` (given instead of ``phases``:
    the phases of the cilia filled only, :meth:`CycleData.phase_at`'s numbers; at an instant kept
    in ``prepared``, :meth:`located` finds the blocks there). ``block``: the sources per cilium
    (n_s, or n_phase n_s); :meth:`fill` writes them."""

    def __init__(self, cycles: CycleData, phases: np.ndarray | None, kept: MeanBlocks | None = None,
                 t: float | None = None, prepared: InstantBlocks | None = None):
        self.cycles, self.phases, self.t = cycles, phases, t
        self.kept = kept if phases is None and t is None else None
        self._at = prepared.index(t) if prepared is not None and t is not None else None
        self.prepared = prepared if self._at is not None else None
        if phases is None and t is None:
            self._all = trig_basis(np.arange(cycles.n_phase) / cycles.n_phase, cycles.harmonics)[None]
            self._weights = cycles.weights / cycles.n_phase
            self.block = cycles.n_phase * cycles.n_s
        else:
            self._weights = cycles.weights
            self.block = cycles.n_s

    def located(self, jc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The blocks of cilia ``jc`` where they are kept (:meth:`InstantBlocks.located`: sources,
        forces (K, 3) and the blocks' slots); None where they are not kept: :meth:`fill`."""
        if self.prepared is None:
            return None
        return self.prepared.located(self._at, np.asarray(jc, np.int64))

    def fill(self, jc: np.ndarray, src: np.ndarray, frc: np.ndarray) -> None:
        """The sources (positions in space) and forces (Simpson weights included) of cilia ``jc``
        into ``src``, ``frc`` (len(jc) * block, 3), block after block (:func:`_blocks`)."""
        c = self.cycles
        jc = np.asarray(jc, np.int64)
        if self.kept is not None:
            rows = self.kept.copy(jc, src, frc)
            if rows.size:  # the others made here, in place, and kept while there is room
                if rows.size == jc.size:
                    ResolvedSources(c, None).fill(jc, src, frc)
                else:
                    s_m, f_m = np.empty((rows.size * self.block, 3)), np.empty((rows.size * self.block, 3))
                    ResolvedSources(c, None).fill(jc[rows], s_m, f_m)
                    _scatter_blocks(rows, s_m, f_m, src, frc)
                self.kept.keep(jc, rows, src, frc)
            return
        if self.t is not None:
            bs = np.empty((len(jc), 1, c.coef.shape[1]))
            phase_basis(c.phase_at(self.t, jc), c.harmonics, bs)
        elif self.phases is None:
            bs = np.ascontiguousarray(np.broadcast_to(self._all, (len(jc),) + self._all.shape[1:]))
        else:
            bs = np.empty((len(jc), 1, c.coef.shape[1]))
            phase_basis(self.phases[jc], c.harmonics, bs)
        e = c.embedding
        _blocks(c.coef, bs, self._weights, c.bases, e.origin, e.axes, np.asarray(jc, np.int64), src, frc)
