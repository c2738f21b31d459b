"""The levels of detail: point-force carriers of each cilium's moments and their rigorous bounds.

Per (cilium, evaluation point) pair the flow is summed at the cheapest representation whose
error bound meets the tolerance (DESIGN.md "flow fidelity"). Around the force centre c_j of
cilium j (every filament point lies within the radius a_j of it; :class:`~.cycles.CycleData`),
with h = r - c, its moments F = int f ds (2,), D = int h f^T ds (2, 2), T = int h h f ds
(2, 2, 2) and Qk = int |h|^k |f| ds are carried by point forces at fixed positions about c_j, at
one of three orders:

* the *monopole*: F at c_j;
* the *dipole*: three forces at c_j + delta_j u_m, u_m the unit vectors of an equilateral triangle
  (:data:`DIPOLE` at 90, 210 and 330 degrees, :func:`triangle`), delta_j = a_j / 2, reproducing F
  and D: f_m = F / 3 + 2 / (3 delta) D^T u_m, from the inverse of their moment matrix
  (:func:`dipole_forces`, the one implementation, which the design model uses too, with its own
  triangle at 0, 120 and 240 degrees, :data:`DESIGN_DIPOLE`);
* the *quadrupole*: six forces, one at c_j and five on a regular pentagon of radius delta_j
  (:data:`~ciliary_carpet.stokes.treecode.QUADRUPOLE`, a vertex at 90 degrees; the treecode's stencil), reproducing F, D and T.

The bounds that choose among the orders per (cilium, point) pair are in
:mod:`~ciliary_carpet.carpet.bounds`; the carriers of many cilia at an instant, made in one
compiled pass, in :mod:`~ciliary_carpet.carpet.instants`.

Shapes: per cilium arrays (N,); carrier forces (N, 3, 2) and (N, 6, 2) in each cilium's 2D frame
(:mod:`~ciliary_carpet.carpet.geometry`), mapped into space when stacked. A standing carpet's
frames are vertical: its bounds take the kernel's constants for any direction (larger with a
wall: :meth:`Kernel.taylor_constants <ciliary_carpet.stokes.kernel.Kernel.taylor_constants>`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit

from ciliary_carpet.carpet.bounds import LOD_SLACK, LOD_SLACK_STANDING, PHASE_MARGIN, Bounds, tier_bound
from ciliary_carpet.carpet.cycles import CycleData
from ciliary_carpet.stokes import QUADRUPOLE, QUADRUPOLE_INV, Kernel

__all__ = ["CarrierForces", "Carriers", "DIPOLE", "DIPOLE_INV", "DESIGN_DIPOLE", "HARMONIC_TAIL", "MOMENT_ROWS",
           "dipole_forces", "triangle"]


def triangle(angle: float) -> np.ndarray:
    """(3, 2) the unit vectors at ``angle``, ``angle + 2 pi / 3`` and ``angle + 4 pi / 3``
    (radians, anticlockwise from +x): the positions of dipole carriers for unit delta."""
    return np.array([[math.cos(2 * math.pi * m / 3 + angle), math.sin(2 * math.pi * m / 3 + angle)]
                     for m in range(3)])


DIPOLE = triangle(math.pi / 2)
"""Positions of the carpet's dipole carriers for unit delta: an equilateral triangle with a vertex
at 90 degrees (90, 210, 330), the vertex the pentagon of :data:`~ciliary_carpet.stokes.treecode.QUADRUPOLE` has too. Any
orientation reproduces F and D exactly; the orientation sets the carriers' own second moment
T_rep, hence what the dipole order misses (its bound uses nu(T - T_rep))."""
DESIGN_DIPOLE = np.array([[1.0, 0.0], [-0.5, math.sqrt(3) / 2], [-0.5, -math.sqrt(3) / 2]])
"""Positions of the design model's dipole carriers for unit delta (:mod:`ciliary_carpet.design.model`):
the triangle at 0, 120 and 240 degrees. The same carriers (:func:`dipole_forces`), another
orientation: the design model's flow is its own approximation (corrected by the full flow
between passes), and its designs were calibrated with this one. Measured on the five bundled
scenes (reduced): the carpet's orientation would move the designed layouts' flows by up to 3 %
(path-line velocities; the pattern a carpet can hold, e.g. 24.4 against 23.0 degrees for
vortex_turn), so the design keeps its own."""


def dipole_forces(F: np.ndarray, D: np.ndarray, delta: np.ndarray, unit: np.ndarray = DIPOLE) -> np.ndarray:
    """(K, 3, 2) the forces of the dipole carriers at c + delta u_m that reproduce the moments
    F (K, 2) and D (K, 2, 2) about c of K cilia with carrier scales ``delta`` (K,):
    f_m = F / 3 + 2 / (3 delta) D^T u_m, from the inverse of the carriers' moment matrix (rows 1,
    x, y). ``unit`` (3, 2): the u_m, an equilateral triangle: the carpet's :data:`DIPOLE` (default)
    or the design model's :data:`DESIGN_DIPOLE`. Linear in (F, D): the derivatives of F and D
    give the carriers' derivatives. The one implementation of the dipole carriers, for the
    carpet's levels of detail and the design model (one compiled pass over the cilia: every
    evaluation of a carpet's flow makes them for all its cilia)."""
    unit = np.asarray(unit, dtype=float)
    inv = DIPOLE_INV if unit is DIPOLE else np.linalg.inv(np.stack([np.ones(3), unit[:, 0], unit[:, 1]]))
    F = np.ascontiguousarray(F, dtype=float)
    D = np.ascontiguousarray(D, dtype=float)
    d = np.ascontiguousarray(np.broadcast_to(np.asarray(delta, dtype=float), (F.shape[0],)))
    out = np.empty((F.shape[0], 3, 2))
    _dipole_forces(F, D, d, inv, out)
    return out


@njit(cache=True, nogil=True)
def _dipole_forces(F, D, delta, inv, out):  # pragma: no cover - compiled
    """out[j, m] = inv[m, 0] F[j] + inv[m, 1] D[j, 0] / delta[j] + inv[m, 2] D[j, 1] / delta[j]
    (:func:`dipole_forces`, in the order numpy's broadcast took)."""
    for j in range(F.shape[0]):
        d = delta[j]
        for m in range(3):
            for k in range(2):
                out[j, m, k] = inv[m, 0] * F[j, k] + inv[m, 1] * (D[j, 0, k] / d) + inv[m, 2] * (D[j, 1, k] / d)


@njit(cache=True, inline="always")
def _solve_carriers(inv, b, fk):  # pragma: no cover - compiled
    """fk (n, 2) = inv (n, n) @ b[:n] (the carriers' forces from their scaled moments); returns
    sum_m |fk_m|."""
    acc = 0.0
    for m in range(inv.shape[0]):
        gx = 0.0
        gy = 0.0
        for q in range(inv.shape[1]):
            gx += inv[m, q] * b[q, 0]
            gy += inv[m, q] * b[q, 1]
        fk[m, 0] = gx
        fk[m, 1] = gy
        acc += math.sqrt(gx * gx + gy * gy)
    return acc


@njit(cache=True, nogil=True)
def _carrier_sets(F, D, T, delta, u3, f3, inv6, f6, nu1, nu2, q3, q6):  # pragma: no cover - compiled
    """Per cilium j the bound terms of the cheap orders about c_j (module docstring), for its
    moments F (N, 2), D (N, 2, 2), T (N, 2, 2, 2) and its dipole carriers' forces f3 (N, 3, 2) at
    c_j + delta_j u3_m (:func:`dipole_forces`):

    * q3 (N,) = delta^3 sum |f3_m|, the dipole carriers' third moment, and nu2 (N,) =
      nu(T - T_rep), T_rep their second moment;
    * f6 (N, 6, 2): the quadrupole carriers' forces at c_j + delta_j u_m (``inv6``: the inverse
      of their moment matrix), reproducing F, D and T; q6 (N,) = delta^3 sum |f6_m|;
    * nu1 (N,) = nu(D), the sum of D's singular values.

    nu of a second moment M (2, 2, 2), symmetric in its first two indices, is
    sum_c (|lambda_1| + |lambda_2|) of the symmetric matrices M[:, :, c]: with M = sum of
    |lambda| u u^T e_c terms, |(grad^2 G) : M| <= C2 nu(M) / R^3 (and |(grad G) : D| <= C1 nu(D) / R^2)."""
    b = np.empty((6, 2))
    for j in range(F.shape[0]):
        d = delta[j]
        d2 = d * d
        for k in range(2):
            b[0, k] = F[j, k]
            b[1, k] = D[j, 0, k] / d
            b[2, k] = D[j, 1, k] / d
            b[3, k] = T[j, 0, 0, k] / d2
            b[4, k] = T[j, 0, 1, k] / d2
            b[5, k] = T[j, 1, 1, k] / d2
        q6[j] = d2 * d * _solve_carriers(inv6, b, f6[j])
        acc = 0.0
        for m in range(3):
            acc += math.sqrt(f3[j, m, 0] * f3[j, m, 0] + f3[j, m, 1] * f3[j, m, 1])
        q3[j] = d2 * d * acc
        nu = 0.0
        for c in range(2):
            # the symmetric part of T[:, :, c] minus the carriers' second moment
            sxx = T[j, 0, 0, c]
            sxy = 0.5 * (T[j, 0, 1, c] + T[j, 1, 0, c])
            syy = T[j, 1, 1, c]
            for m in range(3):
                fm = f3[j, m, c] * d2
                sxx -= u3[m, 0] * u3[m, 0] * fm
                sxy -= u3[m, 0] * u3[m, 1] * fm
                syy -= u3[m, 1] * u3[m, 1] * fm
            tr = sxx + syy
            det = sxx * syy - sxy * sxy
            nu += abs(tr) if det >= 0.0 else math.sqrt(tr * tr - 4.0 * det)
        nu2[j] = nu
        fro = D[j, 0, 0] ** 2 + D[j, 0, 1] ** 2 + D[j, 1, 0] ** 2 + D[j, 1, 1] ** 2
        det = D[j, 0, 0] * D[j, 1, 1] - D[j, 0, 1] * D[j, 1, 0]
        nu1[j] = math.sqrt(fro + 2.0 * abs(det))


@njit(cache=True, nogil=True)
def _stack(F, f3, f6, js, axes, out):  # pragma: no cover - compiled
    """out (10 n, 3) = F[js], then f3[js] (3 per cilium), then f6[js] (6 per cilium), n = len(js),
    each mapped into space by its cilium's axes (N, 3, 2) (:meth:`Carriers.stacked`)."""
    n = js.shape[0]
    for q in range(n):
        j = js[q]
        for k in range(3):
            a0 = axes[j, k, 0]
            a1 = axes[j, k, 1]
            out[q, k] = a0 * F[j, 0] + a1 * F[j, 1]
            for m in range(3):
                out[n + 3 * q + m, k] = a0 * f3[j, m, 0] + a1 * f3[j, m, 1]
            for m in range(6):
                out[4 * n + 6 * q + m, k] = a0 * f6[j, m, 0] + a1 * f6[j, m, 1]


DIPOLE_INV = np.linalg.inv(np.stack([np.ones(3), DIPOLE[:, 0], DIPOLE[:, 1]]))
"""The inverse of the moment matrix (rows 1, x, y) of the carpet's dipole carriers :data:`DIPOLE`."""
MOMENT_ROWS = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 12, 13])
"""The rows of the moments' interpolant (:attr:`CycleData.moment_coef
<ciliary_carpet.carpet.cycles.CycleData.moment_coef>`) the carriers use: F (2), D (4), then
T[0, 0], T[0, 1], T[1, 1] (x and y each; T[1, 0] = T[0, 1]). The monopole and the dipoles need
the first six."""
HARMONIC_TAIL = 1e-3
"""A carpet's carriers at an instant drop the harmonics of the moments' interpolant whose sum,
over the phase, stays below this fraction of the tolerance times the moment's own scale
(:meth:`Carriers.harmonics`; 12-13 of 21 harmonics at tol 1e-4, 9 at 1e-2, for the shipped table).
What that changes is a small part of the levels of detail's own error (at most 0.2 tol of sum_j
S_j / (8 pi mu R_j), :data:`LOD_SLACK`): measured at tol 1e-2 to 1e-4, at most 0.14 times this
fraction of tol of that sum on a random 10 x 10 carpet (tests/test_carpet.py), 0.038 and 0.011
on the designed uniform_deflection carpet at 30 x 30 and 100 x 100 (60 points each)."""


@dataclass(frozen=True, eq=False)
class CarrierForces:
    """The cheap orders' carriers of K cilia for given moments: the dipole and quadrupole forces
    f3 (K, 3, 2), f6 (K, 6, 2) (the monopole is F itself) and the bound terms (K,) nu1 = nu(D),
    nu2 = nu(T - T_rep), q3 and q6 (the dipole's and quadrupole's delta^3 sum |f_m|) of
    :func:`_carrier_sets`."""

    f3: np.ndarray
    f6: np.ndarray
    nu1: np.ndarray
    nu2: np.ndarray
    q3: np.ndarray
    q6: np.ndarray




class Carriers:
    """The level-of-detail carriers of a carpet's cilia and their rigorous bounds (module
    docstring), for the cycle data ``cycles`` and the Green's function ``kernel`` (its Taylor
    constants c1, c2, c3). ``delta`` (N,): the carriers' scale a_j / 2."""

    def __init__(self, cycles: CycleData, kernel: Kernel):
        self.cycles, self.kernel = cycles, kernel
        self.delta = 0.5 * np.maximum(cycles.radius, 1e-12)
        self.constants = kernel.taylor_constants(cycles.embedding.in_plane)
        self.slack = LOD_SLACK if self.constants == (kernel.c1, kernel.c2, kernel.c3) else LOD_SLACK_STANDING
        """The calibration the orders are chosen with: :data:`LOD_SLACK_STANDING` for frames out of
        the plane of a wall (a standing carpet on its substrate), :data:`LOD_SLACK` otherwise (free
        space, where a standing carpet is a planar one turned)."""
        """(c1, c2, c3): the kernel's Taylor constants for the directions the cilia's frames take
        (in the plane of a wall, or any: :meth:`Kernel.taylor_constants
        <ciliary_carpet.stokes.kernel.Kernel.taylor_constants>`)."""

    def forces(self, F: np.ndarray, D: np.ndarray, T: np.ndarray, delta: np.ndarray | None = None) -> CarrierForces:
        """The carriers for moments F (K, 2), D (K, 2, 2), T (K, 2, 2, 2) of cilia of carrier scale
        ``delta`` (K,) (default: every cilium's, K = N)."""
        d = np.ascontiguousarray(self.delta if delta is None else delta, dtype=float)
        k = F.shape[0]
        f3 = np.ascontiguousarray(dipole_forces(F, D, d))
        out = CarrierForces(f3=f3, f6=np.empty((k, 6, 2)), nu1=np.empty(k), nu2=np.empty(k), q3=np.empty(k),
                            q6=np.empty(k))
        _carrier_sets(np.ascontiguousarray(F, dtype=float), np.ascontiguousarray(D, dtype=float),
                      np.ascontiguousarray(T, dtype=float), d, DIPOLE, f3, QUADRUPOLE_INV, out.f6, out.nu1,
                      out.nu2, out.q3, out.q6)
        return out

    @cached_property
    def over_cycle(self) -> Bounds:
        """The bounds of the flow at any instant: the exact terms' maxima over the cycle's phase
        samples times :data:`PHASE_MARGIN`, the remainders' maxima, S the r.m.s. of |F(t)|."""
        c = self.cycles
        n, n_p = c.n, c.n_phase
        car = self.forces(c.F.reshape(-1, 2), c.D.reshape(-1, 2, 2), c.T.reshape(-1, 2, 2, 2),
                          np.repeat(self.delta, n_p))
        nu1, nu2 = (getattr(car, q).reshape(n, n_p).max(axis=1) for q in ("nu1", "nu2"))
        Q3 = c.Q_max
        q3, q6 = ((c.Q + getattr(car, q).reshape(n, n_p)).max(axis=1) - Q3 for q in ("q3", "q6"))
        Q2 = c.Q2.max(axis=1)
        S = c.F_rms * c.flutter
        return self._bounds(S, nu1, nu2, q3, q6, Q2, Q3, PHASE_MARGIN)

    @cached_property
    def dipole_force_max(self) -> np.ndarray:
        """(N, 3) the largest force of each dipole carrier over the cycle's phase samples, times
        :data:`PHASE_MARGIN` (the phases between them): what bounds a group of far cilia
        (:class:`~.plan.FarGroups`)."""
        c = self.cycles
        n, n_p = c.n, c.n_phase
        f3 = dipole_forces(c.F.reshape(-1, 2), c.D.reshape(-1, 2, 2), np.repeat(self.delta, n_p))
        return PHASE_MARGIN * np.sqrt((f3 ** 2).sum(-1)).reshape(n, n_p, 3).max(axis=1)

    @cached_property
    def of_mean(self) -> Bounds:
        """The bounds of the cycle-mean flow: those of the cycle means, S = |Fbar|."""
        c = self.cycles
        car = self.forces(c.F_mean, c.D_mean, c.T_mean)
        S = np.sqrt((c.F_mean ** 2).sum(-1)) * c.flutter
        return self._bounds(S, car.nu1, car.nu2, car.q3, car.q6, c.Q2_mean, c.Q_mean, 1.0)

    def _bounds(self, S, nu1, nu2, q3, q6, Q2, Q3, margin) -> Bounds:
        c1, c2, c3 = self.constants
        return Bounds(S=S, a1=margin * c1 * nu1, b1=0.5 * c2 * Q2, a2=margin * 0.5 * c2 * nu2,
                      b2=c3 / 6.0 * (Q3 + q3), b3=c3 / 6.0 * (Q3 + q6), Q3=Q3, radius=self.cycles.radius,
                      slack=self.slack)

    def positions(self, js: np.ndarray) -> np.ndarray:
        """(10 len(js), 3) the carriers' positions in space of cilia ``js`` in the order a ranged
        sum reads them: the monopoles (at c_j), then the dipoles' three, then the quadrupoles' six
        per cilium (placed in each cilium's 2D frame, then embedded:
        :class:`~ciliary_carpet.carpet.geometry.Embedding`)."""
        js = np.asarray(js, dtype=np.int64)
        cen, dl = self.cycles.centre[js], self.delta[js][:, None, None]
        emb = self.cycles.embedding
        parts = [cen[:, None], cen[:, None] + dl * DIPOLE[None], cen[:, None] + dl * QUADRUPOLE[None]]
        return np.concatenate([emb.points(q, js).reshape(-1, 3) for q in parts])

    def stacked(self, F: np.ndarray, car: CarrierForces, js: np.ndarray) -> np.ndarray:
        """(10 len(js), 3) the carriers' forces in space of cilia ``js`` in the order of
        :meth:`positions` (one compiled gather: every evaluation of a carpet's flow stacks all its
        cilia's)."""
        js = np.ascontiguousarray(js, dtype=np.int64)
        out = np.empty((10 * js.size, 3))
        _stack(np.ascontiguousarray(F, dtype=float), car.f3, car.f6, js, self.cycles.embedding.axes, out)
        return out

    @cached_property
    def _tails(self) -> np.ndarray:
        """(K + 1,) for k' = 0 ... K the largest over cilia and moments of the sum of the
        amplitudes of harmonics k' and up of the moments' interpolant (a bound of what dropping
        them changes at any phase), relative to the moment's scale: S_j for F, S_j a_j for D,
        S_j a_j^2 for T (S_j the r.m.s. force, a_j the swept radius); cilia that make no flow
        left out."""
        c = self.cycles
        co = np.abs(c.moment_coef[:, MOMENT_ROWS])  # (N, 12, 2K - 1)
        K = (co.shape[2] + 1) // 2
        amp = co[:, :, :K].copy()
        amp[:, :, 1:] += co[:, :, K:]
        tail = np.concatenate([np.cumsum(amp[:, :, ::-1], axis=2)[:, :, ::-1], np.zeros(amp.shape[:2] + (1,))],
                              axis=2)  # (N, 12, K + 1): tail[..., k'] = sum_{k >= k'}
        S = c.F_rms * c.flutter
        a = c.radius
        scale = np.concatenate([np.repeat(S[:, None], 2, 1), np.repeat((S * a)[:, None], 4, 1),
                                np.repeat((S * a * a)[:, None], 6, 1)], axis=1)
        live = S > 0
        if not np.any(live):
            return np.zeros(K + 1)
        return (tail[live] / scale[live][:, :, None]).max(axis=(0, 1))

    def harmonics(self, tol: float) -> int:
        """The harmonics of the moments' interpolant an instant's carriers keep at ``tol``: the
        fewest whose dropped tail (:attr:`_tails`) stays below :data:`HARMONIC_TAIL` tol of
        each moment's scale, so that the velocity changes by at most about that fraction of the
        tolerance (every harmonic for tol = 0)."""
        t = self._tails
        ok = np.nonzero(t <= HARMONIC_TAIL * float(tol))[0]
        return int(ok[0]) if ok.size else t.size - 1

    def error_bound(self, targets: np.ndarray, thresholds: tuple, bounds: Bounds, car: CarrierForces,
                    mu: float) -> np.ndarray:
        """(M,) the rigorous bound of |u - u_resolved| at ``targets`` (M, 3): per target the
        Taylor bounds of the cilia summed cheaply at the orders the ``thresholds`` (R1, R2, R3)
        give them (:func:`tier_bound`), at the current moments (``car``)."""
        c1, c2, c3 = self.constants
        k3 = c3 / 6.0
        Q3 = bounds.Q3
        out = np.zeros(targets.shape[0])
        R1, R2, R3 = thresholds
        tier_bound(targets, self.cycles.centre3, self.cycles.radius, R1, R2, R3, c1 * car.nu1, bounds.b1,
                    0.5 * c2 * car.nu2, k3 * (Q3 + car.q3), k3 * (Q3 + car.q6), out)
        return out / (8 * math.pi * mu)
