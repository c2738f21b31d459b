"""The direct O(M N) velocity sums on the CPU: the :class:`Direct` backend (numba loops).

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

Single precision
----------------
``Direct("fp32")`` (:data:`PRECISIONS`) runs the same pair formulas retyped to fp32
(:func:`~ciliary_carpet.stokes.precision.retyped`; the reciprocal square root by LLVM's ``sqrt``
intrinsic, :func:`_rsqrt32`) on inputs shifted to the centre of their bounding box and rounded,
summing each target's terms in fp32 blocks of
:data:`~ciliary_carpet.stokes.precision.FP32_BLOCK` sources whose sums are added in fp64
(:func:`_dense32`, :func:`_ranged32`): 8 pairs to a 256-bit vector instead of 4, and cheaper
square roots and divisions, 2-3 times the pairs per second. Its error is bounded by
:func:`~ciliary_carpet.stokes.precision.fp32_error_bound` (tested for every Green's function). The
path lines' far carriers use it (:func:`ranged_fp32`, over sources rounded once per plan).

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
numba would give them one cache slot): they are compiled into the cached loops.

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
from numba import njit, prange, types
from numba.extending import intrinsic

from ciliary_carpet.stokes.backend import Backend
from ciliary_carpet.stokes.kernel import FASTMATH, INV_8PI, PAIRS, Kernel
from ciliary_carpet.stokes.precision import FP32_BLOCK, origin, retyped, soa

__all__ = ["Direct", "PRECISIONS", "ranged_fp32"]

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------- the loops
def _source_sum(pair, zero=0.0):
    """The sum of ``pair`` over the sources ``[lo, hi)`` of one target (inlined), accumulated in
    the type of ``zero`` (fp64; ``np.float32(0)`` for the fp32 pairs, :func:`_source_sum32`)."""

    @njit(fastmath=FASTMATH, inline="always")
    def source_sum(xi, yi, zi, sx, sy, sz, fx, fy, fz, e2, lo, hi):  # pragma: no cover - compiled
        ux = zero
        uy = zero
        uz = zero
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


@intrinsic
def _sqrt32(typingctx, x):  # pragma: no cover - compiled
    """The fp32 square root as LLVM's intrinsic (numba calls libm's ``sqrtf`` for ``math.sqrt`` of
    a float32, which blocks vectorisation; the intrinsic is the same correctly rounded root)."""
    if x != types.float32:
        return None

    def codegen(context, builder, signature, args):
        return builder.call(builder.module.declare_intrinsic("llvm.sqrt", [context.get_value_type(types.float32)]),
                            args)

    return types.float32(types.float32), codegen


_ONE32 = np.float32(1.0)
_ZERO32 = np.float32(0.0)


@njit(fastmath=FASTMATH, inline="always")
def _rsqrt32(x):  # pragma: no cover - compiled
    """``1 / sqrt(x)`` in fp32, correctly rounded sqrt and division."""
    return _ONE32 / _sqrt32(x)


def _source_sum32(pair):
    """:func:`_source_sum` of an fp32 ``pair`` summed in fp32 (the callers add it in fp64 over
    blocks of at most :data:`~ciliary_carpet.stokes.precision.FP32_BLOCK` sources)."""
    return _source_sum(pair, _ZERO32)


_source_sum32_of = _chain([_source_sum32(njit(fastmath=FASTMATH, inline="always")(retyped(p.py_func, True,
                                                                                         rsqrt=_rsqrt32)))
                           for p in PAIRS])
"""As :data:`_source_sum_of` in fp32 (:func:`_source_sum32`; the pair formulas retyped,
:func:`~ciliary_carpet.stokes.precision.retyped`)."""


@njit(cache=True, nogil=True, fastmath=FASTMATH, parallel=True)
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


@njit(cache=True, nogil=True, fastmath=FASTMATH, parallel=True)
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


@njit(cache=True, nogil=True, fastmath=FASTMATH, parallel=True)
def _dense32(code, T, S, F, e2, blk, scale, out):  # pragma: no cover - compiled
    """:func:`_dense` in fp32 (T, S, F, e2 float32; out float64): :func:`_source_sum32` over
    blocks of ``blk`` sources, added in fp64 (``blk`` an argument, not a constant: with a
    compile-time bound on the trip count LLVM vectorises the blocks' loop less well; timings in
    benchmarks/results/bench_evaluation.md)."""
    sx = S[0]
    sy = S[1]
    sz = S[2]
    fx = F[0]
    fy = F[1]
    fz = F[2]
    n = sx.shape[0]
    for i in prange(T.shape[1]):
        ux = 0.0
        uy = 0.0
        uz = 0.0
        for b in range(0, n, blk):
            a, c, d = _source_sum32_of(code, T[0, i], T[1, i], T[2, i], sx, sy, sz, fx, fy, fz, e2, b,
                                       min(b + blk, n))
            ux += a
            uy += c
            uz += d
        out[i, 0] = scale * ux
        out[i, 1] = scale * uy
        out[i, 2] = scale * uz


@njit(cache=True, nogil=True, fastmath=FASTMATH, parallel=True)
def _ranged32(code, T, S, F, ptr, ranges, e2, blk, scale, out):  # pragma: no cover - compiled
    """:func:`_ranged` in fp32 (T, S, F, e2 float32; out float64) as :func:`_dense32`."""
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
            hi = ranges[k, 1]
            for b in range(ranges[k, 0], hi, blk):
                a, c, d = _source_sum32_of(code, x, y, z, sx, sy, sz, fx, fy, fz, e2, b, min(b + blk, hi))
                ux += a
                uy += c
                uz += d
        out[i, 0] = scale * ux
        out[i, 1] = scale * uy
        out[i, 2] = scale * uz


# --------------------------------------------------------------------------- the cache guard
_FINGERPRINT = int.from_bytes(hashlib.sha256(b"".join(
    [Path(f).read_bytes() for f in sorted({inspect.getfile(p.py_func) for p in PAIRS} | {inspect.getfile(retyped)})]
    + [p.py_func.__qualname__.encode() for p in PAIRS])).digest()[:7], "little")
"""A hash of the source files of the pair formulas (and of their fp32 retyping,
:mod:`~ciliary_carpet.stokes.precision`) and of their order in the registry."""


@njit(cache=True)
def _compiled_for():  # pragma: no cover - compiled
    """The :data:`_FINGERPRINT` this module's cached loops were compiled with (module docstring)."""
    return _FINGERPRINT


def _guard_cache() -> None:
    """Clear the on-disk cache of the loops here when it was compiled for other pair formulas."""
    if _compiled_for() != _FINGERPRINT:
        logger.info("the pair formulas changed since the direct sums were cached: compiling them again")
        for fn in (_dense, _ranged, _dense32, _ranged32, _compiled_for):
            fn.recompile()  # clears the function's on-disk cache (and recompiles what is loaded)


_guard_cache()


# --------------------------------------------------------------------------- the backend
def _soa(a: np.ndarray, z_shift: float | None = None) -> np.ndarray:
    """(K, 3) -> a C-contiguous (3, K) float64 array (structure of arrays), z shifted by
    ``-z_shift``: a copy where the layout or the shift needs one (the caller's array is never
    modified), else ``a.T`` itself (the transpose of coordinate rows, as the carpet's sums pass)."""
    if z_shift:
        out = np.array(a.T, dtype=np.float64, order="C", copy=True)
        out[2] -= z_shift
        return out
    return np.ascontiguousarray(a.T, dtype=np.float64)


def _run_ranged(loop, args: tuple) -> None:
    """Run a ranged loop, its targets handed to the threads in chunks of 16 (the work per target
    is uneven: near-field lists)."""
    if args[1].shape[1] < 2 or numba.get_num_threads() < 2:
        loop(*args)
        return
    old = numba.get_parallel_chunksize()
    numba.set_parallel_chunksize(16)
    try:
        loop(*args)
    finally:
        numba.set_parallel_chunksize(old)


def ranged_fp32(kernel: Kernel, targets: np.ndarray, sources32: np.ndarray, shift: np.ndarray, forces: np.ndarray,
                ptr: np.ndarray, ranges: np.ndarray, mu: float) -> np.ndarray:
    """The ranged sum of :class:`Direct` ``("fp32")`` over sources rounded once for many sums:
    ``sources32`` (3, N) float32, their positions shifted by ``-shift`` (3,) (the centre of the
    points' bounding box, :func:`~ciliary_carpet.stokes.precision.origin`: a carpet's carriers,
    rounded once per plan); ``targets`` (M, 3) and ``forces`` (N, 3) in fp64, rounded here. The
    bound of :func:`~ciliary_carpet.stokes.precision.fp32_error_bound` holds with ``L`` the largest
    coordinate of targets and sources after the shift."""
    out = np.zeros((targets.shape[0], 3))
    if targets.shape[0] == 0 or sources32.shape[1] == 0 or ranges.shape[0] == 0:
        return out
    _run_ranged(_ranged32, (kernel.code, soa(targets, np.float32, shift), sources32, soa(forces, np.float32), ptr,
                            ranges, np.float32(kernel.eps ** 2), FP32_BLOCK, INV_8PI / mu, out))
    return out


PRECISIONS = ("fp64", "fp32")
"""Arithmetic of :class:`Direct`: fp64; fp32 pairs summed in fp32 blocks (module docstring)."""


@dataclass(frozen=True)
class Direct(Backend):
    """Direct O(M N) sums compiled with numba, every Green's function, dense and ranged (module
    docstring), in ``precision`` (:data:`PRECISIONS`): ``"fp64"``, or ``"fp32"``: the inputs
    shifted to the centre of their bounding box and rounded to fp32, each pair evaluated in fp32 and
    summed in fp32 blocks of :data:`~ciliary_carpet.stokes.precision.FP32_BLOCK` sources whose sums
    are added in fp64; bounded by :func:`~ciliary_carpet.stokes.precision.fp32_error_bound` (``block``
    :data:`~ciliary_carpet.stokes.precision.FP32_BLOCK`). fp32 runs 8 pairs to a 256-bit vector
    instead of 4, and its square roots and divisions are cheaper (throughput:
    benchmarks/results/bench_evaluation.md)."""

    precision: str = "fp64"
    ranged_sums = True

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ValueError(f"Direct: precision must be one of {PRECISIONS}, got {self.precision!r}")

    def dense(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
              mu: float) -> np.ndarray:
        out = np.zeros((targets.shape[0], 3))
        if targets.shape[0] == 0 or sources.shape[0] == 0:
            return out
        if self.precision == "fp32":
            o = origin(kernel, targets, sources)
            _dense32(kernel.code, soa(targets, np.float32, o), soa(sources, np.float32, o), soa(forces, np.float32),
                     np.float32(kernel.eps ** 2), FP32_BLOCK, INV_8PI / mu, out)
            return out
        z = kernel.z_origin
        _dense(kernel.code, _soa(targets, z), _soa(sources, z), _soa(forces), kernel.eps ** 2, INV_8PI / mu, out)
        return out

    def ranged(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
               ptr: np.ndarray, ranges: np.ndarray, mu: float) -> np.ndarray:
        out = np.zeros((targets.shape[0], 3))
        if targets.shape[0] == 0 or sources.shape[0] == 0 or ranges.shape[0] == 0:
            return out
        if self.precision == "fp32":
            o = origin(kernel, targets, sources)
            return ranged_fp32(kernel, targets, soa(sources, np.float32, o), o, forces, ptr, ranges, mu)
        z = kernel.z_origin
        _run_ranged(_ranged, (kernel.code, _soa(targets, z), _soa(sources, z), _soa(forces), ptr, ranges,
                              kernel.eps ** 2, INV_8PI / mu, out))
        return out

    def describe(self) -> str:
        fp = ", fp32" if self.precision == "fp32" else ""
        return f"direct (numba, CPU{fp}, {numba.get_num_threads()} threads)"
