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
from ciliary_carpet.carpet.cycles import cycle_moments
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
(tested). Measured at h = 1.5 L: 8.1e-3 at the default :data:`STEP` 0.1 L, 2.1e-3 at 0.05 L
(second order: the bilinear interpolation in space dominates; 65 curvatures instead of 33 change
nothing). The design model's own error, which the defect correction carries: 0.3 % of the flow
on a 6 x 6 carpet at random (chi, psi)."""
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
    """Choose (chi_N, psi) for the cilia of the standing ``carpet`` (its bases, phases, table,
    wall are kept) so that its mean flow on the plane z = ``height`` at ``control`` (P, 2) runs
    along ``directions`` (P,) [rad, anticlockwise from +x] or equals ``velocities`` (P, 2).

    Each cilium starts pumping along the direction asked at the control point nearest its base, at
    chi_hi (:func:`pumping_curvature`): the *local* layout (velocity targets: along U there). See
    the module docstring for the model, the objective (``speed_floor`` sigma, ``floor_weight``,
    ``regularization``, ``smoothness``) and the passes (at most ``outer``, each at most ``maxiter``
    L-BFGS-B iterations, stopped when an iteration lowers J by less than ``ftol`` times its value
    at the pass's start; checks at ``check_tol``, default max(tol, 1e-2)); ``threshold``: the
    acceptance threshold of the rms residual, whose half the final check's error bar is made to
    meet. ``robust_sigma`` > 0 or ``robust_sigma_psi`` > 0 [rad]: design for the expected objective
    under fabrication errors chi_j (1 + sigma eps_j), psi_j + sigma_psi eps'_j instead of the nominal
    one: the flow terms averaged over ``robust_samples`` fixed samples (seed ``robust_seed``), each
    the design model plus the pass's defect, the regularisers at the nominal layout; the passes'
    layouts are then compared by that expected J (the full model's defect at each). Target
    velocities faster than 1.5 times what the cilia around them make pumping along them are a
    TargetError with ``strict`` (the default); without it a warning lists them and the design
    returns the closest flow the cilia make (its residual says how far). Returns a
    :class:`~ciliary_carpet.design.result.Design` with ``azimuth`` (N,) and ``height``; its
    ``carpet`` is the designed standing carpet."""
    clock = _time.perf_counter()
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
    check_tol = max(tol, 1e-2) if check_tol is None else float(check_tol)
    P, N = X.shape[0], carpet.n
    rs = np.random.default_rng(robust_seed)
    eps = [(1.0 + float(robust_sigma) * rs.standard_normal(N), float(robust_sigma_psi) * rs.standard_normal(N))
           for _ in range(int(robust_samples) if robust else 0)]
    model = SurfaceModel(carpet, X, height)
    chi_hi = model.resp.chi_hi
    _, m_of = pumping_curvature(carpet.table)
    g_max = float(m_of(chi_hi))
    near = cKDTree(X).query(carpet.bases)[1]
    if directions is not None:
        A = np.broadcast_to(np.asarray(directions, dtype=float), (P,)).copy()
        if not np.all(np.isfinite(A)):
            raise TargetError("target directions contain NaN or inf")
        kind = "angle"
        T = np.column_stack([np.cos(A), np.sin(A)])
        s_ref = np.maximum(model.reference_speed(T), 1e-300)
        psi0 = A[near]
    else:
        U = np.asarray(velocities, dtype=float)
        if U.shape != X.shape or not np.all(np.isfinite(U)):
            raise TargetError(f"velocities must be finite, shape {X.shape}, got {U.shape}")
        kind = "velocity"
        T = U
        th = np.arctan2(U[:, 1], U[:, 0])
        top = model.reference_speed(np.column_stack([np.cos(th), np.sin(th)]))
        bad = np.nonzero(np.linalg.norm(U, axis=1) > 1.5 * np.maximum(top, 0.0))[0]
        if bad.size:
            lst = "; ".join(f"#{k} at ({X[k, 0]:.3g}, {X[k, 1]:.3g}) asks {np.linalg.norm(U[k]):.3g} L/tau, the cilia "
                            f"around it make at most about {max(top[k], 0):.3g}" for k in bad[:5])
            msg = f"{bad.size} target velocities are faster than the cilia can pump there: {lst}"
            if strict:
                raise TargetError(msg + " (with [target] strict = false the design returns the closest flow)")
            warnings.warn(msg + "; designing for the closest flow the cilia make (strict = false)", UserWarning,
                          stacklevel=2)
        u2 = float(np.sum(U * U))
        psi0 = th[near]
    chi0 = np.full(N, chi_hi)
    g0 = np.column_stack([np.cos(psi0), np.sin(psi0)]) * float(m_of(chi_hi))
    edges = layout.neighbours(carpet.bases)

    def g_of(chi, psi, nu=0):
        m = m_of(chi, nu)
        return m[:, None] * np.column_stack([np.cos(psi), np.sin(psi)]), m

    def objective(u, chi, psi, grad: bool):
        """J and dJ/du (P, 3), dJ/dchi, dJ/dpsi (N,) from the regularisers."""
        J, dJ = flow_objective(u, grad)
        Jr, gc, gp = regularisers(chi, psi, grad)
        return J + Jr, dJ, gc, gp

    def flow_objective(u, grad: bool):
        """The flow terms of J and dJ/du (P, 3)."""
        uxy = u[:, :2]
        if kind == "angle":
            sp = np.linalg.norm(uxy, axis=1)
            spc = np.maximum(sp, 1e-300)
            cosang = np.einsum("pa,pa->p", uxy, T) / spc
            along = np.einsum("pa,pa->p", uxy, T)
            gap = np.maximum(0.0, 1.0 - along / (speed_floor * s_ref)) if speed_floor > 0 else np.zeros(P)
            J = float(np.mean(1.0 - cosang) + 0.5 * floor_weight * np.mean(gap ** 2))
            dJ = np.zeros((P, 3))
            if grad:
                # d(1 - uhat.t)/du = -(t - cos uhat)/|u|
                uh = uxy / spc[:, None]
                dJ[:, :2] = -(T - cosang[:, None] * uh) / spc[:, None] / P
                if speed_floor > 0:
                    dJ[:, :2] += (-floor_weight * gap / (speed_floor * s_ref))[:, None] * T / P
        else:
            d = uxy - U
            J = float(0.5 * np.sum(d * d) / u2)
            dJ = np.zeros((P, 3))
            dJ[:, :2] = d / u2
        return J, dJ

    def regularisers(chi, psi, grad: bool):
        """The regularisers' J, dJ/dchi, dJ/dpsi (N,)."""
        J = 0.0
        g, m = g_of(chi, psi)
        gc = np.zeros(N)
        gp = np.zeros(N)
        if regularization > 0:
            dg = (g - g0) / g_max
            J += regularization / N * float(np.sum(dg * dg))
            if grad:
                w = 2 * regularization / N * dg / g_max
                gc += _pull_g(w, chi, psi)
                gp += _pull_g_psi(w, g)
        if smoothness > 0 and edges.size:
            de = (g[edges[:, 0]] - g[edges[:, 1]]) / g_max
            J += smoothness / edges.shape[0] * float(np.sum(de * de))
            if grad:
                we = 2 * smoothness / edges.shape[0] * de / g_max
                w = np.zeros((N, 2))
                np.add.at(w, edges[:, 0], we)
                np.add.at(w, edges[:, 1], -we)
                gc += _pull_g(w, chi, psi)
                gp += _pull_g_psi(w, g)
        return J, gc, gp

    def expected(chi, psi, defect):
        """The robust objective's flow terms: the mean over the samples of J of the design model
        plus ``defect``, with the pullbacks' chain to the nominal (chi, psi)."""
        J, g_c, g_p = 0.0, np.zeros(N), np.zeros(N)
        for f_c, d_p in eps:
            ch_k = np.clip(chi * f_c, 0.0, None)
            u_k, aux = model.flow(ch_k, psi + d_p)
            J_k, dJ_k = flow_objective(u_k + defect, True)
            a_c, a_p = model.pullback(dJ_k, aux)
            J += J_k / len(eps)
            g_c += a_c * f_c * (chi * f_c >= 0) / len(eps)
            g_p += a_p / len(eps)
        return J, g_c, g_p

    def judged(chi, psi, u_full):
        """J by which layouts are compared: on the full model's flow, or (robust) the expected one
        with the full model's defect at the layout."""
        if not robust:
            return objective(u_full, chi, psi, False)[0]
        defect = u_full - model.flow(chi, psi)[0]
        return expected(chi, psi, defect)[0] + regularisers(chi, psi, False)[0]

    def _pull_g(w, chi, psi):
        dm = m_of(chi, 1)
        return dm * (w[:, 0] * np.cos(psi) + w[:, 1] * np.sin(psi))

    def _pull_g_psi(w, g):
        return -w[:, 0] * g[:, 1] + w[:, 1] * g[:, 0]

    def residuals(u):
        uxy = u[:, :2]
        if kind == "angle":
            sp = np.maximum(np.linalg.norm(uxy, axis=1), 1e-300)
            return np.arccos(np.clip(np.einsum("pa,pa->p", uxy, T) / sp, -1.0, 1.0))
        return np.linalg.norm(uxy - U, axis=1) / math.sqrt(u2 / P)

    def full(chi, psi, tol_):
        t0 = _time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            c = replace(carpet, chi_N=chi, azimuth=psi)
        s = c.evaluate(model.X3, CycleMean(), tol_)
        work["seconds_checks"] += _time.perf_counter() - t0
        return c, s

    def bar(u, bound):
        if kind == "angle":
            sp = np.maximum(np.linalg.norm(u[:, :2], axis=1), 1e-300)
            return float(np.sqrt(np.mean(np.arcsin(np.minimum(1.0, bound / sp)) ** 2)))
        return float(np.sqrt(np.mean((bound / math.sqrt(u2 / P)) ** 2)))

    work = {"iterations": 0, "evaluations": 0, "checks": 0, "pairs_near": model.pairs,
            "response_seconds": model.resp.seconds, "seconds_checks": 0.0}
    chi, psi = chi0.copy(), psi0.copy()
    c_full, s_full = full(chi, psi, check_tol)
    work["checks"] += 1
    J_full0 = judged(chi, psi, s_full.velocity)
    local_rms = float(np.sqrt(np.mean(residuals(s_full.velocity) ** 2)))
    best = {"J": J_full0, "chi": chi, "psi": psi, "carpet": c_full, "sample": s_full, "returned": "local"}
    status, msg = "success", ""
    for k in range(int(outer)):
        u_mod, _ = model.flow(chi, psi)
        defect = s_full.velocity - u_mod
        scale = 1.0 / max(judged(chi, psi, s_full.velocity), 1e-300)  # J of order 1: L-BFGS-B's
        # first step and its ftol test are scale-dependent (a J of 3e-4 stopped 10^4 cilia after one iteration)

        last = {}

        def fun(z):
            ch = np.clip(z[:N], 0.0, 1.0) * chi_hi
            ps = z[N:]
            if robust:
                J, a_c, a_p = expected(ch, ps, defect)
                Jr, gc, gp = regularisers(ch, ps, True)
                J += Jr
            else:
                u, aux = model.flow(ch, ps)
                u = u + defect
                last["u"] = u
                J, dJ, gc, gp = objective(u, ch, ps, True)
                a_c, a_p = model.pullback(dJ, aux)
            return J * scale, np.concatenate([(a_c + gc) * chi_hi, a_p + gp]) * scale

        def good_enough(intermediate_result):
            """Stop once the model's rms residual is GOOD_ENOUGH of the threshold (the design's job
            is the threshold; a full-model check follows)."""
            if threshold is not None and "u" in last and \
                    np.sqrt(np.mean(residuals(last["u"]) ** 2)) <= GOOD_ENOUGH * threshold:
                raise StopIteration

        z0 = np.concatenate([chi / chi_hi, psi])
        res = minimize(fun, z0, jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * N + [(None, None)] * N,
                       options={"maxiter": int(maxiter), "ftol": ftol, "gtol": 1e-10}, callback=good_enough)
        work["iterations"] += int(res.nit)
        work["evaluations"] += int(res.nfev)
        if not res.success and res.status not in (0, 99):  # 99: stopped by good_enough
            status, msg = "inaccurate", f"L-BFGS-B stopped in pass {k + 1}: {res.message}"
        chi, psi = np.clip(res.x[:N], 0.0, 1.0) * chi_hi, np.mod(res.x[N:], 2 * math.pi)
        c_full, s_full = full(chi, psi, check_tol)
        work["checks"] += 1
        Jf = judged(chi, psi, s_full.velocity)
        logger.info("surface design pass %d: J model %.4g, full %.4g, rms %.4g", k + 1, res.fun / scale, Jf,
                    float(np.sqrt(np.mean(residuals(s_full.velocity) ** 2))))
        gained = best["J"] - Jf
        if Jf < best["J"]:
            best = {"J": Jf, "chi": chi, "psi": psi, "carpet": c_full, "sample": s_full, "returned": f"pass {k + 1}"}
        if abs(res.fun / scale - Jf) <= 0.05 * Jf or gained < 0.02 * best["J"]:
            break
    c_best, s_best = best["carpet"], best["sample"]
    err = bar(s_best.velocity, s_best.error_bound)
    final_tol = check_tol
    if threshold is not None:
        while err > 0.5 * threshold and final_tol > 1e-5:
            final_tol /= 10.0
            t0 = _time.perf_counter()
            s_best = c_best.evaluate(model.X3, CycleMean(), final_tol)
            work["seconds_checks"] += _time.perf_counter() - t0
            work["checks"] += 1
            err = bar(s_best.velocity, s_best.error_bound)
        if err > 0.5 * threshold:
            final_tol = 0.0
            s_best = c_best.evaluate(model.X3, CycleMean(), 0.0)
            err = 0.0
    r = residuals(s_best.velocity)
    rms = float(np.sqrt(np.mean(r ** 2)))
    work.update(final_tol=final_tol, model_evaluations=model.evaluations, robust_samples=len(eps),
                seconds=_time.perf_counter() - clock)
    speed = None
    if kind == "angle":
        speed = np.einsum("pa,pa->p", s_best.velocity[:, :2], T) / s_ref
    tgt = T if kind == "velocity" else T
    msg = msg or (f"designed {N} standing cilia for {P} control points at z = {float(height):g} L: rms residual "
                  f"{rms:.3g} {'rad' if kind == 'angle' else '(relative)'} +- {err:.2g} (local layout {local_rms:.3g}); "
                  f"{work['iterations']} L-BFGS-B iterations, {work['checks']} full-model checks, "
                  f"{work['seconds']:.1f} s")
    m_best = m_of(best["chi"])
    weak = np.nonzero(m_best < 0.25 * g_max)[0]
    return Design(chi_N=best["chi"], control=X, target=tgt, achieved=s_best.velocity[:, :2], residual=r,
                  residual_rms=rms, kind=kind, residual_error=err, speed_ratio=speed, local_rms=local_rms,
                  objective=float(best["J"]), local_objective=float(J_full0), returned=best["returned"],
                  near_cutoff=tuple(int(i) for i in weak), status=status, message=msg, work=work, carpet=c_best,
                  threshold=None if threshold is None else float(threshold), azimuth=best["psi"],
                  height=float(height))
