"""The design model of standing carpets: one cilium's surface flow tabulated, the carpet's summed.

A standing carpet (:mod:`~ciliary_carpet.carpet.geometry`) clamps cilium j at b_j on the substrate
z = 0 with the field along +z; its curvature chi_N_j >= 0 sets how far its mean thrust leans from
the normal, its azimuth psi_j which way. The surface flow is the cycle-mean flow on the plane
z = h above the substrate. :func:`~ciliary_carpet.design.surface.design_surface` chooses
(chi_N, psi) with this model and corrects it by the full flow.

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
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

from single_cilium.table import ThrustTable

from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.design.moments import cycle_moments
from ciliary_carpet.stokes import stokeslet_velocity, stokeslet_velocity_ranges

__all__ = ["SurfaceResponse", "SurfaceModel", "pumping_curvature", "surface_response", "REACH", "STEP", "PIVOT",
           "PIVOT_DELTA", "HEIGHT", "RESPONSE_ERROR", "TETRA"]

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
