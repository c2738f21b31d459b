"""The direct O(M N) velocity sums on the CPU: the :class:`Direct` evaluator (numba loops).

``u(x_i) = 1/(8 pi mu) sum_j G(x_i, xi_j) f_j`` summed pair by pair, for every Green's function
of :data:`~ciliary_carpet.stokes.kernel.KERNELS`: parallel over targets (``prange``, numba's
default thread count), the reduction over sources vectorised (structure-of-arrays copies of
targets, sources and forces are made once per call, heights from the kernel's
:attr:`~ciliary_carpet.stokes.kernel.Kernel.z_origin`). Exact up to rounding: with the value-safe
:data:`~ciliary_carpet.stokes.kernel.FASTMATH` flags (reordered sums, fused multiply-adds, no
approximate ``1/sqrt``) the sums agree with the numpy reference to about 1e-15 relative to
``max |u|`` (tested to 1e-12), and in free space each velocity to a few ulps. With a wall, the
velocity close to the wall (target height ``<< h``) or far from the source (``|R| >> h``) is a
small difference of ``O(|f| / |R|)`` image terms, in this and in any implementation of the image
system: there the absolute error is ~1e-16 of the free-space scale ``|f| / (8 pi mu |R|)``, the
relative error of ``u`` correspondingly larger. Throughput on 2 cores:
benchmarks/results/bench_kernel.md.

How the loops find the pair formula
-----------------------------------
The compiled loops :func:`_dense` and :func:`_ranged` are written once and take the kernel's
:attr:`~ciliary_carpet.stokes.kernel.Kernel.code`, the position of its pair formula in
:data:`~ciliary_carpet.stokes.kernel.PAIRS`. For each pair formula this module builds, at import,
the loop over a block of a target's sources that inlines it (:func:`_source_sum`), and a chain
of branches on the code that selects it (:func:`_chain`), inlined in turn into both loops; so a
new Green's function in :mod:`ciliary_carpet.stokes.kernel` needs nothing here. Why not pass the
pair function itself to the loops: numba keys a dispatcher argument by the object's identity, so
its on-disk cache never hits (every process would compile again); an integer code keeps
``cache=True`` working. The closures are not cached themselves (they share one source, and
numba would give them one cache slot): they are compiled into the cached loops. Measured against
the three hand-written loops this replaces (bit-identical results): the same compile time (about
2 s per loop, once) and the same speed.

numba's on-disk cache of :func:`_dense` and :func:`_ranged` is keyed by this file only, while
the code they inline lives in :mod:`ciliary_carpet.stokes.kernel`: after an edit there, the
cached loops would still run the old formulas. :func:`_compiled_for` guards against that: a
cached function returning the fingerprint of the pair formulas' source (:data:`_FINGERPRINT`)
that it was compiled with; at import a stale value clears the cache of every loop here.
"""
from __future__ import annotations

import hashlib
import inspect
import logging
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
from numba import njit, prange

from ciliary_carpet.stokes.backend import Backend
from ciliary_carpet.stokes.kernel import FASTMATH, INV_8PI, PAIRS, Kernel

__all__ = ["Direct"]

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------- the loops
def _source_sum(pair):
    """The sum of ``pair`` over the sources ``[lo, hi)`` of one target (inlined)."""

    @njit(fastmath=FASTMATH, inline="always")
    def source_sum(xi, yi, zi, sx, sy, sz, fx, fy, fz, e2, lo, hi):  # pragma: no cover - compiled
        ux = 0.0
        uy = 0.0
        uz = 0.0
        # sliced views: the loop then runs from 0 with known bounds and vectorises (indexing
        # with range(lo, hi) keeps numba's negative-index wraparound and is 3-4x slower)
        sx = sx[lo:hi]
        sy = sy[lo:hi]
        sz = sz[lo:hi]
        fx = fx[lo:hi]
        fy = fy[lo:hi]
        fz = fz[lo:hi]
        for j in range(hi - lo):
            a, b, c = pair(xi, yi, zi, sx[j], sy[j], sz[j], fx[j], fy[j], fz[j], e2)
            ux += a
            uy += b
            uz += c
        return ux, uy, uz

    return source_sum


def _chain(fns: list, k: int = 0):
    """``f(code, *args) = fns[code - k](*args)`` for functions of :func:`_source_sum`'s arguments:
    a compiled chain of branches on the code (the last function also takes any code beyond)."""
    head = fns[0]
    if len(fns) == 1:
        @njit(fastmath=FASTMATH, inline="always")
        def last(code, xi, yi, zi, sx, sy, sz, fx, fy, fz, e2, lo, hi):  # pragma: no cover - compiled
            return head(xi, yi, zi, sx, sy, sz, fx, fy, fz, e2, lo, hi)

        return last
    tail = _chain(fns[1:], k + 1)

    @njit(fastmath=FASTMATH, inline="always")
    def branch(code, xi, yi, zi, sx, sy, sz, fx, fy, fz, e2, lo, hi):  # pragma: no cover - compiled
        if code == k:
            return head(xi, yi, zi, sx, sy, sz, fx, fy, fz, e2, lo, hi)
        return tail(code, xi, yi, zi, sx, sy, sz, fx, fy, fz, e2, lo, hi)

    return branch


_source_sum_of = _chain([_source_sum(p) for p in PAIRS])
"""``_source_sum_of(code, x, y, z, sx, sy, sz, fx, fy, fz, e2, lo, hi)``: the sum over the sources
``[lo, hi)`` of one target of the pair formula ``PAIRS[code]``."""


@njit(cache=True, fastmath=FASTMATH, parallel=True)
def _dense(code, T, S, F, e2, scale, out):  # pragma: no cover - compiled
    """out[i] = scale * sum_j G(T[:, i], S[:, j]) F[:, j] for the pair formula ``code``; T (3, M),
    S, F (3, N) C-order, heights from the kernel's z_origin."""
    sx = S[0]
    sy = S[1]
    sz = S[2]
    fx = F[0]
    fy = F[1]
    fz = F[2]
    n = sx.shape[0]
    for i in prange(T.shape[1]):
        ux, uy, uz = _source_sum_of(code, T[0, i], T[1, i], T[2, i], sx, sy, sz, fx, fy, fz, e2, 0, n)
        out[i, 0] = scale * ux
        out[i, 1] = scale * uy
        out[i, 2] = scale * uz


@njit(cache=True, fastmath=FASTMATH, parallel=True)
def _ranged(code, T, S, F, ptr, ranges, e2, scale, out):  # pragma: no cover - compiled
    """out[i] = scale * sum over k in ptr[i]:ptr[i+1], j in ranges[k, 0]:ranges[k, 1] of
    G(T[:, i], S[:, j]) F[:, j] for the pair formula ``code`` (as :func:`_dense`)."""
    sx = S[0]
    sy = S[1]
    sz = S[2]
    fx = F[0]
    fy = F[1]
    fz = F[2]
    for i in prange(T.shape[1]):
        ux = 0.0
        uy = 0.0
        uz = 0.0
        x = T[0, i]
        y = T[1, i]
        z = T[2, i]
        for k in range(ptr[i], ptr[i + 1]):
            a, b, c = _source_sum_of(code, x, y, z, sx, sy, sz, fx, fy, fz, e2, ranges[k, 0], ranges[k, 1])
            ux += a
            uy += b
            uz += c
        out[i, 0] = scale * ux
        out[i, 1] = scale * uy
        out[i, 2] = scale * uz


# --------------------------------------------------------------------------- the cache guard
_FINGERPRINT = int.from_bytes(hashlib.sha256(b"".join(
    [Path(f).read_bytes() for f in sorted({inspect.getfile(p.py_func) for p in PAIRS})]
    + [p.py_func.__qualname__.encode() for p in PAIRS])).digest()[:7], "little")
"""A hash of the source files of the pair formulas and of their order in the registry."""


@njit(cache=True)
def _compiled_for():  # pragma: no cover - compiled
    """The :data:`_FINGERPRINT` this module's cached loops were compiled with (module docstring)."""
    return _FINGERPRINT


def _guard_cache() -> None:
    """Clear the on-disk cache of the loops here when it was compiled for other pair formulas."""
    if _compiled_for() != _FINGERPRINT:
        logger.info("the pair formulas changed since the direct sums were cached: compiling them again")
        for fn in (_dense, _ranged, _compiled_for):
            fn.recompile()  # clears the function's on-disk cache (and recompiles what is loaded)


_guard_cache()


# --------------------------------------------------------------------------- the evaluator
def _soa(a: np.ndarray, z_shift: float | None = None) -> np.ndarray:
    """(K, 3) -> a C-contiguous (3, K) float64 array (structure of arrays), z shifted by
    ``-z_shift``: a copy where the layout or the shift needs one (the caller's array is never
    modified), else ``a.T`` itself (the transpose of coordinate rows, as the carpet's sums pass)."""
    if z_shift:
        out = np.array(a.T, dtype=np.float64, order="C", copy=True)
        out[2] -= z_shift
        return out
    return np.ascontiguousarray(a.T, dtype=np.float64)


@dataclass(frozen=True)
class Direct(Backend):
    """Direct O(M N) sums compiled with numba, every Green's function, dense and ranged (module
    docstring)."""

    ranged_sums = True

    def dense(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
              mu: float) -> np.ndarray:
        out = np.zeros((targets.shape[0], 3))
        if targets.shape[0] == 0 or sources.shape[0] == 0:
            return out
        z = kernel.z_origin
        _dense(kernel.code, _soa(targets, z), _soa(sources, z), _soa(forces), kernel.eps ** 2, INV_8PI / mu, out)
        return out

    def ranged(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
               ptr: np.ndarray, ranges: np.ndarray, mu: float) -> np.ndarray:
        out = np.zeros((targets.shape[0], 3))
        if targets.shape[0] == 0 or sources.shape[0] == 0 or ranges.shape[0] == 0:
            return out
        z = kernel.z_origin
        args = (kernel.code, _soa(targets, z), _soa(sources, z), _soa(forces), ptr, ranges, kernel.eps ** 2,
                INV_8PI / mu, out)
        if targets.shape[0] < 2 or numba.get_num_threads() < 2:
            _ranged(*args)
            return out
        old = numba.get_parallel_chunksize()
        numba.set_parallel_chunksize(16)  # the work per target is uneven (near-field lists)
        try:
            _ranged(*args)
        finally:
            numba.set_parallel_chunksize(old)
        return out

    def describe(self) -> str:
        return f"direct (numba, CPU, {numba.get_num_threads()} threads)"
