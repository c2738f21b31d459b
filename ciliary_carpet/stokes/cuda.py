"""The velocity sums on an NVIDIA GPU: the :class:`Cuda` backend (numba-cuda kernels).

:class:`Cuda` is a :class:`~ciliary_carpet.stokes.backend.Backend`: it evaluates the dense sum and the
ranged (near-field) sum (:mod:`ciliary_carpet.stokes.dispatch`),
``u(x_i) = 1/(8 pi mu) sum_j G(x_i, xi_j) f_j``, for every
:class:`~ciliary_carpet.stokes.kernel.Kernel` (free space, Blake's wall, regularised, regularised with
wall, and any other of :data:`~ciliary_carpet.stokes.kernel.KERNELS`), with the same conventions
(coincident singular pairs skipped, heights above the wall).

The physics is not written twice. The per-pair formulas are the ``pair`` functions of the
Green's functions (:data:`ciliary_carpet.stokes.kernel.PAIRS`), which the CPU loops inline; here
their Python source (``.py_func``) is compiled a second time, by
``numba.cuda.jit(device=True)``, into the device functions of the kernels below. For fp32 the
copy is compiled with the module constants (:data:`~ciliary_carpet.stokes.kernel.PAIR_CONSTANTS`)
retyped to float32, so that no literal promotes the arithmetic to fp64. The CPU loops themselves
(:mod:`ciliary_carpet.stokes.direct`) are not shared: they slice host arrays and rely on numba's
CPU vectorisation; a GPU thread instead reads its sources from a shared-memory tile.

Kernels
-------
* dense: each thread owns ``targets_per_thread`` targets (strided by the block size, so that
  their loads coalesce) and keeps their positions and sums in registers; the block stages the
  sources and forces through shared memory in tiles of ``threads`` sources (one load per thread),
  and every thread sums each tile into its targets (register tiling: one shared-memory read of a
  source serves all of a thread's targets).
* ranged: one warp per target; its 32 lanes stride through the concatenation of the target's
  source ranges (each lane carries on, in the next range, where the lane before it stopped, so
  that short ranges keep every lane busy; reads of consecutive sources coalesce) and their
  partial sums are reduced in shared memory.

Precision (:data:`PRECISIONS`)
------------------------------
``"fp64"`` (default) evaluates and sums in fp64: the same result as
:class:`~ciliary_carpet.stokes.direct.Direct` up to the order of the sums (tested to 1e-12 relative
to ``max |u|``). ``"fp32"`` evaluates and sums in fp32; ``"fp32-acc64"`` evaluates each pair in
fp32 and sums in fp64. The inputs are shifted and rounded, and the error bounded, as the CPU's fp32
sums are (:mod:`~ciliary_carpet.stokes.precision`: ``(C + a n_i) u B_i`` with ``a = 2`` for
``"fp32"``, ``n_i`` the terms summed for target ``i``, and ``a = 2^-28`` for ``"fp32-acc64"``);
:func:`~ciliary_carpet.stokes.precision.fp32_error_bound` evaluates it (also importable from here).
tests/test_cuda.py checks it on every kernel. In practice the error is far below the bound (the
summation term is a worst case): under the simulator, 70 targets and 75 sources in a
2 x 2 x 1.7 box give ``max |error| / max |u|`` of 1e-7 to 8e-7 and ``|error| / (u B_i)`` below
0.6; benchmarks/bench_gpu.py measures it at large N on a GPU.

On a GPU the reciprocal square root of the pair formulas is libdevice's (``rsqrt``: 1 ulp in
fp64; ``rsqrtf``, with fast math in fp32: ``rsqrt.approx``, relative error below 2^-22.9), not
the CPU's correctly rounded ``1 / sqrt``: fp64 results then differ from
:class:`~ciliary_carpet.stokes.direct.Direct` by a few ulps per pair, far inside 1e-12 (the simulator,
which has no libdevice, uses ``1 / sqrt``).

The kernels run on a GPU when numba's CUDA target finds one, and under numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1``, set before numba is imported), which is how CI tests them. Without
a GPU, constructing :class:`Cuda` raises :class:`CudaUnavailableError` naming what is missing:
numba-cuda (``pip install cilia-flow[gpu]``), the NVIDIA driver, a GPU, or the CUDA compiler
library NVVM. The kernels are compiled on first use in each process (a second or so per kernel,
precision and block shape) and kept for the process: numba caches only functions defined at
module level, and these are specialised per kernel, precision and tile shape by closures.
"""
from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numpy as np

from ciliary_carpet.stokes.backend import Backend
from ciliary_carpet.stokes.kernel import INV_8PI, PAIRS, Kernel, rsqrt
from ciliary_carpet.stokes.precision import FP32_PAIR_CONSTANT, fp32_error_bound
from ciliary_carpet.stokes.precision import origin as _origin
from ciliary_carpet.stokes.precision import retyped as _retyped
from ciliary_carpet.stokes.precision import soa as _soa

__all__ = ["Cuda", "CudaUnavailableError", "PRECISIONS", "FP32_PAIR_CONSTANT", "cuda_available",
           "cuda_status", "fp32_error_bound"]

logger = logging.getLogger(__name__)

PRECISIONS = ("fp64", "fp32", "fp32-acc64")
"""Arithmetic of :class:`Cuda`: fp64; fp32; fp32 pairs summed in fp64 (module docstring)."""

_WARP = 32

cuda = None
"""The ``numba.cuda`` module once :func:`_probe` has found it usable. A module global on purpose:
the kernels must reach it as a global name, which numba's simulator swaps for its own API."""


class CudaUnavailableError(RuntimeError):
    """The CUDA backend cannot run here; the message names what is missing."""


# ------------------------------------------------------------------------------- availability
@functools.cache
def _probe() -> tuple[object | None, str]:
    """(the ``numba.cuda`` module, "") when a GPU can run the kernels, else (None, why not)."""
    global cuda
    try:
        from numba import cuda as module
    except ImportError as exc:  # numba without its CUDA target
        return None, (f"numba's CUDA target cannot be imported ({exc}): install numba-cuda with "
                      f"pip install 'cilia-flow[gpu]'")
    from numba.core import config

    if config.ENABLE_CUDASIM:
        cuda = module
        return cuda, ""
    if not module.is_available():
        why = ""
        try:
            from numba.cuda.cudadrv.driver import driver

            why = " ".join(str(getattr(driver, "initialization_error", "") or "").split())
        except Exception:  # noqa: BLE001 -- only for the message
            pass
        if "cannot be found" in why or "driver library" in why:
            what = "no NVIDIA driver (libcuda) was found"
        elif why:
            what = f"the CUDA driver did not start: {why}"
        else:
            what = "the CUDA driver sees no GPU"
        return None, (f"{what}. The 'cuda' backend needs an NVIDIA GPU with its driver, and numba-cuda "
                      f"(pip install 'cilia-flow[gpu]'); use backend 'auto' or 'direct' on this machine")
    try:
        from numba.cuda.cudadrv import nvvm

        if not nvvm.is_available():
            return None, ("the CUDA compiler library NVVM was not found: pip install 'cilia-flow[gpu]' "
                          "installs it (numba-cuda[cu12]), or set CUDA_HOME to a CUDA toolkit")
    except ImportError:
        pass
    cuda = module
    return cuda, ""


def cuda_status() -> str:
    """"" when :class:`Cuda` can run here, else the reason it cannot (the error's message)."""
    return _probe()[1]


def cuda_available() -> bool:
    """Whether :class:`Cuda` can run here (a GPU, its driver and numba-cuda; or the simulator)."""
    return _probe()[0] is not None


def _require():
    module, why = _probe()
    if module is None:
        raise CudaUnavailableError(f"backend 'cuda' cannot run here: {why}")
    return module


# ------------------------------------------------------------------------------- kernels
def _device_pair(code: int, precision: str):
    """The pair formula ``code`` (:data:`~ciliary_carpet.stokes.kernel.PAIRS`, its Python source)
    as a CUDA device function: constants in the precision's type, and ``rsqrt`` the GPU's reciprocal
    square root (libdevice ``rsqrt`` / ``rsqrtf``: within 1 / 2 ulp), or, under the simulator, which has
    no libdevice, the CPU's ``1 / sqrt``."""
    from numba.core import config

    fp32 = precision != "fp64"
    if config.ENABLE_CUDASIM:
        device_rsqrt = _retyped(rsqrt.py_func, fp32)
    else:
        from numba.cuda import libdevice

        device_rsqrt = libdevice.rsqrtf if fp32 else libdevice.rsqrt
    return cuda.jit(device=True, fastmath=fp32)(_retyped(PAIRS[code].py_func, fp32, rsqrt=device_rsqrt))


def _types(precision: str):
    import numba

    ft = numba.float32 if precision != "fp64" else numba.float64
    at = numba.float32 if precision == "fp32" else numba.float64
    return ft, at, (np.float32 if precision != "fp64" else np.float64), (np.float32 if precision == "fp32"
                                                                        else np.float64)


@functools.cache
def _dense_kernel(code: int, precision: str, threads: int, per_thread: int):
    """The dense kernel: out[:, i] = scale * sum_j pair(T[:, i], S[:, j], F[:, j]) (see the module
    docstring), T (3, M), S, F (3, N), out (3, M) float64; launch with blocks of ``threads``."""
    _require()
    ft, at, _, acc_np = _types(precision)
    fast = precision != "fp64"
    pair = _device_pair(code, precision)
    TPB, P = threads, per_thread
    zero = acc_np(0.0)

    @cuda.jit(fastmath=fast)
    def dense(T, S, F, e2, scale, out):  # pragma: no cover - runs on the device
        tid = cuda.threadIdx.x
        base = cuda.blockIdx.x * (TPB * P)
        m = T.shape[1]
        n = S.shape[1]
        tile = cuda.shared.array((6, TPB), ft)
        x = cuda.local.array(P, ft)
        y = cuda.local.array(P, ft)
        z = cuda.local.array(P, ft)
        ux = cuda.local.array(P, at)
        uy = cuda.local.array(P, at)
        uz = cuda.local.array(P, at)
        for p in range(P):
            i = min(base + p * TPB + tid, m - 1)  # surplus threads repeat the last target, unwritten
            x[p] = T[0, i]
            y[p] = T[1, i]
            z[p] = T[2, i]
            ux[p] = zero
            uy[p] = zero
            uz[p] = zero
        for start in range(0, n, TPB):
            j = start + tid
            if j < n:
                tile[0, tid] = S[0, j]
                tile[1, tid] = S[1, j]
                tile[2, tid] = S[2, j]
                tile[3, tid] = F[0, j]
                tile[4, tid] = F[1, j]
                tile[5, tid] = F[2, j]
            cuda.syncthreads()
            for k in range(min(TPB, n - start)):
                sx = tile[0, k]
                sy = tile[1, k]
                sz = tile[2, k]
                fx = tile[3, k]
                fy = tile[4, k]
                fz = tile[5, k]
                for p in range(P):
                    a, b, c = pair(x[p], y[p], z[p], sx, sy, sz, fx, fy, fz, e2)
                    ux[p] += a
                    uy[p] += b
                    uz[p] += c
            cuda.syncthreads()
        for p in range(P):
            i = base + p * TPB + tid
            if i < m:
                out[0, i] = scale * ux[p]
                out[1, i] = scale * uy[p]
                out[2, i] = scale * uz[p]

    return dense


@functools.cache
def _ranged_kernel(code: int, precision: str, threads: int):
    """The ranged kernel: one warp per target, lanes striding through its source ranges
    ``ranges[ptr[i]:ptr[i+1]]``; partial sums reduced in shared memory. Launch with blocks of
    ``threads`` (a multiple of 32): ``threads / 32`` targets per block."""
    _require()
    ft, at, _, acc_np = _types(precision)
    fast = precision != "fp64"
    pair = _device_pair(code, precision)
    TPB, W = threads, threads // _WARP
    zero = acc_np(0.0)

    @cuda.jit(fastmath=fast)
    def ranged(T, S, F, ptr, ranges, e2, scale, out):  # pragma: no cover - runs on the device
        tid = cuda.threadIdx.x
        lane = tid % _WARP
        i = cuda.blockIdx.x * W + tid // _WARP
        m = T.shape[1]
        ux = zero
        uy = zero
        uz = zero
        if i < m:
            x = T[0, i]
            y = T[1, i]
            z = T[2, i]
            off = 0  # pairs of the earlier ranges, mod 32: the lanes carry on where they stopped
            for k in range(ptr[i], ptr[i + 1]):
                lo = ranges[k, 0]
                hi = ranges[k, 1]
                for j in range(lo + (lane - off + _WARP) % _WARP, hi, _WARP):
                    a, b, c = pair(x, y, z, S[0, j], S[1, j], S[2, j], F[0, j], F[1, j], F[2, j], e2)
                    ux += a
                    uy += b
                    uz += c
                off = (off + hi - lo) % _WARP
        red = cuda.shared.array((3, TPB), at)
        red[0, tid] = ux
        red[1, tid] = uy
        red[2, tid] = uz
        cuda.syncthreads()
        s = _WARP // 2
        while s > 0:
            if lane < s:
                red[0, tid] += red[0, tid + s]
                red[1, tid] += red[1, tid + s]
                red[2, tid] += red[2, tid + s]
            cuda.syncthreads()
            s //= 2
        if lane == 0 and i < m:
            out[0, i] = scale * red[0, tid]
            out[1, i] = scale * red[1, tid]
            out[2, i] = scale * red[2, tid]

    return ranged


# ------------------------------------------------------------------------------- the backend
@dataclass(frozen=True)
class Cuda(Backend):
    """Dense and ranged velocity sums on an NVIDIA GPU (numba-cuda kernels), every kernel.

    See the module docstring for the kernels, the precision and its error bound. Each call copies
    targets, sources and forces to the GPU and the velocities back.

    Parameters
    ----------
    precision : "fp64" | "fp32" | "fp32-acc64", default "fp64"
        Arithmetic (:data:`PRECISIONS`): fp64 agrees with :class:`~ciliary_carpet.stokes.direct.Direct`
        to rounding; the fp32 variants within :func:`fp32_error_bound`.
    threads : int, default 128
        Threads per block (a multiple of 32, at most 1024): the source tile of the dense kernel,
        and ``threads / 32`` targets per block of the ranged kernel.
    targets_per_thread : int, default 2
        Targets each thread of the dense kernel sums into (1 to 8). The defaults are not tuned on
        hardware: ``benchmarks/bench_gpu.py --tune`` measures them.

    Raises
    ------
    ValueError
        For a precision, block size or targets per thread out of range.
    CudaUnavailableError
        When no GPU can run the kernels here (the message names what is missing: numba-cuda, the
        NVIDIA driver, a GPU, NVVM), at construction, before any work.
    """

    precision: str = "fp64"
    threads: int = 128
    targets_per_thread: int = 2
    ranged_sums = True

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        t = self.threads
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or not (32 <= t <= 1024 and t % _WARP == 0):
            raise ValueError(f"threads must be a multiple of 32 in [32, 1024], got {t!r}")
        p = self.targets_per_thread
        if isinstance(p, bool) or not isinstance(p, (int, np.integer)) or not 1 <= p <= 8:
            raise ValueError(f"targets_per_thread must be an integer in [1, 8], got {p!r}")
        object.__setattr__(self, "threads", int(t))
        object.__setattr__(self, "targets_per_thread", int(p))
        _require()

    def describe(self) -> str:
        try:
            name = cuda.get_current_device().name
            name = name.decode() if isinstance(name, bytes) else str(name)
        except Exception:  # noqa: BLE001 -- only for the label
            name = "GPU"
        return f"cuda ({self.precision}, {name})"

    @property
    def _dtype(self):
        return np.float64 if self.precision == "fp64" else np.float32

    def dense(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
              mu: float) -> np.ndarray:
        m, n = targets.shape[0], sources.shape[0]
        if m == 0 or n == 0:
            return np.zeros((m, 3))
        _require()
        o = _origin(kernel, targets, sources)
        dt = self._dtype
        k = _dense_kernel(kernel.code, self.precision, self.threads, self.targets_per_thread)
        out = cuda.device_array((3, m), dtype=np.float64)
        blocks = -(-m // (self.threads * self.targets_per_thread))
        k[blocks, self.threads](cuda.to_device(_soa(targets, dt, o)), cuda.to_device(_soa(sources, dt, o)),
                                cuda.to_device(_soa(forces, dt)), dt(kernel.eps ** 2), INV_8PI / mu, out)
        return np.ascontiguousarray(out.copy_to_host().T)

    def ranged(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
               ptr: np.ndarray, ranges: np.ndarray, mu: float) -> np.ndarray:
        m = targets.shape[0]
        if m == 0 or sources.shape[0] == 0 or ranges.shape[0] == 0:
            return np.zeros((m, 3))
        _require()
        o = _origin(kernel, targets, sources)
        dt = self._dtype
        k = _ranged_kernel(kernel.code, self.precision, self.threads)
        out = cuda.device_array((3, m), dtype=np.float64)
        blocks = -(-m // (self.threads // _WARP))
        k[blocks, self.threads](cuda.to_device(_soa(targets, dt, o)), cuda.to_device(_soa(sources, dt, o)),
                                cuda.to_device(_soa(forces, dt)), cuda.to_device(np.ascontiguousarray(ptr)),
                                cuda.to_device(np.ascontiguousarray(ranges)), dt(kernel.eps ** 2), INV_8PI / mu,
                                out)
        return np.ascontiguousarray(out.copy_to_host().T)
