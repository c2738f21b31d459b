"""Green's functions of Stokes flow: which tensor ``G`` a velocity sum uses.

A :class:`Kernel` says *what* is summed, ``u(x) = 1/(8 pi mu) sum_j G(x, xi_j) f_j``; an
evaluator (:class:`ciliary_carpet.stokes.stokeslet.Backend`: numba CPU, FMM) says *how*. Four kernels:

* :class:`Stokeslet`: the singular free-space Stokeslet ``G^S(R) = I/r + R R^T/r^3``;
* :class:`Blake`: ``G^S`` with Blake's (1971) image system of a no-slip plane wall;
* :class:`RegularisedStokeslet`: the regularised Stokeslet of the blob
  ``phi_eps(r) = 15 eps^4 / (8 pi (r^2 + eps^2)^{7/2})`` (Cortez, Fauci & Medovikov 2005, eq. 10a),

  .. math::

      G^\\epsilon(R) = \\frac{(r^2 + 2\\epsilon^2) I + R R^T}{(r^2 + \\epsilon^2)^{3/2}},

  bounded at the source (``G^eps(0) = 2 I / eps``) and equal to ``G^S`` up to
  ``G^eps - G^S = eps^2 (I/2 - 3 R R^T / (2 r^2)) / r^3 + O(eps^4 / r^5)``, i.e. a difference that
  decays as ``eps^2 / r^3`` (tested);
* :class:`RegularisedBlake`: the same blob above a no-slip wall, with the regularised image system
  of Ainley, Durkin, Embid, Boindala & Cortez (2008, J. Comput. Phys. 227, 4600), as corrected by
  Smith (2009, Proc. R. Soc. A 465, 3605): regularised Stokeslet minus its image, a blob term, a
  potential source dipole, a regularised Stokes doublet and a rotlet difference, all at the image
  point. It vanishes exactly on the wall (tested) and tends to :class:`Blake` as ``eps -> 0``.

Every kernel carries the facts its users need: :attr:`Kernel.c1`, :attr:`Kernel.c2` and
:attr:`Kernel.c3`, the Taylor constants of the levels of detail (``sup |(h . grad)^k G f|`` over
unit vectors at unit distance, times ``R^(k+1)`` with a wall; see :mod:`ciliary_carpet.carpet.carpet`), and :attr:`Kernel.symmetric`, whether the reciprocity
``G_ij(x, y) = G_ji(y, x)`` holds (an adjoint may then swap targets and sources): it does for
all four (Lorentz's reciprocal theorem; for the regularised image system of the wall see
:class:`RegularisedBlake`; tested to rounding).

The regularisation length ``eps`` is the filament's radius (the blob spreads each force over a
tube of that radius): the flow then stays bounded on the filament and tracers pass between
filaments, while ``eps / r`` -> 0 away from them recovers the singular flow. Cortez et al. (2005)
use ``eps`` of the order of the radius for slender bodies.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Wall", "Kernel", "Stokeslet", "Blake", "RegularisedStokeslet", "RegularisedBlake", "make_kernel",
           "C1_FREE", "C1_WALL", "C2_FREE", "C2_WALL", "C3_FREE", "C3_WALL"]

C1_FREE = 2.0
"""sup |(h . grad) G^S(e) f| over unit h, f, e: the first-order Taylor constant of the free-space
Stokeslet (attained at h = f = e: ``(h . grad)(f/r + R (R . f)/r^3) = -2 e`` there; sampled
maximum 1.99, tested), an upper bound for the regularised one too."""
C1_WALL = 4.0
"""The same for Blake's tensor (in-plane source derivatives) times R^2, over wall heights and
directions (sampled maximum 1.98 singular, 1.95 regularised, tested; a margin of 2 as for
:data:`C2_WALL`)."""

C2_FREE = 4.0
"""sup |(h . grad)^2 G^S(e) f| over unit h, f, e: the Taylor constant of the free-space Stokeslet
(and an upper bound for the regularised one: the blob only lowers the derivatives, tested)."""
C2_WALL = 16.0
"""The same constant for Blake's tensor, second derivatives in the in-plane source position,
relative to the source distance (a safe upper bound of the measured supremum, tested)."""


C3_FREE = 16.0
"""sup |(h . grad)^3 G^S(e) f| over unit in-plane h, f and unit e (sampled maximum 12.3, tested);
the Taylor constant of the third-order levels of detail."""
C3_WALL = 64.0
"""The same for Blake's tensor times R^4, over wall heights and directions (sampled maximum 12.9,
tested; a wide margin as for C2_WALL)."""


@dataclass(frozen=True)
class Wall:
    """A no-slip plane wall ``z = z`` (fluid above it, ``z > z_wall``).

    Parameters
    ----------
    z : float, default 0
        Height of the wall; must be finite.

    Raises
    ------
    ValueError
        If ``z`` is not a finite real number.
    """

    z: float = 0.0

    def __post_init__(self) -> None:
        try:
            z = float(self.z)
        except (TypeError, ValueError):
            raise ValueError(f"Wall.z must be a real number, got {self.z!r}") from None
        if not math.isfinite(z):
            raise ValueError(f"Wall.z must be finite, got {z}")
        object.__setattr__(self, "z", z)


def _eps(value: Any) -> float:
    try:
        e = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"eps (the blob size) must be a real number, got {value!r}") from None
    if not (math.isfinite(e) and e > 0):
        raise ValueError(f"eps (the blob size) must be finite and > 0, got {e}")
    return e


def _wall(value: Any) -> Wall:
    if not isinstance(value, Wall):
        raise TypeError(f"wall must be a Wall, got {type(value).__name__}")
    return value


class Kernel:
    """A Green's function of Stokes flow (base class; see the module docstring).

    Attributes every kernel has: ``eps`` (regularisation length, 0 for a singular kernel),
    ``wall`` (a :class:`Wall` or None), the Taylor constants :attr:`c1`, :attr:`c2`, :attr:`c3` and
    :attr:`symmetric`; ``code`` is the integer
    the compiled evaluators dispatch on (0 free space, 1 Blake, 2 regularised Blake).
    """

    eps: float = 0.0
    wall: Wall | None = None
    code: int = 0

    @property
    def c1(self) -> float:
        """First-order Taylor constant of the levels of detail (:data:`C1_FREE`, :data:`C1_WALL`)."""
        return C1_WALL if self.wall is not None else C1_FREE

    @property
    def c2(self) -> float:
        """Taylor constant of the levels of detail (module docstring)."""
        return C2_WALL if self.wall is not None else C2_FREE

    @property
    def c3(self) -> float:
        """Third-order Taylor constant of the levels of detail (:data:`C3_FREE`, :data:`C3_WALL`)."""
        return C3_WALL if self.wall is not None else C3_FREE

    @property
    def symmetric(self) -> bool:
        """Whether ``G_ij(x, y) = G_ji(y, x)``."""
        return True

    @property
    def regularised(self) -> bool:
        return self.eps > 0


@dataclass(frozen=True)
class Stokeslet(Kernel):
    """The singular free-space Stokeslet ``I/r + R R^T/r^3`` (coincident pairs skipped)."""


@dataclass(frozen=True)
class Blake(Kernel):
    """The Stokeslet above the no-slip ``wall`` with Blake's image system (symmetric)."""

    wall: Wall = Wall()
    code = 1

    def __post_init__(self) -> None:
        _wall(self.wall)


@dataclass(frozen=True)
class RegularisedStokeslet(Kernel):
    """Cortez-Fauci-Medovikov regularised Stokeslet of blob size ``eps > 0`` (symmetric)."""

    eps: float = 0.02

    def __post_init__(self) -> None:
        object.__setattr__(self, "eps", _eps(self.eps))


@dataclass(frozen=True)
class RegularisedBlake(Kernel):
    """Regularised Stokeslet of blob size ``eps`` above the no-slip ``wall`` (Ainley et al. 2008
    with Smith's 2009 correction). Symmetric: exactly reciprocal, ``G_ij(x, y) = G_ji(y, x)`` for
    any two points above the wall (an independent 40-digit evaluation of the formula gives an
    asymmetry of 1e-35). In float64 the two sides agree to rounding: the image terms are each of
    size up to about ``1/|R_eps| + h^2/|R_eps|^3 + h/|R_eps|^2`` and cancel in part, and the
    difference is a few ulps of that scale (measured at most 2.7, tested to 64:
    tests/test_treecode.py). The earlier "reciprocal only up
    to O(eps^2)" was wrong; what is O(eps^2 / r^2) is its difference from Blake's tensor."""

    eps: float = 0.02
    wall: Wall = Wall()
    code = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "eps", _eps(self.eps))
        _wall(self.wall)


def make_kernel(wall: Wall | None = None, eps: float = 0.0) -> Kernel:
    """The kernel for an optional ``wall`` and blob size ``eps`` (0: singular)."""
    if eps is None or float(eps) == 0.0:
        return Stokeslet() if wall is None else Blake(_wall(wall))
    return RegularisedStokeslet(eps) if wall is None else RegularisedBlake(eps, _wall(wall))


def regularised_blake_tensor(x: np.ndarray, xi: np.ndarray, eps: float) -> np.ndarray:
    """The regularised Blake tensors (M, N, 3, 3), wall z = 0, as a plain-numpy reference.

    Term by term as in Ainley et al. (2008) with Smith's (2009) sign correction, in tensor form
    (``R = x - xi*``, ``h`` the source height, ``Delta = diag(1, 1, -1)``, ``Re = sqrt(|R|^2 + eps^2)``)::

        G = G^eps(x - xi) - G^eps(R) - 6 h^2 eps^2 Delta / Re^5
            + 2 h^2 (Delta / Re^3 - 3 R (Delta R)^T / Re^5)
            + 2 h (e3 (Delta R)^T (|R|^2 + 4 eps^2) / Re^5 - R_3 Delta / Re^3 + R e3^T / Re^3
                   + 3 R_3 R (Delta R)^T / Re^5)
            - 6 h eps^2 (e3 R^T - R_3 I) / Re^5
    """
    x = np.asarray(x, float)[:, None, :]
    xi = np.asarray(xi, float)[None, :, :]
    e2 = float(eps) ** 2
    eye = np.eye(3)
    e3 = eye[2]
    dlt = np.diag([1.0, 1.0, -1.0])

    def g_eps(R):
        r2 = np.sum(R * R, axis=-1)[..., None, None]
        return ((r2 + 2 * e2) * eye + R[..., :, None] * R[..., None, :]) / (r2 + e2) ** 1.5

    r = x - xi
    h = xi[..., 2][..., None, None]
    R = x - xi * np.array([1.0, 1.0, -1.0])
    R2 = np.sum(R * R, axis=-1)[..., None, None]
    Re3 = (R2 + e2) ** 1.5
    Re5 = (R2 + e2) ** 2.5
    R3 = R[..., 2][..., None, None]
    RdR = R[..., :, None] * (R @ dlt)[..., None, :]
    G = g_eps(r) - g_eps(R) - 6 * h ** 2 * e2 * dlt / Re5
    G = G + 2 * h ** 2 * (dlt / Re3 - 3 * RdR / Re5)
    G = G + 2 * h * (e3[:, None] * (R @ dlt)[..., None, :] * (R2 + 4 * e2) / Re5 - R3 * dlt / Re3
                     + R[..., :, None] * e3[None, :] / Re3 + 3 * R3 * RdR / Re5)
    G = G - 6 * h * e2 * (e3[:, None] * R[..., None, :] - R3 * eye) / Re5
    return G
