"""Velocity of point forces in Stokes flow: free space, or above a no-slip plane wall.

The velocity at ``x`` of point forces ``f_j`` at ``xi_j`` in a fluid of viscosity ``mu`` is

.. math::

    u(x) = \\frac{1}{8 \\pi \\mu} \\sum_j G(x, \\xi_j) f_j,

with, in free space, the Stokeslet (Oseen tensor) of ``R = x - xi``

.. math::

    G^S(R) = \\frac{I}{|R|} + \\frac{R R^T}{|R|^3}.

Above a no-slip wall, the plane ``z = z_w`` (:class:`Wall`), ``G`` is the Blake (1971) tensor:
the Stokeslet, an image Stokeslet, a Stokes doublet and a source doublet, all at the image point
``xi* = (xi_x, xi_y, 2 z_w - xi_z)``. With the wall shifted to ``z = 0``, ``h = xi_z`` the height
of the source, ``R* = x - xi*`` and ``M = diag(1, 1, -1)`` (Blake 1971; Ainley et al. 2008,
J. Comput. Phys. 227, eq. 8 in the singular limit),

.. math::

    G^B_{ij} = G^S_{ij}(R) - G^S_{ij}(R^*)
        + 2 h M_{jk} \\frac{\\partial}{\\partial R^*_k}
          \\left[ \\frac{h R^*_i}{|R^*|^3} - G^S_{i3}(R^*) \\right].

It vanishes for targets on the wall and satisfies the reciprocity ``G_ij(x, y) = G_ji(y, x)``.
Sources must lie strictly above the wall, targets above or on it.

Conventions shared by every function here:

* points and forces are ``(M, 3)`` / ``(N, 3)`` float arrays; ``(M, 2)`` / ``(N, 2)`` arrays are
  accepted and padded with ``z = 0`` (forces too: a planar force has no z component); the result
  is always ``(M, 3)`` float64;
* a target that coincides with a source (``R = 0``) gets no contribution from that source's
  singular Stokeslet (the term is skipped, i.e. counts as zero); with a wall, the image terms of
  that source are regular and are kept;
* ``M = 0`` or ``N = 0`` give zeros of shape ``(M, 3)``.

Evaluation strategies (:class:`Backend`): :class:`Direct`, the O(MN) sum compiled with numba
(parallel over targets, vectorised over sources; free space and wall); :class:`FMM`, the Stokes
fast multipole method of ``fmm3dpy`` (free space only; optional dependency
``pip install cilia-flow[fmm]``); :class:`~ciliary_carpet.stokes.cuda.Cuda`, both sums on an NVIDIA GPU
(optional dependency ``pip install cilia-flow[gpu]``); :class:`Auto` (the default), which picks
the GPU when one is usable, else one of the first two. :func:`backend_named` maps the names a
scene or the command line gives (:data:`BACKENDS`) to these objects.
:func:`stokeslet_velocity_ranges` sums, per target, over a sparse list of source index ranges
(near-field corrections); :func:`stokeslet_velocity_numpy` is the slow plain-numpy reference.

Accuracy: the numba kernels use ``fastmath={'reassoc', 'contract', 'nsz', 'arcp'}`` only
(reordered sums and fused multiply-adds, so that the reduction over sources vectorises; no
approximate ``1/sqrt``, no assumption of finite values): they agree with the numpy reference to
about 1e-15 relative to ``max |u|`` (tested to 1e-12), and in free space each velocity to a few
ulps. With a wall, the velocity close to the wall (target height ``<< h``) or far from the
source (``|R| >> h``) is a small difference of ``O(|f| / |R|)`` image terms, in this and in any
implementation of the image system: there the absolute error is ~1e-16 of the free-space scale
``|f| / (8 pi mu |R|)``, the relative error of ``u`` correspondingly larger. Throughput and the
FMM crossover are measured by ``benchmarks/bench_flow.py`` (``benchmarks/results/bench_kernel.md``).
"""
from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numba import njit, prange

from ciliary_carpet.stokes.kernel import Kernel, Stokeslet, Wall, make_kernel, regularised_blake_tensor

__all__ = [
    "Wall",
    "Kernel",
    "Backend",
    "Direct",
    "FMM",
    "Auto",
    "Cuda",
    "CudaUnavailableError",
    "BACKENDS",
    "backend_named",
    "stokeslet_velocity",
    "stokeslet_velocity_numpy",
    "stokeslet_velocity_ranges",
    "FMM_CROSSOVER_PAIRS",
]

logger = logging.getLogger(__name__)

#: Default :class:`Auto` threshold on ``M * N``: below it the direct sum is used. The measured
#: crossover (benchmarks/results/bench_kernel.md; 2 cores, AMD EPYC Zen 3) of the numba direct sum
#: (1.5e9 pairs/s) and the serial fmm3dpy 2.1.0 wheel at eps = 1e-12 (64 s for M = N = 1e5) on
#: random points in the unit cube: M = N ~ 1e6, extrapolated from M = N = 1e5 (at eps = 1e-6 it
#: would be M = N ~ 5e5). In practice Auto therefore means Direct unless a scene is huge.
FMM_CROSSOVER_PAIRS: float = 1.0e12

#: Value-safe fast-math flags: reassociation (vectorised reductions), FMA contraction, no signed
#: zeros, reciprocal allowed. Not ``afn`` (approximate ``1/sqrt``) nor ``nnan``/``ninf``.
_FASTMATH = {"reassoc", "contract", "nsz", "arcp"}

_INV_8PI = 1.0 / (8.0 * math.pi)


# --------------------------------------------------------------------------- validation
def _finite_positive(name: str, value: Any) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite, got {x}")
    if x <= 0.0:
        raise ValueError(f"{name} must be > 0, got {x}")
    return x


def _points(name: str, a: Any) -> np.ndarray:
    """``a`` as a C-contiguous (K, 3) float64 array (z = 0 padded from (K, 2)), validated."""
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real (K, 3) or (K, 2) array") from None
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise ValueError(f"{name} must have shape (K, 3) or (K, 2), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    if arr.shape[1] == 2:
        out = np.zeros((arr.shape[0], 3))
        out[:, :2] = arr
        return out
    return np.ascontiguousarray(arr)


def _check_wall(wall: Any, targets: np.ndarray, sources: np.ndarray) -> Wall | None:
    if wall is None:
        return None
    if not isinstance(wall, Wall):
        raise TypeError(f"wall must be a Wall or None, got {type(wall).__name__}")
    if sources.shape[0] and not np.all(sources[:, 2] > wall.z):
        k = int(np.argmin(sources[:, 2]))
        raise ValueError(f"sources must lie strictly above the wall z = {wall.z}: "
                         f"sources[{k}] has z = {sources[k, 2]}")
    if targets.shape[0] and not np.all(targets[:, 2] >= wall.z):
        k = int(np.argmin(targets[:, 2]))
        raise ValueError(f"targets must lie on or above the wall z = {wall.z}: "
                         f"targets[{k}] has z = {targets[k, 2]}")
    return wall


def _validate(targets: Any, sources: Any, forces: Any, mu: Any, wall: Any
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, Wall | None]:
    t = _points("targets", targets)
    s = _points("sources", sources)
    f = _points("forces", forces)
    if f.shape[0] != s.shape[0]:
        raise ValueError(f"forces must have one row per source: sources has {s.shape[0]} rows, "
                         f"forces has {f.shape[0]}")
    m = _finite_positive("mu", mu)
    w = _check_wall(wall, t, s)
    return t, s, f, m, w


# --------------------------------------------------------------------------- numba kernels
# The per-pair formulas are written once, below, as scalar functions of one (target, source) pair:
# the CPU loops (_acc_*) inline them, and ciliary_carpet.stokes.cuda compiles the same Python source
# (``.py_func``) into CUDA device functions. Their constants are module globals, not literals, so
# that the CUDA evaluator can compile an fp32 copy with fp32 constants (a float literal would
# promote every fp32 operation it touches to fp64 under numba's typing), and their one special
# function is the global _rsqrt, which the GPU copies bind to the hardware's reciprocal square root.
_ZERO = 0.0
_ONE = 1.0
_TWO = 2.0
_THREE = 3.0
_FOUR = 4.0
_SIX = 6.0
PAIR_CONSTANTS = ("_ZERO", "_ONE", "_TWO", "_THREE", "_FOUR", "_SIX")
"""Names of the constants of the pair functions (retyped by the fp32 CUDA kernels)."""


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _rsqrt(x):  # pragma: no cover - compiled
    """``1 / sqrt(x)``, correctly rounded sqrt and division (the CPU's; not ``afn``)."""
    return _ONE / math.sqrt(x)


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _pair_free(xi, yi, zi, sx, sy, sz, a, b, c, e2):  # pragma: no cover - compiled
    """``G^eps(x - xi) f`` of one pair (no 1/(8 pi mu)), ``e2 = eps^2``:
    ``(f (r^2 + 2 e2) + R (R.f)) / (r^2 + e2)^{3/2}``; the singular Stokeslet for ``e2 = 0``, its
    coincident pair (``R = 0``) counting as zero."""
    dx = xi - sx
    dy = yi - sy
    dz = zi - sz
    r2 = dx * dx + dy * dy + dz * dz
    q2 = r2 + e2
    ir = _rsqrt(q2) if q2 > _ZERO else _ZERO
    ir3 = ir * ir * ir
    rf = (dx * a + dy * b + dz * c) * ir3
    iso = (r2 + _TWO * e2) * ir3
    return a * iso + dx * rf, b * iso + dy * rf, c * iso + dz * rf


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _pair_wall(xi, yi, zt, sx, sy, h, a, b, c, e2):  # pragma: no cover - compiled
    """``G^B(x, xi) f`` of one pair, wall at z = 0 (``zt`` the target's height, ``h`` the
    source's; ``e2`` unused, for a common signature; no 1/(8 pi mu)).

    With ``R = x - xi``, ``R* = x - xi*``, ``g = M f = (f_x, f_y, -f_z)`` the Blake doublet
    terms reduce (``R*_z - h = zt``) to
    ``2 h [-zt g / r*^3 + R* (3 zt (R*.g) / r*^5 - g_z / r*^3) + e_z (R*.g) / r*^3]``.
    """
    dx = xi - sx
    dy = yi - sy
    dz = zt - h
    ez = zt + h
    p2 = dx * dx + dy * dy
    r2 = p2 + dz * dz
    ir = _rsqrt(r2) if r2 > _ZERO else _ZERO
    ir3 = ir * ir * ir
    iq = _rsqrt(p2 + ez * ez)
    iq2 = iq * iq
    iq3 = iq * iq2
    pf = dx * a + dy * b
    rf = (pf + dz * c) * ir3          # (R . f) / r^3
    qf = pf + ez * c                  # R* . f
    qg = pf - ez * c                  # R* . g
    h2 = _TWO * h * iq3
    d = h2 * zt
    cf = ir - iq
    cq = h2 * (c + _THREE * zt * qg * iq2) - qf * iq3
    cxy = rf + cq
    return ((cf - d) * a + cxy * dx, (cf - d) * b + cxy * dy,
            (cf + d) * c + rf * dz + cq * ez + h2 * qg)


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _pair_regwall(xi, yi, zt, sx, sy, h, a, b, c, e2):  # pragma: no cover - compiled
    """The regularised Blake tensor (:func:`ciliary_carpet.stokes.kernel.regularised_blake_tensor`)
    times ``f`` for one pair, wall at z = 0, ``e2 = eps^2`` (no 1/(8 pi mu)).

    With ``r = x - xi``, ``R = x - xi*``, ``g = (f_x, f_y, -f_z)`` the tensor's terms collect to
    ``G^eps(r) f + a_f f + a_g g + a_R R + a_z e_z`` (coefficients below)."""
    dx = xi - sx
    dy = yi - sy
    dz = zt - h
    ez = zt + h
    p2 = dx * dx + dy * dy
    r2 = p2 + dz * dz
    R2 = p2 + ez * ez
    ir = _rsqrt(r2 + e2)
    ir3 = ir * ir * ir
    iq = _rsqrt(R2 + e2)
    iq3 = iq * iq * iq
    iq5 = iq3 * iq * iq
    pf = dx * a + dy * b
    rf = (pf + dz * c) * ir3
    Rf = pf + ez * c
    Rg = pf - ez * c
    iso = (r2 + _TWO * e2) * ir3
    hh = h * h
    cf = -(R2 + _TWO * e2) * iq3 + _SIX * h * e2 * iq5 * ez
    cg = (_TWO * hh - _TWO * h * ez) * iq3 - _SIX * hh * e2 * iq5
    cR = -Rf * iq3 + (_SIX * h * ez - _SIX * hh) * Rg * iq5 + _TWO * h * c * iq3
    cz = _TWO * h * Rg * (R2 + _FOUR * e2) * iq5 - _SIX * h * e2 * iq5 * Rf
    return (a * (iso + cf) + dx * (rf + cR) + cg * a,
            b * (iso + cf) + dy * (rf + cR) + cg * b,
            c * (iso + cf) + dz * rf + ez * cR - cg * c + cz)


PAIRS = {0: _pair_free, 1: _pair_wall, 2: _pair_regwall}
"""The pair function of each :attr:`Kernel.code <ciliary_carpet.stokes.kernel.Kernel.code>`."""


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _acc_free(xi, yi, zi, sx, sy, sz, fx, fy, fz, e2, lo, hi):  # pragma: no cover - compiled
    """Sum of :func:`_pair_free` over the sources ``[lo, hi)`` of one target (one loop per
    kernel, so that each vectorises)."""
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
        a, b, c = _pair_free(xi, yi, zi, sx[j], sy[j], sz[j], fx[j], fy[j], fz[j], e2)
        ux += a
        uy += b
        uz += c
    return ux, uy, uz


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _acc_wall(xi, yi, zi, sx, sy, sz, fx, fy, fz, e2, lo, hi):  # pragma: no cover - compiled
    """Sum of :func:`_pair_wall` over the sources ``[lo, hi)`` of one target."""
    ux = 0.0
    uy = 0.0
    uz = 0.0
    sx = sx[lo:hi]
    sy = sy[lo:hi]
    sz = sz[lo:hi]
    fx = fx[lo:hi]
    fy = fy[lo:hi]
    fz = fz[lo:hi]
    for j in range(hi - lo):
        a, b, c = _pair_wall(xi, yi, zi, sx[j], sy[j], sz[j], fx[j], fy[j], fz[j], e2)
        ux += a
        uy += b
        uz += c
    return ux, uy, uz


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _acc_regwall(xi, yi, zi, sx, sy, sz, fx, fy, fz, e2, lo, hi):  # pragma: no cover - compiled
    """Sum of :func:`_pair_regwall` over the sources ``[lo, hi)`` of one target."""
    ux = 0.0
    uy = 0.0
    uz = 0.0
    sx = sx[lo:hi]
    sy = sy[lo:hi]
    sz = sz[lo:hi]
    fx = fx[lo:hi]
    fy = fy[lo:hi]
    fz = fz[lo:hi]
    for j in range(hi - lo):
        a, b, c = _pair_regwall(xi, yi, zi, sx[j], sy[j], sz[j], fx[j], fy[j], fz[j], e2)
        ux += a
        uy += b
        uz += c
    return ux, uy, uz


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _acc(code, x, y, z, sx, sy, sz, fx, fy, fz, e2, lo, hi):  # pragma: no cover - compiled
    """Dispatch on the kernel code (0 free / regularised free, 1 Blake, 2 regularised Blake)."""
    if code == 0:
        return _acc_free(x, y, z, sx, sy, sz, fx, fy, fz, e2, lo, hi)
    if code == 1:
        return _acc_wall(x, y, z, sx, sy, sz, fx, fy, fz, e2, lo, hi)
    return _acc_regwall(x, y, z, sx, sy, sz, fx, fy, fz, e2, lo, hi)


@njit(cache=True, fastmath=_FASTMATH, parallel=True)
def _direct(code, T, S, F, e2, scale, out):  # pragma: no cover - compiled
    """out[i] = scale * sum_j G(T[:, i], S[:, j]) F[:, j]; T (3, M), S, F (3, N) C-order,
    heights above the wall z = 0 for codes 1, 2."""
    sx = S[0]
    sy = S[1]
    sz = S[2]
    fx = F[0]
    fy = F[1]
    fz = F[2]
    n = sx.shape[0]
    for i in prange(T.shape[1]):
        ux, uy, uz = _acc(code, T[0, i], T[1, i], T[2, i], sx, sy, sz, fx, fy, fz, e2, 0, n)
        out[i, 0] = scale * ux
        out[i, 1] = scale * uy
        out[i, 2] = scale * uz


@njit(cache=True, fastmath=_FASTMATH, parallel=True)
def _ranges_kernel(code, T, S, F, ptr, ranges, e2, scale, out):  # pragma: no cover - compiled
    """out[i] = scale * sum over k in ptr[i]:ptr[i+1], j in ranges[k, 0]:ranges[k, 1] of
    G(T[:, i], S[:, j]) F[:, j] for the kernel ``code`` (as :func:`_direct`; one loop per code so
    that each inner sum vectorises)."""
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
        if code == 0:
            for k in range(ptr[i], ptr[i + 1]):
                a, b, c = _acc_free(x, y, z, sx, sy, sz, fx, fy, fz, e2, ranges[k, 0], ranges[k, 1])
                ux += a
                uy += b
                uz += c
        elif code == 1:
            for k in range(ptr[i], ptr[i + 1]):
                a, b, c = _acc_wall(x, y, z, sx, sy, sz, fx, fy, fz, e2, ranges[k, 0], ranges[k, 1])
                ux += a
                uy += b
                uz += c
        else:
            for k in range(ptr[i], ptr[i + 1]):
                a, b, c = _acc_regwall(x, y, z, sx, sy, sz, fx, fy, fz, e2, ranges[k, 0], ranges[k, 1])
                ux += a
                uy += b
                uz += c
        out[i, 0] = scale * ux
        out[i, 1] = scale * uy
        out[i, 2] = scale * uz


def _soa(a: np.ndarray, z_shift: float = 0.0) -> np.ndarray:
    """(K, 3) -> a new C-contiguous (3, K) array (structure of arrays), z shifted by
    ``-z_shift`` (always a copy: the caller's array is never modified)."""
    out = np.array(a.T, order="C", copy=True)
    if z_shift != 0.0:
        out[2] -= z_shift
    return out


# --------------------------------------------------------------------------- backends
class Backend:
    """Evaluator of velocity sums for any :class:`~ciliary_carpet.stokes.kernel.Kernel` (base class).

    One interface for the two sums a flow model needs: :meth:`dense` (every source for every
    target) and :meth:`ranged` (per target, a CSR list of source index ranges: near-field
    corrections). The front doors (:func:`stokeslet_velocity`, :func:`stokeslet_velocity_ranges`)
    validate and normalise the inputs first, so an implementation may assume: ``targets`` (M, 3),
    ``sources`` (N, 3), ``forces`` (N, 3) C-contiguous finite float64 arrays, ``M, N >= 1``;
    ``mu`` a finite float > 0; sources strictly above / targets on or above the kernel's wall;
    valid ``ptr`` (M + 1,) and ``ranges`` (K, 2) int64 arrays. It returns the (M, 3) float64
    velocity ``u(x) = 1/(8 pi mu) sum_j G(x, xi_j) f_j``, skips the singular term of a coincident
    pair, and raises ValueError for a kernel it cannot evaluate.
    """

    def dense(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
              mu: float) -> np.ndarray:
        """Velocity (M, 3) at ``targets`` of every source; see the class docstring."""
        raise TypeError(f"{type(self).__name__} does not implement dense sums")

    def ranged(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
               ptr: np.ndarray, ranges: np.ndarray, mu: float) -> np.ndarray:
        """Velocity (M, 3) at ``targets`` of each one's listed source ranges (the sparse
        near-field sums are always evaluated directly, by :class:`Direct`)."""
        return Direct().ranged(kernel, targets, sources, forces, ptr, ranges, mu)

    def describe(self) -> str:
        """One line naming the evaluator (for summaries)."""
        return type(self).__name__.lower()


def _shift(kernel: Kernel) -> float:
    return 0.0 if kernel.wall is None else kernel.wall.z


@dataclass(frozen=True)
class Direct(Backend):
    """Direct O(M N) sums compiled with numba, every kernel.

    Parallel over targets (``prange``, numba's default thread count), the reduction over sources
    vectorised (structure-of-arrays copies of sources and forces are made once per call).
    Exact up to rounding (about 1e-15 relative). Throughput on 2 cores:
    benchmarks/results/bench_kernel.md.
    """

    def dense(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
              mu: float) -> np.ndarray:
        out = np.zeros((targets.shape[0], 3))
        if targets.shape[0] == 0 or sources.shape[0] == 0:
            return out
        z = _shift(kernel)
        _direct(kernel.code, _soa(targets, z), _soa(sources, z), _soa(forces), kernel.eps ** 2, _INV_8PI / mu, out)
        return out

    def describe(self) -> str:
        return f"direct (numba, CPU, {numba.get_num_threads()} threads)"

    def ranged(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
               ptr: np.ndarray, ranges: np.ndarray, mu: float) -> np.ndarray:
        out = np.zeros((targets.shape[0], 3))
        if targets.shape[0] == 0 or sources.shape[0] == 0 or ranges.shape[0] == 0:
            return out
        z = _shift(kernel)
        old = numba.get_parallel_chunksize()
        numba.set_parallel_chunksize(16)  # the work per target is uneven (near-field lists)
        try:
            _ranges_kernel(kernel.code, _soa(targets, z), _soa(sources, z), _soa(forces), ptr, ranges,
                           kernel.eps ** 2, _INV_8PI / mu, out)
        finally:
            numba.set_parallel_chunksize(old)
        return out


@functools.cache
def _import_fmm3dpy():
    try:
        import fmm3dpy
    except ImportError:
        return None
    return fmm3dpy


def _fmm_available() -> bool:
    return _import_fmm3dpy() is not None


@dataclass(frozen=True)
class FMM(Backend):
    """Stokes fast multipole method, ``fmm3dpy.stfmm3d``: the singular free-space Stokeslet only.

    ``stfmm3d`` computes ``sum_j (1/(8 pi)) G^S(x - xi_j) f_j`` (its Stokeslet carries the
    ``1/(8 pi)``; checked numerically), and omits coincident pairs; the result is divided by
    ``mu``. The pip wheel of fmm3dpy 2.1.0 runs on one thread. Ranged sums run :class:`Direct`.

    Parameters
    ----------
    eps : float, default 1e-12
        Requested relative precision, in (0, 1).

    Raises
    ------
    ImportError
        From :meth:`dense`, if fmm3dpy is not installed (``pip install cilia-flow[fmm]``).
    ValueError
        From :meth:`dense`, for a kernel other than :class:`~ciliary_carpet.stokes.kernel.Stokeslet`
        (the FMM has no image system and no blob: use :class:`Direct`).
    """

    eps: float = 1e-12

    def __post_init__(self) -> None:
        eps = _finite_positive("eps", self.eps)
        if eps >= 1.0:
            raise ValueError(f"eps must be < 1, got {eps}")
        object.__setattr__(self, "eps", eps)

    def dense(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
              mu: float) -> np.ndarray:
        if not isinstance(kernel, Stokeslet):
            raise ValueError(f"the FMM backend supports the singular free-space Stokeslet only, not "
                             f"{type(kernel).__name__}; use backend=Direct() (or Auto())")
        m = targets.shape[0]
        if m == 0 or sources.shape[0] == 0:
            return np.zeros((m, 3))
        fmm3dpy = _import_fmm3dpy()
        if fmm3dpy is None:
            raise ImportError("the FMM backend needs fmm3dpy: pip install cilia-flow[fmm]")
        res = fmm3dpy.stfmm3d(eps=self.eps, sources=np.asfortranarray(sources.T),
                              stoklet=np.asfortranarray(forces.T),
                              targets=np.asfortranarray(targets.T), ifppregtarg=1)
        ier = int(np.asarray(getattr(res, "ier", 0)))
        if ier != 0:
            raise RuntimeError(f"fmm3dpy.stfmm3d failed with ier = {ier}")
        u = np.asarray(res.pottarg, dtype=np.float64).reshape(3, m).T
        return np.ascontiguousarray(u) / mu

    def describe(self) -> str:
        return f"fmm (fmm3dpy, eps {self.eps:g})"


@functools.cache
def _gpu() -> Backend | None:
    """:class:`~ciliary_carpet.stokes.cuda.Cuda` () when a GPU can run it here, else None (asked once
    per process: every flow evaluation asks)."""
    from ciliary_carpet.stokes.cuda import Cuda, cuda_available

    return Cuda() if cuda_available() else None


@dataclass(frozen=True)
class Auto(Backend):
    """The GPU when one is usable, else :class:`Direct` or :class:`FMM`, whichever is expected
    to be faster.

    :class:`~ciliary_carpet.stokes.cuda.Cuda` (fp64) for every sum, dense and ranged, when
    :func:`ciliary_carpet.stokes.cuda.cuda_available` (numba-cuda, an NVIDIA driver and GPU). Otherwise,
    for the dense sum, :class:`Direct` when ``M * N < threshold``, or the kernel is not the
    singular free-space Stokeslet, or fmm3dpy is not installed; :class:`FMM` (precision ``eps``)
    otherwise; ranged sums run :class:`Direct`.

    Parameters
    ----------
    threshold : float, default :data:`FMM_CROSSOVER_PAIRS`
        Pair count ``M * N`` from which the FMM is used (the measured crossover); > 0.
    eps : float, default 1e-12
        Precision of the FMM when it is used.
    """

    threshold: float = FMM_CROSSOVER_PAIRS
    eps: float = 1e-12

    def __post_init__(self) -> None:
        object.__setattr__(self, "threshold", _finite_positive("threshold", self.threshold))
        FMM(self.eps)  # validates eps
        object.__setattr__(self, "eps", float(self.eps))

    def choose(self, m: int, n: int, kernel: Kernel | Wall | None = None) -> Backend:
        """The backend used for ``m`` targets, ``n`` sources and ``kernel`` (a Wall or None
        stand for the singular kernels with and without wall)."""
        gpu = _gpu()
        if gpu is not None:
            return gpu
        if not isinstance(kernel, Kernel):
            kernel = make_kernel(kernel)
        if (not isinstance(kernel, Stokeslet) or float(m) * float(n) < self.threshold
                or not _fmm_available()):
            return Direct()
        return FMM(self.eps)

    def dense(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
              mu: float) -> np.ndarray:
        b = self.choose(targets.shape[0], sources.shape[0], kernel)
        logger.debug("Auto: %s for M=%d, N=%d, %s", type(b).__name__, targets.shape[0], sources.shape[0], kernel)
        return b.dense(kernel, targets, sources, forces, mu)

    def ranged(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
               ptr: np.ndarray, ranges: np.ndarray, mu: float) -> np.ndarray:
        b = _gpu() or Direct()
        return b.ranged(kernel, targets, sources, forces, ptr, ranges, mu)

    def describe(self) -> str:
        gpu = _gpu()
        if gpu is not None:
            return f"auto: {gpu.describe()}"
        fmm = f"FMM above {self.threshold:.3g} pairs" if _fmm_available() else "no FMM (fmm3dpy not installed)"
        return f"auto: {Direct().describe()}; {fmm}"


BACKENDS = ("auto", "direct", "fmm", "cuda", "cuda-fp32", "cuda-fp32-acc64")
"""Backend names of scenes and the command line (:func:`backend_named`)."""


def backend_named(name: str) -> Backend:
    """The evaluator called ``name`` (:data:`BACKENDS`): ``"auto"`` :class:`Auto`, ``"direct"``
    :class:`Direct`, ``"fmm"`` :class:`FMM`, ``"cuda"`` :class:`~ciliary_carpet.stokes.cuda.Cuda` in fp64,
    ``"cuda-fp32"`` / ``"cuda-fp32-acc64"`` the same in fp32 / fp32 summed in fp64 (error bound:
    :mod:`ciliary_carpet.stokes.cuda`).

    Raises
    ------
    ValueError
        For an unknown name (the message lists the known ones).
    ciliary_carpet.stokes.cuda.CudaUnavailableError
        For a ``cuda`` name where no GPU can run it (the message names what is missing), before
        any work.
    """
    if name == "auto":
        return Auto()
    if name == "direct":
        return Direct()
    if name == "fmm":
        return FMM()
    if name in ("cuda", "cuda-fp32", "cuda-fp32-acc64"):
        from ciliary_carpet.stokes.cuda import Cuda

        return Cuda("fp64" if name == "cuda" else name[len("cuda-"):])
    raise ValueError(f"unknown backend {name!r} (known: {', '.join(BACKENDS)})")


# --------------------------------------------------------------------------- public functions
def _kernel(kernel: Kernel | None, wall: Wall | None) -> Kernel:
    if kernel is None:
        if wall is not None and not isinstance(wall, Wall):
            raise TypeError(f"wall must be a Wall or None, got {type(wall).__name__}")
        return make_kernel(wall)
    if not isinstance(kernel, Kernel):
        raise TypeError(f"kernel must be a Kernel, got {type(kernel).__name__}")
    if wall is not None and wall != kernel.wall:
        raise ValueError(f"wall = {wall} contradicts the kernel's wall {kernel.wall}: give the wall in the kernel")
    return kernel


def stokeslet_velocity(targets: Any, sources: Any, forces: Any, mu: float = 1.0, *,
                       wall: Wall | None = None, backend: Backend | None = None,
                       kernel: Kernel | None = None) -> np.ndarray:
    """Velocity of point forces in Stokes flow, ``u(x_i) = 1/(8 pi mu) sum_j G(x_i, xi_j) f_j``.

    ``G`` is the ``kernel`` (:mod:`ciliary_carpet.stokes.kernel`); by default the Stokeslet
    ``I/|R| + R R^T/|R|^3`` (``R = x - xi``) in free space, the Blake tensor with a no-slip
    ``wall`` (module docstring). The singular term of a target that coincides with a source is
    skipped (contributes zero).

    Parameters
    ----------
    targets : (M, 3) or (M, 2) array_like
        Evaluation points ``x_i`` ((M, 2) is padded with z = 0).
    sources : (N, 3) or (N, 2) array_like
        Force positions ``xi_j``.
    forces : (N, 3) or (N, 2) array_like
        Point forces ``f_j`` exerted on the fluid ((N, 2): f_z = 0).
    mu : float, default 1
        Dynamic viscosity, finite and > 0.
    wall : Wall, optional
        No-slip plane ``z = wall.z`` for the singular kernels (or give a ``kernel``).
    backend : Backend, optional
        Evaluation strategy; default :class:`Auto` ().
    kernel : Kernel, optional
        The Green's function; default ``make_kernel(wall)``. Sources strictly above its wall,
        targets on or above it.

    Returns
    -------
    (M, 3) float64 ndarray
        The velocities (zeros if M = 0 or N = 0).

    Raises
    ------
    ValueError
        Naming the argument: wrong ndim or width, sources and forces with different row counts,
        NaN or inf, ``mu`` not finite and > 0, a source not above / a target below the wall; or
        from the backend (the FMM with another kernel than the free Stokeslet).
    """
    k = _kernel(kernel, wall)
    t, s, f, m, _ = _validate(targets, sources, forces, mu, k.wall)
    if backend is None:
        backend = Auto()
    elif not isinstance(backend, Backend):
        raise TypeError(f"backend must be a Backend, got {type(backend).__name__}")
    if t.shape[0] == 0 or s.shape[0] == 0:
        return np.zeros((t.shape[0], 3))
    return backend.dense(k, t, s, f, m)


def stokeslet_velocity_ranges(targets: Any, sources: Any, forces: Any, ptr: Any, ranges: Any,
                              mu: float = 1.0, *, wall: Wall | None = None, backend: Backend | None = None,
                              kernel: Kernel | None = None) -> np.ndarray:
    """Velocities with a sparse, per-target list of source blocks.

    For target ``i`` the sum runs over sources ``j`` in ``ranges[k, 0] : ranges[k, 1]`` for every
    ``k`` in ``ptr[i] : ptr[i + 1]`` (a CSR list of source blocks per target)::

        u_i = 1/(8 pi mu) sum_{k = ptr[i]}^{ptr[i+1]-1} sum_{j = ranges[k,0]}^{ranges[k,1]-1}
              G(x_i, xi_j) f_j

    A block listed twice for one target is summed twice (nothing is deduplicated). Parallel over
    targets (each writes only its own row). Same ``G``, conventions and validation as
    :func:`stokeslet_velocity`.

    Parameters
    ----------
    targets : (M, 3) or (M, 2) array_like
    sources, forces : (N, 3) or (N, 2) array_like
    ptr : (M + 1,) integer array_like
        Non-decreasing, ``0 <= ptr[0]``, ``ptr[M] <= K``.
    ranges : (K, 2) integer array_like
        ``0 <= ranges[k, 0] <= ranges[k, 1] <= N``.
    mu : float, default 1
    wall : Wall, optional
    backend : Backend, optional (default :class:`Auto`: the GPU when usable, else :class:`Direct`)
    kernel : Kernel, optional

    Returns
    -------
    (M, 3) float64 ndarray

    Raises
    ------
    ValueError
        As :func:`stokeslet_velocity`, and naming ``ptr`` or ``ranges`` if they are not integer
        arrays of the right shape, ``ptr`` is not monotone or out of ``[0, K]``, or a range is
        reversed or outside ``[0, N]``.
    """
    k = _kernel(kernel, wall)
    t, s, f, m, _ = _validate(targets, sources, forces, mu, k.wall)
    M, N = t.shape[0], s.shape[0]
    p = np.asarray(ptr)
    r = np.asarray(ranges)
    if p.dtype.kind not in "iu":
        raise ValueError(f"ptr must be an integer array, got dtype {p.dtype}")
    if r.dtype.kind not in "iu":
        raise ValueError(f"ranges must be an integer array, got dtype {r.dtype}")
    if p.shape != (M + 1,):
        raise ValueError(f"ptr must have shape (M + 1,) = ({M + 1},), got {p.shape}")
    if r.ndim != 2 or r.shape[1] != 2:
        raise ValueError(f"ranges must have shape (K, 2), got {r.shape}")
    p = np.ascontiguousarray(p, dtype=np.int64)
    r = np.ascontiguousarray(r, dtype=np.int64)
    K = r.shape[0]
    if p[0] < 0 or p[-1] > K or np.any(np.diff(p) < 0):
        raise ValueError(f"ptr must be non-decreasing within [0, K = {K}]")
    if K and (np.any(r[:, 0] < 0) or np.any(r[:, 1] > N) or np.any(r[:, 0] > r[:, 1])):
        raise ValueError(f"ranges must satisfy 0 <= ranges[k, 0] <= ranges[k, 1] <= N = {N}")
    if M == 0 or N == 0 or K == 0:
        return np.zeros((M, 3))
    backend = Auto() if backend is None else backend
    return backend.ranged(k, t, s, f, p, r, m)


def _blake_numpy(R: np.ndarray, Rs: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Blake tensors (..., 3, 3) from R = x - xi, R* = x - xi*, h the source heights (...),
    written term by term as in the module docstring (independent of the numba algebra)."""
    eye = np.eye(3)
    e3 = eye[2]

    def stokeslet(X, skip_zero):
        r = np.sqrt(np.sum(X * X, axis=-1))
        with np.errstate(divide="ignore", invalid="ignore"):
            ir = np.where(r > 0, 1.0 / r, 0.0) if skip_zero else 1.0 / r
        return eye * ir[..., None, None] + X[..., :, None] * X[..., None, :] * (ir ** 3)[..., None, None]

    r = np.sqrt(np.sum(Rs * Rs, axis=-1))[..., None, None]
    Ri = Rs[..., :, None]
    Rk = Rs[..., None, :]
    R3 = Rs[..., 2][..., None, None]
    hh = h[..., None, None]
    # dPhi_i / dR*_k of Phi_i = h R*_i / r^3 - G^S_i3(R*)
    dPhi = (hh * (eye / r ** 3 - 3.0 * Ri * Rk / r ** 5)
            + e3[:, None] * Rk / r ** 3
            - (eye * R3 + Ri * e3[None, :]) / r ** 3
            + 3.0 * Ri * R3 * Rk / r ** 5)
    Mdiag = np.array([1.0, 1.0, -1.0])
    return stokeslet(R, True) - stokeslet(Rs, False) + 2.0 * hh * dPhi * Mdiag  # (.., i, j=k)


def stokeslet_velocity_numpy(targets: Any, sources: Any, forces: Any, mu: float = 1.0,
                             wall: Wall | None = None, *, chunk_pairs: int = 65536,
                             kernel: Kernel | None = None) -> np.ndarray:
    """Plain-numpy reference of :func:`stokeslet_velocity` (slow; for tests and benchmarks).

    Vectorised over all pairs of a chunk of targets (about ``chunk_pairs`` pairs at a time, which
    bounds the memory: a few hundred bytes per pair of the chunk); free space in the vector form
    ``(f (r^2 + 2 eps^2) + R (R.f)) / (r^2 + eps^2)^{3/2}``, the walls as full 3x3 tensors written
    term by term (Blake; :func:`ciliary_carpet.stokes.kernel.regularised_blake_tensor`), independent of
    the algebra of the numba kernels. Same arguments, conventions and validation as
    :func:`stokeslet_velocity`; always exact (no FMM).
    """
    k = _kernel(kernel, wall)
    t, s, f, m, w = _validate(targets, sources, forces, mu, k.wall)
    e2 = k.eps ** 2
    M, N = t.shape[0], s.shape[0]
    out = np.zeros((M, 3))
    if M == 0 or N == 0:
        return out
    step = max(1, int(chunk_pairs) // N)
    if w is None:
        sx, sy, sz = (np.ascontiguousarray(c) for c in s.T)
        fx, fy, fz = (np.ascontiguousarray(c) for c in f.T)
    else:
        sh = s.copy()
        sh[:, 2] -= w.z
        simg = sh * np.array([1.0, 1.0, -1.0])
    for lo in range(0, M, step):
        x = t[lo:lo + step]
        if w is None:
            dx = x[:, 0:1] - sx
            dy = x[:, 1:2] - sy
            dz = x[:, 2:3] - sz
            r2 = dx * dx + dy * dy + dz * dz
            q2 = r2 + e2
            with np.errstate(divide="ignore", invalid="ignore"):
                ir3 = 1.0 / (q2 * np.sqrt(q2))
                iso = (r2 + 2 * e2) * ir3
            ir3[q2 == 0.0] = 0.0  # coincident points: skipped
            iso[q2 == 0.0] = 0.0
            rf = (dx * fx + dy * fy + dz * fz) * ir3
            u = np.column_stack([iso @ fx + np.einsum("ij,ij->i", dx, rf),
                                 iso @ fy + np.einsum("ij,ij->i", dy, rf),
                                 iso @ fz + np.einsum("ij,ij->i", dz, rf)])
        else:
            xs = x.copy()
            xs[:, 2] -= w.z
            if k.regularised:
                G = regularised_blake_tensor(xs, sh, k.eps)
            else:
                R = xs[:, None, :] - sh[None]
                Rs = xs[:, None, :] - simg[None]
                G = _blake_numpy(R, Rs, np.broadcast_to(sh[:, 2], R.shape[:2]))
            u = np.einsum("mnij,nj->mi", G, f)
        out[lo:lo + step] = u / (8.0 * math.pi * m)
    return out


def __getattr__(name: str):
    """The GPU evaluator, re-exported beside the others (``from ciliary_carpet.stokes.stokeslet import
    Cuda``); imported on first use, as :mod:`ciliary_carpet.stokes.cuda` builds on this module."""
    if name in ("Cuda", "CudaUnavailableError"):
        from . import cuda

        return getattr(cuda, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
