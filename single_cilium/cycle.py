"""Limit cycles of a fluttering filament and the thrust they exert (MODEL.md section 5).

Method: shooting on the Galerkin system of :mod:`single_cilium.filament`. The period map
``Phi(y0, T)`` is ``N`` constant steps ``h = T / N`` of Radau IIA(5) (:meth:`Radau.fixed`), a
smooth function of ``(y0, T)``; the periodic orbit solves

    Phi(y0, T) - y0 = 0,      theta_tip(y0) = c        (a Poincare section),

by Newton's method with GMRES on finite-difference products of the monodromy (Newton-Krylov):
the system is stiff, so all but a handful of Floquet multipliers are ~0 and GMRES converges in
a few iterations, far cheaper than forming the monodromy matrix or integrating through the
transient (which near the flutter cutoff lasts hundreds of periods; see the benchmark).

The ``N`` step ends are the uniform phase grid of the result, so cycle averages are trapezoid
sums of a periodic function: exponentially accurate in ``N`` beyond the integrator's own
order-5 error, and the averaging window is exactly one period.

Phase 0 is the upward crossing of the tip angle ``theta(1)`` through its mean over the cycle.

Seeds: the leading (Hopf) eigenvector of :func:`single_cilium.stability`, grown by a short
transient; while the transient is still near-linear (near the cutoff) its measured growth
``alpha_eff(a) = alpha + l a^2`` gives the Hopf normal-form amplitude ``a* = a sqrt(alpha /
(alpha - alpha_eff))``; or a cycle of a neighbouring chi_N (:func:`limit_cycle`'s ``seed``).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import xarray as xr
from scipy.optimize import brentq
from scipy.sparse.linalg import LinearOperator, gmres

from . import __version__
from ._blas import single_threaded_blas
from .equilibrium import NoLimitAngleError, limit_angle
from .filament import Filament
from .mesh import Mesh
from .params import CiliumParams
from .radau import ConvergenceError, Radau
from .stability import stability

logger = logging.getLogger(__name__)

__all__ = ["limit_cycle", "LimitCycle", "CycleError"]


class CycleError(ConvergenceError):
    """The periodic orbit could not be converged; the message says what to change."""


@dataclass
class _Work:
    period_maps: int = 0
    newton: int = 0
    gmres: int = 0


def _wrap(angle: float) -> float:
    """Wrap into (-pi, pi]."""
    a = math.remainder(angle, 2 * math.pi)
    return math.pi if a == -math.pi else a


def thrust_angle(Fx: float, Fy: float) -> float:
    """DESIGN.md convention: ``phi_F - pi`` wrapped into (-pi, pi], ``phi_F`` the anticlockwise
    angle of ``(Fx, Fy)`` from ``e2``; close to ``theta_lim`` for the mean thrust."""
    return _wrap(math.atan2(-Fx, Fy) - math.pi)


@dataclass(frozen=True)
class LimitCycle:
    """A converged limit cycle, or the statement that there is none.

    Attributes
    ----------
    flutter : bool
        False when the equilibrium is stable: no oscillation, zero thrust, NaN period.
    period : float
    data : xarray.Dataset or None
        dims ``phase`` (uniform in [0, 1), phase 0 at the upward crossing of the tip angle
        through its cycle mean) and ``s``: ``theta``, ``kappa``, ``x``, ``y``, ``fx``, ``fy``
        (force per length ON the fluid, ``= -d``); per phase ``Fx``, ``Fy`` (clamp force
        ``F = -int d``, the force on the fluid).
    thrust : (2,) array
        ``Fbar``, the mean of F over exactly one period (field frame, e2 along the field).
    thrust_norm, thrust_angle : float
        ``|Fbar|`` and ``phi_Fbar - pi`` wrapped into (-pi, pi] (DESIGN.md), close to theta_lim.
    theta_lim : float
        Limit angle of the equilibrium (NaN where it has none).
    tip_area : float
        Signed area enclosed by the tip orbit (anticlockwise positive): the non-reciprocity.
    floquet_multipliers : (k,) complex
        The trivial multiplier (flow direction) and Ritz estimates of the largest non-trivial
        ones. ``floquet`` is the largest non-trivial modulus, at least ``exp(-T)`` (the kappa
        relaxation's essential multiplier, exact for kappa at the clamp); ``floquet < 1``: the
        cycle is stable. ``floquet_trivial_error`` is the distance of the trivial multiplier
        from 1 (an accuracy diagnostic).
    errors : dict
        Estimates for ``period``, ``thrust_norm`` (relative) and ``thrust_angle`` (absolute,
        radians): the change when the steps per period are halved (time) plus the change when
        the degree is lowered by 2 (space); upper estimates, as each is the error of the cheaper run.
    work : dict
        Period maps, Newton and GMRES iterations.
    """

    params: CiliumParams
    mesh: Mesh
    flutter: bool
    period: float = math.nan
    data: xr.Dataset | None = None
    thrust: np.ndarray = field(default_factory=lambda: np.zeros(2))
    theta_lim: float = math.nan
    tip_area: float = 0.0
    floquet_multipliers: np.ndarray = field(default_factory=lambda: np.zeros(0, complex))
    floquet: float = math.nan
    floquet_trivial_error: float = math.nan
    errors: dict = field(default_factory=dict)
    work: dict = field(default_factory=dict)
    status: str = "success"
    message: str = ""
    state0: np.ndarray | None = None

    @property
    def thrust_norm(self) -> float:
        return float(np.hypot(*self.thrust))

    @property
    def thrust_angle(self) -> float:
        return thrust_angle(*self.thrust) if self.flutter else math.nan

    @property
    def thrust_x(self) -> float:
        return float(self.thrust[0])

    @property
    def thrust_y(self) -> float:
        return float(self.thrust[1])

    def as_dict(self) -> dict:
        e = self.errors
        return {"chi_E": self.params.chi_E, "eta": self.params.eta, "chi_N": self.params.chi_N,
                "flutter": self.flutter, "period": self.period, "thrust_norm": self.thrust_norm,
                "thrust_angle": self.thrust_angle, "thrust_x": self.thrust_x, "thrust_y": self.thrust_y,
                "theta_lim": self.theta_lim, "tip_area": self.tip_area, "floquet": self.floquet,
                "floquet_trivial_error": self.floquet_trivial_error,
                "period_error": e.get("period", math.nan), "thrust_norm_error": e.get("thrust_norm", math.nan),
                "thrust_angle_error": e.get("thrust_angle", math.nan),
                "status": self.status, "message": self.message, "mesh": self.mesh.describe(),
                "work": self.work}


class _Shooter:
    """Period map, Newton-Krylov shooting and post-processing on one discretisation."""

    def __init__(self, params: CiliumParams, mesh: Mesh, n_phase: int):
        self.fil = Filament(params, mesh)
        self.solver = Radau(self.fil, rtol=1e-12, atol=1e-12 * self.fil.scale)
        self.n_phase = int(n_phase)
        self.scale = self.fil.scale
        self.i_tip = self.fil.n - 2  # theta at the tip, in the state vector
        self.work = _Work()
        self._last = None  # the last period map: converged orbits are mapped by several steps

    def pmap(self, y0, T):
        key = (y0.tobytes(), float(T))
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        self.work.period_maps += 1
        try:
            Y, Yd, _ = self.solver.fixed(y0, T / self.n_phase, self.n_phase)
        except ConvergenceError as exc:
            raise CycleError(f"{exc}; the period is split into n_phase={self.n_phase} steps: "
                             f"raise n_phase (e.g. to {2 * self.n_phase})", exc.t) from None
        self._last = (key, (Y, Yd))
        return Y, Yd

    def shoot(self, y0, T, c, tol, max_newton=20):
        """Newton-Krylov for Phi(y0, T) = y0 with theta_tip(y0) = c."""
        N = y0.size
        y0, T = y0.copy(), float(T)
        for it in range(max_newton):
            Y, _ = self.pmap(y0, T)
            r = np.concatenate([(Y[-1] - y0) / self.scale, [y0[self.i_tip] - c]])
            res = float(np.max(np.abs(r)))
            logger.debug("shoot it %d: residual %.3e, T %.10g", it, res, T)
            if not np.isfinite(res):
                raise CycleError("the period map produced non-finite values", 0.0)
            if res <= tol:
                return y0, T, res
            self.work.newton += 1
            yend = Y[-1]

            def matvec(v):
                dy = v[:N] * self.scale
                dT = v[N] * T
                eps = 1e-7 / max(np.max(np.abs(v)), 1e-300)
                Yp, _ = self.pmap(y0 + eps * dy, T + eps * dT)
                return np.concatenate([((Yp[-1] - yend) / eps - dy) / self.scale, [dy[self.i_tip]]])

            A = LinearOperator((N + 1, N + 1), matvec=matvec, dtype=float)
            count = [0]

            def cb(_):
                count[0] += 1

            # inexact Newton: the linear solve need only beat the current residual
            forcing = min(1e-2, max(1e-6, res))
            dx, info = gmres(A, -r, rtol=forcing, atol=0.0, restart=60, maxiter=2, callback=cb,
                             callback_type="pr_norm")
            self.work.gmres += count[0]
            step_y, step_T = dx[:N] * self.scale, dx[N] * T
            # damp wild steps (far from the orbit): keep the period positive, |dtheta| moderate
            lam = 1.0
            big = np.max(np.abs(step_y[: self.fil.n - 1]))
            if big > 0.5:
                lam = 0.5 / big
            if T + lam * step_T <= 0.2 * T:
                lam = min(lam, 0.8 * T / abs(step_T))
            y0 = y0 + lam * step_y
            T = T + lam * step_T
        raise CycleError(f"Newton-Krylov shooting did not converge in {max_newton} iterations "
                         f"(residual {res:.2e}); the seed may be too far from the cycle: give a seed "
                         "from a neighbouring chi_N or raise the resolution", 0.0)

    def rephase(self, y0, T):
        """Move the start to phase 0: the upward crossing of theta_tip through its cycle mean."""
        Y, _ = self.pmap(y0, T)
        tip = Y[:-1, self.i_tip]
        n = tip.size
        coef = np.fft.rfft(tip) / n
        mean = coef[0].real

        def trig(t):  # trigonometric interpolant at time t in [0, T]
            k = np.arange(coef.size)
            w = np.where((k == 0) | ((n % 2 == 0) & (k == n // 2)), 1.0, 2.0)
            return float(np.sum(w * (coef * np.exp(2j * np.pi * k * t / T)).real)) - mean

        d = tip - mean
        up = np.nonzero((d[:-1] < 0) & (d[1:] >= 0))[0]
        if up.size == 0:
            j = n - 1 if d[-1] < 0 <= d[0] else None
            if j is None:
                raise CycleError("the tip angle does not cross its mean: not an oscillation", 0.0)
        else:
            j = int(up[0])
        h = T / n
        t_star = brentq(trig, j * h, (j + 1) * h, xtol=1e-15 * T)
        k0 = int(math.floor(t_star / h))
        frac = t_star - k0 * h
        y = Y[k0]
        if frac > 0:
            Ys, _, _ = self.solver.fixed(y, frac, 1)
            y = Ys[-1]
        return y

    def observables(self, y0, T):
        """Shape, drag and clamp force on the uniform phase grid (N points, phase 0 first)."""
        Y, Yd = self.pmap(y0, T)
        # derivatives from the collocation polynomial at each step end; at phase 0 the one at
        # the end of the period (the orbit is closed)
        Yd = np.concatenate([Yd[-1:], Yd[1:-1]])
        Y = Y[:-1]
        fil = self.fil
        theta, kappa = fil.split(Y)
        theta_t, _ = fil.split(Yd)
        d = fil.drag(theta, theta_t)
        return theta, kappa, fil.shape(theta), d, fil.clamp_force(d)


def _seed_from_eigenvector(st, y_eq, fil, T0, work):
    """Grow the Hopf mode by a transient; extrapolate by the normal form while near-linear."""
    v = fil.join(st.theta_modes[0], st.kappa_modes[0])
    alpha = st.alpha
    solver = Radau(fil, rtol=1e-9, atol=1e-9 * fil.scale)
    a = 0.02
    y = y_eq + a * np.real(v)
    amps = []
    n_sample = 24
    for k in range(60):
        Y, _, _ = solver.integrate(y, np.linspace(0.0, T0, n_sample + 1))
        work.period_maps += 1
        tip = Y[:, fil.n - 2]
        amps.append(0.5 * (tip.max() - tip.min()))
        y = Y[-1]
        if len(amps) >= 3:
            g_now = math.log(amps[-1] / amps[-2]) / T0
            if abs(g_now) * T0 < 0.01 and g_now < 0.5 * alpha:
                break  # saturated: the transient is on (or near) the cycle
            if k >= 5 and g_now > 0.5 * alpha and g_now * T0 < 0.05:
                # still near-linear and slow: Hopf normal form alpha_eff = alpha + l a^2
                a_now = amps[-1]
                if g_now < alpha:
                    a_star = a_now * math.sqrt(alpha / (alpha - g_now))
                else:
                    a_star = 2 * a_now
                y = y_eq + (a_star / a_now) * (y - y_eq)
                break
    return y


def limit_cycle(params: CiliumParams, *, mesh: Mesh | None = None, degree: int = 10,
                n_phase: int = 64, tol: float = 1e-10, seed: "LimitCycle | None" = None,
                floquet: bool = True, error_estimate: bool = True) -> LimitCycle:
    """The limit cycle of a fluttering filament, its period, averaged thrust and stability.

    Parameters
    ----------
    params : CiliumParams
    mesh : Mesh, optional
        Default ``Mesh.for_params(params, degree)``.
    n_phase : int
        Constant steps per period = points of the uniform phase grid (>= 16).
    tol : float
        Newton tolerance on the scaled shooting residual.
    seed : LimitCycle, optional
        A converged cycle (e.g. at a neighbouring chi_N) to start from, instead of the Hopf
        eigenvector and a transient.
    floquet, error_estimate : bool
        Compute the Floquet multipliers (17 period maps) / the refinement error
        estimates (two more shooting solves from the converged cycle).

    Returns
    -------
    LimitCycle
        With ``flutter=False`` and zero thrust when the equilibrium is stable (no oscillation).

    Raises
    ------
    CycleError
        When the shooting does not converge (the message says what to change).
    """
    if not isinstance(params, CiliumParams):
        raise TypeError(f"params must be a CiliumParams, got {type(params).__name__}")
    if int(n_phase) != n_phase or n_phase < 16:
        raise ValueError(f"n_phase must be an integer >= 16, got {n_phase}")
    if not (0 < tol < 1e-3):
        raise ValueError(f"tol must lie in (0, 1e-3), got {tol}")
    mesh = mesh if mesh is not None else Mesh.for_params(params, degree)
    try:
        theta_lim = limit_angle(params)
    except NoLimitAngleError:
        theta_lim = math.nan
    with single_threaded_blas():
        st = stability(params, mesh=mesh, n_modes=2, check=False)
        if st.regime != "flutter":
            return LimitCycle(params, mesh, False, theta_lim=theta_lim, status="no oscillation",
                              message=f"the equilibrium is {st.regime} (leading eigenvalue "
                                      f"{st.alpha:.4g}{st.beta:+.4g}i): no limit cycle, zero thrust")
        sh = _Shooter(params, mesh, n_phase)
        fil = sh.fil
        y_eq = fil.equilibrium_state()
        def converge(y0, T):
            # section through the seed's orbit, away from the equilibrium's tip angle
            Y, _ = sh.pmap(y0, T)
            tip = Y[:, sh.i_tip]
            k = int(np.argmin(np.abs(tip - 0.5 * (tip.max() + tip.min()))))
            return sh.shoot(Y[k], T, float(Y[k][sh.i_tip]), tol)

        y0 = None
        if seed is not None and seed.flutter and seed.state0 is not None:
            try:
                y0, T, res = converge(_transfer(seed, fil), seed.period)
            except ConvergenceError as exc:
                logger.info("limit_cycle %s: seed did not converge (%s); starting from the Hopf mode", params, exc)
                y0 = None
        if y0 is None:
            T = 2 * math.pi / st.beta
            y0, T, res = converge(_seed_from_eigenvector(st, y_eq, fil, T, sh.work), T)
        y0 = sh.rephase(y0, T)
        y0, T, res = sh.shoot(y0, T, float(y0[sh.i_tip]), tol)
        result = _assemble(params, mesh, sh, y0, T)
        mults = np.zeros(0, complex)
        fl = triv = math.nan
        if floquet:
            mults, fl, triv = _floquet(sh, y0, T)
        errors = {}
        if error_estimate:
            errors = _error_estimates(params, mesh, n_phase, result, y0, T, tol)
    work = {"period_maps": sh.work.period_maps, "newton": sh.work.newton, "gmres": sh.work.gmres}
    msg = f"converged: shooting residual {res:.1e}"
    return LimitCycle(params, mesh, True, T, result["data"], result["thrust"], theta_lim,
                      result["tip_area"], mults, fl, triv, errors, work, "success", msg, y0)


def _transfer(seed: LimitCycle, fil: Filament) -> np.ndarray:
    """The seed's orbit point carried over as a deviation from its own equilibrium, added to
    this problem's equilibrium (a raw copy would violate the new clamp/tip compatibility and
    start a stiff initial layer)."""
    sfil = Filament(seed.params, seed.mesh)
    dth, dka = sfil.split(seed.state0 - sfil.equilibrium_state())
    th, ka = fil.split(fil.equilibrium_state())
    if seed.mesh != fil.mesh:
        dth, dka = seed.mesh.interpolate(dth, fil.mesh.nodes), seed.mesh.interpolate(dka, fil.mesh.nodes)
    return fil.join(th + dth, ka + dka)


def _assemble(params, mesh, sh: _Shooter, y0, T) -> dict:
    theta, kappa, r, d, F = sh.observables(y0, T)
    Fbar = F.mean(axis=0)
    xt, yt = r[:, -1, 0], r[:, -1, 1]
    area = 0.5 * float(np.sum(xt * np.roll(yt, -1) - np.roll(xt, -1) * yt))
    n = sh.n_phase
    phase = np.arange(n) / n

    def var(dims, values, long_name):
        return (dims, values, {"long_name": long_name, "units": "1"})

    data = xr.Dataset(
        {
            "theta": var(("phase", "s"), theta, "tangent angle from e2, anticlockwise"),
            "kappa": var(("phase", "s"), kappa, "spontaneous curvature"),
            "x": var(("phase", "s"), r[..., 0], "position along e1"),
            "y": var(("phase", "s"), r[..., 1], "position along e2 (field direction)"),
            "fx": var(("phase", "s"), -d[..., 0], "force per length on the fluid (-d), e1"),
            "fy": var(("phase", "s"), -d[..., 1], "force per length on the fluid (-d), e2"),
            "Fx": var(("phase",), F[:, 0], "clamp force -int d ds (on the fluid), e1"),
            "Fy": var(("phase",), F[:, 1], "clamp force -int d ds (on the fluid), e2"),
        },
        coords={"phase": ("phase", phase, {"long_name": "phase t/T from the upward crossing of the tip "
                                                        "angle through its cycle mean", "units": "1"}),
                "s": ("s", mesh.nodes, {"long_name": "arc length / filament length", "units": "1"})},
        attrs={"chi_E": params.chi_E, "eta": params.eta, "chi_N": params.chi_N, "period": T,
               "package_version": __version__},
    )
    return {"data": data, "thrust": Fbar, "tip_area": area}


def _floquet(sh: _Shooter, y0, T, m: int = 12, n_power: int = 3):
    """Floquet multipliers of the cycle from finite-difference products with the monodromy.

    The trivial multiplier belongs to the flow direction ``u = y'(0)``: it is measured as
    ``u . A u / |u|^2`` (its distance from 1 is the accuracy diagnostic). The others are the
    eigenvalues of ``A`` deflated by the projector onto ``u`` (``A`` is block triangular in
    ``[u, u^perp]``): Ritz values of ``n_power`` power steps followed by an ``m``-step Arnoldi
    run (``m + n_power + 2`` period maps). The monodromy of this stiff system has a cluster near
    ``exp(-T)`` (the kappa relaxation; exactly ``exp(-T)`` for kappa at the clamp) and the rest
    near 0, so the largest non-trivial modulus is resolved to a few digits.
    """
    Y, Yd = sh.pmap(y0, T)
    yend = Y[-1]
    N = y0.size

    def A(v):
        eps = 1e-7 / max(np.max(np.abs(v)), 1e-300)
        Yp, _ = sh.pmap(y0 + eps * v * sh.scale, T)
        return (Yp[-1] - yend) / eps / sh.scale

    u = Yd[-1] / sh.scale
    u /= np.linalg.norm(u)
    Au = A(u)
    triv_mult = float(u @ Au)

    def B(v):
        w = A(v - (u @ v) * u)
        return w - (u @ w) * u

    q = np.random.default_rng(12345).standard_normal(N)
    q -= (u @ q) * u
    for _ in range(n_power):
        q = B(q / np.linalg.norm(q))
    Q = np.zeros((N, m + 1))
    H = np.zeros((m + 1, m))
    Q[:, 0] = q / np.linalg.norm(q)
    k_done = m
    for j in range(m):
        w = B(Q[:, j])
        for _ in range(2):  # Gram-Schmidt, twice
            c = Q[:, : j + 1].T @ w
            H[: j + 1, j] += c
            w -= Q[:, : j + 1] @ c
        H[j + 1, j] = np.linalg.norm(w)
        if H[j + 1, j] < 1e-12:
            k_done = j + 1
            break
        Q[:, j + 1] = w / H[j + 1, j]
    ritz = np.linalg.eigvals(H[:k_done, :k_done])
    ritz = ritz[np.argsort(-np.abs(ritz))]
    mults = np.concatenate([[triv_mult], ritz[:5]])
    # the kappa relaxation's essential multiplier exp(-T) (exact for kappa at the clamp, which
    # theta cannot drive) bounds the largest non-trivial modulus from below; Arnoldi resolves
    # the cluster around it only slowly, so it is taken explicitly
    return mults, max(float(np.abs(ritz[0])), math.exp(-T)), abs(triv_mult - 1.0)


def _error_estimates(params, mesh, n_phase, result, y0, T, tol) -> dict:
    """Re-converge with half the steps (time) and with the degree lowered by 2 (space)."""
    def quantities(res_T, thrust):
        return res_T, float(np.hypot(*thrust)), thrust_angle(*thrust)

    base = quantities(T, result["thrust"])
    diffs = {"period": 0.0, "thrust_norm": 0.0, "thrust_angle": 0.0}
    variants = [(mesh, n_phase // 2), (Mesh(mesh.breaks, mesh.degree - 2), n_phase)]
    for m, n in variants:
        sh = _Shooter(params, m, n)
        fil0 = Filament(params, mesh)
        th, ka = fil0.split(y0)
        yv = sh.fil.join(mesh.interpolate(th, m.nodes), mesh.interpolate(ka, m.nodes)) if m != mesh else y0
        yv, Tv, _ = sh.shoot(yv, T, float(yv[sh.i_tip]), tol)
        other = quantities(Tv, _assemble(params, m, sh, yv, Tv)["thrust"])
        diffs["period"] += abs(other[0] - base[0]) / base[0]
        diffs["thrust_norm"] += abs(other[1] - base[1]) / base[1]
        diffs["thrust_angle"] += abs(_wrap(other[2] - base[2]))
    return diffs
