"""The design problem of a standing carpet: its model, target, objective and full-model checks.

:class:`SurfaceProblem` holds what one run of :func:`~ciliary_carpet.design.surface.design_surface`
works on: the design model (:class:`~ciliary_carpet.design.surface_model.SurfaceModel`), the
target (directions or velocities at the control points), the objective J with its exact
gradient (flow terms, speed floor, smoothness and regulariser on the pumping vectors, and the
expected objective over fabrication samples), and the checks of a layout in the full model with
their error bars. :class:`PassObjective` is one pass's objective for L-BFGS-B, :class:`Layout` a
checked layout. The objective is stated in :mod:`~ciliary_carpet.design.surface`.
"""
from __future__ import annotations

import math
import time as _time
import warnings
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.design.errors import TargetError
from ciliary_carpet.design.model import GOOD_ENOUGH
from ciliary_carpet.design.surface_model import SurfaceModel, pumping_curvature

__all__ = ["Layout", "PassObjective", "SurfaceProblem"]


@dataclass(frozen=True, eq=False)
class Layout:
    """A checked layout: its (chi, psi) (N,) each, J by which layouts are compared
    (:meth:`SurfaceProblem.judged`), its carpet and the full model's sample at the control
    points, and which layout it is ("local" or "pass k")."""

    J: float
    chi: np.ndarray
    psi: np.ndarray
    carpet: Carpet
    sample: object
    returned: str


class SurfaceProblem:
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


class PassObjective:
    """One pass's objective for L-BFGS-B over z = (chi / chi_hi, psi): the design model plus the
    pass's defect, scaled to J of order 1 (L-BFGS-B's first step and its ftol test depend on J's
    scale).

    Parameters
    ----------
    problem : SurfaceProblem
        The design problem.
    defect : numpy.ndarray, shape (P, 3)
        The full model's flow less the design model's at the pass's start.
    scale : float
        The factor of J.
    threshold : float or None
        :func:`design_surface`'s ``threshold``.
    """

    def __init__(self, problem: SurfaceProblem, defect: np.ndarray, scale: float, threshold: float | None):
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
