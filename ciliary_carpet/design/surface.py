"""The design of standing carpets: (chi_N, psi) per cilium so that the surface flow meets a target.

A standing carpet (:mod:`~ciliary_carpet.carpet.geometry`) clamps cilium j at b_j on the substrate
z = 0 with the field along +z; its curvature chi_N_j >= 0 sets how far its mean thrust leans from
the normal, its azimuth psi_j which way. The target is the cycle-mean flow on the plane z = h
(``height``) above the substrate -- the *surface flow* -- at control points x_k (P, 2): its
direction t_k (angle targets, any direction: pumps, vortices, mixers, U-turns) or its velocity
U_k (velocity targets).

Design model
------------
By the rotation symmetry about e_z, cilium j's mean flow at x_k is

    u_kj(chi, psi) = R(psi) S(chi; R(psi)^T (x_k - b_j)),

with S the flow on the plane z = h of one cilium at the origin beating in the x-z plane
(psi = 0), R(psi) the rotation about e_z. :class:`SurfaceResponse` tabulates S once per (table,
h, viscosity, blob, wall): the resolved mean flow (every phase and arc-length sample of the
table) on a square grid of half-width :data:`REACH` and step :data:`STEP` at ``n_chi`` curvatures
over the flutter branch. The design chooses chi_N in [0, chi_hi], chi_hi the pumping maximum (the
curvature whose force-layer moment F_t c_z + D_zt, the flow a uniform carpet of it makes, is
largest: :func:`pumping_curvature`; beyond it a cilium leans further but pumps less). It is interpolated bilinearly in space and by the cubic spline in
chi (interpolation error: :data:`RESPONSE_ERROR`, tested), with exact derivatives, so that
dJ/dchi_j and dJ/dpsi_j are exact for the model.

Pairs farther than :data:`REACH` are summed as the cilium's mean force F and first moment D
about the fixed point p_j = b_j + :data:`PIVOT` e_z, carried by four point forces at the vertices
of a tetrahedron of radius :data:`PIVOT_DELTA` about p_j (f_m = F/4 + 3/(4 delta) D^T u_m):
the geometry does not move with (chi, psi), so the far sum is one fixed linear operator of the
forces and its adjoint is the sum with sources and targets swapped (the regularised Blake tensor
is reciprocal). The near pairs' carriers are subtracted by a ranged sum.

Defect correction, never worse, error bars: as :mod:`ciliary_carpet.design.inverse`. After each
solve the full model (:meth:`Carpet.evaluate` of the :class:`CycleMean`, levels of detail with
rigorous bounds) is evaluated at the control points and the next solve minimises the objective
of ``model + (full - model)`` at the pass's layout; the best layout by J on the full model over
the local layout and the passes is returned; the residual's error bar is the rms of
``arcsin(b_k / |u_k|)`` from the check's bound, made at most half the threshold by a final check at
a tighter tolerance.

Objective (angle targets), P control points, u_k the surface flow's in-plane part::

    J = 1/P sum_k [(1 - uhat_k . t_k) + (w/2) max(0, 1 - (u_k . t_k) / (sigma s_k))^2]
        + mu/E sum_{edges} |g_i - g_j|^2 / g_max^2 + lambda/N sum_j |g_j - g0_j|^2 / g_max^2,

with s_k the speed the cilia within :data:`REACH` of x_k make along t_k when they all pump along
it at chi_hi (the speed floor's reference), g_j = m(chi_j) e_psi_j the cilium's pumping vector
(m the force-layer moment: the smoothness and the regulariser act on it, so psi's periodicity is
respected and a cilium near chi = 0, whose psi does not matter, is not held to its neighbours'
psi), the edges the Delaunay neighbours of the bases. Velocity targets:
``J = 1/2 sum |u_k - U_k|^2 / sum |U_k|^2`` + the regularisers. L-BFGS-B over chi_j / chi_hi in [0, 1] and psi_j (free).
"""
from __future__ import annotations

import logging
import math
import time as _time
import warnings
from dataclasses import dataclass, replace

import numpy as np
from numba import njit, prange
from scipy.interpolate import CubicSpline
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from single_cilium.table import ThrustTable

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.design.moments import cycle_moments
from ciliary_carpet.design.model import GOOD_ENOUGH
from ciliary_carpet.design.result import Design
from ciliary_carpet.design.errors import TargetError
from ciliary_carpet.stokes import stokeslet_velocity, stokeslet_velocity_ranges

logger = logging.getLogger(__name__)

__all__ = ["SurfaceResponse", "SurfaceModel", "design_surface", "pumping_curvature", "surface_response", "REACH",
           "STEP", "PIVOT", "PIVOT_DELTA", "HEIGHT", "RESPONSE_ERROR"]

HEIGHT = 1.5
"""Default height h of the surface-flow plane above the substrate [L]: above the tips (a standing
cilium reaches at most L)."""
REACH = 6.0
"""Half-width [L] of the tabulated single-cilium response: pairs closer than this (in the plane)
are interpolated from it, farther ones summed as carriers (their error there: about (0.7 / 6)^2
of the pair's dipole flow, which the defect correction carries)."""
STEP = 0.1
"""Grid step [L] of the tabulated response (bilinear: error about STEP^2 / 8 times its second
derivative; :data:`RESPONSE_ERROR`)."""
PIVOT = 0.5
"""Height [L] of the fixed point p_j the far carriers expand about."""
PIVOT_DELTA = 0.25
"""Radius [L] of the far carriers' tetrahedron about p_j (its lowest vertex at z = 0.42 L)."""
RESPONSE_ERROR = 1.5e-2
"""Bound on the error of the interpolated response against the resolved single-cilium mean flow
at random points (within :data:`REACH`) and curvatures, relative to the largest flow there
(tests/test_surface_design.py). The bilinear interpolation in space dominates it: it falls as
:data:`STEP` squared. The design model as a whole is within 1 % of the full model's flow on a
6 x 6 carpet at random (chi, psi) (tested); what is left is in the defect correction."""
_N_CHI = 49
"""Curvatures of the tabulated response, uniform over the flutter branch [0, cutoff] (the design
uses [0, chi_hi]; the tolerance study's perturbed layouts may leave it)."""

TETRA = np.array([[0.0, 0.0, 1.0], [math.sqrt(8.0 / 9.0), 0.0, -1.0 / 3.0],
                  [-math.sqrt(2.0 / 9.0), math.sqrt(2.0 / 3.0), -1.0 / 3.0],
                  [-math.sqrt(2.0 / 9.0), -math.sqrt(2.0 / 3.0), -1.0 / 3.0]])
"""Unit vertices of the far carriers' tetrahedron (sum u u^T = 4/3 I)."""


def pumping_curvature(table: ThrustTable) -> tuple[float, CubicSpline]:
    """(chi_hi, m): the curvature in [0, cutoff] at which a standing cilium's force-layer moment
    m(chi) = F_t c_z + D_zt (its tangential force times its centre's height plus the first moment:
    the plug flow n m / mu of a uniform carpet of it) is largest, and m as a spline of chi."""
    mom = cycle_moments(table)
    chi = np.linspace(0.0, mom.cutoff, 401)
    v = mom(chi)
    m = v["F"][:, 0] * v["offset"][:, 1] + v["D"][:, 1, 0]
    k = int(np.argmax(m))
    return float(chi[k]), CubicSpline(chi, m)


@dataclass(frozen=True, eq=False)
class SurfaceResponse:
    """The mean flow on the plane z = ``height`` of one standing cilium at the origin beating in
    the x-z plane (psi = 0), tabulated (module docstring): ``values`` (n_chi, n, n, 3) on the grid
    ``x0 + STEP * i`` (both axes), ``slopes`` their chi derivatives (the spline's), ``chi`` (n_chi,)
    uniform on the flutter branch [0, cutoff]; ``chi_hi`` the pumping maximum."""

    chi: np.ndarray
    values: np.ndarray
    slopes: np.ndarray
    x0: float
    step: float
    height: float
    chi_hi: float
    seconds: float

    @staticmethod
    def build(carpet: Carpet, height: float, n_chi: int = _N_CHI, reach: float = REACH, step: float = STEP
              ) -> "SurfaceResponse":
        """Tabulate the response for the table, viscosity, blob and wall of the standing ``carpet``."""
        t0 = _time.perf_counter()
        chi_hi, _ = pumping_curvature(carpet.table)
        chi = np.linspace(0.0, cycle_moments(carpet.table).cutoff, int(n_chi))
        n = int(round(2 * reach / step)) + 3
        n += 1 - n % 2  # odd: the grid is symmetric about y = 0 and holds it
        x0 = -step * (n - 1) / 2
        g = x0 + step * np.arange(n)
        h = (n - 1) // 2  # the row y = 0
        gx, gy = np.meshgrid(g, g[h:], indexing="ij")
        pts = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, float(height))])
        vals = np.empty((chi.size, n, n, 3))
        for i, c in enumerate(chi):
            one = Carpet(np.zeros((1, 2)), c, carpet.table, wall=carpet.wall, viscosity=carpet.mu,
                         blob=carpet.blob, geometry="standing")
            half = one.evaluate(pts, CycleMean(), 0.0).velocity.reshape(n, n - h, 3)
            # the cilium beats in the plane y = 0: its mean flow is mirror symmetric about it,
            # u(x, -y, z) = (u_x, -u_y, u_z)(x, y, z), so half the grid is evaluated
            vals[i, :, h:] = half
            vals[i, :, :h] = half[:, :0:-1] * np.array([1.0, -1.0, 1.0])
        sl = CubicSpline(chi, vals, axis=0)(chi, 1)
        return SurfaceResponse(chi=chi, values=np.ascontiguousarray(vals), slopes=np.ascontiguousarray(sl),
                               x0=float(x0), step=float(step), height=float(height), chi_hi=chi_hi,
                               seconds=_time.perf_counter() - t0)


_RESPONSES: dict = {}


def surface_response(carpet: Carpet, height: float) -> SurfaceResponse:
    """The :class:`SurfaceResponse` of ``carpet`` at ``height``, cached per (table, height,
    viscosity, blob, wall)."""
    key = (id(carpet.table), float(height), carpet.mu, carpet.blob, carpet.wall)
    hit = _RESPONSES.get(key)
    if hit is None or hit[0] is not carpet.table:
        if len(_RESPONSES) > 8:
            _RESPONSES.clear()
        _RESPONSES[key] = hit = (carpet.table, SurfaceResponse.build(carpet, height))
    return hit[1]


@njit(cache=True, nogil=True, parallel=True)
def _near(X, bases, pk, pj, chi, cp, sp, V, dV, x0, h, c0, hc, u, du_chi, du_psi):  # pragma: no cover - compiled
    """Per pair q (control point pk[q], cilium pj[q]) the interpolated response u[q] (3,) of the
    cilium at curvature chi[q], azimuth (cp[q], sp[q]) = (cos, sin) psi, and its derivatives in chi
    and psi (module docstring): bilinear in space, cubic Hermite in chi (values V, slopes dV)."""
    nc, n = V.shape[0], V.shape[1]
    for q in prange(pk.shape[0]):
        k = pk[q]
        j = pj[q]
        rx = X[k, 0] - bases[j, 0]
        ry = X[k, 1] - bases[j, 1]
        c = cp[q]
        s = sp[q]
        ax = c * rx + s * ry
        ay = -s * rx + c * ry
        gx = (ax - x0) / h
        gy = (ay - x0) / h
        ix = min(max(int(math.floor(gx)), 0), n - 2)
        iy = min(max(int(math.floor(gy)), 0), n - 2)
        tx = gx - ix
        ty = gy - iy
        gc = (chi[q] - c0) / hc
        ic = min(max(int(math.floor(gc)), 0), nc - 2)
        t = min(max(gc - ic, 0.0), 1.0)  # beyond the branch: its end (a still cilium makes no flow)
        t2 = t * t
        t3 = t2 * t
        h00 = 2 * t3 - 3 * t2 + 1
        h10 = (t3 - 2 * t2 + t) * hc
        h01 = -2 * t3 + 3 * t2
        h11 = (t3 - t2) * hc
        d00 = (6 * t2 - 6 * t) / hc
        d10 = 3 * t2 - 4 * t + 1
        d01 = (-6 * t2 + 6 * t) / hc
        d11 = 3 * t2 - 2 * t
        S = np.empty(3)
        Sc = np.empty(3)
        Sx = np.empty(3)
        Sy = np.empty(3)
        for a in range(3):
            v = np.empty(4)
            w = np.empty(4)
            for m in range(4):
                i = ix + (m & 1)
                jj = iy + (m >> 1)
                v[m] = h00 * V[ic, i, jj, a] + h10 * dV[ic, i, jj, a] + h01 * V[ic + 1, i, jj, a] \
                    + h11 * dV[ic + 1, i, jj, a]
                w[m] = d00 * V[ic, i, jj, a] + d10 * dV[ic, i, jj, a] + d01 * V[ic + 1, i, jj, a] \
                    + d11 * dV[ic + 1, i, jj, a]
            S[a] = (1 - tx) * (1 - ty) * v[0] + tx * (1 - ty) * v[1] + (1 - tx) * ty * v[2] + tx * ty * v[3]
            Sc[a] = (1 - tx) * (1 - ty) * w[0] + tx * (1 - ty) * w[1] + (1 - tx) * ty * w[2] + tx * ty * w[3]
            Sx[a] = ((1 - ty) * (v[1] - v[0]) + ty * (v[3] - v[2])) / h
            Sy[a] = ((1 - tx) * (v[2] - v[0]) + tx * (v[3] - v[1])) / h
        u[q, 0] = c * S[0] - s * S[1]
        u[q, 1] = s * S[0] + c * S[1]
        u[q, 2] = S[2]
        du_chi[q, 0] = c * Sc[0] - s * Sc[1]
        du_chi[q, 1] = s * Sc[0] + c * Sc[1]
        du_chi[q, 2] = Sc[2]
        # d/dpsi [R S(R^T r)] = R' S + R (grad S . (ay, -ax))
        g0 = Sx[0] * ay - Sy[0] * ax
        g1 = Sx[1] * ay - Sy[1] * ax
        g2 = Sx[2] * ay - Sy[2] * ax
        du_psi[q, 0] = -s * S[0] - c * S[1] + c * g0 - s * g1
        du_psi[q, 1] = c * S[0] - s * S[1] + s * g0 + c * g1
        du_psi[q, 2] = g2


class SurfaceModel:
    """The design model of a standing ``carpet``'s surface flow at control points ``X`` (P, 2) on
    the plane z = ``height`` (module docstring): :meth:`flow` (P, 3) at (chi, psi) and
    :meth:`pullback` of a weight w (P, 3) to (dJ/dchi, dJ/dpsi) (N,) each."""

    def __init__(self, carpet: Carpet, X: np.ndarray, height: float):
        self.carpet, self.height = carpet, float(height)
        self.X = np.ascontiguousarray(X, dtype=float)
        self.X3 = np.column_stack([self.X, np.full(self.X.shape[0], self.height)])
        self.resp = surface_response(carpet, self.height)
        self.mom = cycle_moments(carpet.table)
        b = carpet.bases
        n, P = carpet.n, self.X.shape[0]
        lim = REACH - 2 * STEP
        lists = cKDTree(b).query_ball_point(self.X, lim)
        self.pk = np.repeat(np.arange(P, dtype=np.int64), [len(x) for x in lists])
        self.pj = np.concatenate([np.asarray(x, dtype=np.int64) for x in lists]) if P else np.zeros(0, np.int64)
        # the far carriers: fixed points about p_j = b_j + PIVOT e_z
        p = np.column_stack([b, np.full(n, PIVOT)])
        self.pos = np.ascontiguousarray((p[:, None, :] + PIVOT_DELTA * TETRA[None]).reshape(-1, 3))
        # ranges: per control point the carriers of its near cilia; per carrier its near control points
        order = np.argsort(self.pj, kind="stable")
        self.ptr = np.zeros(P + 1, np.int64)
        np.cumsum(np.bincount(self.pk, minlength=P), out=self.ptr[1:])
        self.rng = np.column_stack([4 * self.pj, 4 * self.pj + 4]).astype(np.int64)
        cnt = np.bincount(self.pj, minlength=n)
        self.ptr_t = np.zeros(4 * n + 1, np.int64)
        np.cumsum(np.repeat(cnt, 4), out=self.ptr_t[1:])
        ks = self.pk[order]
        starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        rows = [np.column_stack([ks[starts[j]:starts[j] + cnt[j]], ks[starts[j]:starts[j] + cnt[j]] + 1])
                for j in range(n) for _ in range(4)]
        self.rng_t = np.ascontiguousarray(np.concatenate(rows) if rows else np.zeros((0, 2)), dtype=np.int64)
        self.kernel, self.mu = carpet.kernel, carpet.mu
        self.evaluations = 0

    @property
    def pairs(self) -> int:
        """Near (interpolated) pairs."""
        return int(self.pk.size)

    # ---------------------------------------------------------------- the far carriers
    def _moments(self, chi, nu: int):
        v = self.mom(chi, nu)
        return v["F"], v["D"], v["offset"]

    def carrier_forces(self, chi: np.ndarray, psi: np.ndarray, grad: bool = False):
        """(N, 4, 3) the far carriers' forces (module docstring); with ``grad`` also their
        derivatives in chi and psi (N, 4, 3) each."""
        F2, D2c, o = self._moments(chi, 0)
        piv = np.array([0.0, PIVOT])
        D2 = D2c + (o - piv)[:, :, None] * F2[:, None, :]
        c, s = np.cos(psi), np.sin(psi)
        E = np.zeros((chi.size, 3, 2))
        E[:, 0, 0], E[:, 1, 0], E[:, 2, 1] = c, s, 1.0

        def forces(E_F, E_D, F2_, D2_):
            F3 = np.einsum("nqa,na->nq", E_F, F2_)
            D3 = np.einsum("nqa,nab,nrb->nqr", E_D[0], D2_, E_D[1])
            return F3[:, None, :] / 4.0 + 0.75 / PIVOT_DELTA * np.einsum("nqr,mq->nmr", D3, TETRA)

        f = forces(E, (E, E), F2, D2)
        if not grad:
            return f
        F2d, D2cd, od = self._moments(chi, 1)
        D2d = D2cd + od[:, :, None] * F2[:, None, :] + (o - piv)[:, :, None] * F2d[:, None, :]
        f_chi = forces(E, (E, E), F2d, D2d)
        Ep = np.zeros_like(E)
        Ep[:, 0, 0], Ep[:, 1, 0] = -s, c
        f_psi = forces(Ep, (Ep, E), F2, D2) + forces(np.zeros_like(E), (E, Ep), F2, D2)
        return f, f_chi, f_psi

    # ---------------------------------------------------------------- flow and pullback
    def flow(self, chi: np.ndarray, psi: np.ndarray) -> tuple[np.ndarray, tuple]:
        """(P, 3) the model's surface flow at (chi, psi), and what :meth:`pullback` needs."""
        self.evaluations += 1
        f, f_chi, f_psi = self.carrier_forces(chi, psi, grad=True)
        fl = np.ascontiguousarray(f.reshape(-1, 3))
        u = stokeslet_velocity(self.X3, self.pos, fl, self.mu, kernel=self.kernel, backend=self.carpet.backend)
        if self.pairs:
            u -= stokeslet_velocity_ranges(self.X3, self.pos, fl, self.ptr, self.rng, self.mu, kernel=self.kernel,
                                           backend=self.carpet.backend)
            cs = np.cos(psi[self.pj]), np.sin(psi[self.pj])
            un, uc, up = self._near_pairs(chi[self.pj], cs)
            u += np.stack([np.bincount(self.pk, un[:, a], minlength=self.X.shape[0]) for a in range(3)], axis=1)
        else:
            uc = up = np.zeros((0, 3))
        return u, (f_chi, f_psi, uc, up)

    def _near_pairs(self, chi_p, cs):
        r = self.resp
        q = chi_p.size
        u, uc, up = np.empty((q, 3)), np.empty((q, 3)), np.empty((q, 3))
        if q:
            _near(self.X, self.carpet.bases, self.pk, self.pj, np.ascontiguousarray(chi_p),
                  np.ascontiguousarray(cs[0]), np.ascontiguousarray(cs[1]), r.values, r.slopes, r.x0, r.step,
                  float(r.chi[0]), float(r.chi[1] - r.chi[0]), u, uc, up)
        return u, uc, up

    def pullback(self, w: np.ndarray, aux: tuple) -> tuple[np.ndarray, np.ndarray]:
        """(dJ/dchi, dJ/dpsi) (N,) each for dJ/du = ``w`` (P, 3) at the layout of :meth:`flow`."""
        f_chi, f_psi, uc, up = aux
        n = self.carpet.n
        w = np.ascontiguousarray(w, dtype=float)
        a = stokeslet_velocity(self.pos, self.X3, w, self.mu, kernel=self.kernel, backend=self.carpet.backend)
        if self.pairs:
            a -= stokeslet_velocity_ranges(self.pos, self.X3, w, self.ptr_t, self.rng_t, self.mu, kernel=self.kernel,
                                           backend=self.carpet.backend)
        a = a.reshape(n, 4, 3)
        g_chi = np.einsum("nmq,nmq->n", a, f_chi)
        g_psi = np.einsum("nmq,nmq->n", a, f_psi)
        if self.pairs:
            wk = w[self.pk]
            g_chi += np.bincount(self.pj, np.einsum("qa,qa->q", wk, uc), minlength=n)
            g_psi += np.bincount(self.pj, np.einsum("qa,qa->q", wk, up), minlength=n)
        return g_chi, g_psi

    def reference_speed(self, directions: np.ndarray) -> np.ndarray:
        """(P,) the speed along ``directions`` (P, 2) (unit) that the cilia within :data:`REACH`
        of each control point make there when they all pump along it at chi_hi (the speed
        floor's reference)."""
        th = np.arctan2(directions[:, 1], directions[:, 0])
        chi_p = np.full(self.pj.size, self.resp.chi_hi)
        un, _, _ = self._near_pairs(chi_p, (np.cos(th[self.pk]), np.sin(th[self.pk])))
        u = np.stack([np.bincount(self.pk, un[:, a], minlength=self.X.shape[0]) for a in range(2)], axis=1)
        return np.einsum("pa,pa->p", u, directions)


def design_surface(carpet: Carpet, control, *, height: float = HEIGHT, directions=None, velocities=None,
                   tol: float = 1e-3, check_tol: float | None = None, speed_floor: float = 0.3,
                   floor_weight: float = 1.0, regularization: float = 1e-3, smoothness: float = 0.0,
                   outer: int = 3, maxiter: int = 400, ftol: float = 1e-5, threshold: float | None = None,
                   robust_sigma: float = 0.0, robust_sigma_psi: float = 0.0, robust_samples: int = 16,
                   robust_seed: int = 12345, strict: bool = True) -> Design:
    """Choose (chi_N, psi) per cilium so that a standing carpet's surface flow meets a target.

    The cilia of ``carpet`` keep their bases, phases, table and wall; the design chooses their
    curvatures and azimuths so that the mean flow on the plane z = ``height`` at ``control`` runs
    along ``directions`` or equals ``velocities``. Each cilium starts pumping along the direction
    asked at the control point nearest its base, at chi_hi (:func:`pumping_curvature`): the
    *local* layout (velocity targets: along U there). The module docstring gives the model and the
    objective.

    Parameters
    ----------
    carpet : Carpet
        A standing carpet (``geometry = "standing"``).
    control : array_like, shape (P, 2)
        The control points on the plane z = ``height``.
    height : float
        Height of the surface-flow plane above the substrate [L], > 0.
    directions : array_like, shape (P,), optional
        Target directions [rad, anticlockwise from +x] (angle targets).
    velocities : array_like, shape (P, 2), optional
        Target velocities [L/tau] (velocity targets); exactly one of ``directions`` and
        ``velocities`` is given.
    tol : float
        Accuracy asked of the design; the checks default to max(tol, 1e-2).
    check_tol : float, optional
        Tolerance of the full-model checks after the passes.
    speed_floor, floor_weight, regularization, smoothness : float
        The objective's sigma, w, lambda and mu (module docstring), each >= 0.
    outer : int
        Most passes of defect correction.
    maxiter : int
        Most L-BFGS-B iterations per pass.
    ftol : float
        A pass stops when an iteration lowers J by less than ``ftol`` times its value at the pass's
        start.
    threshold : float, optional
        Acceptance threshold of the rms residual: a pass stops once the model's rms residual is
        :data:`~ciliary_carpet.design.model.GOOD_ENOUGH` of it, and the final check's error bar
        is made at most half of it.
    robust_sigma, robust_sigma_psi : float
        Relative curvature error sigma and azimuth error sigma_psi [rad] of fabrication. Either
        > 0: the design minimises the expected objective under errors chi_j (1 + sigma eps_j),
        psi_j + sigma_psi eps'_j instead of the nominal one -- the flow terms averaged over
        ``robust_samples`` fixed samples (seed ``robust_seed``), each the design model plus the
        pass's defect, the regularisers at the nominal layout -- and compares the passes' layouts
        by that expected J (the full model's defect at each).
    robust_samples : int
        Fabrication samples of the robust objective, >= 1.
    robust_seed : int
        Seed of those samples.
    strict : bool
        Target velocities faster than 1.5 times what the cilia around them make pumping along
        them are a TargetError; without ``strict`` a warning lists them and the design returns the
        closest flow the cilia make (its residual says how far).

    Returns
    -------
    Design
        With ``azimuth`` (N,) and ``height``; its ``carpet`` is the designed standing carpet.

    Raises
    ------
    ValueError
        A planar carpet, or a setting out of its range.
    TargetError
        Control points or targets that are not finite or not of their shapes; too fast velocities
        with ``strict``.
    """
    clock = _time.perf_counter()
    X, kind, aim = _checked_inputs(carpet, control, height, directions, velocities, speed_floor=speed_floor,
                                   floor_weight=floor_weight, regularization=regularization, smoothness=smoothness,
                                   threshold=threshold, robust_sigma=robust_sigma, robust_sigma_psi=robust_sigma_psi,
                                   robust_samples=robust_samples)
    check_tol = max(tol, 1e-2) if check_tol is None else float(check_tol)
    eps = _fabrication_samples(carpet.n, robust_sigma, robust_sigma_psi, robust_samples, robust_seed)
    problem = _SurfaceProblem(carpet, X, height, kind, aim, eps, strict=strict, speed_floor=speed_floor,
                              floor_weight=floor_weight, regularization=regularization, smoothness=smoothness)
    local = _local_layout(problem, check_tol)
    best, status, msg = _passes(problem, local, check_tol=check_tol, outer=outer, maxiter=maxiter, ftol=ftol,
                                threshold=threshold)
    sample, err, final_tol = _final_check(problem, best, threshold, check_tol)
    return _result(problem, best, local, sample, err, final_tol, threshold, status, msg, clock)


def _checked_inputs(carpet: Carpet, control, height, directions, velocities, *, speed_floor, floor_weight,
                    regularization, smoothness, threshold, robust_sigma, robust_sigma_psi, robust_samples
                    ) -> tuple[np.ndarray, str, np.ndarray]:
    """Check :func:`design_surface`'s arguments and read its target.

    Parameters
    ----------
    carpet, control, height, directions, velocities, speed_floor, floor_weight, regularization, \
smoothness, threshold, robust_sigma, robust_sigma_psi, robust_samples
        As :func:`design_surface`.

    Returns
    -------
    X : numpy.ndarray, shape (P, 2)
        The control points.
    kind : {"angle", "velocity"}
        The target's kind.
    aim : numpy.ndarray
        The target: directions (P,) [rad] or velocities (P, 2).

    Raises
    ------
    ValueError, TargetError
        As :func:`design_surface`.
    """
    if carpet.geometry != "standing":
        raise ValueError("design_surface designs standing carpets (geometry = 'standing'); a planar carpet's "
                         "design is design_layout")
    if not (math.isfinite(float(height)) and float(height) > 0):
        raise ValueError(f"height must be a positive number of L above the substrate, got {height!r}")
    X = np.asarray(control, dtype=float)
    if X.ndim != 2 or X.shape[1] != 2 or X.shape[0] < 1 or not np.all(np.isfinite(X)):
        raise TargetError(f"control points must be finite, shape (P, 2), got shape {X.shape}")
    if (directions is None) == (velocities is None):
        raise ValueError("give exactly one of directions (P,) or velocities (P, 2)")
    for name, v in (("speed_floor", speed_floor), ("floor_weight", floor_weight),
                    ("regularization", regularization), ("smoothness", smoothness)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    if threshold is not None and not (math.isfinite(float(threshold)) and float(threshold) > 0):
        raise ValueError(f"threshold must be a finite number > 0, got {threshold!r}")
    for name, v in (("robust_sigma", robust_sigma), ("robust_sigma_psi", robust_sigma_psi)):
        if not (math.isfinite(float(v)) and float(v) >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    robust = float(robust_sigma) > 0 or float(robust_sigma_psi) > 0
    if robust and (isinstance(robust_samples, bool) or not isinstance(robust_samples, (int, np.integer))
                   or robust_samples < 1):
        raise ValueError(f"robust_samples must be an integer >= 1, got {robust_samples!r}")
    if directions is not None:
        A = np.broadcast_to(np.asarray(directions, dtype=float), (X.shape[0],)).copy()
        if not np.all(np.isfinite(A)):
            raise TargetError("target directions contain NaN or inf")
        return X, "angle", A
    U = np.asarray(velocities, dtype=float)
    if U.shape != X.shape or not np.all(np.isfinite(U)):
        raise TargetError(f"velocities must be finite, shape {X.shape}, got {U.shape}")
    return X, "velocity", U


def _fabrication_samples(n: int, sigma: float, sigma_psi: float, samples: int, seed: int
                         ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The fixed fabrication errors of the robust objective.

    Parameters
    ----------
    n : int
        Cilia.
    sigma, sigma_psi, samples, seed
        :func:`design_surface`'s ``robust_sigma``, ``robust_sigma_psi``, ``robust_samples``,
        ``robust_seed``.

    Returns
    -------
    list of (numpy.ndarray, numpy.ndarray)
        Per sample the curvature factors 1 + sigma eps_j and the azimuth offsets sigma_psi eps'_j
        (n,) each; empty when both sigmas are 0 (the nominal design).
    """
    robust = float(sigma) > 0 or float(sigma_psi) > 0
    rs = np.random.default_rng(seed)
    return [(1.0 + float(sigma) * rs.standard_normal(n), float(sigma_psi) * rs.standard_normal(n))
            for _ in range(int(samples) if robust else 0)]


@dataclass(frozen=True, eq=False)
class _Layout:
    """A checked layout: its (chi, psi) (N,) each, J by which layouts are compared
    (:meth:`_SurfaceProblem.judged`), its carpet and the full model's sample at the control
    points, and which layout it is ("local" or "pass k")."""

    J: float
    chi: np.ndarray
    psi: np.ndarray
    carpet: Carpet
    sample: object
    returned: str


class _SurfaceProblem:
    """The design problem of :func:`design_surface`: the design model, the target, the objective
    and the full-model checks of one design.

    Parameters
    ----------
    carpet : Carpet
        The standing carpet.
    X : numpy.ndarray, shape (P, 2)
        The control points.
    height : float
        Height of the surface-flow plane [L].
    kind : {"angle", "velocity"}
        The target's kind.
    aim : numpy.ndarray
        Target directions (P,) [rad] or velocities (P, 2).
    eps : list
        The fabrication samples (:func:`_fabrication_samples`); empty: the nominal objective.
    strict : bool
        Too fast target velocities are a TargetError (else a warning).
    speed_floor, floor_weight, regularization, smoothness : float
        The objective's weights (module docstring).

    Attributes
    ----------
    model : SurfaceModel
        The design model at the control points.
    chi_hi : float
        The pumping maximum, the largest curvature designed.
    m_of : scipy.interpolate.CubicSpline
        The force-layer moment m(chi).
    g_max : float
        m(chi_hi), the scale of the pumping vectors g_j.
    T : numpy.ndarray, shape (P, 2)
        Unit target directions (angle targets) or the target velocities.
    s_ref : numpy.ndarray or None
        The speed floor's reference speeds (P,) (angle targets).
    U, u2 : numpy.ndarray, float or None
        The target velocities and sum |U_k|^2 (velocity targets).
    chi0, psi0 : numpy.ndarray
        The local layout (N,) each.
    work : dict
        The design's work, counted as it goes (:class:`~ciliary_carpet.design.result.Design`).
    """

    def __init__(self, carpet: Carpet, X: np.ndarray, height: float, kind: str, aim: np.ndarray, eps: list, *,
                 strict: bool, speed_floor: float, floor_weight: float, regularization: float, smoothness: float):
        self.carpet, self.X, self.height, self.kind, self.eps = carpet, X, height, kind, eps
        self.robust = bool(eps)
        self.speed_floor, self.floor_weight = speed_floor, floor_weight
        self.regularization, self.smoothness = regularization, smoothness
        self.P, self.N = X.shape[0], carpet.n
        self.model = SurfaceModel(carpet, X, height)
        self.chi_hi = self.model.resp.chi_hi
        _, self.m_of = pumping_curvature(carpet.table)
        self.g_max = float(self.m_of(self.chi_hi))
        near = cKDTree(X).query(carpet.bases)[1]
        self.s_ref = self.U = self.u2 = None
        if kind == "angle":
            self.psi0 = self._angle_target(aim, near)
        else:
            self.psi0 = self._velocity_target(aim, near, strict)
        self.chi0 = np.full(self.N, self.chi_hi)
        self.g0 = np.column_stack([np.cos(self.psi0), np.sin(self.psi0)]) * float(self.m_of(self.chi_hi))
        self.edges = layout.neighbours(carpet.bases)
        self.work = {"iterations": 0, "evaluations": 0, "checks": 0, "pairs_near": self.model.pairs,
                     "response_seconds": self.model.resp.seconds, "seconds_checks": 0.0}

    # ---------------------------------------------------------------- the target
    def _angle_target(self, A: np.ndarray, near: np.ndarray) -> np.ndarray:
        """Set the unit directions ``T`` and the speed floor's reference ``s_ref``.

        Parameters
        ----------
        A : numpy.ndarray, shape (P,)
            Target directions [rad].
        near : numpy.ndarray, shape (N,)
            Per cilium the control point nearest its base.

        Returns
        -------
        numpy.ndarray, shape (N,)
            The local layout's azimuths: the direction at each cilium's nearest control point.
        """
        self.T = np.column_stack([np.cos(A), np.sin(A)])
        self.s_ref = np.maximum(self.model.reference_speed(self.T), 1e-300)
        return A[near]

    def _velocity_target(self, U: np.ndarray, near: np.ndarray, strict: bool) -> np.ndarray:
        """Set the target velocities ``U`` (= ``T``) and their scale ``u2``, having checked that the
        cilia can pump them.

        Parameters
        ----------
        U : numpy.ndarray, shape (P, 2)
            Target velocities.
        near : numpy.ndarray, shape (N,)
            Per cilium the control point nearest its base.
        strict : bool
            Velocities faster than 1.5 times what the cilia around them make pumping along them
            are a TargetError; else a UserWarning names them.

        Returns
        -------
        numpy.ndarray, shape (N,)
            The local layout's azimuths: along U at each cilium's nearest control point.
        """
        X = self.X
        self.U = self.T = U
        th = np.arctan2(U[:, 1], U[:, 0])
        top = self.model.reference_speed(np.column_stack([np.cos(th), np.sin(th)]))
        bad = np.nonzero(np.linalg.norm(U, axis=1) > 1.5 * np.maximum(top, 0.0))[0]
        if bad.size:
            lst = "; ".join(f"#{k} at ({X[k, 0]:.3g}, {X[k, 1]:.3g}) asks {np.linalg.norm(U[k]):.3g} L/tau, the cilia "
                            f"around it make at most about {max(top[k], 0):.3g}" for k in bad[:5])
            msg = f"{bad.size} target velocities are faster than the cilia can pump there: {lst}"
            if strict:
                raise TargetError(msg + " (with [target] strict = false the design returns the closest flow)")
            # stacklevel 4: the caller of design_surface (through __init__ and this method)
            warnings.warn(msg + "; designing for the closest flow the cilia make (strict = false)", UserWarning,
                          stacklevel=4)
        self.u2 = float(np.sum(U * U))
        return th[near]

    # ---------------------------------------------------------------- the objective
    def g_of(self, chi: np.ndarray, psi: np.ndarray, nu: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """The pumping vectors g_j = m(chi_j) e_psi_j.

        Parameters
        ----------
        chi, psi : numpy.ndarray, shape (N,)
            The layout.
        nu : int
            Derivative order of m in chi.

        Returns
        -------
        g : numpy.ndarray, shape (N, 2)
            The vectors (of m's ``nu``-th derivative).
        m : numpy.ndarray, shape (N,)
            m(chi) (its ``nu``-th derivative).
        """
        m = self.m_of(chi, nu)
        return m[:, None] * np.column_stack([np.cos(psi), np.sin(psi)]), m

    def objective(self, u: np.ndarray, chi: np.ndarray, psi: np.ndarray, grad: bool):
        """The objective J of the flow ``u`` at the layout (chi, psi).

        Parameters
        ----------
        u : numpy.ndarray, shape (P, 3)
            The surface flow at the control points.
        chi, psi : numpy.ndarray, shape (N,)
            The layout.
        grad : bool
            Whether the derivatives are wanted (else zero).

        Returns
        -------
        J : float
            The flow terms plus the regularisers.
        dJ : numpy.ndarray, shape (P, 3)
            dJ/du.
        gc, gp : numpy.ndarray, shape (N,)
            The regularisers' dJ/dchi and dJ/dpsi.
        """
        J, dJ = self.flow_objective(u, grad)
        Jr, gc, gp = self.regularisers(chi, psi, grad)
        return J + Jr, dJ, gc, gp

    def flow_objective(self, u: np.ndarray, grad: bool) -> tuple[float, np.ndarray]:
        """The flow terms of J (module docstring).

        Parameters
        ----------
        u : numpy.ndarray, shape (P, 3)
            The surface flow at the control points.
        grad : bool
            Whether dJ/du is wanted (angle targets; velocity targets always give it).

        Returns
        -------
        J : float
            The flow terms.
        dJ : numpy.ndarray, shape (P, 3)
            dJ/du (zero without ``grad`` for angle targets).
        """
        P, T = self.P, self.T
        speed_floor, floor_weight = self.speed_floor, self.floor_weight
        uxy = u[:, :2]
        if self.kind == "angle":
            sp = np.linalg.norm(uxy, axis=1)
            spc = np.maximum(sp, 1e-300)
            cosang = np.einsum("pa,pa->p", uxy, T) / spc
            along = np.einsum("pa,pa->p", uxy, T)
            gap = np.maximum(0.0, 1.0 - along / (speed_floor * self.s_ref)) if speed_floor > 0 else np.zeros(P)
            J = float(np.mean(1.0 - cosang) + 0.5 * floor_weight * np.mean(gap ** 2))
            dJ = np.zeros((P, 3))
            if grad:
                # d(1 - uhat.t)/du = -(t - cos uhat)/|u|
                uh = uxy / spc[:, None]
                dJ[:, :2] = -(T - cosang[:, None] * uh) / spc[:, None] / P
                if speed_floor > 0:
                    dJ[:, :2] += (-floor_weight * gap / (speed_floor * self.s_ref))[:, None] * T / P
        else:
            d = uxy - self.U
            J = float(0.5 * np.sum(d * d) / self.u2)
            dJ = np.zeros((P, 3))
            dJ[:, :2] = d / self.u2
        return J, dJ

    def regularisers(self, chi: np.ndarray, psi: np.ndarray, grad: bool) -> tuple[float, np.ndarray, np.ndarray]:
        """The regularisers of J: the pull to the local layout and the smoothness (module
        docstring).

        Parameters
        ----------
        chi, psi : numpy.ndarray, shape (N,)
            The layout.
        grad : bool
            Whether the derivatives are wanted (else zero).

        Returns
        -------
        J : float
            The regularisers' terms.
        gc, gp : numpy.ndarray, shape (N,)
            Their dJ/dchi and dJ/dpsi.
        """
        N, g_max, edges = self.N, self.g_max, self.edges
        regularization, smoothness = self.regularization, self.smoothness
        J = 0.0
        g, m = self.g_of(chi, psi)
        gc = np.zeros(N)
        gp = np.zeros(N)
        if regularization > 0:
            dg = (g - self.g0) / g_max
            J += regularization / N * float(np.sum(dg * dg))
            if grad:
                w = 2 * regularization / N * dg / g_max
                gc += self._pull_g(w, chi, psi)
                gp += self._pull_g_psi(w, g)
        if smoothness > 0 and edges.size:
            de = (g[edges[:, 0]] - g[edges[:, 1]]) / g_max
            J += smoothness / edges.shape[0] * float(np.sum(de * de))
            if grad:
                we = 2 * smoothness / edges.shape[0] * de / g_max
                w = np.zeros((N, 2))
                np.add.at(w, edges[:, 0], we)
                np.add.at(w, edges[:, 1], -we)
                gc += self._pull_g(w, chi, psi)
                gp += self._pull_g_psi(w, g)
        return J, gc, gp

    def _pull_g(self, w: np.ndarray, chi: np.ndarray, psi: np.ndarray) -> np.ndarray:
        """(N,) the chi derivative of sum_j w_j . g_j for weights ``w`` (N, 2) at (chi, psi)."""
        dm = self.m_of(chi, 1)
        return dm * (w[:, 0] * np.cos(psi) + w[:, 1] * np.sin(psi))

    @staticmethod
    def _pull_g_psi(w: np.ndarray, g: np.ndarray) -> np.ndarray:
        """(N,) the psi derivative of sum_j w_j . g_j for weights ``w`` (N, 2) at the vectors ``g``."""
        return -w[:, 0] * g[:, 1] + w[:, 1] * g[:, 0]

    def expected(self, chi: np.ndarray, psi: np.ndarray, defect: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """The robust objective's flow terms.

        Parameters
        ----------
        chi, psi : numpy.ndarray, shape (N,)
            The nominal layout.
        defect : numpy.ndarray, shape (P, 3)
            The full model's flow less the design model's, added to each sample's flow.

        Returns
        -------
        J : float
            The mean over the fabrication samples of the flow terms of the design model plus
            ``defect``.
        g_c, g_p : numpy.ndarray, shape (N,)
            Its derivatives in the nominal chi and psi.
        """
        eps, model = self.eps, self.model
        J, g_c, g_p = 0.0, np.zeros(self.N), np.zeros(self.N)
        for f_c, d_p in eps:
            ch_k = np.clip(chi * f_c, 0.0, None)
            u_k, aux = model.flow(ch_k, psi + d_p)
            J_k, dJ_k = self.flow_objective(u_k + defect, True)
            a_c, a_p = model.pullback(dJ_k, aux)
            J += J_k / len(eps)
            g_c += a_c * f_c * (chi * f_c >= 0) / len(eps)
            g_p += a_p / len(eps)
        return J, g_c, g_p

    def judged(self, chi: np.ndarray, psi: np.ndarray, u_full: np.ndarray) -> float:
        """J by which layouts are compared.

        Parameters
        ----------
        chi, psi : numpy.ndarray, shape (N,)
            The layout.
        u_full : numpy.ndarray, shape (P, 3)
            The full model's flow at the control points for it.

        Returns
        -------
        float
            J of the full model's flow; robust: the expected J with the full model's defect at the
            layout.
        """
        if not self.robust:
            return self.objective(u_full, chi, psi, False)[0]
        defect = u_full - self.model.flow(chi, psi)[0]
        return self.expected(chi, psi, defect)[0] + self.regularisers(chi, psi, False)[0]

    # ---------------------------------------------------------------- residuals and checks
    def residuals(self, u: np.ndarray) -> np.ndarray:
        """(P,) per control point the angle [rad] between the flow ``u`` (P, 3) and the target
        direction, or (velocity targets) |u - U| relative to the rms target speed."""
        uxy = u[:, :2]
        if self.kind == "angle":
            sp = np.maximum(np.linalg.norm(uxy, axis=1), 1e-300)
            return np.arccos(np.clip(np.einsum("pa,pa->p", uxy, self.T) / sp, -1.0, 1.0))
        return np.linalg.norm(uxy - self.U, axis=1) / math.sqrt(self.u2 / self.P)

    def rms(self, u: np.ndarray) -> float:
        """The rms of :meth:`residuals` of the flow ``u`` (P, 3)."""
        return float(np.sqrt(np.mean(self.residuals(u) ** 2)))

    def error_bar(self, u: np.ndarray, bound: np.ndarray) -> float:
        """The rms residual's error bar.

        Parameters
        ----------
        u : numpy.ndarray, shape (P, 3)
            The full model's flow.
        bound : numpy.ndarray, shape (P,)
            Its error bound per control point.

        Returns
        -------
        float
            The rms of arcsin(bound / |u|) (angle targets) or of the bound relative to the rms
            target speed.
        """
        if self.kind == "angle":
            sp = np.maximum(np.linalg.norm(u[:, :2], axis=1), 1e-300)
            return float(np.sqrt(np.mean(np.arcsin(np.minimum(1.0, bound / sp)) ** 2)))
        return float(np.sqrt(np.mean((bound / math.sqrt(self.u2 / self.P)) ** 2)))

    def evaluate(self, carpet: Carpet, tol: float):
        """The full model's cycle-mean flow of ``carpet`` at the control points at ``tol``, timed
        into ``work["seconds_checks"]``."""
        t0 = _time.perf_counter()
        s = carpet.evaluate(self.model.X3, CycleMean(), tol)
        self.work["seconds_checks"] += _time.perf_counter() - t0
        return s

    def check(self, chi: np.ndarray, psi: np.ndarray, tol: float):
        """The layout's carpet and its full model's sample at the control points (one check,
        counted in ``work["checks"]``).

        Parameters
        ----------
        chi, psi : numpy.ndarray, shape (N,)
            The layout.
        tol : float
            Tolerance of the evaluation.

        Returns
        -------
        carpet : Carpet
            The standing carpet of the layout.
        sample
            Its :meth:`Carpet.evaluate` of the :class:`CycleMean` at the control points.
        """
        t0 = _time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            c = replace(self.carpet, chi_N=chi, azimuth=psi)
        s = c.evaluate(self.model.X3, CycleMean(), tol)
        self.work["seconds_checks"] += _time.perf_counter() - t0
        self.work["checks"] += 1
        return c, s


class _PassObjective:
    """One pass's objective for L-BFGS-B over z = (chi / chi_hi, psi): the design model plus the
    pass's defect, scaled to J of order 1 (L-BFGS-B's first step and its ftol test depend on J's
    scale).

    Parameters
    ----------
    problem : _SurfaceProblem
        The design problem.
    defect : numpy.ndarray, shape (P, 3)
        The full model's flow less the design model's at the pass's start.
    scale : float
        The factor of J.
    threshold : float or None
        :func:`design_surface`'s ``threshold``.
    """

    def __init__(self, problem: _SurfaceProblem, defect: np.ndarray, scale: float, threshold: float | None):
        self.problem, self.defect, self.scale, self.threshold = problem, defect, scale, threshold
        self.last_u = None

    def __call__(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """J times ``scale`` at z (2 N,) and its gradient (2 N,)."""
        pb, N, chi_hi, defect, scale = self.problem, self.problem.N, self.problem.chi_hi, self.defect, self.scale
        ch = np.clip(z[:N], 0.0, 1.0) * chi_hi
        ps = z[N:]
        if pb.robust:
            J, a_c, a_p = pb.expected(ch, ps, defect)
            Jr, gc, gp = pb.regularisers(ch, ps, True)
            J += Jr
        else:
            u, aux = pb.model.flow(ch, ps)
            u = u + defect
            self.last_u = u
            J, dJ, gc, gp = pb.objective(u, ch, ps, True)
            a_c, a_p = pb.model.pullback(dJ, aux)
        return J * scale, np.concatenate([(a_c + gc) * chi_hi, a_p + gp]) * scale

    def good_enough(self, intermediate_result) -> None:
        """L-BFGS-B's callback: raise StopIteration once the model's rms residual (nominal design)
        is :data:`~ciliary_carpet.design.model.GOOD_ENOUGH` of the threshold (a full-model check
        follows)."""
        if self.threshold is not None and self.last_u is not None and \
                np.sqrt(np.mean(self.problem.residuals(self.last_u) ** 2)) <= GOOD_ENOUGH * self.threshold:
            raise StopIteration


def _local_layout(problem: _SurfaceProblem, check_tol: float) -> _Layout:
    """The local layout, checked on the full model.

    Parameters
    ----------
    problem : _SurfaceProblem
        The design problem.
    check_tol : float
        Tolerance of the check.

    Returns
    -------
    _Layout
        The local layout (``returned`` "local").
    """
    chi, psi = problem.chi0.copy(), problem.psi0.copy()
    c_full, s_full = problem.check(chi, psi, check_tol)
    J = problem.judged(chi, psi, s_full.velocity)
    return _Layout(J=J, chi=chi, psi=psi, carpet=c_full, sample=s_full, returned="local")


def _solve_pass(problem: _SurfaceProblem, chi: np.ndarray, psi: np.ndarray, u_full: np.ndarray, *, maxiter: int,
                ftol: float, threshold: float | None):
    """One L-BFGS-B solve of the design model plus the defect at the layout (chi, psi).

    Parameters
    ----------
    problem : _SurfaceProblem
        The design problem.
    chi, psi : numpy.ndarray, shape (N,)
        The pass's starting layout.
    u_full : numpy.ndarray, shape (P, 3)
        The full model's flow there.
    maxiter, ftol, threshold
        As :func:`design_surface`.

    Returns
    -------
    res : scipy.optimize.OptimizeResult
        L-BFGS-B's result over z = (chi / chi_hi, psi) (its ``fun`` scaled).
    scale : float
        The factor of J in ``res.fun``.
    """
    N, chi_hi = problem.N, problem.chi_hi
    u_mod, _ = problem.model.flow(chi, psi)
    defect = u_full - u_mod
    scale = 1.0 / max(problem.judged(chi, psi, u_full), 1e-300)
    fun = _PassObjective(problem, defect, scale, threshold)
    z0 = np.concatenate([chi / chi_hi, psi])
    res = minimize(fun, z0, jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * N + [(None, None)] * N,
                   options={"maxiter": int(maxiter), "ftol": ftol, "gtol": 1e-10}, callback=fun.good_enough)
    return res, scale


def _passes(problem: _SurfaceProblem, local: _Layout, *, check_tol: float, outer: int, maxiter: int, ftol: float,
            threshold: float | None) -> tuple[_Layout, str, str]:
    """The passes of defect correction from the local layout.

    Each pass solves the design model plus the full model's defect at the previous pass's layout
    (:func:`_solve_pass`) and checks its layout on the full model. The passes stop when the model's
    J and the full model's agree to 5 %, or a pass gains less than 2 % of the best J.

    Parameters
    ----------
    problem : _SurfaceProblem
        The design problem.
    local : _Layout
        The local layout (:func:`_local_layout`).
    check_tol, outer, maxiter, ftol, threshold
        As :func:`design_surface`.

    Returns
    -------
    best : _Layout
        The layout of least J (:meth:`_SurfaceProblem.judged`) among the local one and the passes'.
    status : {"success", "inaccurate"}
        "inaccurate" when an L-BFGS-B solve failed.
    message : str
        Why, or "".
    """
    N, chi_hi, work = problem.N, problem.chi_hi, problem.work
    best = local
    chi, psi, s_full = local.chi, local.psi, local.sample
    status, msg = "success", ""
    for k in range(int(outer)):
        res, scale = _solve_pass(problem, chi, psi, s_full.velocity, maxiter=maxiter, ftol=ftol, threshold=threshold)
        work["iterations"] += int(res.nit)
        work["evaluations"] += int(res.nfev)
        if not res.success and res.status not in (0, 99):  # 99: stopped by good_enough
            status, msg = "inaccurate", f"L-BFGS-B stopped in pass {k + 1}: {res.message}"
        chi, psi = np.clip(res.x[:N], 0.0, 1.0) * chi_hi, np.mod(res.x[N:], 2 * math.pi)
        c_full, s_full = problem.check(chi, psi, check_tol)
        Jf = problem.judged(chi, psi, s_full.velocity)
        logger.info("surface design pass %d: J model %.4g, full %.4g, rms %.4g", k + 1, res.fun / scale, Jf,
                    problem.rms(s_full.velocity))
        gained = best.J - Jf
        if Jf < best.J:
            best = _Layout(J=Jf, chi=chi, psi=psi, carpet=c_full, sample=s_full, returned=f"pass {k + 1}")
        if abs(res.fun / scale - Jf) <= 0.05 * Jf or gained < 0.02 * best.J:
            break
    return best, status, msg


def _final_check(problem: _SurfaceProblem, best: _Layout, threshold: float | None, check_tol: float):
    """The best layout's flow with an error bar of at most half the threshold.

    Given a threshold, the tolerance is divided by 10 until the error bar is at most half of it
    (down to 1e-5); beyond, the flow is evaluated exactly (tol 0, error bar 0).

    Parameters
    ----------
    problem : _SurfaceProblem
        The design problem.
    best : _Layout
        The layout returned.
    threshold : float or None
        As :func:`design_surface`; None: the check at ``check_tol`` stands.
    check_tol : float
        Tolerance of the best layout's check.

    Returns
    -------
    sample
        The full model's sample at the control points.
    err : float
        Its rms residual's error bar (:meth:`_SurfaceProblem.error_bar`).
    final_tol : float
        Its tolerance.
    """
    c_best, s_best = best.carpet, best.sample
    err = problem.error_bar(s_best.velocity, s_best.error_bound)
    final_tol = check_tol
    if threshold is not None:
        while err > 0.5 * threshold and final_tol > 1e-5:
            final_tol /= 10.0
            s_best = problem.evaluate(c_best, final_tol)
            problem.work["checks"] += 1
            err = problem.error_bar(s_best.velocity, s_best.error_bound)
        if err > 0.5 * threshold:
            final_tol = 0.0
            s_best = c_best.evaluate(problem.model.X3, CycleMean(), 0.0)
            err = 0.0
    return s_best, err, final_tol


def _result(problem: _SurfaceProblem, best: _Layout, local: _Layout, sample, err: float, final_tol: float,
            threshold: float | None, status: str, msg: str, clock: float) -> Design:
    """The :class:`~ciliary_carpet.design.result.Design` of the best layout.

    Parameters
    ----------
    problem : _SurfaceProblem
        The design problem.
    best, local : _Layout
        The layout returned and the local one.
    sample
        The best layout's final check (:func:`_final_check`), with its error bar ``err`` and
        tolerance ``final_tol``.
    threshold, status, msg
        The threshold (:func:`design_surface`), the passes' status and message (:func:`_passes`).
    clock : float
        ``time.perf_counter()`` at the design's start.

    Returns
    -------
    Design
        The design, its ``carpet`` the best layout's.
    """
    kind, N, P, T, work = problem.kind, problem.N, problem.P, problem.T, problem.work
    local_rms = problem.rms(local.sample.velocity)
    r = problem.residuals(sample.velocity)
    rms = float(np.sqrt(np.mean(r ** 2)))
    work.update(final_tol=final_tol, model_evaluations=problem.model.evaluations, robust_samples=len(problem.eps),
                seconds=_time.perf_counter() - clock)
    speed = None
    if kind == "angle":
        speed = np.einsum("pa,pa->p", sample.velocity[:, :2], T) / problem.s_ref
    msg = msg or (f"designed {N} standing cilia for {P} control points at z = {float(problem.height):g} L: rms "
                  f"residual {rms:.3g} {'rad' if kind == 'angle' else '(relative)'} +- {err:.2g} (local layout "
                  f"{local_rms:.3g}); {work['iterations']} L-BFGS-B iterations, {work['checks']} full-model checks, "
                  f"{work['seconds']:.1f} s")
    m_best = problem.m_of(best.chi)
    weak = np.nonzero(m_best < 0.25 * problem.g_max)[0]
    return Design(chi_N=best.chi, control=problem.X, target=T, achieved=sample.velocity[:, :2], residual=r,
                  residual_rms=rms, kind=kind, residual_error=err, speed_ratio=speed, local_rms=local_rms,
                  objective=float(best.J), local_objective=float(local.J), returned=best.returned,
                  near_cutoff=tuple(int(i) for i in weak), status=status, message=msg, work=work, carpet=best.carpet,
                  threshold=None if threshold is None else float(threshold), azimuth=best.psi,
                  height=float(problem.height))
