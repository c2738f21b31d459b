"""The design of standing carpets: (chi_N, psi) per cilium so that the surface flow meets a target.

A standing carpet (:mod:`~ciliary_carpet.carpet.geometry`) clamps cilium j at b_j on the substrate
z = 0 with the field along +z; its curvature chi_N_j >= 0 sets how far its mean thrust leans from
the normal, its azimuth psi_j which way. The target is the cycle-mean flow on the plane z = h
(``height``) above the substrate -- the *surface flow* -- at control points x_k (P, 2): its
direction t_k (angle targets, any direction: pumps, vortices, mixers, U-turns) or its velocity
U_k (velocity targets).

The design model (the tabulated single-cilium response, the far carriers and their adjoint) is
:mod:`~ciliary_carpet.design.surface_model`.

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

import numpy as np
from scipy.optimize import minimize

from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.design.errors import TargetError
from ciliary_carpet.design.result import Design
from ciliary_carpet.design.surface_model import HEIGHT
from ciliary_carpet.design.surface_problem import Layout, PassObjective, SurfaceProblem

logger = logging.getLogger(__name__)

__all__ = ["design_surface"]


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
    problem = SurfaceProblem(carpet, X, height, kind, aim, eps, strict=strict, speed_floor=speed_floor,
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


def _local_layout(problem: SurfaceProblem, check_tol: float) -> Layout:
    """The local layout, checked on the full model.

    Parameters
    ----------
    problem : SurfaceProblem
        The design problem.
    check_tol : float
        Tolerance of the check.

    Returns
    -------
    Layout
        The local layout (``returned`` "local").
    """
    chi, psi = problem.chi0.copy(), problem.psi0.copy()
    c_full, s_full = problem.check(chi, psi, check_tol)
    J = problem.judged(chi, psi, s_full.velocity)
    return Layout(J=J, chi=chi, psi=psi, carpet=c_full, sample=s_full, returned="local")


def _solve_pass(problem: SurfaceProblem, chi: np.ndarray, psi: np.ndarray, u_full: np.ndarray, *, maxiter: int,
                ftol: float, threshold: float | None):
    """One L-BFGS-B solve of the design model plus the defect at the layout (chi, psi).

    Parameters
    ----------
    problem : SurfaceProblem
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
    fun = PassObjective(problem, defect, scale, threshold)
    z0 = np.concatenate([chi / chi_hi, psi])
    res = minimize(fun, z0, jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * N + [(None, None)] * N,
                   options={"maxiter": int(maxiter), "ftol": ftol, "gtol": 1e-10}, callback=fun.good_enough)
    return res, scale


def _passes(problem: SurfaceProblem, local: Layout, *, check_tol: float, outer: int, maxiter: int, ftol: float,
            threshold: float | None) -> tuple[Layout, str, str]:
    """The passes of defect correction from the local layout.

    Each pass solves the design model plus the full model's defect at the previous pass's layout
    (:func:`_solve_pass`) and checks its layout on the full model. The passes stop when the model's
    J and the full model's agree to 5 %, or a pass gains less than 2 % of the best J.

    Parameters
    ----------
    problem : SurfaceProblem
        The design problem.
    local : Layout
        The local layout (:func:`_local_layout`).
    check_tol, outer, maxiter, ftol, threshold
        As :func:`design_surface`.

    Returns
    -------
    best : Layout
        The layout of least J (:meth:`SurfaceProblem.judged`) among the local one and the passes'.
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
            best = Layout(J=Jf, chi=chi, psi=psi, carpet=c_full, sample=s_full, returned=f"pass {k + 1}")
        if abs(res.fun / scale - Jf) <= 0.05 * Jf or gained < 0.02 * best.J:
            break
    return best, status, msg


def _final_check(problem: SurfaceProblem, best: Layout, threshold: float | None, check_tol: float):
    """The best layout's flow with an error bar of at most half the threshold.

    Given a threshold, the tolerance is divided by 10 until the error bar is at most half of it
    (down to 1e-5); beyond, the flow is evaluated exactly (tol 0, error bar 0).

    Parameters
    ----------
    problem : SurfaceProblem
        The design problem.
    best : Layout
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
        Its rms residual's error bar (:meth:`SurfaceProblem.error_bar`).
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


def _result(problem: SurfaceProblem, best: Layout, local: Layout, sample, err: float, final_tol: float,
            threshold: float | None, status: str, msg: str, clock: float) -> Design:
    """The :class:`~ciliary_carpet.design.result.Design` of the best layout.

    Parameters
    ----------
    problem : SurfaceProblem
        The design problem.
    best, local : Layout
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
