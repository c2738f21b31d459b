"""Velocity of point forces in Stokes flow: the front doors, and the choice of backend.

The velocity at ``x`` of point forces ``f_j`` at ``xi_j`` in a fluid of viscosity ``mu`` is

.. math::

    u(x) = \\frac{1}{8 \\pi \\mu} \\sum_j G(x, \\xi_j) f_j,

with ``G`` a Green's function (:mod:`ciliary_carpet.stokes.kernel`: the Stokeslet in free space,
Blake's tensor above a no-slip :class:`~ciliary_carpet.stokes.kernel.Wall`, their regularised
versions). :func:`stokeslet_velocity` sums every source for every target;
:func:`stokeslet_velocity_ranges` sums, per target, over a sparse list of source index ranges
(near-field corrections). Both validate their inputs and hand them to a backend
(:class:`~ciliary_carpet.stokes.backend.Backend`, whose docstring is the contract a new one
meets).

Conventions shared by every function here:

* points and forces are ``(M, 3)`` / ``(N, 3)`` float arrays; ``(M, 2)`` / ``(N, 2)`` arrays are
  accepted and padded with ``z = 0`` (forces too: a planar force has no z component); the result
  is always ``(M, 3)`` float64;
* a target that coincides with a source (``R = 0``) gets no contribution from that source's
  singular Stokeslet (the term is skipped, i.e. counts as zero); with a wall, the image terms of
  that source are regular and are kept;
* sources and targets lie on or above the wall (a source on it makes no flow);
* ``M = 0`` or ``N = 0`` give zeros of shape ``(M, 3)``.

The backends, by the names a scene or the command line gives (:data:`BACKENDS`,
:func:`backend_named`): :class:`Auto` (``"auto"``, the default), which picks the GPU when one is
usable, else :class:`~ciliary_carpet.stokes.direct.Direct` or
:class:`~ciliary_carpet.stokes.fmm.FMM`; ``"direct"``, the O(MN) sums compiled with numba;
``"fmm"``, the fast multipole method of ``fmm3dpy`` (the singular free-space Stokeslet only:
the dense sums of other kernels run on :class:`~ciliary_carpet.stokes.direct.Direct`; optional
dependency ``pip install cilia-flow[fmm]``; no ranged sums: :func:`ranged_backend` runs them on
:class:`~ciliary_carpet.stokes.direct.Direct`; both said in the log and in ``describe()``); ``"cuda"``,
``"cuda-fp32"``, ``"cuda-fp32-acc64"``, :class:`~ciliary_carpet.stokes.cuda.Cuda`, both sums on
an NVIDIA GPU (optional dependency ``pip install cilia-flow[gpu]``). A new backend is one module
(a :class:`~ciliary_carpet.stokes.backend.Backend`) plus its entry in ``_NAMED`` here.
"""
from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from single_cilium.checks import positive

from ciliary_carpet.stokes.backend import Backend, kernel_of, validated, validated_ranges
from ciliary_carpet.stokes.cuda import Cuda, cuda_available
from ciliary_carpet.stokes.direct import Direct
from ciliary_carpet.stokes.fmm import FMM, FMM_CROSSOVER_PAIRS, fmm_available
from ciliary_carpet.stokes.kernel import Kernel, Wall, make_kernel

__all__ = ["Auto", "BACKENDS", "backend_named", "in_fp32", "ranged_backend", "stokeslet_velocity",
           "stokeslet_velocity_ranges"]

logger = logging.getLogger(__name__)


@functools.cache
def _gpu() -> Backend | None:
    """:class:`~ciliary_carpet.stokes.cuda.Cuda` () when a GPU can run it here, else None (asked
    once per process: every flow evaluation asks)."""
    return Cuda() if cuda_available() else None


@dataclass(frozen=True)
class Auto(Backend):
    """The GPU when one is usable, else :class:`~ciliary_carpet.stokes.direct.Direct` or
    :class:`~ciliary_carpet.stokes.fmm.FMM`, whichever is expected to be faster.

    :class:`~ciliary_carpet.stokes.cuda.Cuda` (fp64) for every sum, dense and ranged, when
    :func:`ciliary_carpet.stokes.cuda.cuda_available` (numba-cuda, an NVIDIA driver and GPU).
    Otherwise, for the dense sum, :class:`~ciliary_carpet.stokes.fmm.FMM` (precision ``eps``)
    when ``M * N >= threshold``, the FMM supports the kernel (the singular free-space Stokeslet)
    and fmm3dpy is installed, else :class:`~ciliary_carpet.stokes.direct.Direct`; ranged sums
    run :class:`~ciliary_carpet.stokes.direct.Direct`. :meth:`describe` names the choice.

    Parameters
    ----------
    threshold : float, default :data:`~ciliary_carpet.stokes.fmm.FMM_CROSSOVER_PAIRS`
        Pair count ``M * N`` from which the FMM is used (the measured crossover); > 0.
    eps : float, default 1e-12
        Precision of the FMM when it is used.
    """

    threshold: float = FMM_CROSSOVER_PAIRS
    eps: float = 1e-12
    ranged_sums = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "threshold", positive("threshold", self.threshold))
        FMM(self.eps)  # validates eps
        object.__setattr__(self, "eps", float(self.eps))

    def choose(self, m: int, n: int, kernel: Kernel | Wall | None = None) -> Backend:
        """The backend of the dense sum of ``m`` targets, ``n`` sources and ``kernel`` (a Wall or
        None stand for the singular kernels with and without wall)."""
        gpu = _gpu()
        if gpu is not None:
            return gpu
        if not isinstance(kernel, Kernel):
            kernel = make_kernel(kernel)
        fmm = FMM(self.eps)
        if float(m) * float(n) >= self.threshold and fmm.supports(kernel) and fmm_available():
            return fmm
        return Direct()

    def dense(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
              mu: float) -> np.ndarray:
        b = self.choose(targets.shape[0], sources.shape[0], kernel)
        logger.debug("Auto: %s for M=%d, N=%d, %s", type(b).__name__, targets.shape[0], sources.shape[0], kernel)
        return b.dense(kernel, targets, sources, forces, mu)

    def ranged(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
               ptr: np.ndarray, ranges: np.ndarray, mu: float) -> np.ndarray:
        return (_gpu() or Direct()).ranged(kernel, targets, sources, forces, ptr, ranges, mu)

    def describe(self) -> str:
        gpu = _gpu()
        if gpu is not None:
            return f"auto: {gpu.describe()}"
        fmm = f"FMM above {self.threshold:.3g} pairs" if fmm_available() else "no FMM (fmm3dpy not installed)"
        return f"auto: {Direct().describe()}; {fmm}"


_NAMED: dict[str, Callable[[], Backend]] = {
    "auto": Auto,
    "direct": Direct,
    "fmm": functools.partial(FMM, direct_otherwise=True),
    "cuda": functools.partial(Cuda, "fp64"),
    "cuda-fp32": functools.partial(Cuda, "fp32"),
    "cuda-fp32-acc64": functools.partial(Cuda, "fp32-acc64"),
}
"""The registry of backends: how each name of :data:`BACKENDS` is built."""

BACKENDS: tuple[str, ...] = tuple(_NAMED)
"""Backend names of scenes and the command line (:func:`backend_named`)."""


def backend_named(name: str) -> Backend:
    """The backend called ``name`` (:data:`BACKENDS`): ``"auto"`` :class:`Auto`, ``"direct"``
    :class:`~ciliary_carpet.stokes.direct.Direct`, ``"fmm"`` :class:`~ciliary_carpet.stokes.fmm.FMM` (``direct_otherwise=True``),
    ``"cuda"`` :class:`~ciliary_carpet.stokes.cuda.Cuda` in fp64, ``"cuda-fp32"`` /
    ``"cuda-fp32-acc64"`` the same in fp32 / fp32 summed in fp64 (error bound:
    :mod:`ciliary_carpet.stokes.cuda`).

    Raises
    ------
    ValueError
        For an unknown name (the message lists the known ones).
    ciliary_carpet.stokes.cuda.CudaUnavailableError
        For a ``cuda`` name where no GPU can run it (the message names what is missing), before
        any work.
    """
    try:
        make = _NAMED[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown backend {name!r} (known: {', '.join(BACKENDS)})") from None
    return make()


@functools.cache
def _told(asked: str, ran: str) -> None:
    logger.info("%s does no ranged sums: they run on %s", asked, ran)


def ranged_backend(backend: Backend) -> Backend:
    """The backend that runs ``backend``'s ranged sums: itself when it does them
    (:attr:`~ciliary_carpet.stokes.backend.Backend.ranged_sums`), else
    :class:`~ciliary_carpet.stokes.direct.Direct` (logged, once per process and backend)."""
    if backend.ranged_sums:
        return backend
    ran = Direct()
    _told(backend.describe(), ran.describe())
    return ran


def in_fp32(backend: Backend) -> Backend:
    """The backend of ``backend``'s ranged sums where they may run in fp32 (the far cilia's
    carriers of path lines, whose error budget is far above fp32's: ``ResolvedFlow(precision=
    "fp32")``, :mod:`ciliary_carpet.transport.flow`): :class:`~ciliary_carpet.stokes.direct.Direct`
    ``("fp32")`` where they would run on the CPU's ``Direct()`` (:class:`Auto` without a GPU, or
    ``Direct()`` itself), else ``backend`` unchanged (a GPU keeps its own precision). Asked at
    every evaluation of a path line's flow: kept per (hashable) backend."""
    try:
        return _in_fp32(backend)
    except TypeError:  # an unhashable backend of a user's
        return _in_fp32.__wrapped__(backend)


@functools.lru_cache(maxsize=16)
def _in_fp32(backend: Backend) -> Backend:
    run = ranged_backend(backend)
    if isinstance(run, Auto):
        run = _gpu() or Direct()
    return Direct("fp32") if run == Direct() else backend


def _backend(backend: Backend | None) -> Backend:
    if backend is None:
        return Auto()
    if not isinstance(backend, Backend):
        raise TypeError(f"backend must be a Backend, got {type(backend).__name__}")
    return backend


def stokeslet_velocity(targets: Any, sources: Any, forces: Any, mu: float = 1.0, *,
                       wall: Wall | None = None, backend: Backend | None = None,
                       kernel: Kernel | None = None) -> np.ndarray:
    """Velocity of point forces in Stokes flow, ``u(x_i) = 1/(8 pi mu) sum_j G(x_i, xi_j) f_j``.

    ``G`` is the ``kernel`` (:mod:`ciliary_carpet.stokes.kernel`); by default the Stokeslet
    ``I/|R| + R R^T/|R|^3`` (``R = x - xi``) in free space, the Blake tensor with a no-slip
    ``wall``. The singular term of a target that coincides with a source is skipped (contributes
    zero).

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
        The Green's function; default ``make_kernel(wall)``. Sources and targets on or above
        its wall.

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
    k = kernel_of(kernel, wall)
    t, s, f, m = validated(k, targets, sources, forces, mu)
    backend = _backend(backend)
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
    backend : Backend, optional
        Default :class:`Auto` (the GPU when usable, else
        :class:`~ciliary_carpet.stokes.direct.Direct`); one without ranged sums has them run by
        :func:`ranged_backend`'s choice.
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
    k = kernel_of(kernel, wall)
    t, s, f, m = validated(k, targets, sources, forces, mu)
    M, N = t.shape[0], s.shape[0]
    p, r = validated_ranges(ptr, ranges, M, N)
    backend = _backend(backend)
    if M == 0 or N == 0 or r.shape[0] == 0:
        return np.zeros((M, 3))
    return ranged_backend(backend).ranged(k, t, s, f, p, r, m)
