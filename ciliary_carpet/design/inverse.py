"""Inverse design: a signed chi_N for every cilium so that the carpet's mean flow matches a target.

The solve works on the design model (:mod:`ciliary_carpet.design.model`: each cilium's dipole
carriers, the exact flow of the cilia near each control point), corrected by the full flow model.

Defect correction. After each inner solve the full flow model
(:meth:`Carpet.evaluate` of the :class:`CycleMean`: resolved near pairs, levels of detail elsewhere) is evaluated at
the control points, and the next solve minimises the objective of ``model(chi) + (u_full -
model)(chi_pass)``. The model already holds the monopole and dipole of every cilium (with the
wall when there is one) and the near pairs exactly, so the defect is the far pairs' field
beyond the dipole: small, and weakly dependent on chi.

Objective
---------
* Angle targets (deflection delta_k at control point k; target direction t_k = d0 rotated by
  delta_k, d0 the straight filaments' flow direction), with s_k the speed that the straight
  cilia (chi_N = 0) within ``floor_radius`` (default 5 spacings) of x_k make there (design
  model, :func:`~ciliary_carpet.design.model.floor_reference`):

      J = 1/P sum_k [ (1 - uhat_k . t_k)  +  (w / 2) max(0, 1 - (u_k . t_k) / (sigma s_k))^2 ].

  The first term is 1 - cos(angle error), about half the squared angle error: scale-free,
  because only directions are asked for. Alone it can be "met" by switching cilia off: the
  thrust angle grows up to the flutter cutoff while the thrust vanishes there, so an angle-only
  objective trades all the thrust for angle (this is what drove every cilium of the focusing and
  spreading scenes to the cutoff, where the full model has no flow at all). The second term is a
  floor on the speed along the target direction: a fraction ``sigma`` (``speed_floor``, default
  0.3) of what the straight cilia around x_k make there, with weight ``w`` (``floor_weight``,
  default 1; J = w / 2 per point for a switched-off carpet, far above any design worth keeping). A floor
  rather than a speed target: the target asks for directions, so the speed is free above the
  floor; relative to the straight cilia within a fixed radius, so it is the same statement for
  every carpet size, field and target. (Relative to the whole straight carpet, as before, it
  was not: that speed grows with the carpet's size -- the Stokeslets decay as 1/r -- while the
  cross-stream flow a pattern of width w makes near its line does not, so the floor bound
  harder the larger the carpet: 1000 cilia could not focus at 20 degrees, 0.054 rad against
  0.05, at every regulariser weight and L-BFGS-B tolerance tried, with the design model
  agreeing with the full model within 2%; with the local floor 0.026 rad. Focusing a large
  carpet slows its along-stream flow: the summary reports the cilia near the cutoff.) A cilium
  keeps 30% of the straight thrust up to |chi_N| of about 142 of the cutoff 162.77 at
  chi_E = 200, eta = 1, which turns its own thrust by 0.82 of the reachable 0.93 rad.
* Velocity targets U_k: J = 1/2 sum_k |u_k - U_k|^2 / sum_k |U_k|^2 (it needs no floor).
* Regularisers: ``regularization`` lambda/N sum_j ((chi_j - chi0_j)/chi_c)^2 keeps each cilium
  near its local request unless departing buys a better match (the problem is not unique);
  ``smoothness`` mu/E sum_{(i,j) neighbours} ((chi_i - chi_j)/chi_c)^2 over the Delaunay edges
  of the base points penalises layouts that change from cilium to cilium (fabrication cost:
  fewer distinct curvatures), chi_c the flutter cutoff.

L-BFGS-B (scipy) solves it in x = chi / chi_c with |x| <= 1. The gradient is exact and
matrix-free: dJ/dchi_j = sum_m g(c_jm) . f_jm'(chi_j) with g(y) = sum_k G(x_k - y)^T dJ/du_k,
one more Stokeslet sum with sources and targets swapped (G, and Blake's tensor by the
reciprocal theorem, are symmetric under the swap for points in one plane), so an evaluation
costs two O(P N) kernel sums and no P x N matrix is formed.

Local minima. The objective is not convex in chi (a cilium's flow traces a curve as chi_N runs
over its branch), and L-BFGS-B stops wherever a cilium sits on the wrong side of it: above a
wall, where each cilium's near field dominates, a reachable target stopped at 0.081 rms with 8
cilia of 144 off by more than 30 in chi_N (sign flips). After each solve a sweep
(:func:`~ciliary_carpet.design.model.sweep`) moves each cilium in turn to the best curvature of the near field's grid
(both signs) where that lowers the objective, and L-BFGS-B starts again from there, up to
``sweeps`` times while the model's objective falls (that case: 0.0047).

Error bar. ``residual_error`` bounds |residual_rms - its value on the resolved flow| by the
rms over the control points of the per-point bounds of the levels of detail (the residual of a
point moves by at most b_k / s for velocity targets, arcsin(b_k / |u_k|) for angles). Given a
``threshold`` (:func:`~ciliary_carpet.design.target_design.design_target` passes the target's
``residual``) the returned layout is checked once
more at a tolerance picked so that the bar is at most half the threshold (the bound scales about
like the tolerance; at worst the resolved sum, tol = 0); tested against tol = 0. The bound is
rigorous but, above a wall, loose by orders of magnitude (its Taylor constants are worst cases
over wall heights: measured differences of 1e-10 - 1e-6 under bars of 0.004 - 0.025,
benchmarks/results/bench_design_targets.md).

Control points inside a swept region are used as any other (``inside_swept = "use"``): the
regularised mean flow is bounded there and the near field resolves it; its quadrature error
there is :data:`INSIDE_ACCURACY`. ``"downweight"`` gives them the weight :data:`INSIDE_WEIGHT`
in the objective and in the rms residual, ``"drop"`` removes them.

Never worse. The local layout is the first iterate and is measured with the full model; the
design returns the best layout by the objective J evaluated on the full model's flow, over the
local layout and every pass, and says which (``Design.returned``). (By J, not by the angle
residual alone: a local layout that meets the angles with its cilia switched off is not
better.)

Layout. The design model is :mod:`ciliary_carpet.design.model`, the result
:mod:`ciliary_carpet.design.result`, what a carpet can make :mod:`ciliary_carpet.design.reachability`,
the fabrication tolerance :mod:`ciliary_carpet.design.tolerance`, the design for a resolved target
and its verdict :mod:`ciliary_carpet.design.target_design`. This module holds the solve,
:func:`design_layout`, in named steps: the settings checked (:func:`checked_settings`), the
control points inside swept regions weighed (:func:`weigh_control_points`), the problem and its
objective (:class:`DesignProblem`), the local layout (:func:`_local_layout`), the passes
(:func:`_passes`, each :func:`_solve_pass`), the final check (:func:`final_check`) and the result
(:func:`design_result`).

One concept over 500 lines: the planar design's solve, its objective and the steps that share it.
"""
from __future__ import annotations

import logging
import math
import time as _time
import warnings
from dataclasses import replace

import numpy as np
from scipy.optimize import minimize

from single_cilium.table import ThrustTable

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.carpet.coupling import DENSE_CILIA, CouplingResponse
from ciliary_carpet.design.moments import cycle_moments
from ciliary_carpet.design.control import reachable_check
from ciliary_carpet.design.errors import TargetError
from ciliary_carpet.design.model import (GOOD_ENOUGH, NEAR_RADIUS, DesignModel, NearField, angle_objective,
                                         angle_terms, floor_reference, solver_threads, sweep)
from ciliary_carpet.design.result import Design
from ciliary_carpet.design.target import DEFAULT_SPEED_FLOOR

logger = logging.getLogger(__name__)

__all__ = ["design_layout", "carpet_with", "check_control_points", "INSIDE_SWEPT", "INSIDE_WEIGHT",
           "INSIDE_ACCURACY", "GOOD_ENOUGH", "NEAR_CUTOFF_FRACTION"]

NEAR_CUTOFF_FRACTION = 0.25
"""A cilium is reported "near the cutoff" when its mean thrust is below this fraction of the
straight filament's (for chi_E = 200, eta = 1: |chi_N| above about 146 of the cutoff 162.77)."""

INSIDE_SWEPT = ("use", "downweight", "drop")
"""What the design does with control points inside a cilium's swept region (``[target]
inside_swept``): use them as any other, weight them :data:`INSIDE_WEIGHT`, or drop them."""
INSIDE_WEIGHT = 0.1
"""The weight of a control point inside a swept region with ``inside_swept = "downweight"``, in
the objective and in the rms residual (the others weigh 1)."""


INSIDE_ACCURACY = 5e-3
"""The accuracy of the model's mean flow at points inside a swept region (the table's 65 arc-length x
64 phase samples), relative to the rms flow there: its difference from sums 4x finer in arc
length and phase is 1.4e-3 - 1.8e-3 rms (at most 4e-3 of the largest flow; chi_N 0, 60, -120, free
and with a wall 0.5 L below), tested below this bound: an order of magnitude under the error bar
the design allows (half the threshold, 0.025), so no finer quadrature is needed there."""


def _unit(a: np.ndarray) -> np.ndarray:
    return np.column_stack([np.cos(a), np.sin(a)])


# ------------------------------------------------------------------------------ checks
def check_control_points(carpet: Carpet, X: np.ndarray, spacing: float | None = None) -> np.ndarray:
    """Raise :class:`TargetError` for control points outside the carpet (farther than two
    spacings + 1 L from every base point); return the indices (sorted) of those inside a cilium's
    swept region (the convex hull of its cycle samples, :meth:`Carpet.in_swept_region`).

    Points inside a swept region are not an error: with regularised Stokeslets the mean flow is
    bounded and well defined there, and the design resolves it exactly (:class:`~ciliary_carpet.design.model.NearField`).
    How accurate the model's mean flow is there (its quadrature over arc length and phase, the
    table's 65 x 64 samples, against 4 x finer sums) is measured in tests/test_design.py
    (:data:`INSIDE_ACCURACY`). ``spacing`` default: the median nearest-neighbour distance of
    the bases (1 for a single cilium). A standing carpet's control points (on a plane above its
    substrate) get the first check only."""
    from scipy.spatial import cKDTree

    tree = cKDTree(carpet.bases)
    if spacing is None:
        spacing = float(np.median(tree.query(carpet.bases, k=2)[0][:, 1])) if carpet.n > 1 else 1.0
    d, _ = tree.query(X)
    far = np.nonzero(d > 2.0 * spacing + 1.0)[0]
    if far.size:
        lst = "; ".join(f"#{k} at ({X[k, 0]:.4g}, {X[k, 1]:.4g}), {d[k]:.3g} L from the nearest base"
                        for k in far[:5])
        raise TargetError(f"{far.size} control point(s) lie outside the carpet (more than 2 spacings + 1 L = "
                          f"{2 * spacing + 1:.3g} L from every base point): {lst}")
    if carpet.geometry == "standing":  # its control points lie on a plane above the substrate, where the
        return np.zeros(0, np.int64)   # design chooses each beat plane's azimuth: no swept region is fixed
    rmax = float(carpet.radii.max()) if carpet.n else 0.0
    ctree = cKDTree(X)
    bad = set()
    for j, lst in enumerate(ctree.query_ball_point(carpet.centres, rmax)):
        if lst:
            inside = carpet.in_swept_region(X[lst], j)
            bad.update(int(lst[i]) for i in np.nonzero(inside)[0])
    return np.array(sorted(bad), dtype=np.int64)


def _with_chi(carpet: Carpet, chi: np.ndarray) -> Carpet:
    """The same carpet with other curvatures (no overlap warning: the bases did not move)."""
    if np.array_equal(chi, carpet.chi_N):
        return carpet
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return replace(carpet, chi_N=chi)


# ------------------------------------------------------------------------------ design
def design_layout(carpet: Carpet, control, *, angles=None, velocities=None, cilium_angles=None, clip: bool = False,
                  tol: float = 1e-3, check_tol: float | None = None, speed_floor: float = DEFAULT_SPEED_FLOOR,
                  floor_weight: float = 1.0, regularization: float = 1e-3, smoothness: float = 0.0,
                  outer: int = 2, ftol: float = 1e-6, maxiter: int = 500,
                  spacing: float | None = None, floor_radius: float | None = None,
                  robust_sigma: float = 0.0, robust_samples: int = 16, robust_seed: int = 12345,
                  near_radius: float = NEAR_RADIUS, sweeps: int = 3, threshold: float | None = None,
                  inside_swept: str = "use", sample_weights=None) -> Design:
    """Choose chi_N for the cilia of ``carpet`` (its bases, phases, field, wall and table are
    kept; its chi_N is the starting guess for velocity targets) so that the mean flow at
    ``control`` (P, 2) points along the deflection ``angles`` (P,) [rad, anticlockwise from the
    straight filaments' flow direction] or equals ``velocities`` (P, 2) (lab frame).

    With angle targets each cilium starts from the chi_N whose own thrust has the deflection
    ``cilium_angles`` (default: the angle asked at the control point nearest its force centre):
    the *local* layout. A request outside the table's reachable angles is a TargetError listing
    them, or with ``clip=True`` clipped to the range with a warning. See the module docstring
    for the objective (``speed_floor``, ``floor_weight``, ``regularization``, ``smoothness``)
    and the defect correction (``floor_radius``: the radius [L] of the floor's reference, default
    :data:`~ciliary_carpet.design.model.FLOOR_RADIUS_SPACINGS` x ``spacing``; at most ``outer`` passes, each at most ``maxiter`` L-BFGS-B
    iterations, stopped when an iteration lowers J by less than ``ftol`` times its value at the
    pass's start; no further pass once the design model's J at the pass's result is within 5%
    of the full model's, or a pass gained under 2%). ``near_radius``: the model's near field
    (:class:`~ciliary_carpet.design.model.NearField`; 0: carriers only); ``sweeps``: at most this many sweeps (:func:`~ciliary_carpet.design.model.sweep`)
    and restarts per pass; ``threshold``: the acceptance threshold on the rms residual, whose half
    the error bar is made to meet (module docstring; None: the checks' own bar);
    ``inside_swept``: "use", "downweight" or "drop" the control points inside a swept region;
    ``sample_weights`` (P,): relative weights of the control points in the objective and the rms
    residual (e.g. inverse variances of measured samples, :meth:`~ciliary_carpet.design.target.Target.sample_weights`;
    default all 1), multiplied by the swept-region weights. With a threshold, no further pass starts once the rms residual is below :data:`GOOD_ENOUGH`
    of it.
    The full-model checks use the tolerance ``check_tol`` (default
    max(tol, 3e-2): the levels of detail's bound is loose; on a 1000-cilium carpet the angles at
    the control points differ from tol = 1e-3 by at most 4e-5 rad, at a quarter of the cost of
    tol = 1e-2 and a sixteenth of tol = 1e-3; the residual carries the bound as
    ``residual_error``, 0.004 rad there).

    Returns the best layout by the objective on the full model's flow among the local layout
    and the passes (:attr:`Design.returned`); ``carpet_with(design, carpet)`` is its carpet."""
    clock = _time.perf_counter()
    X = checked_settings(control, angles, velocities, speed_floor, floor_weight, regularization, smoothness,
                          robust_sigma, robust_samples, inside_swept, threshold)
    X, angles, velocities, w_pts, inside_info, done = weigh_control_points(carpet, X, spacing, inside_swept,
                                                                            sample_weights, angles, velocities)
    check_tol = max(tol, 3e-2) if check_tol is None else float(check_tol)
    ob = DesignProblem(carpet, X, w_pts, angles, velocities, cilium_angles, clip, check_tol=check_tol,
                    speed_floor=speed_floor, floor_weight=floor_weight, regularization=regularization,
                    smoothness=smoothness, spacing=spacing, floor_radius=floor_radius, robust_sigma=float(robust_sigma),
                    robust_samples=robust_samples, robust_seed=robust_seed, near_radius=near_radius)
    best = _local_layout(ob)
    rms_loc, J_loc = best["rms"], best["J"]
    best, res = _passes(ob, best, outer=outer, ftol=ftol, maxiter=maxiter, sweeps=sweeps, threshold=threshold)
    chi, u, resid, rms, r_err = final_check(ob, best, threshold, check_tol)
    return design_result(ob, best, res, chi, u, resid, rms, r_err, rms_loc, J_loc, inside_info, done, threshold, clock)


def checked_settings(control, angles, velocities, speed_floor, floor_weight, regularization, smoothness,
                      robust_sigma, robust_samples, inside_swept, threshold) -> np.ndarray:
    """The control points (P, 2) of :func:`design_layout`, its settings checked: a TargetError for
    control points that are not finite (P, 2) points, a ValueError naming any setting out of range."""
    X = np.asarray(control, dtype=float)
    if X.ndim != 2 or X.shape[1] != 2 or X.shape[0] < 1:
        raise TargetError(f"control points must have shape (P, 2), got {X.shape}")
    if not np.all(np.isfinite(X)):
        raise TargetError("control points contain NaN or inf")
    if (angles is None) == (velocities is None):
        raise ValueError("give exactly one of angles (P,) or velocities (P, 2)")
    for name, v, lo in (("speed_floor", speed_floor, 0.0), ("floor_weight", floor_weight, 0.0),
                        ("regularization", regularization, 0.0), ("smoothness", smoothness, 0.0)):
        if not (math.isfinite(v) and v >= lo):
            raise ValueError(f"{name} must be a finite number >= {lo:g}, got {v!r}")
    if not speed_floor < 1:
        raise ValueError(f"speed_floor must be below 1 (a fraction of the straight carpet's speed), got {speed_floor!r}")
    rs = float(robust_sigma)
    if not (math.isfinite(rs) and rs >= 0):
        raise ValueError(f"robust_sigma must be a finite number >= 0 (a relative chi_N error), got {robust_sigma!r}")
    if rs > 0 and (isinstance(robust_samples, bool) or not isinstance(robust_samples, (int, np.integer))
                   or robust_samples < 1):
        raise ValueError(f"robust_samples must be an integer >= 1, got {robust_samples!r}")
    if inside_swept not in INSIDE_SWEPT:
        raise ValueError(f"inside_swept must be one of {', '.join(INSIDE_SWEPT)}, got {inside_swept!r}")
    if threshold is not None and not (math.isfinite(float(threshold)) and float(threshold) > 0):
        raise ValueError(f"threshold must be a finite number > 0, got {threshold!r}")
    return X


def weigh_control_points(carpet: Carpet, X: np.ndarray, spacing, inside_swept: str, sample_weights, angles,
                          velocities) -> tuple:
    """The control points inside a swept region used (the regularised mean flow is bounded and
    resolved there, see NearField), down-weighted or dropped as ``inside_swept`` asks, and the
    points' weights (``sample_weights`` scaled to mean 1, times the swept-region weights): returns
    (X, angles, velocities, weights, the summary's ``inside_swept`` record, what was done in words)."""
    inside = check_control_points(carpet, X, spacing)
    w_pts = np.ones(X.shape[0])
    if sample_weights is not None:
        sw = np.asarray(sample_weights, dtype=float)
        if sw.shape != (X.shape[0],) or not np.all(np.isfinite(sw)) or not np.all(sw > 0):
            raise ValueError(f"sample_weights must be {X.shape[0]} finite numbers > 0, got shape {sw.shape}")
        w_pts = sw / sw.mean()
    done = {"use": "used", "downweight": f"weighted {INSIDE_WEIGHT:g}", "drop": "dropped"}[inside_swept]
    inside_info = {"count": int(inside.size), "action": inside_swept, "indices": inside.tolist(),
                   "weight": {"use": 1.0, "downweight": INSIDE_WEIGHT, "drop": 0.0}[inside_swept]}
    if inside.size:
        logger.info("design: %d of %d control points lie inside a cilium's swept region: %s", inside.size,
                    X.shape[0], done)
    if inside.size and inside_swept == "drop" and inside.size == X.shape[0]:
        warnings.warn("every control point lies inside a cilium's swept region: dropping them would leave none, so "
                      "they are used (inside_swept = \"drop\" taken as \"use\")", UserWarning, stacklevel=3)
        inside_swept = "use"
        inside_info["action"], inside_info["weight"] = "use (all inside: none to drop)", 1.0
        done = "used (all inside: none to drop)"
    if inside.size and inside_swept == "drop":
        keep = np.ones(X.shape[0], bool)
        keep[inside] = False
        if angles is not None:
            angles = np.broadcast_to(np.asarray(angles, dtype=float), (X.shape[0],))[keep]
        else:
            velocities = np.asarray(velocities, dtype=float)
            if velocities.shape != X.shape:
                raise TargetError(f"velocities must have shape {X.shape}, got {velocities.shape}")
            velocities = velocities[keep]
        X, w_pts = X[keep], w_pts[keep]
    elif inside.size and inside_swept == "downweight":
        w_pts[inside] *= INSIDE_WEIGHT
    return X, angles, velocities, w_pts, inside_info, done


class DesignProblem:
    """The design problem of one :func:`design_layout` call: the targets at the control points
    (``kind`` "angle": unit directions; "velocity": velocities), the local layout ``chi0``, the
    floor's reference speeds, the regularisers' neighbours, the robust objective's samples, the
    near field, and the work counters; its methods are the residual, the full-model check, the
    data term and the objective J (module docstring).

    ``chi0`` (N,) replaces the local layout (the regularisers' centre and the first iterate) and
    ``scale`` the curvature scale chi_c of the regularisers: a program's states share both
    (:mod:`ciliary_carpet.design.program`). ``carpet_of`` (set after construction; None: the
    carpet with other curvatures) makes the full model's carpet of curvatures chi, its later
    calls warm-started from the last carpet it made (a coupled solve starts from its flows)."""

    def __init__(self, carpet: Carpet, X: np.ndarray, w_pts: np.ndarray, angles, velocities, cilium_angles,
                 clip: bool, *, check_tol: float, speed_floor: float, floor_weight: float, regularization: float,
                 smoothness: float, spacing, floor_radius, robust_sigma: float, robust_samples: int,
                 robust_seed: int, near_radius: float, chi0=None, scale: float | None = None):
        t: ThrustTable = carpet.table
        self.carpet, self.X, self.w_pts, self.check_tol = carpet, X, w_pts, check_tol
        self.speed_floor, self.floor_weight = speed_floor, floor_weight
        self.regularization, self.smoothness, self.rs = regularization, smoothness, robust_sigma
        self.wsum = float(np.sum(w_pts))
        self.uniform_w = bool(np.all(w_pts == 1.0))
        rot = carpet.rotation
        d0 = rot @ np.array([0.0, -1.0])  # the straight filaments' flow direction, lab frame
        base_angle = math.atan2(d0[1], d0[0])
        self.mom = mom = cycle_moments(t)
        self.b1 = b1 = mom.cutoff
        lo_a, hi_a = t.thrust_angle_range()
        self.clipped: list[int] = []
        self.P, self.N = P, N = X.shape[0], carpet.n
        if angles is not None:
            A = np.broadcast_to(np.asarray(angles, dtype=float), (P,)).copy()
            if not np.all(np.isfinite(A)):
                raise TargetError("target angles contain NaN or inf")
            self.kind = "angle"
            self.target = _unit(base_angle + A)
            from scipy.spatial import cKDTree

            want = A[cKDTree(X).query(carpet.centres)[1]] if cilium_angles is None else \
                np.broadcast_to(np.asarray(cilium_angles, dtype=float), (N,)).copy()
            want, bad = reachable_check(want, (lo_a, hi_a), clip, what="cilium", points=carpet.bases)
            self.clipped = np.nonzero(bad)[0].tolist()
            self.chi0 = np.asarray(t.chi_N_for_angle(want), dtype=float)
        else:
            U = np.asarray(velocities, dtype=float)
            if U.shape != X.shape:
                raise TargetError(f"velocities must have shape {X.shape}, got {U.shape}")
            if not np.all(np.isfinite(U)):
                raise TargetError("target velocities contain NaN or inf")
            self.kind = "velocity"
            self.target = U
            self.chi0 = np.clip(carpet.chi_N, -b1, b1)
        self.carpet_of, self._last = None, None  # a program's state: see design.program.StateProblem
        if chi0 is not None:  # a program's joint local layout (design.program)
            self.chi0 = np.broadcast_to(np.asarray(chi0, dtype=float), (N,)).copy()
        if scale is not None:  # a program's common curvature scale
            self.b1 = float(scale)
        self.scaleU = float(np.sum(w_pts[:, None] * self.target ** 2)) if self.kind == "velocity" else 1.0
        if self.kind == "velocity" and self.scaleU == 0:
            raise TargetError("target velocities are all zero")
        self.edges = edges = layout.neighbours(carpet.bases) if smoothness > 0 else np.zeros((0, 2), np.int64)
        self.counters = {"iterations": 0, "evaluations": 0, "checks": 0, "seconds_carpets": 0.0,
                         "seconds_checks": 0.0, "seconds_model": 0.0, "sweeps": 0, "swept_cilia": 0}
        # the reference speed of the floor: what the straight carpet makes at each control point
        self.sref = floor_reference(carpet, X, floor_radius, spacing, moments=mom)
        self.c_pts = w_pts / self.wsum
        self.floor_pts = speed_floor * self.sref
        self.nbrs = [[] for _ in range(N)]
        for e0, e1 in edges:
            self.nbrs[e0].append(e1)
            self.nbrs[e1].append(e0)
        # the fabrication-tolerance samples of the robust objective: chi_j (1 + sigma eps_sj)
        rs = robust_sigma
        self.mult = (1.0 + rs * np.random.default_rng(robust_seed).standard_normal((int(robust_samples), N))) \
            if rs > 0 else np.ones((1, N))
        # the exact mean flows of the cilia near the control points, tabulated in chi (NearField)
        self.near = near = NearField(carpet, X, near_radius, moments=mom) if near_radius > 0 else None
        self.counters["seconds_near"] = near.seconds if near is not None else 0.0
        self.counters["near_pairs"] = int(near.k.size) if near is not None else 0

    def residual(self, u):
        """(P,) the residual at each control point of the flow ``u`` (P, 2): the angle error [rad],
        or |u - U| over the rms target speed."""
        target = self.target
        if self.kind == "angle":
            return np.abs(np.angle((u[:, 0] + 1j * u[:, 1]) * np.conj(target[:, 0] + 1j * target[:, 1])))
        return np.linalg.norm(u - target, axis=1) / math.sqrt(self.scaleU / self.wsum)

    def wrms(self, r) -> float:
        """The (weighted) rms over the control points: sqrt(sum w_k r_k^2 / sum w_k)."""
        return float(np.sqrt(np.sum(self.w_pts * np.asarray(r) ** 2) / self.wsum))

    def check(self, chi, ctol=None, c=None):
        """(carpet, flow (P, 2), error bound (P,)): the full model's mean flow at the control points
        for curvatures ``chi`` (or the carpet ``c``), at the tolerance ``ctol`` (default the checks')."""
        counters = self.counters
        counters["checks"] += 1
        t0 = _time.perf_counter()
        if c is None:
            if self.carpet_of is None:
                c = _with_chi(self.carpet, chi)
            else:  # the full model's carpet made elsewhere, warm-started from the last one
                c = self.carpet_of(chi) if self._last is None else _with_chi(self._last, chi)
                self._last = c
        t1 = _time.perf_counter()
        s = c.evaluate(self.X, CycleMean(), tol=self.check_tol if ctol is None else ctol)
        counters["seconds_carpets"] += t1 - t0
        counters["seconds_checks"] += _time.perf_counter() - t1
        return c, s.velocity[:, :2], s.error_bound

    def data(self, u):
        """The data term of J and dJ/du at the flow ``u`` (P, 2)."""
        target, w_pts, scaleU = self.target, self.w_pts, self.scaleU
        if self.kind == "angle":
            return angle_objective(u, target, self.speed_floor * self.sref, self.floor_weight,
                                   None if self.uniform_w else w_pts)
        r = u - target
        return 0.5 * float(np.sum(w_pts[:, None] * r ** 2)) / scaleU, w_pts[:, None] * r / scaleU

    def terms(self, u_sub, ks):
        """The data term's per-point terms (their sum over every point is data(u)[0])."""
        if self.kind == "angle":
            return angle_terms(u_sub, self.target[ks], self.floor_pts[ks], self.floor_weight, self.c_pts[ks])
        return 0.5 * self.w_pts[ks] * np.sum((u_sub - self.target[ks]) ** 2, axis=-1) / self.scaleU

    def penalty(self, j, vals, chi):
        """The change of the regularisers when chi_j takes the values ``vals`` (others as in chi)."""
        chi0, b1, N, edges = self.chi0, self.b1, self.N, self.edges
        out = self.regularization * (((vals - chi0[j]) / b1) ** 2 - ((chi[j] - chi0[j]) / b1) ** 2) / N
        for i in self.nbrs[j]:
            out = out + self.smoothness * (((vals - chi[i]) / b1) ** 2 - ((chi[j] - chi[i]) / b1) ** 2) / len(edges)
        return out

    def expected(self, dmodel, shift_u, c, grad: bool):
        """The data term averaged over the samples (the nominal one without robust_sigma) of
        the flow dmodel.velocity(chi (1 + sigma eps)) + shift_u, and its chi gradient."""
        mult = self.mult
        J, g = 0.0, np.zeros(self.N)
        for m in mult:
            cm = c * m
            Jm, gu = self.data(dmodel.velocity(cm) + shift_u)
            J += Jm / mult.shape[0]
            if grad:
                g += dmodel.gradient(cm, gu) * m / mult.shape[0]
        return J, g

    def score(self, u, chi, c_full=None):
        """The design objective measured on the full model's flow ``u`` (what "best" means); the
        robust one: the sample average with the defect frozen at ``chi``."""
        chi0, b1, N, edges = self.chi0, self.b1, self.N, self.edges
        if self.rs > 0:
            dmc = DesignModel(self.carpet if c_full is None else c_full, self.X, chi, moments=self.mom, near=self.near)
            with solver_threads(3 * N * self.P):
                J = self.expected(dmc, u - dmc.velocity(chi), chi, False)[0]
        else:
            J = self.data(u)[0]
        return J + self.regularization * float(np.sum(((chi - chi0) / b1) ** 2)) / N + (
            self.smoothness * float(np.sum(((chi[edges[:, 0]] - chi[edges[:, 1]]) / b1) ** 2)) / len(edges)
            if edges.size else 0.0)

    def error_bar(self, bound, u):
        """A bound on |rms residual - its value on the resolved flow| from the levels of detail's
        per-point bounds b_k >= |u_k - u_k(resolved)|: the residual of point k moves by at most
        e_k = b_k / s (velocity targets, s the rms target speed) or arcsin(b_k / |u_k|) (angle
        targets; pi where b_k >= |u_k|), and an rms by at most the rms of the e_k (triangle
        inequality)."""
        if self.kind == "angle":
            nrm = np.linalg.norm(u, axis=1)
            e = np.where(bound < nrm, np.arcsin(np.minimum(bound / np.maximum(nrm, 1e-300), 1.0)), math.pi)
        else:
            e = bound / math.sqrt(self.scaleU / self.wsum)
        return self.wrms(e)


def _local_layout(ob: DesignProblem) -> dict:
    """The local layout, the first iterate, measured with the full model: the first "best"
    (rms residual, objective J, curvatures, flow, residuals, label, carpet, solver result, bound)."""
    c_loc, u_loc, e_loc = ob.check(ob.chi0)
    r_loc = ob.residual(u_loc)
    rms_loc = ob.wrms(r_loc)
    J_loc = ob.score(u_loc, ob.chi0, c_loc)
    return {"rms": rms_loc, "J": J_loc, "chi": ob.chi0.copy(), "u": u_loc, "resid": r_loc,
            "label": "local", "carpet": c_loc, "res": None, "bound": e_loc}


def _solve_pass(ob: DesignProblem, p: int, chi: np.ndarray, u_prev: np.ndarray, c_prev: Carpet, *, ftol: float,
                maxiter: int, sweeps: int) -> tuple:
    """Pass ``p``: the design model at ``chi`` corrected by the full model's defect there
    (``u_prev`` on ``c_prev``), minimised by L-BFGS-B in x = chi / chi_c, then swept out of
    local minima (:func:`~ciliary_carpet.design.model.sweep`) while that lowers the model's
    objective; returns (the solver's result, the objective's scale J at the pass's start)."""
    carpet, X, b1, N, P, counters = ob.carpet, ob.X, ob.b1, ob.N, ob.P, ob.counters
    chi0, edges, regularization, smoothness, near = ob.chi0, ob.edges, ob.regularization, ob.smoothness, ob.near
    # a coupled carpet: the model's forces answer through the flow (the response at this pass's
    # coupled state), so its gradient includes the coupling
    response = CouplingResponse(c_prev) if c_prev.coupled is not None and c_prev.n <= DENSE_CILIA else None
    dm = DesignModel(carpet, X, chi, moments=ob.mom, near=near, response=response)
    shift = u_prev - dm.velocity(chi)  # defect: full model minus design model at this pass's start

    J_scale = 1.0

    def fun(x):
        counters["evaluations"] += 1
        c = x * b1
        J, g = ob.expected(dm, shift, c, True)
        dc = (c - chi0) / b1
        J += regularization * float(np.sum(dc ** 2)) / N
        g = g + 2.0 * regularization * dc / (b1 * N)
        if edges.size:
            de = (c[edges[:, 0]] - c[edges[:, 1]]) / b1
            J += smoothness * float(np.sum(de ** 2)) / len(edges)
            ge = 2.0 * smoothness * de / (b1 * len(edges))
            g = g + np.bincount(edges[:, 0], ge, N) - np.bincount(edges[:, 1], ge, N)
        return J / J_scale, g * (b1 / J_scale)

    t_model = _time.perf_counter()
    with solver_threads(3 * N * P):
        # J in units of its value at the pass's start: ftol is then relative to it
        J_scale = max(fun(chi / b1)[0], 1e-300)
        res = minimize(fun, chi / b1, jac=True, method="L-BFGS-B", bounds=[(-1.0, 1.0)] * N,
                       options={"gtol": 1e-10, "ftol": ftol, "maxiter": maxiter})
        counters["iterations"] += int(res.nit)
        # out of a local minimum: a sweep over the cilia (each to the best curvature of the
        # grid, both signs), then L-BFGS-B again, while that lowers the model's objective
        for _ in range(int(sweeps) if (near is not None and ob.rs == 0) else 0):
            chi_k = np.clip(res.x * b1, -b1, b1)
            chi_s, moved = sweep(dm, near, chi_k, dm.velocity(chi_k) + shift, ob.terms, ob.penalty)
            counters["sweeps"] += 1
            if moved == 0 or not fun(chi_s / b1)[0] < float(res.fun) * (1.0 - 1e-6):
                break
            counters["swept_cilia"] += moved
            res2 = minimize(fun, chi_s / b1, jac=True, method="L-BFGS-B", bounds=[(-1.0, 1.0)] * N,
                            options={"gtol": 1e-10, "ftol": ftol, "maxiter": maxiter})
            counters["iterations"] += int(res2.nit)
            logger.info("design pass %d: sweep moved %d cilia; model objective %.4g -> %.4g of its start", p,
                        moved, float(res.fun), float(res2.fun))
            if not res2.fun < res.fun:
                break
            res = res2
    counters["seconds_model"] += _time.perf_counter() - t_model
    return res, J_scale


def _passes(ob: DesignProblem, best: dict, *, outer: int, ftol: float, maxiter: int, sweeps: int, threshold) -> tuple:
    """At most ``outer`` passes (:func:`_solve_pass`), each measured with the full model and kept
    when its objective J on the full model's flow beats the best so far; stopped once the design
    model agrees with the full model within 5%, a pass gained under 2%, or (given a
    ``threshold``) the rms residual is below GOOD_ENOUGH of it. Returns (the best, the last
    solver result)."""
    u_prev, c_prev, chi = best["u"], best["carpet"], ob.chi0.copy()
    res = None
    for p in range(1, max(1, outer) + 1):
        res, J_scale = _solve_pass(ob, p, chi, u_prev, c_prev, ftol=ftol, maxiter=maxiter, sweeps=sweeps)
        chi = np.clip(res.x * ob.b1, -ob.b1, ob.b1)
        c_full, u_full, e_full = ob.check(chi)
        resid = ob.residual(u_full)
        rms = ob.wrms(resid)
        logger.info("design pass %d: full-model rms residual %.4g (model objective %.4g of its start), "
                    "%d iterations", p, rms, float(res.fun), res.nit)
        J_full = ob.score(u_full, chi, c_full)
        J_model = float(res.fun) * J_scale
        logger.info("design pass %d: objective %.4g on the full model, %.4g on the design model", p, J_full, J_model)
        gain = (best["J"] - J_full) / max(best["J"], 1e-300)
        if gain > 1e-12:  # better by more than rounding (a pass that did not move ties with the layout before)
            best = {"rms": rms, "J": J_full, "chi": chi.copy(), "u": u_full, "resid": resid, "label": f"pass {p}",
                    "carpet": c_full, "res": res, "bound": e_full}
        u_prev, c_prev = u_full, c_full
        # settled: the design model agrees with the full model at this layout (so the next pass
        # would minimise nearly the same objective), or the last pass gained under 2%, or (given
        # a threshold) the residual is below GOOD_ENOUGH of it
        if abs(J_full - J_model) <= 0.05 * J_full or (p > 1 and gain < 0.02):
            break
        if threshold is not None and best["rms"] <= GOOD_ENOUGH * float(threshold):
            logger.info("design pass %d: rms residual %.3g is below %g of the threshold %g: no further pass", p,
                        best["rms"], GOOD_ENOUGH, float(threshold))
            break
    return best, res


def final_check(ob: DesignProblem, best: dict, threshold, check_tol: float) -> tuple:
    """The returned layout's (chi, flow, residuals, rms residual, error bar): with a
    ``threshold``, checked once more at a tolerance picked so that the error bar is at most half
    of it (the bound scales about like the tolerance; the resolved sum, tol = 0, has none). The
    tolerance used is the counters' ``final_tol``."""
    chi, u, resid, rms = best["chi"], best["u"], best["resid"], best["rms"]
    r_err = ob.error_bar(best["bound"], u)
    tol_final = check_tol
    if threshold is not None:
        goal = 0.5 * float(threshold)
        for attempt in range(4):
            if r_err <= goal:
                break
            tol_final = 0.0 if attempt == 3 else tol_final * max(0.02, min(0.5, 0.5 * goal / max(r_err, 1e-300)))
            _, u, bound = ob.check(chi, tol_final, best["carpet"])
            resid = ob.residual(u)
            rms = ob.wrms(resid)
            r_err = ob.error_bar(bound, u)
            logger.info("design: final check at tol %.3g: rms residual %.4g +- %.2g", tol_final, rms, r_err)
    ob.counters["final_tol"] = tol_final
    return chi, u, resid, rms, r_err


def design_result(ob: DesignProblem, best: dict, res, chi, u, resid, rms: float, r_err: float, rms_loc: float, J_loc: float,
            inside_info: dict, done: str, threshold, clock: float) -> Design:
    """The :class:`~ciliary_carpet.design.result.Design` of the returned layout, with its summary
    line (the residual and its bar, the local layout's, which layout was returned, the cilia
    near the flutter cutoff, how the solver ended) and the work counters."""
    kind, mom, counters = ob.kind, ob.mom, ob.counters
    thrust = mom.thrust_norm(chi)
    near_cut = tuple(np.nonzero(thrust < NEAR_CUTOFF_FRACTION * mom.thrust0)[0].tolist())
    ratio = np.sum(u * ob.target, axis=1) / ob.sref if kind == "angle" else None
    last = best["res"] if best["res"] is not None else res
    status = "success" if (last is not None and last.success) else "inaccurate"
    unit = " rad" if kind == "angle" else " (relative)"
    robust = (f"designed for the expected objective under a relative chi_N error {ob.rs:g} "
              f"({ob.mult.shape[0]} samples); ") if ob.rs > 0 else ""
    ins = ""
    if inside_info["count"]:
        ins = f"{inside_info['count']} control point(s) inside a cilium's swept region {done}; "
    message = (f"{kind} target at {ob.P} control points: {ins}{robust}rms residual {rms:.3g}{unit} (+- {r_err:.2g}), "
               f"worst "
               f"{float(resid.max()):.3g}; local layout {rms_loc:.3g}; returned the {best['label']} layout; "
               f"{len(near_cut)} of {ob.N} cilia near the flutter cutoff; L-BFGS-B "
               f"{'converged' if status == 'success' else 'stopped: ' + str(getattr(last, 'message', ''))}")
    logger.info("design: %s", message)
    counters["seconds"] = _time.perf_counter() - clock
    return Design(chi_N=chi, control=ob.X, target=ob.target, achieved=u, residual=resid, residual_rms=rms, kind=kind,
                  residual_error=r_err, speed_ratio=ratio, local_rms=rms_loc, objective=best["J"],
                  local_objective=J_loc, returned=best["label"],
                  near_cutoff=near_cut, clipped=tuple(ob.clipped), status=status, message=message, work=counters,
                  carpet=best["carpet"], threshold=None if threshold is None else float(threshold),
                  inside_swept=inside_info, weights=None if ob.uniform_w else ob.w_pts)


def carpet_with(design: Design, carpet: Carpet) -> Carpet:
    """``carpet`` with the designed chi_N (the design's own carpet when it has one)."""
    if design.carpet is not None and np.array_equal(design.carpet.bases, carpet.bases):
        return design.carpet
    return _with_chi(carpet, design.chi_N)
