"""The backend of velocity sums: the contract every backend meets, and the inputs it may assume.

A backend (:class:`Backend`) says *how* the velocity of point forces in Stokes flow,

.. math::

    u(x_i) = \\frac{1}{8 \\pi \\mu} \\sum_j G(x_i, \\xi_j) f_j,

is summed for a Green's function ``G`` (:class:`~ciliary_carpet.stokes.kernel.Kernel`, which says
*what* is summed). The backends are :class:`~ciliary_carpet.stokes.direct.Direct`,
:class:`~ciliary_carpet.stokes.fmm.FMM`, :class:`~ciliary_carpet.stokes.cuda.Cuda` and
:class:`~ciliary_carpet.stokes.dispatch.Auto`; :mod:`ciliary_carpet.stokes.dispatch` registers
them by name and holds the front doors that validate the inputs (:func:`validated`,
:func:`validated_ranges`) and call them.

The contract (like ``scipy.integrate.OdeSolver``)
-------------------------------------------------
A backend is a frozen dataclass subclass of :class:`Backend` (its fields: its settings,
validated in ``__post_init__``), registered in
:data:`~ciliary_carpet.stokes.dispatch.BACKENDS` under a name, and provides

``dense(kernel, targets, sources, forces, mu) -> (M, 3)``
    The velocity at every target of every source.
``ranged_sums`` : bool (class attribute)
    Whether it implements ``ranged``. The front door
    (:func:`~ciliary_carpet.stokes.dispatch.stokeslet_velocity_ranges`) runs the ranged sums of
    a backend without them on :func:`~ciliary_carpet.stokes.dispatch.ranged_backend`'s
    choice (the CPU's direct sum) and logs it; such a backend's ``describe()`` says so.
``ranged(kernel, targets, sources, forces, ptr, ranges, mu) -> (M, 3)`` (when ``ranged_sums``)
    The velocity at each target of its listed source blocks: for target ``i`` the sources ``j``
    in ``ranges[k, 0] : ranges[k, 1]`` for every ``k`` in ``ptr[i] : ptr[i + 1]`` (a CSR list;
    a block listed twice is summed twice).
``supports(kernel) -> bool``
    Whether it can sum this Green's function (the base class: every one). ``dense`` and
    ``ranged`` raise ValueError for one it cannot.
``describe() -> str``
    One line naming the backend, its settings and where its sums run (for summaries).

Both sums may assume what :func:`validated` and :func:`validated_ranges` establish: ``targets``
(M, 3), ``sources`` (N, 3), ``forces`` (N, 3) C-contiguous finite float64 arrays, ``M, N >= 1``
(``K >= 1`` ranges); ``mu`` a finite float > 0; the points where the kernel is defined
(:meth:`~ciliary_carpet.stokes.kernel.Kernel.check_points`: sources and targets on
or above its wall); valid ``ptr`` (M + 1,) and ``ranges`` (K, 2) int64 arrays. They return the
(M, 3) float64 velocities, skipping the singular term of a coincident pair (``R = 0``; with a
wall the image terms of that source are regular and are kept).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

from single_cilium.checks import positive

from ciliary_carpet.stokes.kernel import Kernel, Wall, make_kernel

__all__ = ["Backend", "validated", "validated_ranges", "kernel_of"]


class Backend(ABC):
    """Backend of velocity sums for any :class:`~ciliary_carpet.stokes.kernel.Kernel` (base class;
    the contract is in the module docstring)."""

    ranged_sums: ClassVar[bool] = False

    @abstractmethod
    def dense(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
              mu: float) -> np.ndarray:
        """Velocity (M, 3) at ``targets`` of every source (module docstring)."""

    def ranged(self, kernel: Kernel, targets: np.ndarray, sources: np.ndarray, forces: np.ndarray,
               ptr: np.ndarray, ranges: np.ndarray, mu: float) -> np.ndarray:
        """Velocity (M, 3) at ``targets`` of each one's listed source ranges (module docstring);
        only where :attr:`ranged_sums`."""
        raise NotImplementedError(f"{type(self).__name__} does no ranged sums (ranged_sums is False): "
                                  f"call stokeslet_velocity_ranges, which runs them elsewhere")

    def supports(self, kernel: Kernel) -> bool:
        """Whether this backend sums ``kernel`` (the base class: every Green's function)."""
        return True

    def describe(self) -> str:
        """One line naming the backend (for summaries)."""
        return type(self).__name__.lower()


# --------------------------------------------------------------------------- the inputs
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


def kernel_of(kernel: Kernel | None, wall: Wall | None) -> Kernel:
    """The Green's function of a sum given a ``kernel`` or a ``wall`` (None: the singular
    Stokeslet of :func:`~ciliary_carpet.stokes.kernel.make_kernel`); TypeError for other types,
    ValueError when both are given and disagree."""
    if kernel is None:
        if wall is not None and not isinstance(wall, Wall):
            raise TypeError(f"wall must be a Wall or None, got {type(wall).__name__}")
        return make_kernel(wall)
    if not isinstance(kernel, Kernel):
        raise TypeError(f"kernel must be a Kernel, got {type(kernel).__name__}")
    if wall is not None and wall != kernel.wall:
        raise ValueError(f"wall = {wall} contradicts the kernel's wall {kernel.wall}: give the wall in the kernel")
    return kernel


def validated(kernel: Kernel, targets: Any, sources: Any, forces: Any, mu: Any
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """``(targets, sources, forces, mu)`` as a backend may assume them (module docstring):
    (M, 3), (N, 3), (N, 3) float64 arrays ((K, 2) padded with z = 0) and a float.

    Raises
    ------
    ValueError
        Naming the argument: wrong ndim or width, sources and forces with different row counts,
        NaN or inf, ``mu`` not finite and > 0, points where ``kernel`` is not defined.
    """
    t = _points("targets", targets)
    s = _points("sources", sources)
    f = _points("forces", forces)
    if f.shape[0] != s.shape[0]:
        raise ValueError(f"forces must have one row per source: sources has {s.shape[0]} rows, "
                         f"forces has {f.shape[0]}")
    m = positive("mu", mu)
    kernel.check_points(t, s)
    return t, s, f, m


def validated_ranges(ptr: Any, ranges: Any, M: int, N: int) -> tuple[np.ndarray, np.ndarray]:
    """``ptr`` (M + 1,) and ``ranges`` (K, 2) as C-contiguous int64 arrays, or ValueError naming
    the one that is not an integer array of the right shape, ``ptr`` not monotone or out of
    ``[0, K]``, a range reversed or outside ``[0, N]``."""
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
    return p, r
