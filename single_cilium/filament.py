"""The semi-discrete filament: a Galerkin (spectral-element) discretisation of MODEL.md section 2.

Weak form
---------
With kappa frozen, the dynamics is the gradient flow of the bending energy
``E = 1/2 int_0^1 (theta_s - kappa - chi_N)^2 ds`` in the dissipation metric of resistive force
theory, ``R = eta/2 int_0^1 (v_par^2 + 2 v_perp^2) ds`` with ``v(s) = int_0^s n theta_t``.
Rayleigh's principle, for every test function ``dtheta`` with ``dtheta(0) = 0``::

    eta int (v_par dv_par + 2 v_perp dv_perp) ds + int (theta_s - kappa - chi_N) dtheta_s ds = 0,

with ``dv = int_0^s n dtheta``. Integrating by parts gives back ``M_s + V = 0`` with
``V = n . int_s^1 d`` and the tip condition ``M(1) = 0`` as the *natural* boundary condition, so
no algebraic constraint is imposed on the state and every smooth initial state is admissible
(the discrete tip condition holds in the weak sense at every time).

Discretisation
--------------
theta and kappa are continuous piecewise polynomials on a :class:`~single_cilium.mesh.Mesh`
(nodal values at the GLL points; ``theta(0) = 0`` is the clamp, ``phi = 0``). All integrals use
the composite GLL rule. The result is

    D(theta) theta_t = -K theta + B (kappa + chi_N)        (rows of the free nodes 1..n-1)
    kappa_t          = -kappa - chi_E sin(theta)            (every node)

with ``K`` the stiffness matrix, ``B`` the load matrix (``B[i, q] = int kappa_q-basis phi_i'``)
and ``D(theta)`` the symmetric positive definite drag (resistance) matrix
``D_ij = eta sum_q w_q I_qi I_qj [sin(th_q - th_i) sin(th_q - th_j) + 2 cos(th_q - th_i) cos(th_q - th_j)]``,
``I`` the cumulative integration matrix. It is never formed in the residual: ``D theta_t`` is
applied matrix-free, as the physics reads: velocity by cumulative integration, drag density,
then ``(D theta_t)_i = -n_i . int phi_i C`` with ``C = int_s^1 d``.

With kappa frozen the semi-discrete energy ``E_h = 1/2 sum_q w_q (theta_s - kappa - chi_N)^2``
(element-wise derivative at the nodes) obeys ``dE_h/dt = -theta_t^T D theta_t <= 0`` exactly.

Background flow
---------------
In a uniform stream ``U = (U1, U2)`` (``params.background``; field frame, ``e2`` along the field,
units ``L / tau``) the drag acts on the velocity relative to the fluid,
``d = -eta ((v - U).t t + 2 (v - U).n n)``. The dissipation is then that of the relative velocity
and the weak form gains a load that depends on theta alone::

    eta int ((v - U)_par dv_par + 2 (v - U)_perp dv_perp) ds + int (theta_s - kappa - chi_N) dtheta_s ds = 0,

so that, discretised, ``D(theta) theta_t = -K theta + B (kappa + chi_N) - g_U(theta)`` with
``g_U(theta)_i = -n_i . int phi_i C_U``, ``C_U = int_s^1 eta (U.t t + 2 U.n n)`` (the drag of the
stream on the filament held still). ``g_U`` is part of ``f`` (:meth:`Filament.rhs`); the mass
matrix ``D(theta)`` is unchanged. The energy identity below then holds only for ``U = 0``
(the stream does work on the filament). ``U = (0, 0)`` reproduces the still-fluid equations bit
for bit.

State vector
------------
``y = [theta_1, ..., theta_{n-1}, kappa_0, ..., kappa_{n-1}]`` (length ``2n - 1``). Helpers
:meth:`Filament.split` and :meth:`Filament.join` convert to and from full nodal arrays.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla

from ._kernels import stage_terms, stage_residual
from cilia_runtime.signals import native_call
from .equilibrium import equilibrium
from .mesh import Mesh
from .params import CiliumParams

__all__ = ["Filament"]


@dataclass(frozen=True, eq=False)
class Filament:
    """Semi-discrete equations of one filament on a mesh (see the module docstring).

    Implements the problem interface of :class:`single_cilium.radau.Radau` for
    ``M(y) y' = f(y)`` with ``M = diag(D(theta), I)``.

    ``kappa_frozen=True`` replaces the activity law by ``kappa_t = 0`` (a passive filament with a
    fixed spontaneous curvature): the dynamics is then a pure gradient flow of the bending energy
    (in still fluid).

    ``params.background`` (the uniform stream ``U``, module docstring) enters the drag
    (:meth:`drag`, hence the clamp force) and ``f`` (:meth:`rhs`, :meth:`residual`) through
    ``g_U(theta)``; the Newton matrices (:meth:`factor`) include ``dg_U/dtheta``.
    """

    params: CiliumParams
    mesh: Mesh
    kappa_frozen: bool = False
    _K: np.ndarray = field(init=False, repr=False)
    _B: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        m = self.mesh
        n = m.n_nodes
        K = np.zeros((n, n))
        B = np.zeros((n, n))
        _, wr, Dx, _ = m._reference
        for e in range(m.n_elements):
            idx = m.element_nodes[e]
            K[np.ix_(idx, idx)] += (2.0 / m.sizes[e]) * (Dx.T * wr) @ Dx
            B[np.ix_(idx, idx)] += Dx.T * wr
        object.__setattr__(self, "_K", K)
        object.__setattr__(self, "_B", B)

    # ------------------------------------------------------------------ bookkeeping
    @property
    def n(self) -> int:
        """Number of nodes."""
        return self.mesh.n_nodes

    @property
    def size(self) -> int:
        """Length of the state vector, ``2n - 1``."""
        return 2 * self.n - 1

    def split(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Full nodal ``theta`` (with the clamp value 0) and ``kappa`` from state(s) ``y`` (..., 2n-1)."""
        y = np.asarray(y)
        n = self.n
        theta = np.concatenate([np.zeros(y.shape[:-1] + (1,)), y[..., : n - 1]], axis=-1)
        return theta, y[..., n - 1:]

    def join(self, theta: np.ndarray, kappa: np.ndarray) -> np.ndarray:
        """State vector from full nodal ``theta`` (its clamp value is dropped) and ``kappa``."""
        return np.concatenate([np.asarray(theta)[..., 1:], np.asarray(kappa)], axis=-1)

    @property
    def scale(self) -> np.ndarray:
        """Typical size of each state component (1 for theta, ``max(1, |chi_E|, |chi_N|)`` for kappa),
        used to set absolute tolerances."""
        p = self.params
        ks = max(1.0, abs(p.chi_E), abs(p.chi_N))
        return np.concatenate([np.ones(self.n - 1), np.full(self.n, ks)])

    # ------------------------------------------------------------------ physics
    def drag(self, theta: np.ndarray, theta_t: np.ndarray) -> np.ndarray:
        """Drag density ``d`` (force per length of the fluid ON the filament) at the nodes.

        ``d = -eta ((v - U).t t + 2 (v - U).n n)``, ``v = int_0^s n theta_t``, ``U`` the background
        flow (``params.background``, field frame, units ``L / tau``; ``(0, 0)``: the fluid at rest).
        Shapes: ``theta``, ``theta_t`` (..., n) full nodal arrays; returns (..., n, 2).
        """
        return self._drag(theta, theta_t, self.params.background)

    def _drag(self, theta, theta_t, U) -> np.ndarray:
        c, s = np.cos(theta), np.sin(theta)
        I = self.mesh.cumulative
        a = (c * theta_t) @ I.T  # v_x = -a
        b = (s * theta_t) @ I.T  # v_y = -b
        if U[0] != 0.0 or U[1] != 0.0:
            a = a + U[0]  # v - U = -(a + U1, b + U2)
            b = b + U[1]
        v_par = a * s - b * c
        v_perp = a * c + b * s
        eta = self.params.eta
        dx = eta * (v_par * s + 2.0 * v_perp * c)
        dy = eta * (-v_par * c + 2.0 * v_perp * s)
        return np.stack([dx, dy], axis=-1)

    def resistance(self, theta: np.ndarray, theta_t: np.ndarray) -> np.ndarray:
        """``D(theta) theta_t`` on the free nodes, matrix-free (the drag of the motion alone, without
        the background flow's ``g_U``). Shapes (..., n) -> (..., n-1)."""
        return self._project(self._drag(theta, theta_t, (0.0, 0.0)), theta)

    def stream_load(self, theta: np.ndarray) -> np.ndarray:
        """``g_U(theta)``: the background flow's drag on the filament held still, as a load on the
        free nodes (module docstring; zero for ``U = 0``). Shapes (..., n) -> (..., n-1)."""
        return self._project(self.drag(theta, np.zeros_like(theta)), theta)

    def stream_jacobian(self, theta: np.ndarray) -> np.ndarray:
        """``dg_U/dtheta`` on the free nodes, shape (n-1, n-1), for full nodal ``theta`` (n,)."""
        m = self.mesh
        U1, U2 = self.params.background
        with native_call():  # a signal meanwhile waits for the kernel (cilia_runtime.signals)
            return stage_terms(np.ascontiguousarray(theta, dtype=float), np.zeros(self.n), m.cumulative,
                                m.weights, float(self.params.eta), float(U1), float(U2))[2]

    def _project(self, d: np.ndarray, theta: np.ndarray) -> np.ndarray:
        w = self.mesh.weights
        I = self.mesh.cumulative
        Px = (w * d[..., 0]) @ I  # P[i] = sum_q w_q I_qi d_q  (= int phi_i C)
        Py = (w * d[..., 1]) @ I
        return (np.cos(theta) * Px + np.sin(theta) * Py)[..., 1:]

    def resistance_matrix(self, theta: np.ndarray) -> np.ndarray:
        """The SPD matrix ``D(theta)`` on the free nodes, shape (n-1, n-1)."""
        I = self.mesh.cumulative[:, 1:]
        w = self.mesh.weights
        dth = theta[:, None] - theta[None, 1:]
        Wt = I * np.sin(dth)
        Wn = I * np.cos(dth)
        wc = w[:, None]
        return self.params.eta * (Wt.T @ (wc * Wt) + 2.0 * (Wn.T @ (wc * Wn)))

    def rhs(self, y: np.ndarray) -> np.ndarray:
        """``f(y)``: elastic force on the free nodes and the kappa relaxation. Shape (..., 2n-1)."""
        theta, kappa = self.split(y)
        p = self.params
        f_theta = (kappa + p.chi_N) @ self._B.T - theta @ self._K.T
        if self.kappa_frozen:
            f_kappa = np.zeros_like(kappa)
        else:
            f_kappa = -kappa - p.chi_E * np.sin(theta)
        f_theta = f_theta[..., 1:]
        if p.has_background:
            f_theta = f_theta - self.stream_load(theta)
        return np.concatenate([f_theta, f_kappa], axis=-1)

    def mass_apply(self, y: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``M(y) v`` with ``M = diag(D(theta), I)``. Shapes (..., 2n-1)."""
        theta, _ = self.split(y)
        n = self.n
        theta_t = np.concatenate([np.zeros(v.shape[:-1] + (1,)), v[..., : n - 1]], axis=-1)
        return np.concatenate([self.resistance(theta, theta_t), v[..., n - 1:]], axis=-1)

    def residual(self, Y: np.ndarray, Kd: np.ndarray) -> np.ndarray:
        """Stage residuals ``f(Y_j) - M(Y_j) K_j`` row-wise, shapes ``(k, 2n-1)`` (one compiled
        kernel; equal to ``rhs(Y) - mass_apply(Y, Kd)``)."""
        p = self.params
        relax, cE = (0.0, 0.0) if self.kappa_frozen else (1.0, p.chi_E)
        m = self.mesh
        U1, U2 = p.background
        with native_call():  # a signal meanwhile waits for the kernel (cilia_runtime.signals)
            return stage_residual(np.ascontiguousarray(Y, dtype=float), np.ascontiguousarray(Kd, dtype=float),
                                  m.cumulative, m.weights, self._K, self._B, p.eta, cE, p.chi_N, relax, U1, U2)

    def factor(self, y: np.ndarray, sigmas) -> list["_SchurFactor"]:
        """Factorisations of ``sigma M(y) - J(y)`` for each ``sigma`` in ``sigmas`` (``J = df/dy``;
        the derivative of ``D(theta)`` with respect to theta is left out, as in a simplified
        Newton method; the background flow's ``dg_U/dtheta`` is included). ``D(theta)`` is
        formed once for all of them.

        The kappa block is diagonal, so it is eliminated (Schur complement) and only an
        ``(n-1) x (n-1)`` matrix is LU-factorised per ``sigma``.
        """
        theta, _ = self.split(y)
        D = self.resistance_matrix(theta)
        p = self.params
        # kappa rows of sigma M - J: (sigma + r) x_kappa + chi_E cos(theta) x_theta
        r, cE = (0.0, 0.0) if self.kappa_frozen else (1.0, p.chi_E)
        coupling = cE * np.cos(theta[1:])
        Br = self._B[1:, :]
        Kr = self._K[1:, 1:]
        if p.has_background:
            Kr = Kr + self.stream_jacobian(theta)
        out = []
        for sigma in sigmas:
            A = sigma * D + Kr + Br[:, 1:] * (coupling / (sigma + r))[None, :]
            out.append(_SchurFactor(A, Br, coupling, sigma + r, self.n))
        return out

    def velocity(self, y: np.ndarray) -> np.ndarray:
        """``y' = M(y)^{-1} f(y)`` (Cholesky solve with the SPD drag matrix). Shape (2n-1,)."""
        f = self.rhs(y)
        theta, _ = self.split(y)
        D = self.resistance_matrix(theta)
        out = f.copy()
        out[: self.n - 1] = sla.cho_solve(sla.cho_factor(D, check_finite=False), f[: self.n - 1],
                                          check_finite=False)
        return out

    # ------------------------------------------------------------------ observables
    def shape(self, theta: np.ndarray) -> np.ndarray:
        """Positions ``r(s) = int_0^s t`` at the nodes, ``t = (-sin theta, cos theta)``. (..., n) -> (..., n, 2)."""
        I = self.mesh.cumulative
        return np.stack([(-np.sin(theta)) @ I.T, np.cos(theta) @ I.T], axis=-1)

    def clamp_force(self, drag: np.ndarray) -> np.ndarray:
        """``F = -int_0^1 d ds`` (the force the filament exerts on the fluid). (..., n, 2) -> (..., 2)."""
        return -np.einsum("q,...qk->...k", self.mesh.weights, drag)

    def bending_energy(self, theta: np.ndarray, kappa: np.ndarray) -> np.ndarray:
        """Discrete ``E_h = 1/2 sum_q w_q (theta_s - kappa - chi_N)^2`` (element-wise ``theta_s``)."""
        m = self.mesh
        theta = np.asarray(theta)
        kappa = np.asarray(kappa)
        ts = np.einsum("eab,...eb->...ea", m.element_derivative, theta[..., m.element_nodes])
        g = ts - kappa[..., m.element_nodes] - self.params.chi_N
        wloc = 0.5 * m.sizes[:, None] * m._reference[1][None, :]
        return 0.5 * np.einsum("ea,...ea->...", wloc, g * g)

    # ------------------------------------------------------------------ equilibrium
    def equilibrium_state(self, tol: float = 1e-13, max_iter: int = 30) -> np.ndarray:
        """The discrete equilibrium (state vector): ``K theta = B (kappa + chi_N)``,
        ``kappa = -chi_E sin theta``, solved by Newton's method from the closed form of
        MODEL.md section 3 interpolated at the nodes. It differs from the closed form by the
        discretisation error, and stays put to round-off under :func:`~single_cilium.simulate`.

        In a background flow ``U != 0`` (``params.background``) there is no closed form: the
        steady state solves ``K theta + B (chi_E sin theta - chi_N) + g_U(theta) = 0``
        (``kappa = -chi_E sin theta``; the stream's drag ``g_U``, module docstring), by Newton's
        method with the exact Jacobian, continued in the flow from the still-fluid state: the
        stream is scaled by ``lambda`` from 0 to 1 in steps (secant predictor) that are cut by 4
        when Newton fails and doubled when it succeeds. A fold of the branch (e.g. a filament
        buckled by a strong stream against it) ends the continuation with a RuntimeError.
        """
        p = self.params
        if p.has_background:
            cached = self.__dict__.get("_steady")
            if cached is None:
                cached = self._steady_state(tol, max_iter)
                object.__setattr__(self, "_steady", cached)
            return cached.copy()
        theta = equilibrium(p, self.mesh.nodes)
        theta[0] = 0.0
        Kr, Br = self._K[1:, 1:], self._B[1:, :]
        last = np.inf
        for _ in range(max_iter):
            g = Kr @ theta[1:] + Br @ (p.chi_E * np.sin(theta) - p.chi_N)
            J = Kr + Br[:, 1:] * (p.chi_E * np.cos(theta[1:]))[None, :]
            step = np.linalg.solve(J, g)
            theta[1:] -= step
            size = np.max(np.abs(step)) / max(1.0, np.max(np.abs(theta)))
            # converged, or stagnating at round-off (the Newton matrix has condition ~1e5-1e6)
            if size <= tol or (size <= 1e-9 and size >= 0.5 * last):
                break
            last = size
        else:
            raise RuntimeError(
                f"Newton's method for the discrete equilibrium did not converge (last step {size:.2g}); "
                f"the mesh ({self.mesh.describe()}) probably does not resolve the equilibrium: use "
                "Mesh.for_params or a higher degree")
        return self.join(theta, -p.chi_E * np.sin(theta))

    def _steady_state(self, tol: float, max_iter: int) -> np.ndarray:
        """The steady state in the background flow, by continuation from the still fluid."""
        p = self.params
        still = Filament(p.with_background((0.0, 0.0)), self.mesh, self.kappa_frozen)
        theta = still.split(still.equilibrium_state(tol, max_iter))[0]
        Kr, Br = self._K[1:, 1:], self._B[1:, :]
        m = self.mesh
        I, w = np.ascontiguousarray(m.cumulative), np.ascontiguousarray(m.weights)
        U1, U2 = p.background
        zero = np.zeros(self.n)

        def newton(th, lam):
            th = th.copy()
            last = np.inf
            for it in range(max_iter):
                with native_call():
                    gU, _, JU = stage_terms(th, zero, I, w, p.eta, lam * U1, lam * U2)
                g = Kr @ th[1:] + Br @ (p.chi_E * np.sin(th) - p.chi_N) + gU
                J = Kr + Br[:, 1:] * (p.chi_E * np.cos(th[1:]))[None, :] + JU
                try:
                    step = np.linalg.solve(J, g)
                except np.linalg.LinAlgError:
                    return None
                th[1:] -= step
                size = np.max(np.abs(step)) / max(1.0, np.max(np.abs(th)))
                if not np.isfinite(size) or (it >= 3 and size > last):
                    return None
                if size <= tol or (size <= 1e-9 and size >= 0.5 * last):
                    return th
                last = size
            return None

        lam, dlam = 0.0, 1.0
        prev = None  # (lambda, theta) of the previous point, for the secant predictor
        while lam < 1.0:
            trial = min(1.0, lam + dlam)
            guess = theta if prev is None else theta + (trial - lam) / (lam - prev[0]) * (theta - prev[1])
            th = newton(guess, trial)
            if th is None:
                dlam *= 0.25
                if dlam < 1e-6:
                    raise RuntimeError(
                        f"no steady state of {p} found by continuation in the background flow: "
                        f"Newton fails beyond {lam:.6g} x U (a fold of the branch, e.g. a filament "
                        f"buckled by the stream, or a mesh ({m.describe()}) that does not resolve it)")
                continue
            prev, theta, lam = (lam, theta), th, trial
            dlam = min(2.0 * dlam, 1.0)
        return self.join(theta, -p.chi_E * np.sin(theta))


class _SchurFactor:
    """Solves ``(sigma M - J) x = b`` with the LU factors of the theta Schur complement ``A``
    (LAPACK getrf/getrs called directly: these matrices are small and the solves many)."""

    __slots__ = ("lu", "piv", "getrs", "Br", "coupling", "denom", "n")

    def __init__(self, A, Br, coupling, denom, n):
        getrf, getrs = sla.lapack.get_lapack_funcs(("getrf", "getrs"), (A,))
        lu, piv, info = getrf(A, overwrite_a=True)
        if info > 0:
            raise np.linalg.LinAlgError(f"singular Newton matrix (pivot {info})")
        self.lu, self.piv, self.getrs = lu, piv, getrs
        self.Br, self.coupling, self.denom, self.n = Br, coupling, denom, n

    def solve(self, b: np.ndarray) -> np.ndarray:
        n = self.n
        bt, bk = b[: n - 1], b[n - 1:]
        denom = self.denom
        rhs = (bt + self.Br @ bk / denom).astype(self.lu.dtype, copy=False)
        xt, info = self.getrs(self.lu, self.piv, rhs)
        xk = bk / denom
        xk[1:] -= self.coupling * xt / denom
        return np.concatenate([xt, xk])
