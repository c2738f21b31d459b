"""Linear stability of the equilibrium (MODEL.md section 4): spectra, regimes, Hopf boundaries.

Linearising the Galerkin system ``M(y) y' = f(y)`` of :mod:`single_cilium.filament` about its
discrete equilibrium ``y_eq`` (where ``y' = 0``, so the derivative of ``M`` drops out) gives the
generalised eigenproblem

    omega M X = J X,      M = diag(D(theta_eq), I),
    J = [[-K, B], [-chi_E diag(cos theta_eq), -I]],

i.e. ``omega D theta^l = -K theta^l + B kappa^l``, ``omega kappa^l = -kappa^l - chi_E cos(theta_eq) theta^l``:
the weak form of MODEL.md section 4 with the contact force obtained by integrating the drag
(as in the published treatment). ``M`` is symmetric positive definite, so the pencil has no
infinite eigenvalues and none can turn into spurious finite ones; ``D`` is ill-conditioned
(~1e10), so the pencil is solved by the QZ algorithm (LAPACK ggev), never through ``M^-1``.
In a background flow ``U`` (``params.background``) the equilibrium is the discrete steady state
(:meth:`~single_cilium.filament.Filament.equilibrium_state`, Newton continued in ``|U|``; no
closed form) and ``J``'s theta block gains ``-dg_U/dtheta``, the derivative of the stream's drag
on the held filament (not symmetric); ``M`` is unchanged.
The stiff elastic modes lie far to the left (~ -h^-4/eta); the kappa relaxation contributes a
cluster at Re omega = -1 (an essential spectrum in the continuum limit).

``omega_max = alpha + i beta`` is the eigenvalue of largest real part: ``alpha < 0`` stable;
``alpha >= 0`` with ``beta != 0`` flutter (a supercritical Hopf bifurcation in the published
study; period near onset ``2 pi / beta``); ``alpha >= 0`` with ``beta = 0`` divergence.

The chi_N -> 0 limit for chi_E < 0
----------------------------------
For ``chi_E < 0`` and ``chi_N = 0`` the equilibrium is the straight filament ``theta = 0``,
pointing against the field: an unstable fixed point of ``theta' = chi_N - chi_E sin theta``
that the clamp holds, and it flutters. Any ``chi_N > 0``, however small, makes ``theta`` leave 0
and fold over to ``pi - arcsin(chi_N/chi_E)`` within a front near
``s = ln(|chi_E| / chi_N) / |chi_E|``: the filament now lies along the field, a different
equilibrium altogether, and it is stable. This is why a tiny natural curvature removes flutter
for ``chi_E < 0`` (the published claim; reproduced in the tests) but changes nothing for
``chi_E > 0``, where ``theta = 0`` is the stable fixed point and the equilibrium depends
smoothly on ``chi_N``.

One concept: the spectrum, the regime, the flutter cutoff, the flutter boundary and the
stability map are one linearisation (the same pencil) asked four ways.
"""
from __future__ import annotations

import logging
import math
import warnings
from concurrent.futures import Executor
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import xarray as xr
from scipy.optimize import brentq

from .version import __version__
from cilia_runtime.blas import single_threaded_blas
from .filament import Filament
from .mesh import Mesh
from .params import CiliumParams
from cilia_runtime.progress import Progress

logger = logging.getLogger(__name__)

__all__ = ["stability", "Stability", "ResolutionWarning", "flutter_cutoff", "Cutoff",
           "flutter_boundary", "FlutterBoundary", "stability_map", "spectrum"]

DEFAULT_DEGREE = 10
_STATUSES = ("success", "inaccurate", "unchecked")
COILED_ALPHA = -1.0  # stands for "stable" where coiled points are not computed


class ResolutionWarning(UserWarning):
    """The leading eigenvalue changed under refinement by more than the requested tolerance."""


def _pencil(fil: Filament) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    y = fil.equilibrium_state()
    theta, _ = fil.split(y)
    n, p = fil.n, fil.params
    M = np.eye(fil.size)
    M[: n - 1, : n - 1] = fil.resistance_matrix(theta)
    J = np.zeros((fil.size, fil.size))
    J[: n - 1, : n - 1] = -fil._K[1:, 1:]
    if p.has_background:
        J[: n - 1, : n - 1] -= fil.stream_jacobian(theta)
    J[: n - 1, n - 1:] = fil._B[1:, :]
    J[n:, : n - 1] = -p.chi_E * np.diag(np.cos(theta[1:]))
    J[n - 1:, n - 1:] = -np.eye(n)
    return J, M, theta


def spectrum(params: CiliumParams, mesh: Mesh, vectors: bool = False):
    """The eigenvalues of the linearisation on ``mesh`` (all ``2n - 1`` but those QZ finds
    infinite, see below), by decreasing real part (conjugate pairs: positive imaginary part
    first); with ``vectors=True`` also the right eigenvectors as columns (state layout of
    :class:`Filament`)."""
    fil = Filament(params, mesh)
    J, M, _ = _pencil(fil)
    with single_threaded_blas():
        if vectors:
            w, V = sla.eig(J, M, right=True, check_finite=False)
        else:
            w, V = sla.eig(J, M, right=False, check_finite=False), None
    finite = np.isfinite(w)
    if not np.all(finite):
        # M is SPD but, with the tiny clamp elements of a thin layer, numerically singular
        # (condition > 1e15): QZ reports the stiffest elastic modes (rates ~ -1e18) as infinite.
        # They are dropped; they never carry a positive real part.
        logger.debug("spectrum %s: %d infinite eigenvalue(s) dropped", params, int((~finite).sum()))
        w = w[finite]
        V = V[:, finite] if V is not None else None
    order = np.lexsort((-w.imag, -w.real))
    w = w[order]
    return (w, V[:, order]) if vectors else w


def _leading(w: np.ndarray) -> complex:
    return complex(w[0].real, abs(w[0].imag))


def _hopf_alpha(w: np.ndarray) -> tuple[float, float]:
    """(alpha, beta) of the rightmost eigenvalue with a positive imaginary part."""
    osc = w[w.imag > 0]
    if osc.size == 0:
        return -math.inf, 0.0
    k = np.argmax(osc.real)
    return float(osc[k].real), float(osc[k].imag)


def _rightmost_discrete(w: np.ndarray) -> complex:
    """Rightmost eigenvalue (imaginary part >= 0) to the right of the kappa-relaxation spectrum
    (``Re omega > -1``); NaN if there is none."""
    right = w[(w.real > -1.0 + 1e-9) & (w.imag >= 0)]
    return complex(right[0]) if right.size else complex(np.nan, np.nan)


def _regime(omega: complex) -> str:
    if omega.real < 0:
        return "stable"
    return "flutter" if omega.imag != 0 else "divergence"


@dataclass(frozen=True)
class Stability:
    """Result of :func:`stability`.

    Attributes
    ----------
    eigenvalues : (k,) complex
        The ``k`` rightmost eigenvalues, by decreasing real part.
    theta_modes, kappa_modes : (k, n) complex
        Mode shapes at ``s`` (``theta^l(0) = 0``), each normalised to ``max |theta^l| = 1``.
    s : (n,) mesh nodes.
    alpha, beta : float
        Leading eigenvalue ``omega_max = alpha + i beta`` (``beta >= 0``).
    regime : "stable", "flutter" or "divergence".
    period_estimate : ``2 pi / beta`` (NaN when ``beta = 0``).
    error : float
        Relative change, from the mesh degree ``p - 2`` to ``p``, of the rightmost eigenvalue
        with ``Re omega > -1`` (at ``-1`` and to its left sits the kappa relaxation: the exact
        ``kappa_0`` mode, often the leading eigenvalue of a stable filament, and approximants of
        an essential spectrum that do not converge one by one): the error of the coarser, an
        upper estimate for this one; 0 when neither mesh has such an eigenvalue (stable, every
        rate <= -1). NaN without ``check``.
    status, message : str
        How the solve ended, in the convention of :mod:`single_cilium` results
        (:class:`~single_cilium.cycle.LimitCycle`, :class:`~single_cilium.dynamics.Simulation`):
        ``"success"`` (``error <= rtol``), ``"inaccurate"`` (``error > rtol``; a
        :class:`ResolutionWarning` is issued and the message says what to refine) or
        ``"unchecked"`` (``check=False``: no error estimate); ``message`` is one line.
    converged : bool
        Derived: ``status != "inaccurate"`` (True also when unchecked).
    """

    params: CiliumParams
    mesh: Mesh
    eigenvalues: np.ndarray
    theta_modes: np.ndarray
    kappa_modes: np.ndarray
    s: np.ndarray
    error: float = math.nan
    status: str = "unchecked"
    message: str = ""

    def __post_init__(self):
        if self.status not in _STATUSES:
            raise ValueError(f"status must be one of {_STATUSES}, got {self.status!r}")

    @property
    def converged(self) -> bool:
        return self.status != "inaccurate"

    @property
    def omega(self) -> complex:
        return _leading(self.eigenvalues)

    @property
    def alpha(self) -> float:
        return self.omega.real

    @property
    def beta(self) -> float:
        return self.omega.imag

    @property
    def regime(self) -> str:
        return _regime(self.omega)

    @property
    def period_estimate(self) -> float:
        return 2 * math.pi / self.beta if self.beta > 0 else math.nan

    def as_dict(self) -> dict:
        return {"chi_E": self.params.chi_E, "eta": self.params.eta, "chi_N": self.params.chi_N,
                "alpha": self.alpha, "beta": self.beta, "regime": self.regime,
                "period_estimate": self.period_estimate, "error": self.error,
                "status": self.status, "message": self.message, "mesh": self.mesh.describe(),
                "eigenvalues": [[float(z.real), float(z.imag)] for z in self.eigenvalues]}


def stability(params: CiliumParams, *, mesh: Mesh | None = None, degree: int = DEFAULT_DEGREE,
              n_modes: int = 6, check: bool = True, rtol: float = 1e-6) -> Stability:
    """Leading eigenvalues and modes of the linearisation about the equilibrium (clamp phi = 0).

    Parameters
    ----------
    params : CiliumParams
        With a background flow (``params.background != (0, 0)``) the linearisation is about the
        discrete steady state in that stream (module docstring).
    mesh : Mesh, optional
        Default ``Mesh.for_params(params, degree)``.
    n_modes : int
        How many of the rightmost eigenvalues (and modes) to return.
    check : bool
        Also solve on the same elements with the degree lowered by 2 and report the change of
        the leading eigenvalue as ``error``; warn (:class:`ResolutionWarning`) above ``rtol``.
    """
    if not isinstance(params, CiliumParams):
        raise TypeError(f"params must be a CiliumParams, got {type(params).__name__}")
    if int(n_modes) != n_modes or n_modes < 1:
        raise ValueError(f"n_modes must be a positive integer, got {n_modes}")
    mesh = mesh if mesh is not None else Mesh.for_params(params, degree)
    w, V = spectrum(params, mesh, vectors=True)
    k = min(int(n_modes), w.size)
    w, V = w[:k], V[:, :k]
    n = mesh.n_nodes
    th = np.vstack([np.zeros((1, k)), V[: n - 1]]).T
    ka = V[n - 1:].T
    norm = th[np.arange(k), np.argmax(np.abs(th), axis=1)]
    norm[norm == 0] = 1.0
    th, ka = th / norm[:, None], ka / norm[:, None]
    error, status, message = math.nan, "unchecked", "not checked (check=False): no error estimate"
    if check:
        coarse = Mesh(mesh.breaks, max(4, mesh.degree - 2))
        w_all, w_c = spectrum(params, mesh), spectrum(params, coarse)
        # the rightmost eigenvalue right of Re omega = -1: there sits the kappa relaxation (the
        # exact kappa_0 mode, and approximants of an essential spectrum that approach -1 from the
        # left under refinement and never converge one by one); to its right lie the modes that
        # decide the regime
        a, b = _rightmost_discrete(w_all), _rightmost_discrete(w_c)
        if np.isnan(a.real) and np.isnan(b.real):
            error = 0.0
        elif np.isnan(a.real) or np.isnan(b.real):
            error = math.inf
        else:
            error = abs(a - b) / max(abs(a), 1e-300)
        status = "success" if error <= rtol else "inaccurate"
        message = (f"leading eigenvalues change by {error:.1e} (relative) from degree "
                   f"{coarse.degree} to {mesh.degree}")
        if status == "inaccurate":
            message += f" > rtol={rtol:g}: raise the degree or refine the mesh"
            warnings.warn(f"stability at {params}: {message}", ResolutionWarning, stacklevel=2)
    return Stability(params, mesh, w, th, ka, mesh.nodes, error, status, message)


# ---------------------------------------------------------------------------------- cutoff
@dataclass(frozen=True)
class Cutoff:
    """Flutter cutoff: ``chi_N_cutoff`` where the oscillatory mode crosses ``alpha = 0``, with
    ``beta`` there; ``error`` estimates the cutoff's discretisation error (relative), from the
    same root on the mesh of degree lowered by 4. ``chi_N_cutoff`` is NaN (with a message) when
    the field does not flutter at ``chi_N = 0`` or does at every ``chi_N`` scanned.
    ``background``: the background flow ``U`` it was computed in."""

    chi_E: float
    eta: float
    chi_N_cutoff: float
    beta: float
    error: float
    message: str
    n_eigensolves: int
    background: tuple = (0.0, 0.0)

    def as_dict(self) -> dict:
        return {"chi_E": self.chi_E, "eta": self.eta, "U1": self.background[0], "U2": self.background[1],
                "chi_N_cutoff": self.chi_N_cutoff, "beta": self.beta, "error": self.error, "message": self.message}


def flutter_cutoff(chi_E: float, eta: float, *, degree: int = DEFAULT_DEGREE, xtol: float = 1e-10,
                   n_scan: int = 24, background: tuple[float, float] = (0.0, 0.0)) -> Cutoff:
    """The natural curvature above which the filament stops fluttering, at fixed (chi_E, eta).

    ``chi_N`` in ``[0, |chi_E|)`` is scanned at ``n_scan`` points for the last sign change of
    the oscillatory growth rate ``alpha`` (rightmost eigenvalue with ``beta > 0``), which is then
    located by Brent's method to ``xtol`` (relative). Only an unrolled filament
    (``|chi_E| > chi_N``) may flutter (MODEL.md section 4).

    ``background``: the uniform flow ``U = (U1, U2)`` (field frame, units ``L / tau``) the filament
    sits in; each eigensolve linearises about the steady state in it. Only ``chi_N >= 0`` is
    scanned: negative ``chi_N`` is the mirror image with ``U1 -> -U1``. Where the steady state
    in the stream ceases to exist (a fold, e.g. near ``chi_N = chi_E``, where the still-fluid
    equilibrium is marginal and a weak stream tips it over) the scan stops, and says so.
    """
    base = CiliumParams(chi_E, eta, 0.0, background)
    count = [0]

    def alpha(cN: float, deg: int) -> float:
        p = CiliumParams(base.chi_E, base.eta, cN, base.background)
        count[0] += 1
        try:
            return _hopf_alpha(spectrum(p, Mesh.for_params(p, deg)))[0]
        except RuntimeError:  # no steady state in the stream (continuation met a fold)
            if not base.has_background:
                raise
            return math.nan

    top = abs(base.chi_E) * (1 - 1e-6)
    grid = np.linspace(0.0, top, int(n_scan))
    vals = np.array([alpha(c, degree) for c in grid])
    if np.isnan(vals).any():
        n_ok = int(np.argmax(np.isnan(vals)))
        if n_ok == 0:
            return Cutoff(base.chi_E, base.eta, math.nan, math.nan, math.nan,
                          "no steady state at chi_N = 0 in this stream: no cutoff", count[0], base.background)
        grid, vals = grid[:n_ok], vals[:n_ok]
        top = float(grid[-1])
        logger.info("flutter_cutoff(%g, %g, background=%s): no steady state beyond chi_N = %.6g; scan stops",
                    base.chi_E, base.eta, base.background, top)
    pos = vals >= 0
    if not pos[0]:
        return Cutoff(base.chi_E, base.eta, math.nan, math.nan, math.nan,
                      "no flutter at chi_N = 0 for this field: no cutoff", count[0], base.background)
    if pos[-1]:
        return Cutoff(base.chi_E, base.eta, math.nan, math.nan, math.nan,
                      f"flutter at every chi_N scanned up to {top:.6g}"
                      + (" (no steady state in this stream beyond)" if top < abs(base.chi_E) * (1 - 1e-6) else ""),
                      count[0], base.background)
    k = np.nonzero(pos[:-1] & ~pos[1:])[0][-1]

    def root(deg: int) -> float:
        return brentq(lambda c: alpha(c, deg), grid[k], grid[k + 1], xtol=xtol * grid[k + 1],
                      rtol=4 * np.finfo(float).eps, maxiter=200)

    with single_threaded_blas():
        c = root(degree)
        c_coarse = root(max(4, degree - 4))
    p = CiliumParams(base.chi_E, base.eta, c, base.background)
    beta = _hopf_alpha(spectrum(p, Mesh.for_params(p, degree)))[1]
    err = abs(c - c_coarse) / c
    return Cutoff(base.chi_E, base.eta, c, beta, err,
                  f"Hopf crossing between chi_N = {grid[k]:.6g} and {grid[k + 1]:.6g}", count[0],
                  base.background)


# ---------------------------------------------------------------------------------- boundary
@dataclass(frozen=True)
class FlutterBoundary:
    """Hopf boundaries ``alpha(chi_E, eta) = 0`` (``beta > 0``) in a window, at fixed chi_N.

    ``branches`` is a list of arrays of shape ``(m, 3)``: columns ``eta``, ``chi_E``, ``beta``
    along each branch, in continuation order. Empty, with a message, when the window holds none.
    """

    chi_N: float
    chi_E_window: tuple[float, float]
    eta_window: tuple[float, float]
    branches: list = field(default_factory=list)
    message: str = ""
    n_eigensolves: int = 0


def flutter_boundary(chi_N: float, *, chi_E: tuple[float, float], eta: tuple[float, float],
                     degree: int = 8, n_edge: int = 17, step: float = 0.04, tol: float = 1e-9,
                     max_points: int = 400) -> FlutterBoundary:
    """Trace every Hopf boundary crossing the window ``chi_E x eta`` by pseudo-arclength
    continuation of ``alpha(chi_E, eta) = 0``.

    Seeds are the crossings of the window's four edges (``n_edge`` points per edge, then
    Brent's method); each is continued inward with a tangent predictor and a Newton corrector
    along the gradient (finite differences) in coordinates scaled by the window, ``step`` being
    the arclength step in those units, until it leaves the window; a seed that another branch
    already reached is skipped. ``tol`` bounds ``|alpha|`` at every returned point.
    Coiled points (``|chi_E| < |chi_N|``) count as stable without an eigensolve (see
    :func:`stability_map`).
    """
    lo_E, hi_E = map(float, chi_E)
    lo_e, hi_e = map(float, eta)
    if not (math.isfinite(lo_E) and math.isfinite(hi_E) and lo_E < hi_E):
        raise ValueError(f"chi_E window must be finite and increasing, got {chi_E}")
    if not (math.isfinite(lo_e) and math.isfinite(hi_e) and 0 < lo_e < hi_e):
        raise ValueError(f"eta window must be finite, positive and increasing, got {eta}")
    base = CiliumParams(lo_E, lo_e, chi_N)
    scale = np.array([hi_E - lo_E, hi_e - lo_e])
    origin = np.array([lo_E, lo_e])
    count = [0]
    cache: dict = {}

    def ab(u: np.ndarray) -> tuple[float, float]:
        key = (float(u[0]), float(u[1]))
        if key not in cache:
            x = origin + u * scale
            if abs(x[0]) < abs(base.chi_N):
                cache[key] = (COILED_ALPHA, 0.0)  # coiled: stable, not computed
            else:
                p = CiliumParams(x[0], x[1], base.chi_N)
                count[0] += 1
                cache[key] = _hopf_alpha(spectrum(p, Mesh.for_params(p, degree)))
        return cache[key]

    def a(u):
        return ab(u)[0]

    def grad(u: np.ndarray, h: float = 1e-6) -> np.ndarray:
        a0 = a(u)
        return np.array([(a(u + h * e) - a0) / h for e in np.eye(2)])

    inside = lambda u: np.all(u >= -1e-12) and np.all(u <= 1 + 1e-12)  # noqa: E731

    # seeds on the edges (u-coordinates), walking the boundary anticlockwise
    edges = [(np.array([0.0, 0.0]), np.array([1.0, 0.0])), (np.array([1.0, 0.0]), np.array([1.0, 1.0])),
             (np.array([1.0, 1.0]), np.array([0.0, 1.0])), (np.array([0.0, 1.0]), np.array([0.0, 0.0]))]
    seeds = []
    for P, Q in edges:
        ts = np.linspace(0, 1, n_edge)
        vals = [a(P + t * (Q - P)) for t in ts]
        for i in range(n_edge - 1):
            if np.isfinite(vals[i]) and np.isfinite(vals[i + 1]) and vals[i] * vals[i + 1] < 0:
                t = brentq(lambda t: a(P + t * (Q - P)), ts[i], ts[i + 1], xtol=1e-12)
                seeds.append(P + t * (Q - P))
    branches: list[np.ndarray] = []
    ends: list[np.ndarray] = []
    for seed in seeds:
        if any(np.linalg.norm(seed - e) < 1e-6 for e in ends):
            continue
        g = grad(seed)
        tan = np.array([-g[1], g[0]]) / np.linalg.norm(g)
        if not inside(seed + 1e-3 * tan):
            tan = -tan
        pts = [seed]
        u, ds = seed, step
        while len(pts) < max_points:
            pred = u + ds * tan
            v = pred
            ok = False
            for _ in range(8):
                av = a(v)
                if not np.isfinite(av):
                    break
                gv = grad(v)
                v = v - av * gv / (gv @ gv)
                if abs(a(v)) <= tol:
                    ok = True
                    break
            if not ok or np.linalg.norm(v - u) > 3 * ds:
                ds *= 0.5
                if ds < 1e-5:
                    break
                continue
            if not inside(v):
                w = _exit_point(u, v, a, grad, tol)
                pts.append(w)
                ends.append(w)
                break
            gv = grad(v)
            new_tan = np.array([-gv[1], gv[0]]) / np.linalg.norm(gv)
            tan = new_tan if new_tan @ tan > 0 else -new_tan
            pts.append(v)
            u = v
            ds = min(step, ds * 1.5)
        arr = np.array(pts)
        x = origin + arr * scale
        betas = [ab(p_)[1] for p_ in arr]
        branches.append(np.column_stack([x[:, 1], x[:, 0], betas]))
    msg = (f"{len(branches)} branch(es)" if branches else
           "no Hopf boundary crosses this window (alpha keeps one sign on its edges)")
    return FlutterBoundary(float(chi_N), (lo_E, hi_E), (lo_e, hi_e), branches, msg, count[0])


def _exit_point(u, v, a, grad, tol):
    """Where the branch from ``u`` (inside the unit square) to ``v`` (outside) leaves it:
    the crossing of the segment with the boundary, corrected onto ``alpha = 0`` along the edge."""
    def dist(t):
        q = u + t * (v - u)
        return min(np.min(q), 1.0 - np.max(q))

    w = u + brentq(dist, 0.0, 1.0, xtol=1e-14) * (v - u)
    w = np.clip(w, 0.0, 1.0)
    k = int(np.argmin(np.minimum(np.abs(w), np.abs(1 - w))))  # the coordinate on the edge
    free = 1 - k
    for _ in range(8):
        av = a(w)
        if abs(av) <= tol:
            break
        g = grad(w)
        if g[free] == 0:
            break
        w = w.copy()
        w[free] = np.clip(w[free] - av / g[free], 0.0, 1.0)
    return w


# ---------------------------------------------------------------------------------- map
def _validate_grid(name: str, values) -> np.ndarray:
    a = np.atleast_1d(np.asarray(values, dtype=float))
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"{name} grid must be a non-empty 1-d sequence")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} grid contains NaN or inf")
    if a.size > 1 and np.any(np.diff(a) <= 0):
        raise ValueError(f"{name} grid must be strictly increasing")
    return a


def _map_row(args):
    chi_E, etas, chi_N, degree, skip_coiled = args
    out = np.full((etas.size, 2), np.nan)
    if skip_coiled and abs(chi_E) < abs(chi_N):
        return out
    with single_threaded_blas():
        for j, eta in enumerate(etas):
            p = CiliumParams(chi_E, eta, chi_N)
            lead = _leading(spectrum(p, Mesh.for_params(p, degree)))
            out[j] = lead.real, lead.imag
    return out


def stability_map(chi_N: float, *, chi_E, eta, degree: int = 8, executor: Executor | None = None,
                  progress: Progress | None = None, skip_coiled: bool = True) -> xr.Dataset:
    """Leading eigenvalue over a grid of (chi_E, eta) at fixed chi_N.

    Returns an xarray Dataset with dims ``chi_E`` and ``eta`` and variables ``alpha`` (growth
    rate), ``beta`` (angular frequency), ``frequency`` (``beta / 2 pi``, NaN outside flutter)
    and ``regime`` (0 stable, 1 flutter, 2 divergence, 3 coiled), with CF attributes.
    Coiled points (``|chi_E| < |chi_N|``) are stable (MODEL.md section 4: only an unrolled
    filament may flutter; the tests check spectra there) but need a mesh with an element per
    half turn of the coil, tens of times dearer; with ``skip_coiled`` (default) they are marked
    ``regime = 3`` with ``alpha = beta = NaN`` instead of computed. Rows of constant
    chi_E are computed in parallel on ``executor`` (default: a process pool over the machine's
    cores); pass any ``concurrent.futures.Executor`` (e.g. a dask.distributed client's).
    """
    cE = _validate_grid("chi_E", chi_E)
    et = _validate_grid("eta", eta)
    if np.any(et <= 0):
        raise ValueError("eta grid must be > 0")
    CiliumParams(cE[0], et[0], chi_N)  # validates chi_N
    progress = progress if progress is not None else Progress()
    tasks = [(float(c), et, float(chi_N), degree, skip_coiled) for c in cE]
    own = executor is None
    if own:
        from concurrent.futures import ProcessPoolExecutor

        from cilia_runtime.threads import cores

        executor = ProcessPoolExecutor(max_workers=cores())  # a container's CPU quota, not the host's cores
    progress.start(len(tasks), "stability map")
    try:
        rows = []
        for k, row in enumerate(executor.map(_map_row, tasks)):
            rows.append(row)
            progress.update(k + 1)
    finally:
        progress.close()
        if own:
            executor.shutdown()
    ab = np.stack(rows)
    alpha, beta = ab[..., 0], ab[..., 1]
    regime = np.where(np.isnan(alpha), 3, np.where(alpha < 0, 0, np.where(beta > 0, 1, 2))).astype(np.int8)
    freq = np.where(regime == 1, beta / (2 * np.pi), np.nan)

    def var(v, long_name, units="1", **extra):
        return (("chi_E", "eta"), v, {"long_name": long_name, "units": units, **extra})

    return xr.Dataset(
        {
            "alpha": var(alpha, "growth rate: real part of the leading eigenvalue"),
            "beta": var(beta, "angular frequency: imaginary part of the leading eigenvalue (>= 0)"),
            "frequency": var(freq, "flutter frequency beta / (2 pi) (NaN outside flutter)"),
            "regime": var(regime, "regime of the leading eigenvalue",
                          flag_values=np.array([0, 1, 2, 3], np.int8),
                          flag_meanings="stable flutter divergence coiled_not_computed"),
        },
        coords={"chi_E": ("chi_E", cE, {"long_name": "stimulus L kappa_E", "units": "1"}),
                "eta": ("eta", et, {"long_name": "drag/bending mu_par L^4/(tau B)", "units": "1"})},
        attrs={"chi_N": float(chi_N), "mesh": f"Mesh.for_params(params, degree={degree})",
               "method": "QZ on the Galerkin linearisation", "package_version": __version__},
    )
