"""Limit cycles of a fluttering filament and the thrust they exert (MODEL.md section 5).

:func:`limit_cycle` is the front door. It computes the periodic orbit of the Galerkin system of
:mod:`single_cilium.filament` with an orbit method of :mod:`single_cilium.orbit` (by name:
``method="shooting"``, the default, single shooting with the exact monodromy of the compiled
Radau IIA(5) period map; ``"newton-krylov"``, Newton-Krylov shooting on finite-difference
monodromy products, a cross-check), and does the rest once, against the orbit-solver contract:

* seeding: cycles at neighbouring chi_N (``seed``; with two or three, the secant or parabola
  predictor of a continuation along the branch); otherwise the leading (Hopf) eigenvector of
  :func:`single_cilium.stability`, scaled to the normal-form amplitude guess
  ``0.85 sqrt(alpha)`` and relaxed for two periods; if Newton does not reach a genuine cycle
  from there, the mode is grown by a transient, and while that is still near-linear (near the
  cutoff) its measured growth ``alpha_eff(a) = alpha + l a^2`` gives the Hopf normal-form
  amplitude ``a* = a sqrt(alpha / (alpha - alpha_eff))``;
* the phase: phase 0 is the upward crossing of the tip angle ``theta(1)`` through its mean over
  the cycle (found on the trigonometric interpolant of the tip angle; the orbit is then sampled
  from there, and re-converged only if it does not close to 100 x the Newton tolerance);
* averaging: the ``n_phase`` step ends are the uniform phase grid of the result, so cycle
  averages are trapezoid sums of a periodic function (exponentially accurate in ``n_phase``
  beyond the integrator's own order-5 error), over exactly one period;
* the phase resolution: with ``n_phase=None`` (default) the orbit is converged at 32 steps per
  period and re-converged at twice as many (from the same ``(y0, T)``: 1-2 Newton steps) until
  the change of period, ``|Fbar|`` (relative) and thrust angle (absolute), divided by 15, is
  below ``rtol / 2``; an implicit step that fails doubles the steps; the result says which
  ``n_phase`` it chose. The time part of the error estimate is that change divided by 15
  (Radau IIA is of order 5 at the step ends; 15 = 2^4 - 1 assumes order 4 at least, which the
  tests check); the space part is the change when the degree is lowered by 2 (computed with
  ``n_phase / 2`` steps, the orbit already at hand: time and space errors add to leading
  order), an upper estimate as it is the error of the cheaper run;
* Floquet multipliers: the eigenvalues of the monodromy (exact shooting) or Ritz values
  (Newton-Krylov); ``floquet``, the largest non-trivial modulus, is at least ``exp(-T)``, the
  kappa relaxation's essential multiplier (exact for kappa at the clamp).

Results say how they ended in one way across :mod:`single_cilium`: ``status`` (``"success"``,
``"inaccurate"`` when an error estimate exceeds what was asked, ``"no oscillation"``,
``"unchecked"`` without error estimate) and a one-line ``message``; failures raise
:class:`CycleError` with what to change.

One concept: the limit cycle and the mean thrust at a point (chi_N, U) (``mean_thrust`` is
``limit_cycle`` or the steady state, reported alike); the orbit methods are in
:mod:`single_cilium.orbit`.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import xarray as xr
from scipy.optimize import brentq

from .version import __version__
from cilia_runtime.blas import single_threaded_blas
from .equilibrium import NoLimitAngleError, limit_angle
from .filament import Filament
from .mesh import Mesh
from .orbit import METHODS, Orbit, OrbitError, OrbitSolver
from .params import CiliumParams
from .radau import ConvergenceError
from .stability import stability

logger = logging.getLogger(__name__)

__all__ = ["limit_cycle", "LimitCycle", "CycleError", "METHODS", "mean_thrust", "MeanThrust", "check_degree",
           "check_mesh_size", "check_cycle_cost", "cycle_seconds", "MAX_DEGREE", "MAX_NODES", "MAX_CYCLE_SECONDS"]

N_PHASE_START = 32
N_PHASE_MAX = 1024
#: The highest mesh degree: :meth:`Mesh.for_params <single_cilium.mesh.Mesh.for_params>` resolves
#: the equilibrium to about ``10^(1 - degree / 2)`` per element, which above 32 asks for more than
#: double precision: every element is then bisected, to a mesh of 256 elements (10241 nodes at
#: degree 40, where a cycle would take weeks).
MAX_DEGREE = 32
#: The most nodes of a mesh a computation accepts up front (a coiled filament gets an element per
#: half turn): a limit cycle of 32 steps on 1200 nodes is estimated at about an hour.
MAX_NODES = 1200
#: The longest estimated time of one limit cycle (:func:`cycle_seconds`) that is started.
MAX_CYCLE_SECONDS = 3600.0
#: Seconds per step of the period and per node^3 of the mesh of one limit cycle by shooting (dense
#: solves of the stage system and the monodromy update, O(nodes^3) per step; Newton and Floquet
#: included): measured 5.5e-8 to 6.3e-8 at degrees 16 to 32, 64 steps, on one core.
_SECONDS_PER_STEP_NODE3 = 6e-8
#: the change under halving the steps, divided by this, estimates the time error: Radau IIA is of
#: order 5 at the step ends; 2^4 - 1 assumes order 4 at least (the refinement test checks it)
_RICHARDSON = 15.0


class CycleError(ConvergenceError):
    """The periodic orbit could not be converged; the message says what to change."""


def check_degree(degree, error_estimate: bool = True, name: str = "degree") -> int:
    """``degree`` as an int, or a ValueError naming ``name`` and the valid range: ``[4, MAX_DEGREE]``
    with error estimates (they compare with degree - 2), ``[2, MAX_DEGREE]`` without."""
    lo = 4 if error_estimate else 2
    try:
        ok = float(degree).is_integer() and lo <= int(degree) <= MAX_DEGREE
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        why = ""
        if isinstance(degree, (int, float, np.integer, np.floating)) and math.isfinite(degree):
            if degree > MAX_DEGREE:
                why = (f" (above {MAX_DEGREE} the mesh asks for more than double precision and grows to 256 "
                       "elements)")
            elif degree < lo and error_estimate:
                why = " (the error estimate compares with degree - 2, which must be >= 2)"
        raise ValueError(f"{name} must be an integer in [{lo}, {MAX_DEGREE}]{why}, got {degree!r}")
    return int(degree)


def check_mesh_size(params: CiliumParams, degree: int, chi_N_name: str = "chi_N", degree_name: str = "degree") -> None:
    """A ValueError, before the mesh is made, when ``Mesh.for_params(params, degree)`` would have
    more than :data:`MAX_NODES` nodes: a coiled filament (``|chi_N| > |chi_E|``) gets an element
    per half turn. The message names ``chi_N_name`` and its largest value at this degree."""
    cE, cN = abs(params.chi_E), abs(params.chi_N)
    if cE >= cN:
        return  # a clamp layer and a few elements
    nodes = math.ceil(cN / math.pi) * degree + 1
    if nodes > MAX_NODES:
        top = math.pi * ((MAX_NODES - 1) // degree)
        raise ValueError(f"{chi_N_name} = {params.chi_N:g} is beyond what can be computed here: with |chi_E| = "
                         f"{cE:g} the filament is coiled ({cN / (2 * math.pi):.3g} turns), and its mesh (an element "
                         f"of {degree_name} {degree} per half turn) would have at least {nodes:.3g} nodes; "
                         f"|{chi_N_name}| must be at most {top:.4g} here (a mesh of at most {MAX_NODES} nodes)")


def cycle_seconds(n_nodes: int, n_phase: int) -> float:
    """Estimated seconds of one limit cycle by shooting on a mesh of ``n_nodes`` nodes with
    ``n_phase`` steps per period, without error estimates (they add about half again), on one
    core of a 2020s machine: ``n_phase * n_nodes^3`` times a measured constant."""
    return _SECONDS_PER_STEP_NODE3 * float(n_phase) * float(n_nodes) ** 3


def check_cycle_cost(mesh: Mesh, n_phase: int, name: str = "n_phase", degree_name: str = "degree") -> None:
    """A ValueError when one limit cycle on ``mesh`` with ``n_phase`` steps is estimated
    (:func:`cycle_seconds`) to take longer than :data:`MAX_CYCLE_SECONDS`; the message gives the
    estimate and the largest ``n_phase`` that fits (or says to lower the degree)."""
    est = cycle_seconds(mesh.n_nodes, n_phase)
    if est <= MAX_CYCLE_SECONDS:
        return
    top = int(MAX_CYCLE_SECONDS / cycle_seconds(mesh.n_nodes, 1))
    fix = (f"{name} must be at most {top} on this mesh" if top >= 16 else
           f"lower {degree_name} (now {mesh.degree})")
    raise ValueError(f"{name} = {n_phase} steps per period on a mesh of {mesh.n_nodes} nodes ({mesh.n_elements} "
                     f"elements of degree {mesh.degree}): one limit cycle is estimated at {est / 3600:.3g} hours, "
                     f"beyond the {MAX_CYCLE_SECONDS / 3600:g} hour limit; {fix}")


def _wrap(angle: float) -> float:
    """Wrap into (-pi, pi]."""
    a = math.remainder(angle, 2 * math.pi)
    return math.pi if a == -math.pi else a


def thrust_angle(Fx: float, Fy: float) -> float:
    """DESIGN.md convention: ``phi_F - pi`` wrapped into (-pi, pi], ``phi_F`` the anticlockwise
    angle of ``(Fx, Fy)`` from ``e2``; close to ``theta_lim`` for the mean thrust."""
    return _wrap(math.atan2(-Fx, Fy) - math.pi)


class _Thrust:
    """The components and size of a result's mean thrust ``thrust`` (2,): ``Fbar``, the mean force
    on the fluid in the field frame (DESIGN.md)."""

    @property
    def thrust_x(self) -> float:
        return float(self.thrust[0])

    @property
    def thrust_y(self) -> float:
        return float(self.thrust[1])

    @property
    def thrust_norm(self) -> float:
        return float(np.hypot(*self.thrust))


@dataclass(frozen=True)
class LimitCycle(_Thrust):
    """A converged limit cycle, or the statement that there is none.

    Attributes
    ----------
    flutter : bool
        False when the equilibrium is stable: no oscillation, zero thrust (in a background flow:
        the force of the filament held in the stream, see ``thrust``), NaN period.
    period : float
    data : xarray.Dataset or None
        dims ``phase`` (uniform in [0, 1), phase 0 at the upward crossing of the tip angle
        through its cycle mean) and ``s``: ``theta``, ``kappa``, ``x``, ``y``, ``fx``, ``fy``
        (force per length ON the fluid, ``= -d``); per phase ``Fx``, ``Fy`` (clamp force
        ``F = -int d``, the force on the fluid).
    thrust : (2,) array
        ``Fbar``, the mean of F over exactly one period (field frame, e2 along the field). In a
        background flow it includes the stream's drag on the filament; without flutter it is
        then the force ``-int d ds`` of the (stable) steady state in the stream, and NaN when
        that steady state is unstable without oscillating (divergence).
    thrust_norm, thrust_angle : float
        ``|Fbar|`` and ``phi_Fbar - pi`` wrapped into (-pi, pi] (DESIGN.md), close to theta_lim.
    theta_lim : float
        Limit angle of the equilibrium (NaN where it has none); in a background flow, of the
        still-fluid closed form (the stream does not enter it).
    tip_area : float
        Signed area enclosed by the tip orbit (anticlockwise positive): the non-reciprocity.
    floquet_multipliers : (k,) complex
        The trivial multiplier (flow direction) first, then the largest non-trivial ones by
        modulus. ``floquet`` is the largest non-trivial modulus, at least ``exp(-T)``;
        ``floquet < 1``: the cycle is stable. ``floquet_trivial_error`` is the distance of the
        trivial multiplier from 1 (an accuracy diagnostic).
    errors : dict
        Estimates for ``period``, ``thrust_norm`` (relative) and ``thrust_angle`` (absolute,
        radians): the time part (the change when the steps per period are halved, divided by
        15: order 4 at least is assumed, order 5 observed) plus the space part (the change when
        the degree is lowered by 2, an upper estimate: the error of the cheaper run). The parts
        are also given (``time``, ``space``: the largest of the three quantities).
    work : dict
        Counters of the orbit method(s): period maps, orbit Newton iterations, Newton
        iterations inside the implicit steps, factorisations (and GMRES iterations for
        Newton-Krylov), summed over every solve this result needed.
    status, message : str
        ``"success"``, ``"inaccurate"`` (an error estimate above ``rtol``; the message says
        which), ``"unchecked"`` (``error_estimate=False``), or ``"no oscillation"``.
    state0 : (N,) array or None
        The state at phase 0 (a seed for a neighbouring cycle).
    method : str
        The orbit method used.
    n_phase : int
        Steps per period (= phase points) of the result: chosen by the solver when not given.
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
    method: str = ""
    n_phase: int = 0

    @property
    def thrust_angle(self) -> float:
        return thrust_angle(*self.thrust) if (self.flutter or self.thrust_norm > 0) else math.nan

    def as_dict(self) -> dict:
        e = self.errors
        return {"chi_E": self.params.chi_E, "eta": self.params.eta, "chi_N": self.params.chi_N,
                "U1": self.params.background[0], "U2": self.params.background[1],
                "flutter": self.flutter, "period": self.period, "thrust_norm": self.thrust_norm,
                "thrust_angle": self.thrust_angle, "thrust_x": self.thrust_x, "thrust_y": self.thrust_y,
                "theta_lim": self.theta_lim, "tip_area": self.tip_area, "floquet": self.floquet,
                "floquet_trivial_error": self.floquet_trivial_error,
                "period_error": e.get("period", math.nan), "thrust_norm_error": e.get("thrust_norm", math.nan),
                "thrust_angle_error": e.get("thrust_angle", math.nan),
                "status": self.status, "message": self.message, "mesh": self.mesh.describe(),
                "method": self.method, "n_phase": self.n_phase, "work": self.work}


# ------------------------------------------------------------------------------ helpers
def _quantities(T: float, thrust: np.ndarray) -> tuple[float, float, float]:
    return T, float(np.hypot(*thrust)), thrust_angle(*thrust)


def _differences(a, b) -> dict:
    """Relative change of period and |Fbar|, absolute change of the angle, from a to b."""
    return {"period": abs(b[0] - a[0]) / a[0], "thrust_norm": abs(b[1] - a[1]) / a[1],
            "thrust_angle": abs(_wrap(b[2] - a[2]))}


def _observables(fil: Filament, orbit: Orbit):
    """Shape, drag and clamp force on the uniform phase grid (n_phase points, phase 0 first)."""
    # rates from the collocation polynomial at each step end; at phase 0 the one at the end
    # of the period (the orbit is closed)
    Yd = np.concatenate([orbit.rates[-1:], orbit.rates[1:-1]])
    Y = orbit.states[:-1]
    theta, kappa = fil.split(Y)
    theta_t, _ = fil.split(Yd)
    d = fil.drag(theta, theta_t)
    return theta, kappa, fil.shape(theta), d, fil.clamp_force(d)


def _thrust(fil: Filament, orbit: Orbit) -> np.ndarray:
    return _observables(fil, orbit)[4].mean(axis=0)


def _assemble(params, mesh, fil, orbit: Orbit) -> dict:
    theta, kappa, r, d, F = _observables(fil, orbit)
    Fbar = F.mean(axis=0)
    xt, yt = r[:, -1, 0], r[:, -1, 1]
    area = 0.5 * float(np.sum(xt * np.roll(yt, -1) - np.roll(xt, -1) * yt))
    n = theta.shape[0]
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
        attrs={"chi_E": params.chi_E, "eta": params.eta, "chi_N": params.chi_N,
               "background_U1": params.background[0], "background_U2": params.background[1], "period": orbit.period,
               "package_version": __version__},
    )
    return {"data": data, "thrust": Fbar, "tip_area": area}


def _section_through(solver: OrbitSolver, y0, T) -> tuple[np.ndarray, float]:
    """A point of the guessed orbit whose tip angle is mid-range (a section away from the
    equilibrium's tip angle) and that tip angle."""
    Y, _ = solver.orbit_states(y0, T)
    tip = Y[:, solver.i_tip]
    k = int(np.argmin(np.abs(tip - 0.5 * (tip.max() + tip.min()))))
    return Y[k], float(Y[k][solver.i_tip])


def _rephase(solver: OrbitSolver, orbit: Orbit) -> np.ndarray:
    """The state at phase 0: the upward crossing of theta_tip through its cycle mean."""
    Y, T = orbit.states, orbit.period
    tip = Y[:-1, solver.i_tip]
    n = tip.size
    coef = np.fft.rfft(tip) / n
    mean = coef[0].real
    k = np.arange(coef.size)
    wk = np.where((k == 0) | ((n % 2 == 0) & (k == n // 2)), 1.0, 2.0)

    def trig(t):  # trigonometric interpolant at time t in [0, T], minus the mean
        return float(np.sum(wk * (coef * np.exp(2j * np.pi * k * t / T)).real)) - mean

    d = tip - mean
    up = np.nonzero((d[:-1] < 0) & (d[1:] >= 0))[0]
    if up.size == 0:
        if not d[-1] < 0 <= d[0]:
            raise CycleError("the tip angle does not cross its mean: not an oscillation", 0.0)
        j = n - 1
    else:
        j = int(up[0])
    h = T / n
    t_star = brentq(trig, j * h, (j + 1) * h, xtol=1e-15 * T)
    k0 = min(int(math.floor(t_star / h)), n - 1)
    return solver.advance(Y[k0], t_star - k0 * h)


def _seed_from_eigenvector(st, y_eq, fil, solver: OrbitSolver, T0):
    """Grow the Hopf mode by a transient; extrapolate by the normal form while near-linear."""
    v = fil.join(st.theta_modes[0], st.kappa_modes[0])
    alpha = st.alpha
    a = 0.02
    y = y_eq + a * np.real(v)
    amps = []
    for k in range(60):
        Y, _ = solver.orbit_states(y, T0)
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
                a_star = a_now * math.sqrt(alpha / (alpha - g_now)) if g_now < alpha else 2 * a_now
                y = y_eq + (a_star / a_now) * (y - y_eq)
                break
    return y


def _deviation(seed: "LimitCycle", fil: Filament) -> np.ndarray:
    """The seed's phase-0 state as a deviation from its own equilibrium, on ``fil``'s nodes."""
    sfil = Filament(seed.params, seed.mesh)
    dth, dka = sfil.split(seed.state0 - sfil.equilibrium_state())
    if seed.mesh != fil.mesh:
        dth, dka = seed.mesh.interpolate(dth, fil.mesh.nodes), seed.mesh.interpolate(dka, fil.mesh.nodes)
    return fil.join(dth, dka)


def _coords(p: CiliumParams) -> tuple[float, float, float]:
    return (p.chi_N, p.background[0], p.background[1])


def _predict(seeds: list["LimitCycle"], fil: Filament) -> tuple[np.ndarray, float]:
    """Predictor from cycles at neighbouring chi_N (or background flow U): their phase-0 states
    carried over as deviations from their own equilibria, added to this problem's equilibrium (a
    raw copy would violate the new clamp/tip compatibility and start a stiff initial layer). With
    two or three seeds the deviation and the period are extrapolated along the branch by the
    Lagrange polynomial through them in the one coordinate of ``(chi_N, U1, U2)`` in which the
    seeds and the target differ (the secant, or a parabola), as long as the step is at most
    twice their spacing; otherwise the nearest seed alone (max-norm in ``(chi_N, U1, U2)``)."""
    target = _coords(fil.params)
    seeds = sorted(seeds, key=lambda sd: max(abs(a - b) for a, b in zip(_coords(sd.params), target)))[:3]
    pts = [_coords(sd.params) for sd in seeds]
    axes = [j for j in range(3) if any(q[j] != target[j] for q in pts)]
    k = axes[0] if len(axes) == 1 else 0
    c = target[k]
    x = np.array([q[k] for q in pts])
    y_eq = fil.equilibrium_state()
    if len(axes) > 1:
        seeds, x = seeds[:1], x[:1]
    if len(set(x.tolist())) < len(x) or (len(x) > 1 and abs(c - x[0]) > 2 * np.ptp(x)):
        seeds, x = seeds[:1], x[:1]
    # Lagrange weights at c
    w = np.array([np.prod([(c - x[j]) / (x[i] - x[j]) for j in range(len(x)) if j != i]) for i in range(len(x))])
    dev = sum(wi * _deviation(sd, fil) for wi, sd in zip(w, seeds))
    T = float(sum(wi * sd.period for wi, sd in zip(w, seeds)))
    return y_eq + dev, T


def _total_work(solvers: list[OrbitSolver]) -> dict:
    total: dict = {}
    for solver in solvers:
        for k, v in solver.work.items():
            total[k] = total.get(k, 0) + v
    return total


# ------------------------------------------------------------------------------ front door
def limit_cycle(params: CiliumParams, *, mesh: Mesh | None = None, degree: int = 10,
                n_phase: int | None = None, tol: float = 1e-10, rtol: float = 1e-6,
                method: str = "shooting", seed: "LimitCycle | Sequence[LimitCycle] | None" = None,
                floquet: bool = True, error_estimate: bool = True) -> LimitCycle:
    """The limit cycle of a fluttering filament, its period, averaged thrust and stability.

    Parameters
    ----------
    params : CiliumParams
        With ``params.background = (U1, U2)``, the filament in that uniform flow (field frame,
        ``e2`` along the field, units ``L / tau``): the drag is
        ``d = -eta ((v - U).t t + 2 (v - U).n n)``, the equilibrium the discrete steady state in
        the stream, and the thrust ``Fbar = -<int d ds>`` includes the stream's drag on the
        filament (for a filament held still, ``-int eta (U.t t + 2 U.n n) ds``). The monodromy
        of the shooting method carries the stream's terms exactly.
    mesh : Mesh, optional
        Default ``Mesh.for_params(params, degree)`` (graded for the still-fluid clamp layer).
    degree : int
        Of that mesh: in ``[4, MAX_DEGREE]`` with error estimates (they compare with degree - 2),
        ``[2, MAX_DEGREE]`` without; a coiled filament's mesh must not exceed :data:`MAX_NODES`.
    n_phase : int, optional
        Constant steps per period = points of the uniform phase grid (>= 16). Default: chosen
        by the solver (doubling from 32 until the time error estimate is below ``rtol``). A
        cycle estimated to take longer than :data:`MAX_CYCLE_SECONDS` (:func:`cycle_seconds`,
        with 32 steps when chosen by the solver) is refused up front.
    tol : float
        Newton tolerance on the scaled shooting residual.
    rtol : float
        Target of the time error estimate when ``n_phase`` is chosen, and the level above which
        a result is reported ``"inaccurate"``: relative for period and ``|Fbar|``, absolute
        (radians) for the thrust angle.
    method : str
        Orbit method, a key of :data:`single_cilium.orbit.METHODS`: ``"shooting"`` (exact
        monodromy, default) or ``"newton-krylov"``.
    seed : LimitCycle or sequence of LimitCycle, optional
        Converged cycle(s) at neighbouring chi_N or background flow (same chi_E, eta) to start
        from instead of the Hopf eigenvector: the nearest one's phase-0 state, or with two or
        three that differ from this point in one coordinate of ``(chi_N, U1, U2)`` only, their
        Lagrange extrapolation along the branch (continuation in chi_N, U1 or U2). If Newton does not converge from it, the
        Hopf mode is used.
    floquet, error_estimate : bool
        Compute the Floquet multipliers (free with the exact monodromy; ``m + 5`` period maps
        of Arnoldi with Newton-Krylov) / the error estimates (a re-converge at degree - 2 with
        ``n_phase / 2`` steps; with a given ``n_phase`` also the time part from ``n_phase / 2``
        steps). With ``n_phase=None`` the time part is always computed (it picks ``n_phase``).

    Returns
    -------
    LimitCycle
        With ``flutter=False`` and zero thrust when the equilibrium is stable (no oscillation); in
        a background flow the thrust is then the steady state's force on the fluid.

    Raises
    ------
    ValueError
        A setting out of range, or a cycle whose estimated cost is beyond the limits above
        (the message gives the estimate and the largest sensible value).
    CycleError
        When the orbit does not converge (the message says what to change), or, in a background
        flow, when the filament has no steady state in it to start from.
    """
    mesh = _checked_mesh(params, mesh, degree, n_phase, tol, rtol, method, error_estimate)
    theta_lim = _still_fluid_limit_angle(params)
    used: list[OrbitSolver] = []

    def Method(f: Filament, n_steps: int) -> OrbitSolver:
        solver = METHODS[method](f, n_steps)
        used.append(solver)
        return solver

    with single_threaded_blas():
        st = _linear_stability(params, mesh)
        if st.regime != "flutter":
            return _without_flutter(params, mesh, st, theta_lim, method)
        fil = Filament(params, mesh)
        adaptive = n_phase is None
        orbit, solver, n = _first_converged(Method, fil, st, seed, tol, params, n_phase)
        orbit, solver, n, time_err, half, q_half = _phase_resolution(Method, fil, st, seed, tol, params, orbit,
                                                                     solver, n, n_phase, rtol, error_estimate)
        orbit = _start_at_phase_zero(solver, orbit, fil, tol)
        T = orbit.period
        result = _assemble(params, mesh, fil, orbit)
        base = _quantities(T, result["thrust"])
        mults, fl, triv = _floquet(solver, orbit, T, floquet)
        errors: dict = {}
        if error_estimate or adaptive:
            errors = _error_estimates(Method, params, mesh, fil, orbit, base, time_err, half, q_half, tol,
                                      error_estimate)
    work = _total_work(used)
    status, msg = _verdict(method, n, adaptive, mesh, orbit, errors, error_estimate, rtol)
    return LimitCycle(params, mesh, True, T, result["data"], result["thrust"], theta_lim,
                      result["tip_area"], mults, fl, triv, errors, work, status, msg, orbit.state0,
                      method, n)


# ------------------------------------------------------------------------------ the steps of limit_cycle
def _checked_mesh(params: CiliumParams, mesh: Mesh | None, degree, n_phase, tol, rtol, method: str,
                  error_estimate: bool) -> Mesh:
    """Check the arguments of :func:`limit_cycle` and return the mesh it computes on.

    Returns
    -------
    Mesh
        ``mesh``, or ``Mesh.for_params(params, degree)`` when it is None.

    Raises
    ------
    TypeError
        ``params`` is not a :class:`CiliumParams`.
    ValueError
        ``method``, ``n_phase``, ``tol``, ``rtol`` or the degree out of range, a coiled
        filament's mesh above :data:`MAX_NODES` nodes, or a cycle estimated above
        :data:`MAX_CYCLE_SECONDS` (:func:`check_cycle_cost`).
    """
    if not isinstance(params, CiliumParams):
        raise TypeError(f"params must be a CiliumParams, got {type(params).__name__}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS)}, got {method!r}")
    if n_phase is not None and (int(n_phase) != n_phase or n_phase < 16):
        raise ValueError(f"n_phase must be an integer >= 16 (or None: chosen by the solver), got {n_phase}")
    if not (0 < tol < 1e-3):
        raise ValueError(f"tol must lie in (0, 1e-3), got {tol}")
    if not (0 < rtol < 1e-1):
        raise ValueError(f"rtol must lie in (0, 0.1), got {rtol}")
    if mesh is None:
        check_mesh_size(params, check_degree(degree, error_estimate))
        mesh = Mesh.for_params(params, int(degree))
    else:
        check_degree(mesh.degree, error_estimate, "mesh degree")
    check_cycle_cost(mesh, N_PHASE_START if n_phase is None else int(n_phase))
    return mesh


def _still_fluid_limit_angle(params: CiliumParams) -> float:
    """The limit angle of the equilibrium in fluid at rest (the background flow set to zero),
    or NaN where there is none (:class:`~single_cilium.equilibrium.NoLimitAngleError`)."""
    try:
        return limit_angle(params.with_background((0.0, 0.0)))
    except NoLimitAngleError:
        return math.nan


def _linear_stability(params: CiliumParams, mesh: Mesh):
    """The two leading eigenvalues and modes of the equilibrium (:func:`single_cilium.stability`).

    Raises
    ------
    CycleError
        In a background flow, when the filament has no steady state in it (the continuation of
        the steady state met a fold).
    RuntimeError, ConvergenceError
        Re-raised unchanged in fluid at rest.
    """
    try:
        return stability(params, mesh=mesh, n_modes=2, check=False)
    except RuntimeError as exc:  # in a stream: no steady state (the continuation met a fold)
        if not params.has_background or isinstance(exc, ConvergenceError):
            raise
        raise CycleError(f"{params}: {exc}; no limit cycle about it can be sought", 0.0) from None


def _without_flutter(params: CiliumParams, mesh: Mesh, st, theta_lim: float, method: str) -> LimitCycle:
    """The result when the equilibrium does not flutter (``st.regime`` is not ``"flutter"``).

    In fluid at rest the thrust is zero. In a background flow it is the force ``-int d ds`` of
    the filament held at its steady state in the stream when that state is stable, and NaN when
    it is unstable without oscillating.
    """
    if not params.has_background:
        return LimitCycle(params, mesh, False, theta_lim=theta_lim, status="no oscillation",
                          message=f"the equilibrium is {st.regime} (leading eigenvalue "
                                  f"{st.alpha:.4g}{st.beta:+.4g}i): no limit cycle, zero thrust",
                          method=method)
    # in a stream the filament at rest still exerts the stream's drag on the fluid
    fil = Filament(params, mesh)
    theta = fil.split(fil.equilibrium_state())[0]
    if st.regime == "stable":
        F = fil.clamp_force(fil.drag(theta, np.zeros_like(theta)))
        what = f"thrust = the force of the steady state in the stream ({F[0]:.6g}, {F[1]:.6g})"
    else:
        F = np.full(2, math.nan)
        what = "the steady state in the stream is unstable: no steady or periodic thrust (NaN)"
    return LimitCycle(params, mesh, False, thrust=F, theta_lim=theta_lim, status="no oscillation",
                      message=f"the equilibrium is {st.regime} (leading eigenvalue "
                              f"{st.alpha:.4g}{st.beta:+.4g}i): no limit cycle; {what}",
                      method=method)


def _first_converged(Method, fil: Filament, st, seed, tol: float, params: CiliumParams,
                     n_phase: int | None) -> tuple[Orbit, OrbitSolver, int]:
    """The first converged orbit, the solver that converged it and its steps per period.

    With ``n_phase=None`` it starts at :data:`N_PHASE_START` steps and doubles them (up to
    :data:`N_PHASE_MAX`) while an implicit step fails. With a given ``n_phase`` and no seed it
    starts with ``n_phase / 2`` steps (when that is at least 16; the refinement to ``n_phase``
    then gives the time error estimate), and goes straight to ``n_phase`` if a step fails there.

    Raises
    ------
    CycleError
        When no orbit converges; the message says what to change.
    """
    adaptive = n_phase is None
    seeded = seed is not None and (isinstance(seed, LimitCycle) or len(seed) > 0)
    if adaptive:
        n = N_PHASE_START
    else:
        # without a seed, the orbit is found with half the steps (cheaper maps) and refined
        # once, which also gives the time error estimate
        n = int(n_phase) // 2 if (not seeded and int(n_phase) // 2 >= 16) else int(n_phase)
    while True:
        solver = Method(fil, n)
        try:
            orbit = _first_orbit(solver, fil, st, seed, tol, params)
            break
        except OrbitError as exc:
            if not adaptive and exc.step_failed and n < n_phase:
                n = int(n_phase)  # the coarse start failed: straight to the steps asked for
                continue
            if not (adaptive and exc.step_failed and 2 * n <= N_PHASE_MAX):
                if exc.step_failed:
                    hint = (f"raise n_phase (e.g. to {2 * n})" if not adaptive else
                            f"the implicit steps fail even at {n} steps per period: check the "
                            "parameters or raise the degree")
                else:
                    hint = "give a seed from a neighbouring chi_N or raise the degree"
                raise CycleError(f"{params}: {exc} (n_phase={n}); {hint}", exc.t) from None
            logger.info("limit_cycle %s: %s at n_phase=%d; doubling", params, exc, n)
            n *= 2
    return orbit, solver, n


def _phase_resolution(Method, fil: Filament, st, seed, tol: float, params: CiliumParams, orbit: Orbit,
                      solver: OrbitSolver, n: int, n_phase: int | None, rtol: float, error_estimate: bool):
    """Refine the steps per period, and the time part of the error estimate.

    The orbit is re-converged with twice the steps from the same ``(y0, T)`` (the coarser
    orbit's monodromy as the Newton Jacobian): with ``n_phase=None`` until the change of the
    period, ``|Fbar|`` (relative) and the thrust angle (absolute), divided by ``_RICHARDSON``
    (15), is at most ``rtol / 2`` or :data:`N_PHASE_MAX` is reached; with a given ``n_phase``
    until it is reached. A refinement whose implicit step fails starts afresh at the doubled
    steps. When no refinement gave the time error and ``error_estimate`` is true, the orbit is
    re-converged with half the steps for it.

    Returns
    -------
    orbit, solver, n
        The finest orbit, its solver and its steps per period.
    time_err : dict or None
        The time error estimates of ``period``, ``thrust_norm``, ``thrust_angle``.
    half, q_half
        The orbit with ``n / 2`` steps and its (period, ``|Fbar|``, angle), or None.

    Raises
    ------
    CycleError
        A refinement that does not converge (other than by a failed step).
    """
    adaptive = n_phase is None
    c = float(orbit.state0[fil.n - 2])
    q = _quantities(orbit.period, _thrust(fil, orbit))
    time_err = None
    half, q_half = None, None  # the orbit with n / 2 steps, for the error estimates
    # the phase resolution: re-converge at 2n from (y0, T) until the time estimate is below rtol / 2
    while (2 * n <= N_PHASE_MAX) if adaptive else (n < n_phase):
        finer = Method(fil, 2 * n)
        try:
            orb2 = finer.converge(orbit.state0, orbit.period, c, tol, jacobian=orbit)
        except OrbitError as exc:
            if not exc.step_failed:
                raise CycleError(f"{params}: {exc} (refining to n_phase={2 * n})", exc.t) from None
            logger.info("limit_cycle %s: refinement to n_phase=%d failed (%s)", params, 2 * n, exc)
            n, solver, time_err, half = 2 * n, finer, None, None
            try:
                orbit = _first_orbit(solver, fil, st, seed, tol, params)
            except OrbitError as exc2:
                raise CycleError(f"{params}: {exc2} (n_phase={n})", exc2.t) from None
            c = float(orbit.state0[fil.n - 2])
            q = _quantities(orbit.period, _thrust(fil, orbit))
            continue
        q2 = _quantities(orb2.period, _thrust(fil, orb2))
        time_err = {k: v / _RICHARDSON for k, v in _differences(q2, q).items()}
        half, q_half = orbit, q
        n, solver, orbit, q = 2 * n, finer, orb2, q2
        if adaptive and max(time_err.values()) <= 0.5 * rtol:
            break
    if time_err is None and error_estimate:
        half = Method(fil, n // 2).converge(orbit.state0, orbit.period, c, tol, jacobian=orbit)
        q_half = _quantities(half.period, _thrust(fil, half))
        time_err = {k: v / _RICHARDSON for k, v in _differences(q, q_half).items()}
    return orbit, solver, n, time_err, half, q_half


def _start_at_phase_zero(solver: OrbitSolver, orbit: Orbit, fil: Filament, tol: float) -> Orbit:
    """The same discrete orbit sampled from phase 0 (:func:`_rephase`); re-converged from there
    only if the shifted start does not close to ``100 * tol``."""
    y0 = _rephase(solver, orbit)
    shifted = solver.at_phase(y0, orbit)
    if shifted.residual <= 100 * tol:
        return shifted
    return solver.converge(y0, orbit.period, float(y0[fil.n - 2]), tol, jacobian=shifted)


def _floquet(solver: OrbitSolver, orbit: Orbit, T: float, wanted: bool) -> tuple[np.ndarray, float, float]:
    """The Floquet multipliers (at most 6, the trivial one first), ``floquet`` (the largest
    non-trivial modulus, at least ``exp(-T)``) and the trivial multiplier's distance from 1;
    an empty array and NaNs when not ``wanted``."""
    mults = np.zeros(0, complex)
    fl = triv = math.nan
    if wanted:
        mults = solver.multipliers(orbit)
        triv = abs(mults[0] - 1.0)
        fl = max(float(np.abs(mults[1])) if mults.size > 1 else 0.0, math.exp(-T))
        mults = mults[:6]
    return mults, fl, triv


def _error_estimates(Method, params: CiliumParams, mesh: Mesh, fil: Filament, orbit: Orbit, base, time_err,
                     half, q_half, tol: float, error_estimate: bool) -> dict:
    """The error estimates of a result: ``period``, ``thrust_norm`` (relative) and
    ``thrust_angle`` (absolute, radians), each the time part plus the space part, and the parts
    ``time`` and ``space`` (the largest of the three; NaN when not computed).

    The space part is the change when the degree is lowered by 2, both with ``n / 2`` steps when
    that orbit (``half``) exists, else with the result's steps; it is computed only when
    ``error_estimate`` is true.
    """
    errors: dict = {}
    space_err = None
    if error_estimate:
        # degree - 2 against this degree, both with n / 2 steps when that orbit exists
        # (time and space errors add to leading order; half the cost)
        ref, q_ref = (half, q_half) if half is not None else (orbit, base)
        m2 = Mesh(mesh.breaks, mesh.degree - 2)
        fil2 = Filament(params, m2)
        th, ka = fil.split(ref.state0)
        y2 = fil2.join(mesh.interpolate(th, m2.nodes), mesh.interpolate(ka, m2.nodes))
        o = Method(fil2, ref.n_steps).converge(y2, ref.period, float(y2[fil2.n - 2]), tol)
        space_err = _differences(q_ref, _quantities(o.period, _thrust(fil2, o)))
    for k in ("period", "thrust_norm", "thrust_angle"):
        errors[k] = (time_err[k] if time_err else 0.0) + (space_err[k] if space_err else 0.0)
    errors["time"] = max(time_err.values()) if time_err else math.nan
    errors["space"] = max(space_err.values()) if space_err else math.nan
    return errors


def _verdict(method: str, n: int, adaptive: bool, mesh: Mesh, orbit: Orbit, errors: dict, error_estimate: bool,
             rtol: float) -> tuple[str, str]:
    """The ``status`` and one-line ``message`` of a converged cycle: ``"unchecked"`` without
    error estimates, ``"inaccurate"`` (with what to raise) when an estimate exceeds ``rtol``,
    else ``"success"``."""
    chose = f"n_phase={n} (chosen)" if adaptive else f"n_phase={n}"
    msg = f"converged ({method}, {chose}, degree {mesh.degree}): shooting residual {orbit.residual:.1e}"
    status = "success"
    if not error_estimate:
        status = "unchecked"
        msg += "; no space error estimate (error_estimate=False)"
    worst = max((errors.get(k, 0.0) for k in ("period", "thrust_norm", "thrust_angle")), default=0.0)
    if errors:
        msg += f"; error estimate {worst:.1e} (time {errors['time']:.1e}, space {errors['space']:.1e})"
        if worst > rtol:
            status = "inaccurate"
            fix = ("raise n_phase" if errors["time"] >= errors.get("space", 0.0) or math.isnan(errors["space"])
                   else "raise the degree")
            msg += f"; above rtol={rtol:g}: {fix}"
    return status, msg


@dataclass(frozen=True)
class MeanThrust(_Thrust):
    """The mean force of one cilium on the fluid, with its error (what :func:`mean_thrust` returns).

    Attributes
    ----------
    params : CiliumParams
        Including the background flow ``U = params.background`` (field frame, ``L / tau``).
    flutter : bool
    thrust : (2,) array
        ``Fbar = -<int_0^1 d ds>`` (field frame): averaged over exactly one period of the limit
        cycle when the filament flutters; otherwise the force of the filament at rest in the
        stream (zero in still fluid; NaN if that rest state is unstable without oscillating).
    error : float
        Estimate of ``|Fbar - Fbar_exact|`` (absolute, Euclidean norm): with flutter
        ``|Fbar| (e_norm + e_angle)`` from the cycle's estimates (``e_norm`` relative, time and
        space parts, ``e_angle`` in radians; first order in the errors); without flutter the
        change of the rest state's force when the degree is lowered by 2 (0 in still fluid,
        where the thrust is exactly 0).
    period, period_error : float
        Period and its relative error estimate (NaN without flutter).
    status, message : str
        As :class:`LimitCycle` (``"inaccurate"`` when ``error > rtol * max(|Fbar|, eta |U|)``).
    cycle : LimitCycle
        The full result it was taken from (a seed for a neighbouring point).
    """

    params: CiliumParams
    flutter: bool
    thrust: np.ndarray
    error: float
    period: float
    period_error: float
    status: str
    message: str
    cycle: LimitCycle

    @property
    def thrust_angle(self) -> float:
        """``phi_Fbar - pi`` wrapped into (-pi, pi] (DESIGN.md); NaN for zero thrust."""
        return thrust_angle(*self.thrust) if self.thrust_norm > 0 else math.nan


def mean_thrust(params: CiliumParams, *, degree: int = 10, rtol: float = 1e-6,
                seed: "LimitCycle | Sequence[LimitCycle] | None" = None) -> MeanThrust:
    """The cycle-averaged force ``Fbar`` one cilium exerts on the fluid at ``(chi_E, eta, chi_N)``
    in the uniform background flow ``U = params.background``, with an error estimate.

    The drag is ``d = -eta ((v - U).t t + 2 (v - U).n n)`` (``U`` in the field frame, ``e2``
    along the field, units ``L / tau``), so ``Fbar`` includes the stream's drag on the filament:
    a cilium that does not flutter still exerts the force of its rest state in the stream.
    A thin front door over :func:`limit_cycle` (default discretisation: degree 10, the steps per
    period chosen for ``rtol``); see :class:`MeanThrust` for what the error means.

    Parameters
    ----------
    params : CiliumParams
    degree, rtol : as :func:`limit_cycle`.
    seed : LimitCycle or sequence, optional
        Cycles at neighbouring parameters (e.g. ``MeanThrust.cycle`` of a neighbouring point).

    Raises
    ------
    CycleError
        As :func:`limit_cycle`.
    """
    c = limit_cycle(params, degree=degree, rtol=rtol, seed=seed, floquet=False)
    U = float(np.hypot(*params.background))
    if c.flutter:
        e = c.errors
        error = c.thrust_norm * (e["thrust_norm"] + e["thrust_angle"])
        period, period_error = c.period, e["period"]
        status, message = c.status, c.message
    else:
        period = period_error = math.nan
        if not params.has_background or not np.all(np.isfinite(c.thrust)):
            error = 0.0 if not params.has_background else math.nan
        else:
            coarse = Mesh(c.mesh.breaks, c.mesh.degree - 2)
            fc = Filament(params, coarse)
            th = fc.split(fc.equilibrium_state())[0]
            error = float(np.hypot(*(fc.clamp_force(fc.drag(th, np.zeros_like(th))) - c.thrust)))
        status, message = c.status, c.message
    scale = max(c.thrust_norm if np.all(np.isfinite(c.thrust)) else 0.0, params.eta * U)
    if status == "success" and error > rtol * scale:
        status = "inaccurate"
        message += f"; thrust error estimate {error:.1e} above rtol x {scale:.3g}: raise the degree"
    message += f"; |Fbar| error estimate {error:.1e}"
    return MeanThrust(params, c.flutter, np.array(c.thrust, dtype=float), float(error), period, period_error,
                      status, message, c)


def _first_orbit(solver: OrbitSolver, fil: Filament, st, seed, tol, params) -> Orbit:
    """Converge from the seed (or the Hopf mode), then move the start to phase 0 and re-converge.

    Without a seed, the Hopf mode is first scaled to the amplitude guess ``0.85 sqrt(alpha)``
    (max |theta| of the mode; the normal-form scaling, calibrated at chi_E = 200, eta = 1),
    relaxed for two periods and handed to Newton; if that does not give a genuine cycle (no
    convergence, or collapse onto the equilibrium), the mode is grown by a transient
    (:func:`_seed_from_eigenvector`).
    """
    T0 = 2 * math.pi / st.beta
    orbit = None
    seeds = [sd for sd in ([seed] if isinstance(seed, LimitCycle) else list(seed or []))
             if sd.flutter and sd.state0 is not None]
    if seeds:
        try:
            y, T = _predict(seeds, fil)
            orbit = _genuine(solver, solver.converge(y, T, float(y[solver.i_tip]), tol), T)
        except ConvergenceError as exc:
            logger.info("limit_cycle %s: seed did not converge (%s); starting from the Hopf mode", params, exc)
    y_eq = fil.equilibrium_state()
    if orbit is None:
        v = np.real(fil.join(st.theta_modes[0], st.kappa_modes[0]))
        v = v / np.max(np.abs(v[: fil.n - 1]))
        a = min(1.2, 0.85 * math.sqrt(max(st.alpha, 0.0)))
        try:
            y = y_eq + a * v
            for _ in range(2):
                y = solver.orbit_states(y, T0)[0][-1]
            y, c = _section_through(solver, y, T0)
            orbit = _genuine(solver, solver.converge(y, T0, c, tol, max_newton=12), T0)
        except ConvergenceError as exc:  # (a failed step too: the transient below starts smaller)
            logger.info("limit_cycle %s: the scaled Hopf mode did not converge (%s); growing it", params, exc)
    if orbit is None:
        y, c = _section_through(solver, _seed_from_eigenvector(st, y_eq, fil, solver, T0), T0)
        orbit = _genuine(solver, solver.converge(y, T0, c, tol), T0)
    return orbit


def _genuine(solver: OrbitSolver, orbit: Orbit, T_guess: float) -> Orbit:
    """Refuse a collapse onto the equilibrium (any period, zero amplitude) or a far-off period."""
    tip = orbit.states[:, solver.i_tip]
    if not (0.4 * T_guess < orbit.period < 2.5 * T_guess) or np.ptp(tip) < 1e-7:
        raise OrbitError(f"Newton converged to a degenerate orbit (period {orbit.period:.3g}, tip amplitude "
                         f"{np.ptp(tip):.2g}) instead of the cycle")
    return orbit
