"""The Stokes fast multipole method of ``fmm3dpy``: the :class:`FMM` backend (dense sums of the
singular free-space Stokeslet; an optional dependency, ``pip install cilia-flow[fmm]``).

Throughput and the crossover with :class:`~ciliary_carpet.stokes.direct.Direct` are measured by
``benchmarks/bench_flow.py`` (``benchmarks/results/bench_kernel.md``):
:data:`FMM_CROSSOVER_PAIRS` is where :class:`~ciliary_carpet.stokes.dispatch.Auto` switches.
"""
from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numpy as np

from single_cilium.checks import positive

from ciliary_carpet.stokes.backend import Backend
from ciliary_carpet.stokes.kernel import Kernel, Stokeslet

__all__ = ["FMM", "FMM_CROSSOVER_PAIRS", "fmm_available"]

logger = logging.getLogger(__name__)

#: Default :class:`~ciliary_carpet.stokes.dispatch.Auto` threshold on ``M * N``: below it the
#: direct sum is used. The measured crossover (benchmarks/results/bench_kernel.md; 2 cores, AMD
#: EPYC Zen 3) of the numba direct sum (1.5e9 pairs/s) and the serial fmm3dpy 2.1.0 wheel at
#: eps = 1e-12 (64 s for M = N = 1e5) on random points in the unit cube: M = N ~ 1e6,
#: extrapolated from M = N = 1e5 (at eps = 1e-6 it would be M = N ~ 5e5). In practice Auto
#: therefore means Direct unless a scene is huge.
FMM_CROSSOVER_PAIRS: float = 1.0e12


@functools.cache
def _import_fmm3dpy():
    try:
        import fmm3dpy
    except ImportError:
        return None
    return fmm3dpy


@functools.cache
def _told(kernel: str) -> None:
    logger.warning("backend fmm: the FMM sums only the singular free-space Stokeslet; the dense sums of %s run on "
                   "direct (CPU)", kernel)


def fmm_available() -> bool:
    """Whether fmm3dpy is installed (asked once per process)."""
    return _import_fmm3dpy() is not None


@dataclass(frozen=True)
class FMM(Backend):
    """Stokes fast multipole method, ``fmm3dpy.stfmm3d``: the singular free-space Stokeslet only.

    ``stfmm3d`` computes ``sum_j (1/(8 pi)) G^S(x - xi_j) f_j`` (its Stokeslet carries the
    ``1/(8 pi)``; checked numerically), and omits coincident pairs; the result is divided by
    ``mu``. The pip wheel of fmm3dpy 2.1.0 runs on one thread. No ranged sums
    (``ranged_sums`` False): :func:`~ciliary_carpet.stokes.dispatch.stokeslet_velocity_ranges`
    (and a carpet's sums, through :func:`~ciliary_carpet.stokes.dispatch.ranged_backend`)
    runs them on :class:`~ciliary_carpet.stokes.direct.Direct`, as :meth:`describe` says.

    Parameters
    ----------
    eps : float, default 1e-12
        Requested relative precision, in (0, 1).
    direct_otherwise : bool, default False
        What a dense sum of another kernel (a wall, a blob) does: False, a ValueError; True, it
        runs on :class:`~ciliary_carpet.stokes.direct.Direct` (logged once per process and
        kernel type). The backend a scene's or the command line's ``backend = "fmm"`` names
        has it True (a carpet's Green's function is regularised: the FMM then runs none of its
        sums, and :meth:`describe`, which the render's summary quotes, says which backend
        runs which sums).

    Raises
    ------
    ImportError
        From :meth:`dense`, if fmm3dpy is not installed (``pip install cilia-flow[fmm]``).
    ValueError
        From :meth:`dense`, for a kernel other than :class:`~ciliary_carpet.stokes.kernel.Stokeslet`
        (the FMM has no image system and no blob: use :class:`~ciliary_carpet.stokes.direct.Direct`).
    """

    eps: float = 1e-12
    direct_otherwise: bool = False

    def __post_init__(self) -> None:
        eps = positive("eps", self.eps)
        if eps >= 1.0:
            raise ValueError(f"eps must be < 1, got {eps}")
        object.__setattr__(self, "eps", eps)

    def supports(self, kernel: Kernel) -> bool:
        return isinstance(kernel, Stokeslet)

    def dense(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
              mu: float) -> np.ndarray:
        if not self.supports(kernel) and self.direct_otherwise:
            _told(type(kernel).__name__)
            from ciliary_carpet.stokes.direct import Direct

            return Direct().dense(kernel, targets, sources, forces, mu)
        if not self.supports(kernel):
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
        other = ("; dense sums of kernels other than the singular free-space Stokeslet (a wall, a blob): direct, CPU"
                 if self.direct_otherwise else "")
        return f"fmm (fmm3dpy, eps {self.eps:g}{other}; ranged sums: direct, CPU)"
