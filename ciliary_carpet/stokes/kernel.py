"""Green's functions of Stokes flow: which tensor ``G`` a velocity sum uses.

A :class:`Kernel` says *what* is summed, ``u(x) = 1/(8 pi mu) sum_j G(x, xi_j) f_j``; an
backend (:class:`~ciliary_carpet.stokes.backend.Backend`: numba CPU, FMM, CUDA) says *how*.
Each Green's function is written here once, as one class: its per-pair formula (compiled by
every backend), its plain-numpy reference, its level-of-detail Taylor constants and its
symmetry. :data:`KERNELS` registers them; :func:`make_kernel` picks one from a wall and a blob
size. Four Green's functions:

* :class:`Stokeslet`: the singular free-space Stokeslet ``G^S(R) = I/r + R R^T/r^3``;
* :class:`Blake`: ``G^S`` with Blake's (1971) image system of a no-slip plane wall: the
  Stokeslet, an image Stokeslet, a Stokes doublet and a source doublet, all at the image point
  ``xi* = (xi_x, xi_y, 2 z_w - xi_z)``. With the wall shifted to ``z = 0``, ``h = xi_z`` the
  height of the source, ``R* = x - xi*`` and ``M = diag(1, 1, -1)`` (Blake 1971; Ainley et al.
  2008, J. Comput. Phys. 227, eq. 8 in the singular limit),

  .. math::

      G^B_{ij} = G^S_{ij}(R) - G^S_{ij}(R^*)
          + 2 h M_{jk} \\frac{\\partial}{\\partial R^*_k}
            \\left[ \\frac{h R^*_i}{|R^*|^3} - G^S_{i3}(R^*) \\right];

  it vanishes for targets on the wall;
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
unit vectors at unit distance, times ``R^(k+1)`` with a wall; see
:mod:`ciliary_carpet.carpet.carpet`), and :attr:`Kernel.symmetric`, whether the reciprocity
``G_ij(x, y) = G_ji(y, x)`` holds (an adjoint may then swap targets and sources): it does for
all four (Lorentz's reciprocal theorem; for the regularised image system of the wall see
:class:`RegularisedBlake`; tested to rounding).

The regularisation length ``eps`` is the filament's radius (the blob spreads each force over a
tube of that radius): the flow then stays bounded on the filament and tracers pass between
filaments, while ``eps / r`` -> 0 away from them recovers the singular flow. Cortez et al. (2005)
use ``eps`` of the order of the radius for slender bodies.

The pair formulas
-----------------
Each class's ``pair`` is a scalar numba function of one (target, source) pair, inlined by the
CPU loops (:mod:`ciliary_carpet.stokes.direct`) and compiled a second time from its Python source
(``.py_func``) into CUDA device functions (:mod:`ciliary_carpet.stokes.cuda`). Their constants
are the module globals named in :data:`PAIR_CONSTANTS`, not literals, so that the CUDA backend
can compile an fp32 copy with fp32 constants (a float literal would promote every fp32 operation
it touches to fp64 under numba's typing), and their one special function is the global
:func:`rsqrt`, which the GPU copies bind to the hardware's reciprocal square root. They are
compiled with :data:`FASTMATH`: reordered sums and fused multiply-adds, no approximate
``1/sqrt``, no assumption of finite values.

One concept over 500 lines: each Green's function's pair formula, numpy reference and constants together.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numba import njit

__all__ = ["Wall", "Kernel", "Stokeslet", "Blake", "RegularisedStokeslet", "RegularisedBlake", "KERNELS",
           "PAIRS", "make_kernel", "blake_tensor", "regularised_blake_tensor",
           "C1_FREE", "C1_WALL", "C2_FREE", "C2_WALL", "C3_FREE", "C3_WALL", "C1_WALL_ANY", "C2_WALL_ANY",
           "C3_WALL_ANY",
           "INV_8PI", "FASTMATH", "PAIR_CONSTANTS", "rsqrt"]

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

C1_WALL_ANY = 12.0
"""C1 for Blake's tensor and source displacements and forces of any direction (not only parallel
to the wall: a standing carpet's vertical beat planes), times R^2 (sampled maximum 5.6 over
24,000 heights from 10^-2.5 to 10 and directions, singular and regularised, tested; a margin of
2 as for :data:`C1_WALL`)."""
C2_WALL_ANY = 48.0
"""C2 likewise for any direction, times R^3 (sampled maximum 22.5, tested)."""
C3_WALL_ANY = 256.0
"""C3 likewise for any direction, times R^4 (sampled maximum 118, tested)."""

INV_8PI = 1.0 / (8.0 * math.pi)
"""The prefactor of every sum, ``u = INV_8PI / mu * sum_j G f_j``."""

FASTMATH = {"reassoc", "contract", "nsz", "arcp"}
"""Value-safe fast-math flags of the pair formulas and the loops that inline them: reassociation
(vectorised reductions), FMA contraction, no signed zeros, reciprocal allowed. Not ``afn``
(approximate ``1/sqrt``) nor ``nnan``/``ninf``."""

ZERO = 0.0
ONE = 1.0
TWO = 2.0
THREE = 3.0
FOUR = 4.0
SIX = 6.0
PAIR_CONSTANTS = ("ZERO", "ONE", "TWO", "THREE", "FOUR", "SIX")
"""Names of the constants of the pair formulas (retyped by the fp32 CUDA kernels)."""


@njit(cache=True, fastmath=FASTMATH, inline="always")
def rsqrt(x):  # pragma: no cover - compiled
    """``1 / sqrt(x)``, correctly rounded sqrt and division (the CPU's; not ``afn``)."""
    return ONE / math.sqrt(x)


# --------------------------------------------------------------------------- validation
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


# --------------------------------------------------------------------------- the contract
class Kernel(ABC):
    """A Green's function of Stokes flow (base class; the module docstring lists them).

    A new Green's function is a frozen dataclass subclass, registered in :data:`KERNELS` under its
    :attr:`name`; nothing else needs to change (the backends dispatch on :attr:`pair`). It
    provides

    ``name`` : str (class attribute)
        Its key in :data:`KERNELS`.
    ``pair(x, y, z, sx, sy, sz, fx, fy, fz, e2) -> (ux, uy, uz)`` (a ``staticmethod``)
        ``G(x, xi) f`` for one target ``(x, y, z)`` and one source ``(sx, sy, sz)`` of force
        ``(fx, fy, fz)``, without ``1/(8 pi mu)``; ``e2 = eps^2``; heights measured from
        :attr:`z_origin` (the wall at ``z = 0``). Compiled with
        ``@njit(cache=True, fastmath=FASTMATH, inline="always")``, written with the constants
        of :data:`PAIR_CONSTANTS` and :func:`rsqrt` only (module docstring), and the singular term
        of a coincident pair (``R = 0``) counting as zero. Green's functions may share one pair
        formula (:class:`Stokeslet` and :class:`RegularisedStokeslet` do, with ``e2 = 0``).
    ``reference(x, xi, f) -> (M, 3)``
        ``sum_j G(x_i, xi_j) f_j`` in plain numpy, for (M, 3) targets, (N, 3) sources and forces
        (heights from :attr:`z_origin`, no ``1/(8 pi mu)``), in an algebra independent of
        ``pair`` (the tests compare the two; :mod:`ciliary_carpet.stokes.reference`).
    ``c1``, ``c2``, ``c3`` : float (class attributes)
        Taylor constants of the levels of detail (module docstring), for source displacements
        and forces parallel to the wall (any direction in free space).
    ``c_any`` : tuple or None (class attribute, default None: the same)
        The constants for displacements and forces of any direction (:meth:`taylor_constants`).
    ``symmetric`` : bool (class attribute, default True)
        Whether ``G_ij(x, y) = G_ji(y, x)`` (the treecode's adjoint needs it).
    ``eps``, ``wall`` (fields or class attributes)
        Regularisation length (0: singular) and the no-slip :class:`Wall` or None.

    and may override :meth:`check_points` (where sources and targets may lie; the base class:
    above the wall). Derived: :attr:`code` (the pair's position in :data:`PAIRS`, what compiled
    loops dispatch on) and :attr:`z_origin`.
    """

    name: ClassVar[str] = ""
    eps: float = 0.0
    wall: Wall | None = None
    c1: ClassVar[float]
    c2: ClassVar[float]
    c3: ClassVar[float]
    symmetric: ClassVar[bool] = True
    c_any: ClassVar[tuple | None] = None

    def taylor_constants(self, in_plane: bool) -> tuple[float, float, float]:
        """(c1, c2, c3) for source displacements and forces parallel to the wall (``in_plane``:
        a planar carpet's) or of any direction (a standing carpet's vertical beat planes)."""
        if in_plane or self.c_any is None:
            return (self.c1, self.c2, self.c3)
        return self.c_any

    @staticmethod
    @abstractmethod
    def pair(x, y, z, sx, sy, sz, fx, fy, fz, e2):  # pragma: no cover - the contract only
        """``G(x, xi) f`` of one pair (class docstring); a compiled function."""

    @abstractmethod
    def reference(self, x: np.ndarray, xi: np.ndarray, f: np.ndarray) -> np.ndarray:
        """``sum_j G(x_i, xi_j) f_j`` (M, 3) in plain numpy (class docstring)."""

    @property
    def code(self) -> int:
        """The position of :attr:`pair` in :data:`PAIRS`: what the compiled loops dispatch on."""
        try:
            return PAIRS.index(type(self).pair)
        except ValueError:
            raise ValueError(f"the pair formula of {type(self).__name__} is not in PAIRS: register the Green's "
                             f"function in KERNELS") from None

    @property
    def z_origin(self) -> float | None:
        """The height :attr:`pair` measures ``z`` from: the wall's; None where ``G`` depends on
        ``x - xi`` only (any origin will do)."""
        return None if self.wall is None else self.wall.z

    def check_points(self, targets: np.ndarray, sources: np.ndarray) -> None:
        """Raise ValueError unless the (M, 3) ``targets`` and (N, 3) ``sources`` lie where this
        Green's function is defined: with a wall, sources and targets on or above it (a source on
        the wall, such as a standing cilium's clamp, makes no flow: its image cancels it)."""
        if self.wall is None:
            return
        z = self.wall.z
        if sources.shape[0] and not np.all(sources[:, 2] >= z):
            k = int(np.argmin(sources[:, 2]))
            raise ValueError(f"sources must lie on or above the wall z = {z}: sources[{k}] has z = {sources[k, 2]}")
        if targets.shape[0] and not np.all(targets[:, 2] >= z):
            k = int(np.argmin(targets[:, 2]))
            raise ValueError(f"targets must lie on or above the wall z = {z}: targets[{k}] has z = {targets[k, 2]}")


# --------------------------------------------------------------------------- free space
@njit(cache=True, fastmath=FASTMATH, inline="always")
def _pair_free(xi, yi, zi, sx, sy, sz, a, b, c, e2):  # pragma: no cover - compiled
    """``G^eps(x - xi) f`` of one pair (no 1/(8 pi mu)), ``e2 = eps^2``:
    ``(f (r^2 + 2 e2) + R (R.f)) / (r^2 + e2)^{3/2}``; the singular Stokeslet for ``e2 = 0``, its
    coincident pair (``R = 0``) counting as zero."""
    dx = xi - sx
    dy = yi - sy
    dz = zi - sz
    r2 = dx * dx + dy * dy + dz * dz
    q2 = r2 + e2
    ir = rsqrt(q2) if q2 > ZERO else ZERO
    ir3 = ir * ir * ir
    rf = (dx * a + dy * b + dz * c) * ir3
    iso = (r2 + TWO * e2) * ir3
    return a * iso + dx * rf, b * iso + dy * rf, c * iso + dz * rf


def _free_reference(x: np.ndarray, xi: np.ndarray, f: np.ndarray, e2: float) -> np.ndarray:
    """``sum_j G^eps(x_i - xi_j) f_j`` in the vector form ``(f (r^2 + 2 e2) + R (R.f)) /
    (r^2 + e2)^{3/2}``, coincident singular pairs skipped."""
    dx = x[:, 0:1] - xi[:, 0]
    dy = x[:, 1:2] - xi[:, 1]
    dz = x[:, 2:3] - xi[:, 2]
    fx, fy, fz = (np.ascontiguousarray(c) for c in f.T)
    r2 = dx * dx + dy * dy + dz * dz
    q2 = r2 + e2
    with np.errstate(divide="ignore", invalid="ignore"):
        ir3 = 1.0 / (q2 * np.sqrt(q2))
        iso = (r2 + 2 * e2) * ir3
    ir3[q2 == 0.0] = 0.0  # coincident points: skipped
    iso[q2 == 0.0] = 0.0
    rf = (dx * fx + dy * fy + dz * fz) * ir3
    return np.column_stack([iso @ fx + np.einsum("ij,ij->i", dx, rf),
                            iso @ fy + np.einsum("ij,ij->i", dy, rf),
                            iso @ fz + np.einsum("ij,ij->i", dz, rf)])


@dataclass(frozen=True)
class Stokeslet(Kernel):
    """The singular free-space Stokeslet ``I/r + R R^T/r^3`` (coincident pairs skipped)."""

    name = "stokeslet"
    c1, c2, c3 = C1_FREE, C2_FREE, C3_FREE
    pair = staticmethod(_pair_free)

    def reference(self, x: np.ndarray, xi: np.ndarray, f: np.ndarray) -> np.ndarray:
        return _free_reference(x, xi, f, 0.0)


@dataclass(frozen=True)
class RegularisedStokeslet(Kernel):
    """Cortez-Fauci-Medovikov regularised Stokeslet of blob size ``eps > 0`` (symmetric)."""

    eps: float = 0.02
    name = "regularised-stokeslet"
    c1, c2, c3 = C1_FREE, C2_FREE, C3_FREE
    pair = staticmethod(_pair_free)

    def __post_init__(self) -> None:
        object.__setattr__(self, "eps", _eps(self.eps))

    def reference(self, x: np.ndarray, xi: np.ndarray, f: np.ndarray) -> np.ndarray:
        return _free_reference(x, xi, f, self.eps ** 2)


# --------------------------------------------------------------------------- Blake's wall
@njit(cache=True, fastmath=FASTMATH, inline="always")
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
    ir = rsqrt(r2) if r2 > ZERO else ZERO
    ir3 = ir * ir * ir
    iq = rsqrt(p2 + ez * ez)
    iq2 = iq * iq
    iq3 = iq * iq2
    pf = dx * a + dy * b
    rf = (pf + dz * c) * ir3          # (R . f) / r^3
    qf = pf + ez * c                  # R* . f
    qg = pf - ez * c                  # R* . g
    h2 = TWO * h * iq3
    d = h2 * zt
    cf = ir - iq
    cq = h2 * (c + THREE * zt * qg * iq2) - qf * iq3
    cxy = rf + cq
    return ((cf - d) * a + cxy * dx, (cf - d) * b + cxy * dy,
            (cf + d) * c + rf * dz + cq * ez + h2 * qg)


def blake_tensor(x: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """The Blake tensors (M, N, 3, 3), wall z = 0, as a plain-numpy reference, written term by
    term as in the module docstring (independent of the algebra of the pair formula); the
    singular Stokeslet of a coincident pair counts as zero."""
    x = np.asarray(x, float)[:, None, :]
    xi = np.asarray(xi, float)[None, :, :]
    R = x - xi
    Rs = x - xi * np.array([1.0, 1.0, -1.0])
    h = np.broadcast_to(xi[..., 2], R.shape[:2])
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


@dataclass(frozen=True)
class Blake(Kernel):
    """The Stokeslet above the no-slip ``wall`` with Blake's image system (symmetric)."""

    wall: Wall = Wall()
    name = "blake"
    c1, c2, c3 = C1_WALL, C2_WALL, C3_WALL
    c_any = (C1_WALL_ANY, C2_WALL_ANY, C3_WALL_ANY)
    pair = staticmethod(_pair_wall)

    def __post_init__(self) -> None:
        _wall(self.wall)

    def reference(self, x: np.ndarray, xi: np.ndarray, f: np.ndarray) -> np.ndarray:
        return np.einsum("mnij,nj->mi", blake_tensor(x, xi), f)


# --------------------------------------------------------------------------- regularised wall
@njit(cache=True, fastmath=FASTMATH, inline="always")
def _pair_regwall(xi, yi, zt, sx, sy, h, a, b, c, e2):  # pragma: no cover - compiled
    """The regularised Blake tensor (:func:`regularised_blake_tensor`) times ``f`` for one pair,
    wall at z = 0, ``e2 = eps^2`` (no 1/(8 pi mu)).

    With ``r = x - xi``, ``R = x - xi*``, ``g = (f_x, f_y, -f_z)`` the tensor's terms collect to
    ``G^eps(r) f + a_f f + a_g g + a_R R + a_z e_z`` (coefficients below)."""
    dx = xi - sx
    dy = yi - sy
    dz = zt - h
    ez = zt + h
    p2 = dx * dx + dy * dy
    r2 = p2 + dz * dz
    R2 = p2 + ez * ez
    ir = rsqrt(r2 + e2)
    ir3 = ir * ir * ir
    iq = rsqrt(R2 + e2)
    iq3 = iq * iq * iq
    iq5 = iq3 * iq * iq
    pf = dx * a + dy * b
    rf = (pf + dz * c) * ir3
    Rf = pf + ez * c
    Rg = pf - ez * c
    iso = (r2 + TWO * e2) * ir3
    hh = h * h
    cf = -(R2 + TWO * e2) * iq3 + SIX * h * e2 * iq5 * ez
    cg = (TWO * hh - TWO * h * ez) * iq3 - SIX * hh * e2 * iq5
    cR = -Rf * iq3 + (SIX * h * ez - SIX * hh) * Rg * iq5 + TWO * h * c * iq3
    cz = TWO * h * Rg * (R2 + FOUR * e2) * iq5 - SIX * h * e2 * iq5 * Rf
    return (a * (iso + cf) + dx * (rf + cR) + cg * a,
            b * (iso + cf) + dy * (rf + cR) + cg * b,
            c * (iso + cf) + dz * rf + ez * cR - cg * c + cz)


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


@dataclass(frozen=True)
class RegularisedBlake(Kernel):
    """Regularised Stokeslet of blob size ``eps`` above the no-slip ``wall`` (Ainley et al. 2008
    with Smith's 2009 correction). Symmetric: exactly reciprocal, ``G_ij(x, y) = G_ji(y, x)`` for
    any two points above the wall (an independent 40-digit evaluation of the formula gives an
    asymmetry of 1e-35). In float64 the two sides agree to rounding: the image terms are each of
    size up to about ``1/|R_eps| + h^2/|R_eps|^3 + h/|R_eps|^2`` and cancel in part, and the
    difference is a few ulps of that scale (measured at most 2.7, tested to 64:
    tests/test_treecode.py); what is O(eps^2 / r^2) is its difference from Blake's tensor."""

    eps: float = 0.02
    wall: Wall = Wall()
    name = "regularised-blake"
    c1, c2, c3 = C1_WALL, C2_WALL, C3_WALL
    c_any = (C1_WALL_ANY, C2_WALL_ANY, C3_WALL_ANY)
    pair = staticmethod(_pair_regwall)

    def __post_init__(self) -> None:
        object.__setattr__(self, "eps", _eps(self.eps))
        _wall(self.wall)

    def reference(self, x: np.ndarray, xi: np.ndarray, f: np.ndarray) -> np.ndarray:
        return np.einsum("mnij,nj->mi", regularised_blake_tensor(x, xi, self.eps), f)


# --------------------------------------------------------------------------- the registry
KERNELS: dict[str, type[Kernel]] = {k.name: k for k in (Stokeslet, Blake, RegularisedStokeslet, RegularisedBlake)}
"""The Green's functions by name (:attr:`Kernel.name`)."""

PAIRS: tuple = tuple(dict.fromkeys(k.pair for k in KERNELS.values()))
"""The distinct pair formulas of :data:`KERNELS`, in registry order: :attr:`Kernel.code` indexes
it, and the compiled loops of :mod:`ciliary_carpet.stokes.direct` dispatch over it."""


def make_kernel(wall: Wall | None = None, eps: float = 0.0) -> Kernel:
    """The kernel for an optional ``wall`` and blob size ``eps`` (0: singular)."""
    if eps is None or float(eps) == 0.0:
        return Stokeslet() if wall is None else Blake(_wall(wall))
    return RegularisedStokeslet(eps) if wall is None else RegularisedBlake(eps, _wall(wall))
