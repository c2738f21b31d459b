"""Radau IIA (order 5, three stages) for stiff systems with a state-dependent mass matrix.

Solves ``M(y) y' = f(y)`` with ``M(y)`` symmetric positive definite (or any non-singular mass),
following Hairer & Wanner, *Solving ODEs II*, section IV.8 (RADAU5), in the formulation of
scipy.integrate.Radau, with two changes that matter here:

* the stage residual uses the exact ``M(Y_i)`` at each stage,
  ``G_i = f(Y_i) - M(Y_i) K_i``, ``K = h^-1 A^-1 Z``; the simplified Newton matrices
  ``mu/h M(y_n) - J(y_n)`` are factorised by the problem itself (which can exploit its
  structure, e.g. a Schur complement) and reused across Newton iterations and, while Newton
  converges fast and ``h`` is unchanged, across steps;
* steps are clipped to land exactly on the requested output times, so outputs carry the full
  order-5 accuracy rather than the O(h^4) of the collocation polynomial.

The method is L-stable and stiffly accurate; its embedded error estimate (order 3) drives a
predictive (Gustafsson) step-size controller.

Problem interface
-----------------
A problem passed to :class:`Radau` must provide

``size`` : int
    length of ``y``.
``rhs(Y) -> F``
    ``f`` evaluated row-wise on stacked states ``Y`` of shape ``(k, size)``.
``mass_apply(Y, V) -> MV``
    ``M(Y_i) V_i`` row-wise, shapes ``(k, size)``.
``residual(Y, K) -> G``
    the stage residuals ``f(Y_i) - M(Y_i) K_i`` row-wise (``rhs(Y) - mass_apply(Y, K)``, which
    a problem may evaluate faster in one go).
``factor(y, sigmas) -> list``
    for each ``sigma`` (one real, one complex), an object whose ``solve(b)`` solves
    ``(sigma M(y) - J(y)) x = b`` (``J`` an approximation of ``df/dy``).

The tableau
-----------
This module is the one home of the Radau IIA(5) tableau: the nodes :data:`C`, the Butcher
matrix :data:`A` (and :data:`A_INV`), the eigen-decomposition of ``A^-1`` (:data:`MU_REAL`,
:data:`MU_COMPLEX`, :data:`T`, :data:`TI`), the error weights :data:`E` and the collocation
polynomial :data:`P`. The compiled period map (``single_cilium._kernels``) and the orbit solver
(:mod:`single_cilium.orbit`) take them from here.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

logger = logging.getLogger(__name__)

__all__ = ["Radau", "RadauStats", "ConvergenceError", "StepProblem"]

S6 = 6.0**0.5
C = np.array([(4 - S6) / 10, (4 + S6) / 10, 1.0])
A = np.array([
    [(88 - 7 * S6) / 360, (296 - 169 * S6) / 1800, (-2 + 3 * S6) / 225],
    [(296 + 169 * S6) / 1800, (88 + 7 * S6) / 360, (-2 - 3 * S6) / 225],
    [(16 - S6) / 36, (16 + S6) / 36, 1 / 9]])
"""The Butcher matrix; :data:`C` its nodes (the row sums)."""
A_INV = np.linalg.inv(A)
E = np.array([-13 - 7 * S6, -13 + 7 * S6, -1.0]) / 3
MU_REAL = 3 + 3 ** (2 / 3) - 3 ** (1 / 3)
MU_COMPLEX = 3 + 0.5 * (3 ** (1 / 3) - 3 ** (2 / 3)) - 0.5j * (3 ** (5 / 6) + 3 ** (7 / 6))
T = np.array([
    [0.09443876248897524, -0.14125529502095421, 0.03002919410514742],
    [0.25021312296533332, 0.20412935229379994, -0.38294211275726192],
    [1.0, 1.0, 0.0]])
TI = np.array([
    [4.17871859155190428, 0.32768282076106237, 0.52337644549944951],
    [-4.17871859155190428, -0.32768282076106237, 0.47662355450055044],
    [0.50287263494578682, -2.57192694985560522, 0.59603920482822492]])
TI_REAL = TI[0]
TI_COMPLEX = TI[1] + 1j * TI[2]
# collocation polynomial coefficients (dense output / predictor), as in scipy
P = np.array([
    [13 / 3 + 7 * S6 / 3, -23 / 3 - 22 * S6 / 3, 10 / 3 + 5 * S6],
    [13 / 3 - 7 * S6 / 3, -23 / 3 + 22 * S6 / 3, 10 / 3 - 5 * S6],
    [1 / 3, -8 / 3, 10 / 3]])
NEWTON_MAXITER = 6
MIN_FACTOR = 0.2
MAX_FACTOR = 10.0
EPS = np.finfo(float).eps


class ConvergenceError(RuntimeError):
    """The integrator could not continue. ``t`` is the time reached, ``stats`` the work done."""

    def __init__(self, message: str, t: float, stats: "RadauStats | None" = None):
        super().__init__(message)
        self.t = t
        self.stats = stats


class StepProblem(Protocol):
    size: int

    def rhs(self, Y: np.ndarray) -> np.ndarray: ...
    def mass_apply(self, Y: np.ndarray, V: np.ndarray) -> np.ndarray: ...
    def residual(self, Y: np.ndarray, K: np.ndarray) -> np.ndarray: ...
    def factor(self, y: np.ndarray, sigmas) -> list: ...


@dataclass
class RadauStats:
    """Work counters of one integration."""

    n_steps: int = 0
    n_accepted: int = 0
    n_rejected: int = 0
    n_newton_failures: int = 0
    n_rhs: int = 0
    n_newton: int = 0
    n_factorizations: int = 0
    h_min: float = math.inf
    h_max: float = 0.0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class Radau:
    """Radau IIA(5) integrator for ``M(y) y' = f(y)`` (see the module docstring).

    Parameters
    ----------
    problem : StepProblem
    rtol : float
        Relative tolerance of the local error.
    atol : array_like
        Absolute tolerance, scalar or per component.
    h0 : float, optional
        First step (default ``1e-4``, adapted within a few steps).
    max_steps : int
        Guard against hangs: a :class:`ConvergenceError` is raised beyond it.
    """

    def __init__(self, problem: StepProblem, rtol: float, atol, h0: float | None = None,
                 max_steps: int = 1_000_000):
        if not (0 < rtol < 1):
            raise ValueError(f"rtol must lie in (0, 1), got {rtol}")
        self.problem = problem
        self.rtol = float(rtol)
        self.atol = np.broadcast_to(np.asarray(atol, dtype=float), (problem.size,)).copy()
        if np.any(~np.isfinite(self.atol)) or np.any(self.atol <= 0):
            raise ValueError("atol must be finite and > 0")
        self.h0 = h0
        self.max_steps = int(max_steps)
        self.newton_tol = max(10 * EPS / self.rtol, min(0.03, self.rtol**0.5))

    # ------------------------------------------------------------------
    def integrate(self, y0: np.ndarray, t_out: np.ndarray,
                  callback: Callable[[float, np.ndarray], None] | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, RadauStats]:
        """Integrate from ``t_out[0]`` (state ``y0``) through the increasing times ``t_out``.

        Returns the states at ``t_out`` (shape ``(len(t_out), size)``), their time derivatives
        (same shape; the derivative of the collocation polynomial at the end of the step that
        lands on each output time, and at the initial time that of the first step's polynomial
        at its start) and the work counters.
        ``callback(t, y)`` is called after each accepted step.
        """
        prob = self.problem
        t_out = np.asarray(t_out, dtype=float)
        y = np.array(y0, dtype=float)
        stats = RadauStats()
        out = np.empty((t_out.size, y.size))
        out_dot = np.full((t_out.size, y.size), np.nan)
        out[0] = y
        t = float(t_out[0])
        t_end = float(t_out[-1])
        if t_end <= t:
            return out, out_dot, stats
        h = self.h0 if self.h0 is not None else min(1e-4, 0.1 * (t_end - t))
        h_old = None
        err_old = None
        f = prob.rhs(y[None])[0]
        stats.n_rhs += 1
        if not np.all(np.isfinite(f)):
            raise ConvergenceError("the right-hand side is not finite at the initial state", t, stats)
        lu_real = lu_complex = None
        h_fact = None
        fact_current = False  # factorisation built at the current y (and h_fact)
        Z_prev = None  # stages of the last accepted step, for the predictor
        h_prev = None
        rejected = False
        k_out = 1
        while k_out < t_out.size:
            if stats.n_steps >= self.max_steps:
                raise ConvergenceError(
                    f"max_steps={self.max_steps} reached at t={t:.6g}; the problem may be much stiffer or "
                    "longer than expected: raise max_steps or loosen the tolerance", t, stats)
            if h < 10 * EPS * max(abs(t), 1.0):
                raise ConvergenceError(
                    f"step size fell to {h:.3g} at t={t:.6g}: the state has left the range the "
                    "discretisation can represent (refine the mesh, loosen the tolerance, or check the "
                    "initial state)", t, stats)
            remaining = t_out[k_out] - t
            # land on the output time when the step reaches it, to round-off
            landing = h >= remaining - 16 * EPS * max(abs(t_out[k_out]), 1.0)
            h_take = remaining if landing else h
            if lu_real is None or h_fact != h_take:
                lu_real, lu_complex = prob.factor(y, (MU_REAL / h_take, MU_COMPLEX / h_take))
                stats.n_factorizations += 2
                h_fact, fact_current = h_take, True

            # predictor: extrapolate the collocation polynomial of the last step
            if Z_prev is None:
                Z0 = np.zeros((3, y.size))
            else:
                x = 1.0 + h_take * C / h_prev
                Q = Z_prev.T @ P
                xp = x[:, None] ** np.arange(1, 4)[None, :]
                Z0 = xp @ Q.T - Q.sum(axis=1)[None, :]
            scale = self.atol + np.abs(y) * self.rtol
            converged, n_iter, Z, rate, yp_new = self._newton(y, h_take, Z0, scale, lu_real, lu_complex, stats)
            stats.n_steps += 1
            if not converged:
                stats.n_newton_failures += 1
                if fact_current:
                    h = 0.5 * h_take
                lu_real = None
                continue

            y_new = y + Z[-1]
            ZE = E @ Z / h_take
            MZE = prob.mass_apply(y[None], ZE[None])[0]
            error = np.real(lu_real.solve(f + MZE))
            scale = self.atol + np.maximum(np.abs(y), np.abs(y_new)) * self.rtol
            err = _rms(error / scale)
            if err > 1 and (rejected or stats.n_accepted == 0):
                f_try = prob.rhs((y + error)[None])[0]
                stats.n_rhs += 1
                if np.all(np.isfinite(f_try)):
                    err = _rms(np.real(lu_real.solve(f_try + MZE)) / scale)
            safety = 0.9 * (2 * NEWTON_MAXITER + 1) / (2 * NEWTON_MAXITER + n_iter)
            if not np.isfinite(err) or err > 1:
                stats.n_rejected += 1
                rejected = True
                factor = MIN_FACTOR if not np.isfinite(err) else max(MIN_FACTOR, safety * err ** -0.25)
                h = h_take * factor
                continue

            # accepted
            if stats.n_accepted == 0:
                # derivative at the initial time: of the first step's collocation polynomial,
                # u(t0 + x h) = y0 + (Z^T P) (x, x^2, x^3); well conditioned, unlike M^-1 f(y0)
                out_dot[0] = (Z.T @ P[:, 0]) / h_take
            stats.n_accepted += 1
            stats.h_min = min(stats.h_min, h_take)
            stats.h_max = max(stats.h_max, h_take)
            refresh = n_iter > 2 and rate is not None and rate > 1e-3
            if err_old is None or h_old is None or err == 0:
                mult = 1.0
            else:
                mult = h_take / h_old * (err_old / err) ** 0.25
            # err is a Python float: 0 ** -0.25 raises (an exact steady state, e.g. amplitude 0)
            factor = min(1.0, mult) * err ** -0.25 if err > 0 else MAX_FACTOR
            factor = min(MAX_FACTOR, safety * factor)
            if not refresh and factor < 1.2 and not rejected:
                factor = 1.0  # keep h: the factorisations stay valid
            h_next = h_take * factor
            if landing and h_take < h:
                h_next = max(h_next, h)  # resume the natural step after landing on an output time
            h_old, err_old = h_take, err
            rejected = False
            t = float(t_out[k_out]) if landing else t + h_take
            y = y_new
            Z_prev, h_prev = Z, h_take
            f = prob.rhs(y[None])[0]
            stats.n_rhs += 1
            fact_current = False
            if refresh:
                lu_real = None
            h = h_next
            if landing:
                out[k_out] = y
                out_dot[k_out] = yp_new
                k_out += 1
            if callback is not None:
                callback(t, y)
        return out, out_dot, stats

    # ------------------------------------------------------------------
    def fixed(self, y0: np.ndarray, h: float, n_steps: int) -> tuple[np.ndarray, np.ndarray, RadauStats]:
        """``n_steps`` steps of constant size ``h`` from ``y0``, without error control.

        The result is a smooth function of ``y0`` and ``h`` (the same arithmetic for nearby
        inputs, Newton converged to round-off), as finite-difference derivatives of a period map
        need. Returns the states and their derivatives (collocation polynomial) at the
        ``n_steps + 1`` step ends, shape ``(n_steps + 1, size)``, and the work counters.
        Raises :class:`ConvergenceError` when Newton fails (the step is too large).
        """
        prob = self.problem
        y = np.array(y0, dtype=float)
        stats = RadauStats()
        out = np.empty((n_steps + 1, y.size))
        out_dot = np.empty_like(out)
        out[0] = y
        out_dot[0] = np.nan
        scale = self.atol + np.abs(y) * self.rtol
        Z_prev = None
        for k in range(n_steps):
            lu_real, lu_complex = prob.factor(y, (MU_REAL / h, MU_COMPLEX / h))
            stats.n_factorizations += 2
            if Z_prev is None:
                Z0 = np.zeros((3, y.size))
            else:
                Q = Z_prev.T @ P
                xp = (1.0 + C)[:, None] ** np.arange(1, 4)[None, :]
                Z0 = xp @ Q.T - Q.sum(axis=1)[None, :]
            converged, n_iter, Z, rate, yp = self._newton(y, h, Z0, scale, lu_real, lu_complex, stats,
                                                          maxiter=3 * NEWTON_MAXITER, floor=1.0)
            if not converged:
                raise ConvergenceError(
                    f"fixed step h={h:.3g} too large at step {k} (Newton did not converge): use more steps",
                    k * h, stats)
            if k == 0:
                out_dot[0] = (Z.T @ P[:, 0]) / h
            y = y + Z[-1]
            Z_prev = Z
            out[k + 1] = y
            out_dot[k + 1] = yp
            stats.n_steps += 1
            stats.n_accepted += 1
        stats.h_min = stats.h_max = h
        return out, out_dot, stats

    # ------------------------------------------------------------------
    def _newton(self, y, h, Z0, scale, lu_real, lu_complex, stats, maxiter=NEWTON_MAXITER, floor=0.0):
        """Simplified Newton for the stages. Converged when the predicted remaining increment is
        below ``newton_tol``, or when an increment is below ``floor`` (scaled) and the iteration
        has stalled at round-off."""
        prob = self.problem
        tol = self.newton_tol
        W = TI @ Z0
        Z = Z0
        dW_norm_old = None
        rate = None
        converged = False
        k = 0
        for k in range(maxiter):
            Y = y[None, :] + Z
            LW = np.empty_like(W)
            LW[0] = MU_REAL * W[0]
            wc = MU_COMPLEX * (W[1] + 1j * W[2])
            LW[1], LW[2] = wc.real, wc.imag
            K = (T @ LW) / h
            G = prob.residual(Y, K)
            stats.n_rhs += 3
            stats.n_newton += 1
            if not np.all(np.isfinite(G)):
                break
            dW_real = lu_real.solve(TI_REAL @ G)
            dW_complex = lu_complex.solve(TI_COMPLEX @ G)
            dW = np.stack([np.real(dW_real), dW_complex.real, dW_complex.imag])
            dW_norm = _rms(dW / scale)
            if not np.isfinite(dW_norm):
                break
            if dW_norm_old is not None:
                rate = dW_norm / dW_norm_old
            if rate is not None and (rate >= 1 or rate ** (maxiter - k) / (1 - rate) * dW_norm > tol):
                if dW_norm <= floor:
                    converged = True
                break
            W = W + dW
            Z = T @ W
            if dW_norm == 0 or (rate is not None and rate / (1 - rate) * dW_norm < tol):
                converged = True
                break
            dW_norm_old = dW_norm
        # derivative of the collocation polynomial at the step end (the last stage):
        # M(y_new) u'(t_new) = f(y_new) holds there to the Newton tolerance, and, unlike
        # M^-1 f(y_new), it does not amplify round-off by the stiffness ratio.
        w_end = MU_COMPLEX * (W[1] + 1j * W[2])
        yp_end = (T[2, 0] * MU_REAL * W[0] + T[2, 1] * w_end.real + T[2, 2] * w_end.imag) / h
        return converged, k + 1, Z, rate, yp_end


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))
