"""Periodic-orbit solvers for the Galerkin filament: the contract and its methods.

A periodic orbit of ``M(y) y' = f(y)`` (:mod:`single_cilium.filament`) is a pair ``(y0, T)``
with ``Phi(y0, T) = y0``, ``Phi`` the period map, and a phase condition that fixes the start on
the orbit: here the Poincare section ``theta_tip(y0) = c``. :func:`single_cilium.limit_cycle`
drives any method through this contract and does everything else once (seeding, the phase-0
section, averaging, Floquet multipliers, error estimates, the choice of ``n_phase``).

The contract (like ``scipy.integrate.OdeSolver``)
-------------------------------------------------
An orbit method is a subclass of :class:`OrbitSolver`, registered in :data:`METHODS` under its
name, constructed as ``Method(filament, n_phase)`` (``n_phase`` steps per period: the uniform
phase grid of the result), and provides

``converge(y0, T, c, tol, jacobian=None) -> Orbit``
    Newton's method from the guess ``(y0, T)`` for the orbit through the section
    ``theta_tip = c``, to ``max |scaled residual| <= tol``. Returns the converged
    :class:`Orbit`: its states and rates on the phase grid, the period, and either the
    monodromy matrix (``dPhi/dy0``) or, when the method cannot form it cheaply, ``None``.
    Raises :class:`OrbitError` (message says what to change) when it does not converge or a
    step fails (``OrbitError.step_failed``: the phase grid is too coarse). ``jacobian``, an
    orbit of the same filament nearby (e.g. with fewer steps per period), may be used as the
    Newton Jacobian instead of a fresh one.
``at_phase(y0, orbit) -> Orbit``
    The converged ``orbit`` sampled from another start ``y0`` on it (one period map; used to
    start the result at phase 0). Its ``monodromy`` is the orbit's, taken where Newton
    converged: similar to the one at ``y0`` (the same multipliers).
``advance(y, dt) -> y``
    The state after time ``dt`` (``0 <= dt <= T / n_phase``) on the same discretisation
    (used to move the start onto the phase-0 section).
``multipliers(orbit) -> (k,) complex``
    Floquet multipliers, largest modulus first, the trivial one (closest to 1) first of all.
    The base class takes the eigenvalues of ``orbit.monodromy``.
``work`` : dict
    Counters: ``period_maps``, ``newton`` (orbit Newton iterations), ``step_newton`` (Newton
    iterations inside the implicit steps), ``factorizations``, and method-specific ones.

Methods
-------
``"shooting"`` (:class:`ExactShooting`, the default)
    Single shooting with the exact monodromy. A period is ``n_phase`` Radau IIA(5) steps of
    constant size ``h = T / n_phase``, all in one compiled (numba) call,
    :func:`single_cilium._kernels.radau_steps`. The kappa stages are eliminated exactly (they
    are linear in kappa), leaving ``3 (n - 1)`` theta-stage unknowns per step; these are solved
    by RADAU5's simplified Newton (one real and one complex ``(n - 1)``-square system, with the
    derivative of the drag matrix included), with full Newton as the fallback. At the converged
    stages the exact stage Jacobian is factorised once, and the implicit function theorem gives
    the step's derivative with respect to its start and to ``h``; their product over a period
    is the exact derivative of the discrete period map. Newton on the ``N + 1`` shooting
    unknowns (``N = 2n - 1``, about 80) then converges quadratically (2-3 iterations from a
    continuation predictor, 5-7 from the Hopf mode), and the Floquet multipliers are the
    eigenvalues of the monodromy at no extra cost. A re-solve with more steps per period (or
    fewer, for the error estimate) starts from the same ``(y0, T)`` and uses the coarser
    monodromy as a chord Jacobian: period maps without sensitivities, about 3x cheaper.

    Why the exact monodromy: with finite-difference monodromy products, GMRES needs 15-30
    products per Newton step (the kappa relaxation puts a cluster of multipliers near
    ``exp(-T)``); the exact Jacobian needs none. Why not orthogonal collocation (AUTO,
    MatCont): the state is small, so the dense ``N x N`` monodromy is cheap (a period costs
    ``n_phase`` small factorisations either way); the stiff steps keep Radau's L-stability and
    the step solver tested against the integrator; the orbit Newton has ``N + 1`` unknowns
    instead of ``3 n_phase N``; and refining ``n_phase`` reuses ``(y0, T)`` unchanged.
    Shooting's weakness, an unstable orbit amplifying errors over a period, does not arise:
    these cycles are stable and the stiff modes are contracted to ~0 by the L-stable steps.
    Costs against ``"newton-krylov"``: ``benchmarks/results/bench_cycles.md``.
``"newton-krylov"`` (:class:`KrylovShooting`, a cross-check of ``"shooting"``)
    The same period map (:meth:`single_cilium.radau.Radau.fixed`, simplified Newton in Python);
    Newton-Krylov (GMRES on finite-difference monodromy products); Floquet multipliers by
    Arnoldi on the deflated monodromy.
"""
from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from scipy.sparse.linalg import LinearOperator, gmres

from ._kernels import radau_steps
from cilia_runtime.signals import native_call
from .filament import Filament
from .radau import A_INV
from .radau import P as _P
from .radau import ConvergenceError, Radau

logger = logging.getLogger(__name__)

__all__ = ["Orbit", "OrbitSolver", "OrbitError", "ExactShooting", "KrylovShooting", "METHODS"]



class OrbitError(ConvergenceError):
    """The orbit could not be converged. ``step_failed``: an implicit step failed (more steps
    per period are needed); otherwise Newton did not converge from the guess."""

    def __init__(self, message: str, t: float = 0.0, step_failed: bool = False):
        super().__init__(message, t)
        self.step_failed = step_failed


@dataclass(frozen=True, eq=False)
class Orbit:
    """A converged periodic orbit on the uniform phase grid (what :meth:`OrbitSolver.converge`
    returns).

    Attributes
    ----------
    state0 : (N,) the start, on the section.
    period : float
    states, rates : (n_phase + 1, N)
        The states at phases ``k / n_phase``, ``k = 0..n_phase`` (the last closes the orbit),
        and their time derivatives (of the collocation polynomial at each step end; at phase 0
        of the first step's).
    monodromy : (N, N) or None
        ``dPhi/dy0`` of the discrete period map, if the method forms it (at ``state0``, or
        after :meth:`OrbitSolver.at_phase` at another point of the same orbit).
    residual : float
        Final ``max |scaled residual|`` of the shooting equations.
    period_derivative : (N,) or None
        ``dPhi/dh`` (``h = T / n_steps``), with the monodromy.
    n_steps : int
        Steps per period (default: ``len(states) - 1``).
    """

    state0: np.ndarray | None
    period: float
    states: np.ndarray | None
    rates: np.ndarray | None
    monodromy: np.ndarray | None
    residual: float
    period_derivative: np.ndarray | None = None
    n_steps: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "period", float(self.period))
        object.__setattr__(self, "residual", float(self.residual))
        if not self.n_steps:
            object.__setattr__(self, "n_steps", len(self.states) - 1)


class OrbitSolver(ABC):
    """Base class of the orbit methods (see the module docstring for the contract)."""

    name = ""

    def __init__(self, fil: Filament, n_phase: int):
        self.fil = fil
        self.n_phase = int(n_phase)
        self.scale = fil.scale
        self.i_tip = fil.n - 2  # theta at the tip, in the state vector
        self.work = {"period_maps": 0, "newton": 0, "step_newton": 0, "factorizations": 0}

    @abstractmethod
    def converge(self, y0: np.ndarray, T: float, c: float, tol: float, jacobian: Orbit | None = None) -> Orbit:
        """The orbit through the section ``theta_tip = c`` from the guess ``(y0, T)``."""

    @abstractmethod
    def at_phase(self, y0: np.ndarray, orbit: Orbit) -> Orbit:
        """The converged ``orbit`` sampled from another start ``y0`` on it (one period map)."""

    @abstractmethod
    def advance(self, y: np.ndarray, dt: float) -> np.ndarray:
        """The state after time ``dt <= T / n_phase`` from ``y``."""

    @abstractmethod
    def orbit_states(self, y0: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray]:
        """States and rates at the ``n_phase + 1`` step ends of one period (length ``T``) from ``y0``."""

    def multipliers(self, orbit: Orbit) -> np.ndarray:
        """Eigenvalues of the monodromy, the trivial one (closest to 1) first, then by modulus."""
        w = np.linalg.eigvals(orbit.monodromy)
        k = int(np.argmin(np.abs(w - 1.0)))
        rest = np.delete(w, k)
        return np.concatenate([[w[k]], rest[np.argsort(-np.abs(rest))]])

    def _damped(self, y0, T, step_y, step_T):
        """Damp wild Newton steps (far from the orbit): keep |dtheta| moderate and T positive."""
        lam = 1.0
        big = float(np.max(np.abs(step_y[: self.fil.n - 1])))
        if big > 0.5:
            lam = 0.5 / big
        if T + lam * step_T <= 0.2 * T:
            lam = min(lam, 0.8 * T / abs(step_T))
        return y0 + lam * step_y, T + lam * step_T


class ExactShooting(OrbitSolver):
    """Shooting with the exact monodromy of the compiled Radau period map (module docstring)."""

    name = "shooting"
    #: stage Newton tolerance (absolute, on theta increments) and iteration limit
    step_tol = 1e-12
    step_maxiter = 10
    #: the longest (estimated) single call of the compiled period map: signals wait for a call
    call_seconds = 2.0

    def __init__(self, fil: Filament, n_phase: int):
        super().__init__(fil, n_phase)
        m = fil.mesh
        self._args = (A_INV, _P, np.ascontiguousarray(m.cumulative), np.ascontiguousarray(m.weights),
                      np.ascontiguousarray(fil._K), np.ascontiguousarray(fil._B), float(fil.params.eta),
                      float(fil.params.chi_E), float(fil.params.chi_N), self.step_tol, self.step_maxiter,
                      float(fil.params.background[0]), float(fil.params.background[1]))

    def _steps(self, y0, h, n, sens):
        """``n`` steps of size ``h`` from ``y0`` by the compiled kernel, in calls of at most
        :attr:`call_seconds` (estimated) each: a signal is handled between calls (a kernel cannot
        be interrupted), and the pieces are joined (the monodromy and its derivative in ``h``
        by the chain rule)."""
        N = y0.size
        per_step = (1.5e-8 if sens else 1e-9) * float(N) ** 3
        chunk = max(1, int(self.call_seconds / per_step))
        Ys, Yds, S, Sh = [], [], None, None
        counts = np.array([0, 0, -1], dtype=np.int64)
        y, done = np.ascontiguousarray(y0, dtype=float), 0
        while done < n:
            k = min(chunk, int(n) - done)
            with native_call():  # a signal meanwhile waits for the kernel (cilia_runtime.signals)
                Yc, Ydc, Sc, Shc, cc = radau_steps(y, float(h), k, sens, *self._args)
            counts[:2] += cc[:2]
            Ys.append(Yc if done == 0 else Yc[1:])
            Yds.append(Ydc if done == 0 else Ydc[1:])
            S, Sh = (Sc, Shc) if S is None else ((Sc @ S, Sc @ Sh + Shc) if sens else (S, Sh))
            done += k
            if cc[2] >= 0:
                counts[2] = done - k + cc[2]
                break
            y = np.ascontiguousarray(Yc[-1])
        Y, Yd = (Ys[0], Yds[0]) if len(Ys) == 1 else (np.concatenate(Ys), np.concatenate(Yds))
        self.work["step_newton"] += int(counts[0])
        self.work["factorizations"] += int(counts[1])
        if counts[2] >= 0 or not np.all(np.isfinite(Y[-1])):
            raise OrbitError(f"an implicit Radau step (h = {h:.3g}) failed at step {int(counts[2])}: the "
                             "period needs more steps", float(max(counts[2], 0) * h), step_failed=True)
        return Y, Yd, S, Sh

    def orbit_states(self, y0, T):
        self.work["period_maps"] += 1
        Y, Yd, _, _ = self._steps(y0, T / self.n_phase, self.n_phase, False)
        return Y, Yd

    def advance(self, y, dt):
        if dt <= 0:
            return np.array(y, dtype=float)
        return self._steps(y, dt, 1, False)[0][-1]

    def converge(self, y0, T, c, tol, max_newton=25, jacobian: Orbit | None = None):
        """Newton's method on ``Phi(y0, T) = y0``, ``theta_tip(y0) = c``.

        With ``jacobian`` (an orbit of the same filament, e.g. the same cycle with fewer steps
        per period) its monodromy is used (a chord method: every iteration then costs a period
        map without sensitivities); the exact monodromy is formed instead as soon as the chord
        iteration contracts by less than a factor 10 per step. The returned orbit carries the
        monodromy used last.
        """
        N = y0.size
        n = self.n_phase
        sc = self.scale
        y0, T = np.array(y0, dtype=float), float(T)
        T_start = T
        res = prev = math.inf
        chord = jacobian is not None and jacobian.monodromy is not None and jacobian.monodromy.shape == (N, N)
        S = jacobian.monodromy if chord else None
        Sh = jacobian.period_derivative * (n / jacobian.n_steps) if chord else None  # dPhi/dT = Sh / n
        for it in range(max_newton + 1):
            self.work["period_maps"] += 1
            sens = not chord
            Y, Yd, S_new, Sh_new = self._steps(y0, T / n, n, sens)
            if sens:
                S, Sh = S_new, Sh_new
            r = np.concatenate([(Y[-1] - y0) / sc, [y0[self.i_tip] - c]])
            res = float(np.max(np.abs(r)))
            logger.debug("shooting it %d (%s): residual %.3e, T %.12g", it, "chord" if chord else "exact", res, T)
            if not np.isfinite(res):
                raise OrbitError("the period map produced non-finite values")
            if res <= tol:
                return Orbit(y0, T, Y, Yd, S, res, Sh, n)
            if it == max_newton:
                break
            if chord and res > 0.1 * prev:
                chord = False  # the borrowed Jacobian is not good enough here: form the exact one
                self.work["period_maps"] += 1
                _, _, S, Sh = self._steps(y0, T / n, n, True)
            prev = res
            self.work["newton"] += 1
            # scaled unknowns (y0 / scale, T): J = [[D^-1 (S - I) D, D^-1 Sh / n], [e_tip, 0]]
            J = np.zeros((N + 1, N + 1))
            J[:N, :N] = (S - np.eye(N)) * (sc[None, :] / sc[:, None])
            J[:N, N] = Sh / n / sc
            J[N, self.i_tip] = sc[self.i_tip]
            try:
                dx = np.linalg.solve(J, -r)
            except np.linalg.LinAlgError:
                raise OrbitError("singular shooting Jacobian (the guess is at the equilibrium or the "
                                 "section is tangent to the orbit)") from None
            y0, T = self._damped(y0, T, dx[:N] * sc, dx[N])
            if T < 0.05 * T_start:
                raise OrbitError(f"the period collapses ({T:.3g} from {T_start:.3g}): Newton is heading for the "
                                 "equilibrium, not the cycle")
        raise OrbitError(f"shooting did not converge in {max_newton} Newton iterations (residual {res:.2e}); "
                         "the guess may be too far from the cycle")

    def at_phase(self, y0, orbit):
        self.work["period_maps"] += 1
        Y, Yd = self._steps(y0, orbit.period / self.n_phase, self.n_phase, False)[:2]
        res = float(np.max(np.abs(Y[-1] - y0) / self.scale))
        return Orbit(np.array(y0, dtype=float), orbit.period, Y, Yd, orbit.monodromy, res,
                     orbit.period_derivative, self.n_phase)


class KrylovShooting(OrbitSolver):
    """Newton-Krylov shooting on the Python Radau period map (a cross-check of :class:`ExactShooting`)."""

    name = "newton-krylov"

    def __init__(self, fil: Filament, n_phase: int):
        super().__init__(fil, n_phase)
        self.solver = Radau(fil, rtol=1e-12, atol=1e-12 * fil.scale)
        self.work["gmres"] = 0
        self._last = None  # the last period map: converged orbits are mapped by several steps

    def _pmap(self, y0, T):
        key = (y0.tobytes(), float(T))
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        self.work["period_maps"] += 1
        try:
            Y, Yd, stats = self.solver.fixed(y0, T / self.n_phase, self.n_phase)
        except ConvergenceError as exc:
            raise OrbitError(f"{exc}; the period is split into n_phase={self.n_phase} steps", exc.t,
                             step_failed=True) from None
        self.work["step_newton"] += stats.n_newton
        self.work["factorizations"] += stats.n_factorizations
        self._last = (key, (Y, Yd))
        return Y, Yd

    def orbit_states(self, y0, T):
        return self._pmap(np.asarray(y0, dtype=float), T)

    def at_phase(self, y0, orbit):
        y0 = np.array(y0, dtype=float)
        Y, Yd = self._pmap(y0, orbit.period)
        return Orbit(y0, orbit.period, Y, Yd, None, float(np.max(np.abs(Y[-1] - y0) / self.scale)))

    def advance(self, y, dt):
        if dt <= 0:
            return np.array(y, dtype=float)
        return self.solver.fixed(y, dt, 1)[0][-1]

    def converge(self, y0, T, c, tol, max_newton=20, jacobian=None):
        N = y0.size
        sc = self.scale
        y0, T = np.array(y0, dtype=float), float(T)
        res = math.inf
        for it in range(max_newton + 1):
            Y, Yd = self._pmap(y0, T)
            r = np.concatenate([(Y[-1] - y0) / sc, [y0[self.i_tip] - c]])
            res = float(np.max(np.abs(r)))
            logger.debug("newton-krylov it %d: residual %.3e, T %.10g", it, res, T)
            if not np.isfinite(res):
                raise OrbitError("the period map produced non-finite values")
            if res <= tol:
                return Orbit(y0, T, Y, Yd, None, res)
            if it == max_newton:
                break
            self.work["newton"] += 1
            yend = Y[-1]
            y_c, T_c = y0, T

            def matvec(v):
                dy = v[:N] * sc
                dT = v[N] * T_c
                eps = 1e-7 / max(np.max(np.abs(v)), 1e-300)
                Yp, _ = self._pmap(y_c + eps * dy, T_c + eps * dT)
                return np.concatenate([((Yp[-1] - yend) / eps - dy) / sc, [dy[self.i_tip]]])

            A = LinearOperator((N + 1, N + 1), matvec=matvec, dtype=float)
            count = [0]

            def cb(_):
                count[0] += 1

            # inexact Newton: the linear solve need only beat the current residual
            forcing = min(1e-2, max(1e-6, res))
            dx, _ = gmres(A, -r, rtol=forcing, atol=0.0, restart=60, maxiter=2, callback=cb,
                          callback_type="pr_norm")
            self.work["gmres"] += count[0]
            y0, T = self._damped(y0, T, dx[:N] * sc, dx[N] * T)
        raise OrbitError(f"Newton-Krylov shooting did not converge in {max_newton} iterations "
                         f"(residual {res:.2e}); the guess may be too far from the cycle")

    def multipliers(self, orbit: Orbit, m: int = 12, n_power: int = 3) -> np.ndarray:
        """Arnoldi on finite-difference monodromy products, deflated by the flow direction.

        The trivial multiplier belongs to ``u = y'(0)``: measured as ``u . A u / |u|^2``. The
        others are Ritz values of ``n_power`` power steps and an ``m``-step Arnoldi run on ``A``
        deflated by the projector onto ``u`` (``m + n_power + 2`` period maps); the largest
        non-trivial modulus is resolved to a few digits.
        """
        y0, T = orbit.state0, orbit.period
        sc = self.scale
        yend = orbit.states[-1]
        N = y0.size

        def A(v):
            eps = 1e-7 / max(np.max(np.abs(v)), 1e-300)
            Yp, _ = self._pmap(y0 + eps * v * sc, T)
            return (Yp[-1] - yend) / eps / sc

        u = orbit.rates[-1] / sc
        u /= np.linalg.norm(u)
        triv = float(u @ A(u))

        def B(v):
            w = A(v - (u @ v) * u)
            return w - (u @ w) * u

        q = np.random.default_rng(12345).standard_normal(N)
        q -= (u @ q) * u
        for _ in range(n_power):
            q = B(q / np.linalg.norm(q))
        Qm = np.zeros((N, m + 1))
        H = np.zeros((m + 1, m))
        Qm[:, 0] = q / np.linalg.norm(q)
        k_done = m
        for j in range(m):
            w = B(Qm[:, j])
            for _ in range(2):  # Gram-Schmidt, twice
                cj = Qm[:, : j + 1].T @ w
                H[: j + 1, j] += cj
                w -= Qm[:, : j + 1] @ cj
            H[j + 1, j] = np.linalg.norm(w)
            if H[j + 1, j] < 1e-12:
                k_done = j + 1
                break
            Qm[:, j + 1] = w / H[j + 1, j]
        ritz = np.linalg.eigvals(H[:k_done, :k_done])
        ritz = ritz[np.argsort(-np.abs(ritz))]
        return np.concatenate([[triv], ritz[:5]])


#: orbit methods by name (``limit_cycle(params, method=...)``)
METHODS: dict[str, type[OrbitSolver]] = {"shooting": ExactShooting, "newton-krylov": KrylovShooting}
