"""Inverse design: a signed chi_N for every cilium so that the carpet's mean flow matches a target.

Design model
------------
The design works on the steady (cycle-averaged) flow at control points x_k. Each cilium j is
represented by the carpet's dipole carriers (:func:`~ciliary_carpet.carpet.carriers.dipole_forces`):
three point forces at c_j + delta_j e_m (e_m at 0, 120, 240 degrees,
:data:`~ciliary_carpet.carpet.carriers.DESIGN_DIPOLE`; delta_j = a_j / 2) that carry the
cycle-mean force Fbar(chi_j) and its first moment Dbar(chi_j) about the force centre c_j,

    f_jm(chi) = Fbar(chi) / 3 + 2 / (3 delta_j) Dbar(chi)^T e_m,
    u_k(chi) = 1/(8 pi mu) sum_{j, m} G(x_k - c_j - delta_j e_m) f_jm(chi_j),

with Blake's tensor for G when the carpet has a wall. Fbar, Dbar, the centre offset and the
swept radius are functions of chi_N alone (in the field frame);
:class:`~ciliary_carpet.carpet.cycles.CycleMoments` samples them once from the table's cycle
data (the carpet's own moment code) and interpolates
them with cubic splines, whose chi_N derivatives give the exact gradient. The geometry (c_j,
delta_j) is frozen during one inner solve and refreshed between passes.

Near field. The carriers stand for a cilium only a few swept radii away; for every pair of a
control point and a cilium whose base lies within :data:`NEAR_RADIUS` (2 L) of it the model
uses the pair's exact resolved mean flow instead, tabulated in chi_N (:class:`NearField`):

    u_k(chi) = carriers(chi) + sum_{j near k} [v_kj(chi_j) - carriers_kj(chi_j)].

Without it the carriers were 44 % rms off the full model at 300 scattered points over 144 cilia
above a wall 0.5 L below (5 % in free space), almost all of it within a swept radius of a
cilium, and the defect correction below, a constant shift, could not follow that as chi moved;
with it 0.15 % (0.05 % free). This is what makes points inside swept regions usable
(``inside_swept``) and designs above a wall reach their threshold.

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
  model, :func:`floor_reference`):

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
(:func:`_sweep`) moves each cilium in turn to the best curvature of the near field's grid
(both signs) where that lowers the objective, and L-BFGS-B starts again from there, up to
``sweeps`` times while the model's objective falls (that case: 0.0047).

Error bar. ``residual_error`` bounds |residual_rms - its value on the resolved flow| by the
rms over the control points of the per-point bounds of the levels of detail (the residual of a
point moves by at most b_k / s for velocity targets, arcsin(b_k / |u_k|) for angles). Given a
``threshold`` (:func:`design` passes ``[target] residual``) the returned layout is checked once
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
"""
from __future__ import annotations

import contextlib
import logging
import math
import time as _time
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.optimize import minimize

from single_cilium.table import ThrustTable

from ciliary_carpet.scenes.assembly import assemble
from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.carpet.carriers import DESIGN_DIPOLE, dipole_forces
from ciliary_carpet.carpet.cycles import CycleMoments, cycle_moments
from ciliary_carpet.stokes import Treecode, Wall, make_kernel, stokeslet_velocity, stokeslet_velocity_ranges
from ciliary_carpet.design.target import Frame, TargetError, _as_in_spec, control_points, reachable_check

logger = logging.getLogger(__name__)

__all__ = ["NearField", "NEAR_RADIUS", "NEAR_CHI_SAMPLES", "INSIDE_SWEPT", "INSIDE_WEIGHT", "SWEEP_RADIUS",
           "design", "design_layout", "carpet_with", "Design", "DesignError", "DesignModel",
           "ToleranceStudy", "tolerance_study",
           "angle_objective", "floor_reference", "FLOOR_RADIUS_SPACINGS",
           "Reachability", "reachability", "WIDTH_GRID", "check_control_points", "NEAR_CUTOFF_FRACTION",
           "TREE_PAIRS"]

NEAR_CUTOFF_FRACTION = 0.25
"""A cilium is reported "near the cutoff" when its mean thrust is below this fraction of the
straight filament's (for chi_E = 200, eta = 1: |chi_N| above about 146 of the cutoff 162.77)."""
FLOOR_RADIUS_SPACINGS = 5.0
"""The speed floor's reference is the flow of the straight cilia within this many spacings of
the control point (``floor_radius`` of :func:`design_layout`; see the module docstring)."""
SERIAL_PAIRS = 200_000
"""Kernel sums with fewer (target, source) pairs than this run on one numba thread in the design."""
TREE_PAIRS = 3e7
"""The design model sums through a :class:`~ciliary_carpet.stokes.treecode.Treecode` (opening angle
0.3: velocity error below 2e-4 relative, 1.5e-4 rad in angle; tests/test_treecode.py) from this
many control-point x carrier pairs on (about 3,000 cilia); below it directly (measured on 2
cores: equal cost at 1.8e7 pairs, the treecode 2x faster at 7e7 and 5-7x at 3e8)."""


INSIDE_SWEPT = ("use", "downweight", "drop")
"""What the design does with control points inside a cilium's swept region (``[target]
inside_swept``): use them as any other, weight them :data:`INSIDE_WEIGHT`, or drop them."""
INSIDE_WEIGHT = 0.1
"""The weight of a control point inside a swept region with ``inside_swept = "downweight"``, in
the objective and in the rms residual (the others weigh 1)."""


GOOD_ENOUGH = 0.2
"""Given a threshold, :func:`design_layout` starts no further pass once the full-model rms
residual is at most this fraction of it: the design's job is the threshold, and what a further
pass gains is then below the error bar the design may state (half the threshold). Measured on
900 cilia above a wall 0.5 L below (scattered points): a second pass took 10 of 14 s to go from
0.0061 to 0.0042 against the threshold 0.05."""
INSIDE_ACCURACY = 5e-3
"""The accuracy of the model's mean flow at points inside a swept region (the table's 65 arc-length x
64 phase samples), relative to the rms flow there: its difference from sums 4x finer in arc
length and phase is 1.4e-3 - 1.8e-3 rms (at most 4e-3 of the largest flow; chi_N 0, 60, -120, free
and with a wall 0.5 L below), tested below this bound: an order of magnitude under the error bar
the design allows (half the threshold, 0.025), so no finer quadrature is needed there."""


class DesignError(ValueError):
    """A target the cilia cannot make (listed in the message), or a design that did not converge."""


# ------------------------------------------------------------------------------ result
@dataclass(frozen=True)
class Design:
    """A designed curvature layout and how well its mean flow meets the target.

    chi_N (N,): signed natural curvatures; control (P, 2): control points; target (P, 2): target
    flow direction (unit vectors, angle targets) or velocity; achieved (P, 2): the carpet's mean
    flow there (measured with the full flow model); residual (P,): per control point, the angle
    error in radians (angle targets) or |u - U| / rms|U| (velocity targets); residual_rms: the
    root mean square of those; residual_error: bound on the error of ``residual`` from the flow
    model's tolerance (the full model's error bound divided by |u|, rad; relative for velocity
    targets); kind: "angle" or "velocity"; speed_ratio (P,): speed along the target direction
    over the floor's reference speed (:func:`floor_reference`; angle targets; NaN for velocity targets); local_rms: the
    rms residual of the local (starting) layout; returned: which iterate is returned ("local"
    or "pass k"); objective, local_objective: the design objective J (module docstring) on the
    full model's flow of the returned and of the local layout (objective <= local_objective:
    the never-worse guarantee); near_cutoff: indices of cilia whose thrust is below
    :data:`NEAR_CUTOFF_FRACTION` of the straight filament's; clipped: indices of cilia whose
    request was clipped to the reachable range; status: ``"success"`` (L-BFGS-B converged on the
    design model) or ``"inaccurate"`` (it stopped early: the message says why), the words of the
    other results of the toolkit (:class:`single_cilium.cycle.LimitCycle`); message; work:
    iterations, evaluations, full-model checks, seconds (wall clock; of which seconds_carpets
    building the carpets of the checked layouts, seconds_checks their full-model evaluations,
    seconds_model the L-BFGS-B solves on the design model); tolerance: the fabrication-tolerance
    study (``None`` unless asked, see :func:`tolerance_study`); reachability: what the carpet
    can make (:func:`reachability`; angle targets of :func:`design`); carpet: the carpet with the
    returned layout, on which the residual was measured; threshold: the target's acceptance
    threshold on residual_rms (``[target] residual``; given to :func:`design_layout`, which then
    makes residual_error at most half of it by a final full-model check at a tolerance chosen
    for it, ``work["final_tol"]``); inside_swept: the control points that lie inside a cilium's
    swept region (``count``, ``indices`` into the control points as given, ``action`` "use",
    "downweight" or "drop", ``weight``); weights (P,): the control points' weights in the
    objective and in residual_rms (None: all 1; "downweight" gives the inside points
    :data:`INSIDE_WEIGHT`), residual_rms = sqrt(sum w_k r_k^2 / sum w_k)."""

    chi_N: np.ndarray
    control: np.ndarray
    target: np.ndarray
    achieved: np.ndarray
    residual: np.ndarray
    residual_rms: float
    kind: str
    residual_error: float = 0.0
    speed_ratio: np.ndarray | None = None
    local_rms: float = float("nan")
    objective: float = float("nan")
    local_objective: float = float("nan")
    returned: str = "local"
    near_cutoff: tuple = ()
    clipped: tuple = ()
    status: str = "success"
    message: str = ""
    work: dict = field(default_factory=dict)
    tolerance: dict | None = None
    reachability: dict | None = None
    carpet: Carpet | None = field(default=None, repr=False, compare=False)
    threshold: float | None = None
    inside_swept: dict | None = None
    weights: np.ndarray | None = None

    def worst(self, k: int = 5) -> list[tuple[int, float, float, float]]:
        """The ``k`` worst control points: (index, x, y, residual)."""
        idx = np.argsort(self.residual)[::-1][:k]
        return [(int(i), float(self.control[i, 0]), float(self.control[i, 1]), float(self.residual[i])) for i in idx]

    def summary(self) -> dict:
        """The figures of the design as plain JSON types."""
        out = {"kind": self.kind, "residual_rms": self.residual_rms, "residual_max": float(self.residual.max()),
               "residual_error": self.residual_error,
               "residual_unit": "rad" if self.kind == "angle" else "relative",
               "local_rms": self.local_rms, "objective": self.objective,
               "local_objective": self.local_objective, "returned": self.returned,
               "control_points": int(self.control.shape[0]), "cilia_near_cutoff": len(self.near_cutoff),
               "clipped": list(self.clipped), "status": self.status, "message": self.message,
               "worst": [{"index": i, "x": x, "y": y, "residual": r} for i, x, y, r in self.worst()],
               "work": self.work}
        if self.speed_ratio is not None and self.kind == "angle":
            out["speed_ratio_min"] = float(np.min(self.speed_ratio))
        if self.tolerance is not None:
            out["tolerance"] = self.tolerance
        if self.reachability is not None:
            out["reachability"] = self.reachability
        if self.threshold is not None:
            out["residual_threshold"] = self.threshold
            out["met"] = bool(self.residual_rms <= self.threshold)
            out["residual_error_ok"] = bool(self.residual_error <= 0.5 * self.threshold)
        if "final_tol" in self.work:
            out["residual_error_tol"] = self.work["final_tol"]
        if self.inside_swept is not None:
            out["inside_swept"] = {"count": self.inside_swept["count"], "action": self.inside_swept["action"],
                                   "weight": self.inside_swept["weight"],
                                   "indices": list(self.inside_swept["indices"][:20])}
        return out

    def to_dataset(self, carpet: Carpet):
        """The layout as an xarray Dataset (dims cilium, control; CF attributes)."""
        import xarray as xr

        th = carpet.table.scalar("thrust_angle", self.chi_N)
        near = np.zeros(carpet.n, np.int8)
        near[list(self.near_cutoff)] = 1
        ds = xr.Dataset(
            {"x": ("cilium", carpet.bases[:, 0], {"long_name": "base point x", "units": "L"}),
             "y": ("cilium", carpet.bases[:, 1], {"long_name": "base point y", "units": "L"}),
             "chi_N": ("cilium", self.chi_N, {"long_name": "natural curvature chi_N = L kappa_N", "units": "1"}),
             "thrust_angle": ("cilium", th, {"long_name": "deflection of the mean thrust from the straight "
                                             "filament's (anticlockwise)", "units": "rad"}),
             "near_cutoff": ("cilium", near, {"long_name": "thrust below the near-cutoff fraction", "units": "1"}),
             "phase": ("cilium", carpet.phases, {"long_name": "beat phase at t = 0", "units": "1"}),
             "control_x": ("control", self.control[:, 0], {"long_name": "control point x", "units": "L"}),
             "control_y": ("control", self.control[:, 1], {"long_name": "control point y", "units": "L"}),
             "target_u": ("control", self.target[:, 0], {"long_name": "target flow x component", "units": "1"}),
             "target_v": ("control", self.target[:, 1], {"long_name": "target flow y component", "units": "1"}),
             "u": ("control", self.achieved[:, 0], {"long_name": "designed mean flow x", "units": "L/tau"}),
             "v": ("control", self.achieved[:, 1], {"long_name": "designed mean flow y", "units": "L/tau"}),
             "residual": ("control", self.residual, {"long_name": "residual per control point",
                                                     "units": "rad" if self.kind == "angle" else "1"})},
            attrs={"chi_E": carpet.table.chi_E, "eta": carpet.table.eta, "direction": carpet.direction,
                   "target_kind": self.kind, "residual_rms": self.residual_rms,
                   "residual_error": self.residual_error, "local_rms": self.local_rms, "returned": self.returned,
                   "status": self.status, "message": self.message,
                   "clipped": np.asarray(self.clipped, dtype=np.int64)})
        if self.speed_ratio is not None:
            ds["speed_ratio"] = ("control", self.speed_ratio, {"long_name": "speed along the target over the "
                                                               "local layout's", "units": "1"})
        return ds


def _unit(a: np.ndarray) -> np.ndarray:
    return np.column_stack([np.cos(a), np.sin(a)])


# ------------------------------------------------------------------------------ checks
def check_control_points(carpet: Carpet, X: np.ndarray, spacing: float | None = None) -> np.ndarray:
    """Raise :class:`TargetError` for control points outside the carpet (farther than two
    spacings + 1 L from every base point); return the indices (sorted) of those inside a cilium's
    swept region (the convex hull of its cycle samples, :meth:`Carpet.in_swept_region`).

    Points inside a swept region are not an error: with regularised Stokeslets the mean flow is
    bounded and well defined there, and the design resolves it exactly (:class:`NearField`).
    How accurate the model's mean flow is there (its quadrature over arc length and phase, the
    table's 65 x 64 samples, against 4 x finer sums) is measured in tests/test_design.py
    (:data:`INSIDE_ACCURACY`). ``spacing`` default: the median nearest-neighbour distance of
    the bases (1 for a single cilium)."""
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


@contextlib.contextmanager
def _threads(pairs: int):
    """One BLAS thread for L-BFGS-B (its vectors are tiny: threads cost more than they save,
    the more so on a loaded machine), and one numba thread for the kernel sums when a sum has
    fewer than :data:`SERIAL_PAIRS` pairs (measured in benchmarks/bench_design.py)."""
    import numba
    from threadpoolctl import threadpool_limits

    n0 = numba.get_num_threads()
    with threadpool_limits(limits=1, user_api="blas"):
        if pairs < SERIAL_PAIRS:
            numba.set_num_threads(1)
        try:
            yield
        finally:
            numba.set_num_threads(n0)


def _edges(bases: np.ndarray) -> np.ndarray:
    """Neighbour pairs (E, 2): Delaunay edges of the base points (a row: consecutive points)."""
    n = bases.shape[0]
    if n < 2:
        return np.zeros((0, 2), np.int64)
    try:
        from scipy.spatial import Delaunay

        tri = Delaunay(bases).simplices
        e = np.vstack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [0, 2]]])
    except Exception:  # collinear bases: order along the line
        o = np.argsort(bases @ (bases[-1] - bases[0]))
        e = np.column_stack([o[:-1], o[1:]])
    e = np.sort(e, axis=1)
    return np.unique(e, axis=0)


# ------------------------------------------------------------------------------ design model
def _carriers(moments: CycleMoments, rot: np.ndarray, delta, chi, nu: int = 0) -> np.ndarray:
    """(N, 3, 2) carrier forces f_jm (lab frame; module docstring) of cilia at ``chi`` (N,) with
    carrier radii ``delta`` (N,), or their chi derivatives (nu = 1)."""
    m = moments(np.asarray(chi, dtype=float), nu)
    F = m["F"] @ rot.T
    D = rot @ m["D"] @ rot.T
    return dipole_forces(F, D, np.asarray(delta, dtype=float), DESIGN_DIPOLE)


NEAR_RADIUS = 2.0
"""The design model's near field (:class:`NearField`): the exact mean flow of every cilium whose
base lies within this distance [L] of a control point (the swept region of any curvature lies
within 1 L of the base; beyond 2 L the dipole carriers are accurate: see :class:`NearField`)."""
NEAR_CHI_SAMPLES = 65
"""Curvatures at which :class:`NearField` samples each near pair's mean flow (uniform on
[-chi_c, chi_c], interpolated by a cubic spline; see :class:`NearField` for its error)."""


class NearField:
    """The exact cycle-mean flow of the cilia near each control point, as smooth functions of chi_N.

    The dipole carriers of :class:`DesignModel` stand for a cilium only where their Taylor
    expansion holds, a few swept radii away; at a control point close to a cilium, and above all
    inside its swept region, they are wrong by as much as the flow itself (144 cilia, spacing
    2.5, a wall 0.5 L below, 300 scattered points: the carriers' flow is 44 % rms off the full
    model's, 5 % in free space, almost all of it from the points within one swept radius of a
    cilium). Above a wall, whose image system screens each cilium's far field (a force parallel
    to the wall makes a flow that decays like h^2 / R^3 in the plane), that near field is most
    of the flow, and the defect correction -- a constant shift -- cannot follow it as chi
    changes: this is what held designs above a wall at 0.15-0.2 rms.

    The mean flow of one cilium at a point depends only on its curvature and on the point's
    position relative to its base (the cycle average does not see the cilium's phase, and the
    wall is invariant under translations in the plane):

        v_kj(chi) = 1/(8 pi mu) 1/n_p sum_p sum_s w_s G(x_k - b_j, r(s, p; chi)) f(s, p; chi),

    the resolved mean flow of :meth:`Carpet.evaluate` (:class:`CycleMean`; the table's phase samples, Simpson
    weights w_s, the carpet's own kernel: regularised, with the wall when there is one). For
    every near pair (k, j), |x_k - b_j| <= ``radius`` (:data:`NEAR_RADIUS`), it is sampled at
    ``n_chi`` (:data:`NEAR_CHI_SAMPLES`) uniform curvatures on [-chi_c, chi_c] -- one
    Stokeslet sum per sample, from the sources of one cilium at that curvature to the relative
    positions of every pair -- and interpolated by a cubic spline (its derivative gives the
    exact gradient of the interpolant). The design model then adds, per near pair,
    v_kj(chi_j) minus the pair's carrier flow (:meth:`DesignModel.velocity`): the carriers stay
    in the sums for the far pairs only.

    Cost: n_distinct x n_chi x n_phase x n_s kernel evaluations once per design (4.9e8 for 900
    cilia at 900 scattered points, spacing 2.5: 0.6-1.2 s on the shared 2-core machine).
    Interpolation error of the spline against the resolved flow computed directly between the
    samples (tests/test_design.py): 1.6e-3 of the pairs' largest flow for |chi_N| <= 120, up to
    1.1e-2 within 20 of the cutoff, where the cycle changes fastest and the thrust vanishes; what
    is left is in the defect correction (the full-model checks).

    Pairs with the same relative position (to 1e-9 L) share one sampled flow: on a lattice with
    control points at the cell centres there are only a few distinct ones, whatever the carpet's
    size (4 on a square lattice), so the near field costs next to nothing there.

    Attributes: ``k`` (n_pairs,) control point and ``j`` (n_pairs,) cilium of each pair, ``inv``
    (n_pairs,) its distinct relative position, ``grid`` (n_chi,) the sampled curvatures, ``vals``
    (n_chi, n_distinct, 2) the sampled flows, ``coef`` (4, n_chi - 1, n_distinct, 2) the spline's
    piecewise cubic coefficients, ``key`` (n_pairs,) k N + j (sorted), ``seconds`` the time to
    build it."""

    def __init__(self, carpet: Carpet, control, radius: float = NEAR_RADIUS, n_chi: int = NEAR_CHI_SAMPLES,
                 moments: CycleMoments | None = None):
        from scipy.spatial import cKDTree

        clock = _time.perf_counter()
        X = np.asarray(control, dtype=float)
        self.P, self.N = X.shape[0], carpet.n
        mom = moments if moments is not None else cycle_moments(carpet.table)
        lists = cKDTree(carpet.bases).query_ball_point(X, float(radius))
        cnt = np.array([len(x) for x in lists], np.int64)
        self.k = np.repeat(np.arange(self.P), cnt)
        self.j = np.concatenate([np.asarray(x, np.int64) for x in lists]) if cnt.sum() else np.zeros(0, np.int64)
        o = np.lexsort((self.j, self.k))  # by point, then cilium: ``key`` sorted
        self.k, self.j = self.k[o], self.j[o]
        cut = mom.cutoff
        self.grid = np.linspace(-cut, cut, int(n_chi))
        # the pairs' relative positions, each distinct one sampled once (on a lattice with cell-centre
        # control points there are a handful: 4 on a square lattice, however large the carpet)
        rel2 = X[self.k] - carpet.bases[self.j]
        _, first, self.inv = np.unique(np.round(rel2 * 1e9).astype(np.int64), axis=0, return_index=True,
                                       return_inverse=True)
        self.inv = self.inv.ravel()
        npair = first.size
        vals = np.zeros((self.grid.size, npair, 2))
        if npair:
            rel = np.column_stack([rel2[first], np.zeros(npair)])
            # one cilium per sampled curvature, far apart (no overlap), the carpet's field, kernel and table
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                ref = Carpet(np.column_stack([10.0 * np.arange(self.grid.size), np.zeros(self.grid.size)]),
                             self.grid, carpet.table, None, carpet.direction, carpet.mu, carpet.wall,
                             backend=carpet.backend, blob=carpet.blob)
            c = ref.cycles
            wgt = c.weights / c.n_phase
            on = np.nonzero(c.flutter)[0]  # a still filament makes no flow
            if on.size:
                # one ranged sum: every pair's point against the sources of every sampled curvature
                pos, frc = ref.cycle_samples(on)
                blk = pos.shape[1] * pos.shape[2]
                src = np.zeros((on.size * blk, 3))
                src[:, :2] = (pos - ref.bases[on][:, None, None, :]).reshape(-1, 2)
                f = np.zeros_like(src)
                f[:, :2] = (frc * wgt[None, None, :, None]).reshape(-1, 2)
                tg = np.tile(rel, (on.size, 1))
                m = np.repeat(np.arange(on.size), npair)
                rng = np.ascontiguousarray(np.column_stack([m * blk, (m + 1) * blk]), dtype=np.int64)
                u = stokeslet_velocity_ranges(tg, src, f, np.arange(tg.shape[0] + 1, dtype=np.int64), rng,
                                              carpet.mu, kernel=ref.kernel, backend=carpet.backend)
                vals[on] = u[:, :2].reshape(on.size, npair, 2)
        self.vals = vals
        self.key = self.k * self.N + self.j  # sorted (the pairs come point by point, cilia in order)
        self.coef = CubicSpline(self.grid, vals, axis=0).c if npair else np.zeros((4, self.grid.size - 1, 0, 2))
        self.seconds = _time.perf_counter() - clock
        logger.info("near field: %d pairs (%d distinct relative positions) within %.3g L of %d control points, %d "
                    "curvatures, %.2f s", self.k.size, npair, radius, self.P, self.grid.size, self.seconds)

    def _pieces(self, chi):
        c = np.clip(np.asarray(chi, dtype=float)[self.j], self.grid[0], self.grid[-1])
        i = np.clip(np.searchsorted(self.grid, c, side="right") - 1, 0, self.grid.size - 2)
        t = (c - self.grid[i])[:, None]
        a = self.coef[:, i, self.inv, :]  # (4, n_pairs, 2)
        return a, t

    def pair_velocity(self, chi) -> np.ndarray:
        """(n_pairs, 2) the near pairs' mean flows v_kj(chi_j)."""
        a, t = self._pieces(chi)
        return ((a[0] * t + a[1]) * t + a[2]) * t + a[3]

    def pair_derivative(self, chi) -> np.ndarray:
        """(n_pairs, 2) d v_kj / d chi_j at chi_j."""
        a, t = self._pieces(chi)
        return (3.0 * a[0] * t + 2.0 * a[1]) * t + a[2]


class DesignModel:
    """The design model of ``carpet``'s mean flow at ``control`` (P, 2) points, with the carrier
    geometry (force centres c_j and carrier radii delta_j) frozen at the curvatures ``chi_geom``
    (see the module docstring): :meth:`velocity` (P, 2) for any chi (N,), :meth:`gradient` the
    exact vector-Jacobian product, both one Stokeslet sum of P x 3N pairs."""

    def __init__(self, carpet: Carpet, control, chi_geom, moments: CycleMoments | None = None,
                 near: NearField | None = None):
        self.carpet = carpet
        self.moments = moments if moments is not None else cycle_moments(carpet.table)
        X = np.asarray(control, dtype=float)
        self.X3 = np.column_stack([X, np.zeros(X.shape[0])])
        self.rot = carpet.rotation
        self.wall = None if carpet.wall is None else Wall(z=-float(carpet.wall))
        m = self.moments(np.asarray(chi_geom, dtype=float))
        cen = carpet.bases + m["offset"] @ self.rot.T
        self.delta = 0.5 * np.maximum(m["radius"], 1e-6)
        pos = cen[:, None, :] + self.delta[:, None, None] * DESIGN_DIPOLE[None]
        self.pos3 = np.column_stack([pos.reshape(-1, 2), np.zeros(3 * carpet.n)])
        # large carpets: the sums through a treecode over the frozen geometry (its A^T is the
        # exact transpose, so the gradient stays exact for the model it minimises)
        self.tree = Treecode(self.X3, self.pos3, make_kernel(self.wall), carpet.mu, carpet.backend) \
            if self.X3.shape[0] * self.pos3.shape[0] >= TREE_PAIRS else None
        # the near pairs: their exact flows (NearField) replace their carriers' flows, whose
        # kernel blocks Gc (n_pairs, 2, 3, 2) (velocity component, carrier, force component) are
        # subtracted from the carrier sum
        self.near = near if near is not None and near.j.size else None
        if self.near is not None:
            k, j = self.near.k, self.near.j
            npair = k.size
            self.Gc = self.pair_blocks(k, j)

    def pair_blocks(self, k: np.ndarray, j: np.ndarray) -> np.ndarray:
        """(n, 2, 3, 2) the kernel blocks of the pairs (control point k, cilium j): the in-plane
        velocity at x_k of a unit in-plane force on each of cilium j's three carriers."""
        n = k.size
        out = np.empty((n, 2, 3, 2))
        ptr = np.arange(n + 1, dtype=np.int64)
        for m in range(3):
            rng = np.ascontiguousarray(np.column_stack([3 * j + m, 3 * j + m + 1]), dtype=np.int64)
            for b in range(2):
                f = np.zeros((self.pos3.shape[0], 3))
                f[:, b] = 1.0
                out[:, :, m, b] = stokeslet_velocity_ranges(self.X3[k], self.pos3, f, ptr, rng, self.carpet.mu,
                                                            wall=self.wall, backend=self.carpet.backend)[:, :2]
        return out

    def carriers(self, chi, nu: int = 0) -> np.ndarray:
        """(N, 3, 2) carrier forces (lab frame) at ``chi``, or their chi derivatives (nu = 1)."""
        return _carriers(self.moments, self.rot, self.delta, chi, nu)

    def velocity(self, chi) -> np.ndarray:
        """(P, 2) mean flow at the control points for curvatures ``chi`` (N,)."""
        f3 = self.carriers(chi)
        f = f3.reshape(-1, 2)
        c = self.carpet
        if self.tree is not None:
            u = self.tree.apply(np.column_stack([f, np.zeros(f.shape[0])]))[:, :2]
        else:
            u = stokeslet_velocity(self.X3, self.pos3, np.column_stack([f, np.zeros(f.shape[0])]), c.mu,
                                   wall=self.wall, backend=c.backend)[:, :2]
        if self.near is not None:
            nf = self.near
            d = nf.pair_velocity(chi) - np.einsum("pamb,pmb->pa", self.Gc, f3[nf.j])
            u = u + np.column_stack([np.bincount(nf.k, d[:, 0], u.shape[0]), np.bincount(nf.k, d[:, 1], u.shape[0])])
        return u

    def gradient(self, chi, g_u) -> np.ndarray:
        """(N,) d/dchi_j of sum_k g_u[k] . u_k(chi): the adjoint Stokeslet sum from the control
        points to the carriers, contracted with the carriers' chi derivatives."""
        c = self.carpet
        g_u = np.asarray(g_u, dtype=float)
        if self.tree is not None:
            gp = self.tree.adjoint(np.column_stack([g_u, np.zeros(g_u.shape[0])]))[:, :2].reshape(c.n, 3, 2)
        else:
            gp = stokeslet_velocity(self.pos3, self.X3, np.column_stack([g_u, np.zeros(g_u.shape[0])]), c.mu,
                                    wall=self.wall, backend=c.backend)[:, :2].reshape(c.n, 3, 2)
        if self.near is None:
            return np.einsum("jkb,jkb->j", gp, self.carriers(chi, 1))
        nf = self.near
        gk = g_u[nf.k]
        gp = gp.copy()
        np.subtract.at(gp, nf.j, np.einsum("pa,pamb->pmb", gk, self.Gc))
        out = np.einsum("jkb,jkb->j", gp, self.carriers(chi, 1))
        return out + np.bincount(nf.j, np.sum(gk * nf.pair_derivative(chi), axis=1), c.n)


def floor_reference(carpet: Carpet, control, radius: float | None = None, spacing: float | None = None,
                    moments: CycleMoments | None = None) -> np.ndarray:
    """(P,) the speed floor's reference at the control points (P, 2): the speed of the flow that
    the straight cilia (chi_N = 0) whose force centre lies within ``radius`` of the point make
    there (design model; ``radius`` default :data:`FLOOR_RADIUS_SPACINGS` x ``spacing``, spacing
    default the median nearest-neighbour distance of the bases; ``inf``: every cilium), raised
    to at least a tenth of its median (points at the edge of the carpet).

    Why local: the straight carpet's own speed at a point sums the Stokeslets of every cilium
    (1/r), so it grows with the carpet's size, while the cross-stream flow a pattern of width w
    can make grows only with w; a floor on a fixed fraction of the whole carpet's speed then
    forbids large carpets the patterns small ones make (1000 cilia, focusing at 20 degrees:
    the design model's optimum under the whole-carpet floor is 0.054 rad, with this one 0.026)."""
    X = np.asarray(control, dtype=float)
    zero = np.zeros(carpet.n)
    dm = DesignModel(carpet, X, zero, moments=moments)
    if radius is None:
        if spacing is None:
            from scipy.spatial import cKDTree

            spacing = float(np.median(cKDTree(carpet.bases).query(carpet.bases, k=2)[0][:, 1])) \
                if carpet.n > 1 else 1.0
        radius = FLOOR_RADIUS_SPACINGS * float(spacing)
    radius = float(radius)
    if not radius > 0:
        raise ValueError(f"floor_radius must be > 0 (L), got {radius!r}")
    s = _local_speed(dm, zero, radius)
    return np.maximum(s, 0.1 * float(np.median(s)) + 1e-300)


def _local_speed(dm: "DesignModel", chi: np.ndarray, radius: float) -> np.ndarray:
    return np.linalg.norm(_local_velocity(dm, chi, radius), axis=1)


def _local_velocity(dm: "DesignModel", chi: np.ndarray, radius: float) -> np.ndarray:
    """(P, 2) the flow at each control point of the cilia whose force centre lies within
    ``radius`` of it (design model at ``chi``; every cilium when radius is infinite)."""
    f = dm.carriers(chi).reshape(-1, 2)
    F3 = np.column_stack([f, np.zeros(f.shape[0])])
    if not math.isfinite(radius):
        return stokeslet_velocity(dm.X3, dm.pos3, F3, dm.carpet.mu, wall=dm.wall)[:, :2]
    from scipy.spatial import cKDTree

    cen = dm.pos3[:, :2].reshape(-1, 3, 2).mean(axis=1)
    lists = cKDTree(cen).query_ball_point(dm.X3[:, :2], radius)
    cnt = np.array([len(x) for x in lists], np.int64)
    ptr = np.concatenate([[0], np.cumsum(cnt)]).astype(np.int64)
    j = np.concatenate([np.asarray(x, np.int64) for x in lists]) if cnt.sum() else np.zeros(0, np.int64)
    ranges = np.column_stack([3 * j, 3 * j + 3]).astype(np.int64)
    return stokeslet_velocity_ranges(dm.X3, dm.pos3, F3, ptr, ranges, dm.carpet.mu, wall=dm.wall)[:, :2]


def angle_objective(u, target, floor, weight: float = 1.0, point_weights=None) -> tuple[float, np.ndarray]:
    """J = sum_k c_k [(1 - uhat_k . t_k) + (w/2) max(0, 1 - u_k . t_k / floor_k)^2] and dJ/du
    (P, 2) for velocities ``u`` (P, 2), unit target directions ``target`` (P, 2) and speed
    floors ``floor`` (P,) (no floor term where floor is 0 or w = 0), with c_k = 1/P, or with
    ``point_weights`` omega_k (P,) c_k = omega_k / sum omega; see the module docstring."""
    P = u.shape[0]
    c = np.full(P, 1.0 / P) if point_weights is None else \
        np.asarray(point_weights, dtype=float) / max(float(np.sum(point_weights)), 1e-300)
    nrm = np.maximum(np.linalg.norm(u, axis=1), 1e-300)
    uh = u / nrm[:, None]
    cos = np.sum(uh * target, axis=1)
    J = float(np.sum(c * (1.0 - cos)))
    g_u = -(target - uh * cos[:, None]) * (c / nrm)[:, None]
    floor = np.broadcast_to(np.asarray(floor, dtype=float), (P,))
    if weight > 0 and np.any(floor > 0):
        on = floor > 0
        h = np.zeros(P)
        h[on] = np.maximum(0.0, 1.0 - np.sum(u[on] * target[on], axis=1) / floor[on])
        J += 0.5 * weight * float(np.sum(c * h ** 2))
        g_u[on] -= weight * (c[on] * h[on] / floor[on])[:, None] * target[on]
    return J, g_u


def _angle_terms(u, target, floor, weight: float, c) -> np.ndarray:
    """The per-point terms of :func:`angle_objective` (their sum is J) for flows ``u`` (..., n, 2)
    at n points with targets, floors and point factors c_k (n,)."""
    nrm = np.maximum(np.linalg.norm(u, axis=-1), 1e-300)
    dot = np.sum(u * target, axis=-1)
    out = 1.0 - dot / nrm
    if weight > 0:
        on = floor > 0
        h = np.where(on, np.maximum(0.0, 1.0 - dot / np.where(on, floor, 1.0)), 0.0)
        out = out + 0.5 * weight * h ** 2
    return c * out


SWEEP_RADIUS = 6.0
"""The sweep (:func:`_sweep`) counts the change of the objective at the control points within
this distance [L] of the cilium it moves (the others change by its far field only)."""


def _sweep(dm: DesignModel, near: NearField, chi: np.ndarray, u: np.ndarray, terms, penalty,
           radius: float = SWEEP_RADIUS) -> tuple[np.ndarray, int]:
    """One Gauss-Seidel sweep over the cilia on the design model: in turn, each cilium's chi_N is
    set to the best of the curvatures ``near.grid`` (all of [-chi_c, chi_c], both signs) with
    the others fixed, when that lowers the objective.

    Why: the objective is not convex in chi. Each cilium's flow traces a curve as chi_N runs
    over its branch (the thrust turns and shrinks toward the cutoff, the swept region moves), so
    a cilium whose neighbours' flows pull the wrong way at the start settles on the wrong side
    of that curve (typically the wrong sign of chi_N) and a gradient method cannot leave it: on
    144 cilia above a wall, a reachable target stopped at 0.081 rms with 8 cilia off by more
    than 30 (their signs flipped); one sweep and a second L-BFGS-B solve reach 1e-3.

    ``u`` (P, 2): the model's flow at ``chi`` (the defect included); ``terms(u_sub, ks)``: the
    per-point objective terms of flows u_sub (..., n, 2) at control points ks (n,), whose sum
    over all points is the data term; ``penalty(j, values, chi)``: the change of the regularisers
    when chi_j takes ``values`` (the others at ``chi``). The change of a cilium's flow is taken exactly (near pairs from
    the table, the others from its carriers) at the control points within ``radius``; beyond, it
    is left out of the decision (the caller keeps the sweep only if the full design model's
    objective fell). Returns the new chi and the number of cilia moved."""
    from scipy.spatial import cKDTree

    c = dm.carpet
    N, grid = c.n, near.grid
    lists = cKDTree(dm.X3[:, :2]).query_ball_point(c.bases, float(radius))
    cnt = np.array([len(x) for x in lists], np.int64)
    ptr = np.concatenate([[0], np.cumsum(cnt)])
    jj = np.repeat(np.arange(N), cnt)
    kk = np.concatenate([np.asarray(x, np.int64) for x in lists]) if cnt.sum() else np.zeros(0, np.int64)
    G = dm.pair_blocks(kk, jj)
    key = kk * N + jj
    pos = np.clip(np.searchsorted(near.key, key), 0, max(near.key.size - 1, 0))
    is_near = near.key[pos] == key if near.key.size else np.zeros(key.size, bool)
    ng = grid.size
    Fg = _carriers(dm.moments, dm.rot, np.repeat(dm.delta, ng), np.tile(grid, N)).reshape(N, ng, 3, 2)
    chi = np.array(chi, dtype=float)
    f_cur = dm.carriers(chi)
    v_cur = near.pair_velocity(chi)
    u = np.array(u, dtype=float)
    moved = 0
    for j in range(N):
        sl = slice(ptr[j], ptr[j + 1])
        ks = kk[sl]
        if ks.size == 0:
            continue
        du = np.einsum("pamb,gmb->gpa", G[sl], Fg[j] - f_cur[j])
        nm = is_near[sl]
        if nm.any():
            pi = pos[sl][nm]
            du[:, nm] = near.vals[:, near.inv[pi]] - v_cur[pi][None]
        base = terms(u[ks], ks)
        dJ = np.sum(terms(u[ks][None] + du, ks) - base[None], axis=1) + penalty(j, grid, chi)
        m = int(np.argmin(dJ))
        if dJ[m] < -1e-12 * max(float(np.sum(base)), 1e-300):
            chi[j] = grid[m]
            u[ks] += du[m]
            f_cur[j] = Fg[j, m]
            if nm.any():
                v_cur[pos[sl][nm]] = near.vals[m, near.inv[pos[sl][nm]]]
            moved += 1
    return chi, moved


# ------------------------------------------------------------------------------ design
def design_layout(carpet: Carpet, control, *, angles=None, velocities=None, cilium_angles=None, clip: bool = False,
                  tol: float = 1e-3, check_tol: float | None = None, speed_floor: float = _as_in_spec("speed_floor"),
                  floor_weight: float = 1.0, regularization: float = 1e-3, smoothness: float = 0.0,
                  outer: int = 2, ftol: float = 1e-6, maxiter: int = 500,
                  spacing: float | None = None, floor_radius: float | None = None,
                  robust_sigma: float = 0.0, robust_samples: int = 16, robust_seed: int = 12345,
                  near_radius: float = NEAR_RADIUS, sweeps: int = 3, threshold: float | None = None,
                  inside_swept: str = "use") -> Design:
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
    :data:`FLOOR_RADIUS_SPACINGS` x ``spacing``; at most ``outer`` passes, each at most ``maxiter`` L-BFGS-B
    iterations, stopped when an iteration lowers J by less than ``ftol`` times its value at the
    pass's start; no further pass once the design model's J at the pass's result is within 5%
    of the full model's, or a pass gained under 2%). ``near_radius``: the model's near field
    (:class:`NearField`; 0: carriers only); ``sweeps``: at most this many sweeps (:func:`_sweep`)
    and restarts per pass; ``threshold``: the acceptance threshold on the rms residual, whose half
    the error bar is made to meet (module docstring; None: the checks' own bar);
    ``inside_swept``: "use", "downweight" or "drop" the control points inside a swept region.
    With a threshold, no further pass starts once the rms residual is below :data:`GOOD_ENOUGH`
    of it.
    The full-model checks use the tolerance ``check_tol`` (default
    max(tol, 3e-2): the levels of detail's bound is loose; on a 1000-cilium carpet the angles at
    the control points differ from tol = 1e-3 by at most 4e-5 rad, at a quarter of the cost of
    tol = 1e-2 and a sixteenth of tol = 1e-3; the residual carries the bound as
    ``residual_error``, 0.004 rad there).

    Returns the best layout by the objective on the full model's flow among the local layout
    and the passes (:attr:`Design.returned`); ``carpet_with(design, carpet)`` is its carpet."""
    clock = _time.perf_counter()
    t: ThrustTable = carpet.table
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
    # control points inside a swept region: used (the regularised mean flow is bounded and
    # resolved there, see NearField), down-weighted or dropped as asked
    inside = check_control_points(carpet, X, spacing)
    w_pts = np.ones(X.shape[0])
    done = {"use": "used", "downweight": f"weighted {INSIDE_WEIGHT:g}", "drop": "dropped"}[inside_swept]
    inside_info = {"count": int(inside.size), "action": inside_swept, "indices": inside.tolist(),
                   "weight": {"use": 1.0, "downweight": INSIDE_WEIGHT, "drop": 0.0}[inside_swept]}
    if inside.size:
        logger.info("design: %d of %d control points lie inside a cilium's swept region: %s", inside.size,
                    X.shape[0], done)
    if inside.size and inside_swept == "drop" and inside.size == X.shape[0]:
        warnings.warn("every control point lies inside a cilium's swept region: dropping them would leave none, so "
                      "they are used (inside_swept = \"drop\" taken as \"use\")", UserWarning, stacklevel=2)
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
        w_pts[inside] = INSIDE_WEIGHT
    wsum = float(np.sum(w_pts))
    uniform_w = bool(np.all(w_pts == 1.0))
    check_tol = max(tol, 3e-2) if check_tol is None else float(check_tol)
    rot = carpet.rotation
    d0 = rot @ np.array([0.0, -1.0])  # the straight filaments' flow direction, lab frame
    base_angle = math.atan2(d0[1], d0[0])
    mom = cycle_moments(t)
    b1 = mom.cutoff
    lo_a, hi_a = t.thrust_angle_range()
    clipped: list[int] = []
    P, N = X.shape[0], carpet.n
    if angles is not None:
        A = np.broadcast_to(np.asarray(angles, dtype=float), (P,)).copy()
        if not np.all(np.isfinite(A)):
            raise TargetError("target angles contain NaN or inf")
        kind = "angle"
        target = _unit(base_angle + A)
        from scipy.spatial import cKDTree

        want = A[cKDTree(X).query(carpet.centres)[1]] if cilium_angles is None else \
            np.broadcast_to(np.asarray(cilium_angles, dtype=float), (N,)).copy()
        want, bad = reachable_check(want, (lo_a, hi_a), clip, what="cilium", points=carpet.bases)
        clipped = np.nonzero(bad)[0].tolist()
        chi0 = np.array([t.chi_N_for_angle(a) for a in want])
    else:
        U = np.asarray(velocities, dtype=float)
        if U.shape != X.shape:
            raise TargetError(f"velocities must have shape {X.shape}, got {U.shape}")
        if not np.all(np.isfinite(U)):
            raise TargetError("target velocities contain NaN or inf")
        kind = "velocity"
        target = U
        chi0 = np.clip(carpet.chi_N, -b1, b1)
    scaleU = float(np.sum(w_pts[:, None] * target ** 2)) if kind == "velocity" else 1.0
    if kind == "velocity" and scaleU == 0:
        raise TargetError("target velocities are all zero")
    edges = _edges(carpet.bases) if smoothness > 0 else np.zeros((0, 2), np.int64)
    counters = {"iterations": 0, "evaluations": 0, "checks": 0, "seconds_carpets": 0.0, "seconds_checks": 0.0,
                "seconds_model": 0.0, "sweeps": 0, "swept_cilia": 0}

    def residual(u):
        if kind == "angle":
            return np.abs(np.angle((u[:, 0] + 1j * u[:, 1]) * np.conj(target[:, 0] + 1j * target[:, 1])))
        return np.linalg.norm(u - target, axis=1) / math.sqrt(scaleU / wsum)

    def wrms(r) -> float:
        """The (weighted) rms over the control points: sqrt(sum w_k r_k^2 / sum w_k)."""
        return float(np.sqrt(np.sum(w_pts * np.asarray(r) ** 2) / wsum))

    def check(chi, ctol=None, c=None):
        counters["checks"] += 1
        t0 = _time.perf_counter()
        c = _with_chi(carpet, chi) if c is None else c
        t1 = _time.perf_counter()
        s = c.evaluate(X, CycleMean(), tol=check_tol if ctol is None else ctol)
        counters["seconds_carpets"] += t1 - t0
        counters["seconds_checks"] += _time.perf_counter() - t1
        return c, s.velocity[:, :2], s.error_bound

    # the reference speed of the floor: what the straight carpet makes at each control point
    zero = np.zeros(N)
    sref = floor_reference(carpet, X, floor_radius, spacing, moments=mom)

    def data(u):
        """The data term of J and dJ/du at the flow ``u`` (P, 2)."""
        if kind == "angle":
            return angle_objective(u, target, speed_floor * sref, floor_weight, None if uniform_w else w_pts)
        r = u - target
        return 0.5 * float(np.sum(w_pts[:, None] * r ** 2)) / scaleU, w_pts[:, None] * r / scaleU

    c_pts = w_pts / wsum
    floor_pts = speed_floor * sref

    def terms(u_sub, ks):
        """The data term's per-point terms (their sum over every point is data(u)[0])."""
        if kind == "angle":
            return _angle_terms(u_sub, target[ks], floor_pts[ks], floor_weight, c_pts[ks])
        return 0.5 * w_pts[ks] * np.sum((u_sub - target[ks]) ** 2, axis=-1) / scaleU

    nbrs = [[] for _ in range(N)]
    for e0, e1 in edges:
        nbrs[e0].append(e1)
        nbrs[e1].append(e0)

    def penalty(j, vals, chi):
        """The change of the regularisers when chi_j takes the values ``vals`` (others as in chi)."""
        out = regularization * (((vals - chi0[j]) / b1) ** 2 - ((chi[j] - chi0[j]) / b1) ** 2) / N
        for i in nbrs[j]:
            out = out + smoothness * (((vals - chi[i]) / b1) ** 2 - ((chi[j] - chi[i]) / b1) ** 2) / len(edges)
        return out

    # the fabrication-tolerance samples of the robust objective: chi_j (1 + sigma eps_sj)
    mult = (1.0 + rs * np.random.default_rng(robust_seed).standard_normal((int(robust_samples), N))) if rs > 0 \
        else np.ones((1, N))

    def expected(dmodel, shift_u, c, grad: bool):
        """The data term averaged over the samples (the nominal one without robust_sigma) of
        the flow dmodel.velocity(chi (1 + sigma eps)) + shift_u, and its chi gradient."""
        J, g = 0.0, np.zeros(N)
        for m in mult:
            cm = c * m
            Jm, gu = data(dmodel.velocity(cm) + shift_u)
            J += Jm / mult.shape[0]
            if grad:
                g += dmodel.gradient(cm, gu) * m / mult.shape[0]
        return J, g

    def score(u, chi, c_full=None):
        """The design objective measured on the full model's flow ``u`` (what "best" means); the
        robust one: the sample average with the defect frozen at ``chi``."""
        if rs > 0:
            dmc = DesignModel(carpet if c_full is None else c_full, X, chi, moments=mom, near=near)
            with _threads(3 * N * P):
                J = expected(dmc, u - dmc.velocity(chi), chi, False)[0]
        else:
            J = data(u)[0]
        return J + regularization * float(np.sum(((chi - chi0) / b1) ** 2)) / N + (
            smoothness * float(np.sum(((chi[edges[:, 0]] - chi[edges[:, 1]]) / b1) ** 2)) / len(edges)
            if edges.size else 0.0)

    # the exact mean flows of the cilia near the control points, tabulated in chi (NearField)
    near = NearField(carpet, X, near_radius, moments=mom) if near_radius > 0 else None
    counters["seconds_near"] = near.seconds if near is not None else 0.0
    counters["near_pairs"] = int(near.k.size) if near is not None else 0

    # the local layout: the first iterate, measured with the full model
    c_loc, u_loc, e_loc = check(chi0)
    r_loc = residual(u_loc)
    rms_loc = wrms(r_loc)
    J_loc = score(u_loc, chi0, c_loc)
    best = {"rms": rms_loc, "J": J_loc, "chi": chi0.copy(), "u": u_loc, "resid": r_loc,
            "label": "local", "carpet": c_loc, "res": None, "bound": e_loc}

    u_prev, chi = u_loc, chi0.copy()
    res = None
    for p in range(1, max(1, outer) + 1):
        dm = DesignModel(carpet, X, chi, moments=mom, near=near)
        shift = u_prev - dm.velocity(chi)  # defect: full model minus design model at this pass's start

        J_scale = 1.0

        def fun(x):
            counters["evaluations"] += 1
            c = x * b1
            J, g = expected(dm, shift, c, True)
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
        with _threads(3 * N * P):
            # J in units of its value at the pass's start: ftol is then relative to it
            J_scale = max(fun(chi / b1)[0], 1e-300)
            res = minimize(fun, chi / b1, jac=True, method="L-BFGS-B", bounds=[(-1.0, 1.0)] * N,
                           options={"gtol": 1e-10, "ftol": ftol, "maxiter": maxiter})
            counters["iterations"] += int(res.nit)
            # out of a local minimum: a sweep over the cilia (each to the best curvature of the
            # grid, both signs), then L-BFGS-B again, while that lowers the model's objective
            for _ in range(int(sweeps) if (near is not None and rs == 0) else 0):
                chi_k = np.clip(res.x * b1, -b1, b1)
                chi_s, moved = _sweep(dm, near, chi_k, dm.velocity(chi_k) + shift, terms, penalty)
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
        chi = np.clip(res.x * b1, -b1, b1)
        c_full, u_full, e_full = check(chi)
        resid = residual(u_full)
        rms = wrms(resid)
        logger.info("design pass %d: full-model rms residual %.4g (model objective %.4g of its start), "
                    "%d iterations", p, rms, float(res.fun), res.nit)
        J_full = score(u_full, chi, c_full)
        J_model = float(res.fun) * J_scale
        logger.info("design pass %d: objective %.4g on the full model, %.4g on the design model", p, J_full, J_model)
        gain = (best["J"] - J_full) / max(best["J"], 1e-300)
        if J_full < best["J"]:
            best = {"rms": rms, "J": J_full, "chi": chi.copy(), "u": u_full, "resid": resid, "label": f"pass {p}",
                    "carpet": c_full, "res": res, "bound": e_full}
        u_prev = u_full
        # settled: the design model agrees with the full model at this layout (so the next pass
        # would minimise nearly the same objective), or the last pass gained under 2%, or (given
        # a threshold) the residual is below GOOD_ENOUGH of it
        if abs(J_full - J_model) <= 0.05 * J_full or (p > 1 and gain < 0.02):
            break
        if threshold is not None and best["rms"] <= GOOD_ENOUGH * float(threshold):
            logger.info("design pass %d: rms residual %.3g is below %g of the threshold %g: no further pass", p,
                        best["rms"], GOOD_ENOUGH, float(threshold))
            break
    chi, u, resid, rms = best["chi"], best["u"], best["resid"], best["rms"]

    def error_bar(bound, u):
        """A bound on |rms residual - its value on the resolved flow| from the levels of detail's
        per-point bounds b_k >= |u_k - u_k(resolved)|: the residual of point k moves by at most
        e_k = b_k / s (velocity targets, s the rms target speed) or arcsin(b_k / |u_k|) (angle
        targets; pi where b_k >= |u_k|), and an rms by at most the rms of the e_k (triangle
        inequality)."""
        if kind == "angle":
            nrm = np.linalg.norm(u, axis=1)
            e = np.where(bound < nrm, np.arcsin(np.minimum(bound / np.maximum(nrm, 1e-300), 1.0)), math.pi)
        else:
            e = bound / math.sqrt(scaleU / wsum)
        return wrms(e)

    r_err = error_bar(best["bound"], u)
    # one final check of the returned layout at a tolerance picked for the bar: at most half the
    # threshold (the bound scales about like the tolerance; the resolved sum, tol = 0, has none)
    tol_final = check_tol
    if threshold is not None:
        goal = 0.5 * float(threshold)
        for attempt in range(4):
            if r_err <= goal:
                break
            tol_final = 0.0 if attempt == 3 else tol_final * max(0.02, min(0.5, 0.5 * goal / max(r_err, 1e-300)))
            _, u, bound = check(chi, tol_final, best["carpet"])
            resid = residual(u)
            rms = wrms(resid)
            r_err = error_bar(bound, u)
            logger.info("design: final check at tol %.3g: rms residual %.4g +- %.2g", tol_final, rms, r_err)
    counters["final_tol"] = tol_final
    thrust = mom.thrust_norm(chi)
    near_cut = tuple(np.nonzero(thrust < NEAR_CUTOFF_FRACTION * mom.thrust0)[0].tolist())
    ratio = np.sum(u * target, axis=1) / sref if kind == "angle" else None
    last = best["res"] if best["res"] is not None else res
    status = "success" if (last is not None and last.success) else "inaccurate"
    unit = " rad" if kind == "angle" else " (relative)"
    robust = (f"designed for the expected objective under a relative chi_N error {rs:g} "
              f"({mult.shape[0]} samples); ") if rs > 0 else ""
    ins = ""
    if inside_info["count"]:
        ins = f"{inside_info['count']} control point(s) inside a cilium's swept region {done}; "
    message = (f"{kind} target at {P} control points: {ins}{robust}rms residual {rms:.3g}{unit} (+- {r_err:.2g}), "
               f"worst "
               f"{float(resid.max()):.3g}; local layout {rms_loc:.3g}; returned the {best['label']} layout; "
               f"{len(near_cut)} of {N} cilia near the flutter cutoff; L-BFGS-B "
               f"{'converged' if status == 'success' else 'stopped: ' + str(getattr(last, 'message', ''))}")
    logger.info("design: %s", message)
    counters["seconds"] = _time.perf_counter() - clock
    return Design(chi_N=chi, control=X, target=target, achieved=u, residual=resid, residual_rms=rms, kind=kind,
                  residual_error=r_err, speed_ratio=ratio, local_rms=rms_loc, objective=best["J"],
                  local_objective=J_loc, returned=best["label"],
                  near_cutoff=near_cut, clipped=tuple(clipped), status=status, message=message, work=counters,
                  carpet=best["carpet"], threshold=None if threshold is None else float(threshold),
                  inside_swept=inside_info, weights=None if uniform_w else w_pts)


# ------------------------------------------------------------------------------ reachability
WIDTH_GRID = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
"""The transition widths, in lattice spacings, at which :func:`reachability` estimates a
pattern's residual (the narrowest is a step on the lattice: tanh(4) = 0.9993 one spacing from
the line)."""
WIDTH_PATTERNS = ("focus", "spread", "shear")
"""The target kinds with a transition width (:mod:`ciliary_carpet.design.target`)."""


@dataclass(frozen=True)
class Reachability:
    """What a carpet can make under its field, up front (angles in radians, lengths in L).

    angle_max: the largest deflection of one cilium's thrust (the table's
    ``thrust_angle_range()``): a uniform target is reachable up to it. angle_floor: the
    deflection of a cilium that keeps ``speed_floor`` of the straight filament's thrust (how far
    the design's floor lets a cilium turn at full weight). pattern_max: the deflection a
    two-sided pattern (focus, spread) holds away from its line: the flow angle of the *split
    layout* -- every cilium on one side of the line turned by angle_floor toward it, on the
    other side away from it -- at the control points 3 spacings or more from the line (median;
    design model, every cilium). Less than angle_floor because each side's cross-stream flow is
    partly cancelled by the other's (Stokeslets decay as 1/r). An estimate, not a bound, and on
    the safe side by up to about 5 degrees; validated against full designs (tests; table 4 of
    benchmarks/results/bench_design.md), focusing of width 4 L, spacing 2: on 10 x 10 cilia
    pattern_max 22.6 deg, 20 and 25 deg meet 0.05 rad (0.006, 0.033), 30 and 40 miss (0.083,
    0.21); on 20 x 12 cilia 26.6 deg, 20 and 25 meet (0.009, 0.023), 30 and 40 miss (0.060,
    0.19).

    Width (patterns with a transition width: focus, spread, shear, on a carpet without a wall;
    ``None`` otherwise).
    width_min: the narrowest transition width at which the target's pattern (its kind and
    amplitude) meets its residual threshold on this carpet, estimated; 0 when even a step does
    (width h/4, h the spacing), ``inf`` when no width up to 8 h does (the amplitude is beyond
    the carpet: see pattern_max). width: the target's own width; width_rms: the estimated rms
    residual at it; widths: the scan, ((w, estimated rms), ...) at :data:`WIDTH_GRID` x h;
    residual: the threshold; seconds: the cost of the width estimate.

    How: what limits a transition is the kernel's smoothing across the line. A cilium's mean
    flow decays like 1/r, so the flow at a control point one spacing from the line is pushed by
    the column of cilia beside it *and*, the other way, by the columns across the line only two
    or three times as far; the sharper the requested change of angle across the line, the more
    cross-stream force the columns nearest the line need, until they run out of turn (and, near
    the flutter cutoff, of thrust): the smoothing a lattice of spacing h cannot undo is what is
    left. The estimate solves the design problem across the line on a strip: the design model
    of every cilium (module docstring), with the curvature constant along each column (cilia
    binned by their cross-stream coordinate in bins of h/4), at the control points of the row
    nearest the carpet's centre (within h/2 of it along the stream), with the design's own
    objective (:func:`angle_objective`: angle term and speed floor); L-BFGS-B on one variable per
    column. The Stokeslet sums are done once (a matrix of P_row x n_columns x 3 carriers: 6
    kernel sums per column), so an iteration is two small matrix products (under a millisecond;
    60-120 iterations a solve). The row's
    rms residual estimates the design's rms; width_min is where it crosses the threshold, found
    by bisection on :data:`WIDTH_GRID` (the widest and narrowest widths, then halving: about 6
    solves with the target's own width) and linear interpolation between the two widths around
    the crossing. Cost measured (benchmarks/results/bench_design.md table 4b, 2 cores shared with
    other jobs, load average 6-11): 0.14-0.41 s on 100 cilia, 0.33-0.70 s on 240, 0.31-0.86 s on
    1024, against 1.4-32 s for one full design (6-100x); 0.61 s on 10,000 cilia (100 columns;
    load average 5, the carpet itself 136 s in the same run; not validated against a design).

    Why a strip and not the split layout's profile: the split layout's flow angle reaches 0.76
    of pattern_max only 3.7 L from the line on 100 cilia, 10.6 L on 1000, which would call widths
    the designs meet unreachable: the design concentrates the cross-stream force near the line,
    and so does the strip solve. Why constant along each column: the design's freedom along the
    stream fixes the carpet's upstream and downstream edges, not the transition; on every row of
    the carpet the column solve misses 0.02-0.03 rad more than the design far from the line,
    on the centre row it follows the design. Validated against full designs (table 4b: focusing
    at 10, 20, 40 deg, spreading at 20, shear at 30; spacings 2 and 3; widths 0.5 h to 2 h (6 h
    at 40 deg); 100, 240 and 1024 cilia; 32 designs): the estimate never called a width
    reachable that the design missed, and called 3 unreachable that it met (their estimated rms
    within 0.006 rad of the threshold). Where the rms lies between 0.03 and 0.08 rad the estimate is above the
    design's by 0.004-0.016 rad (so width_min errs on the wide side by up to about a quarter
    spacing); for wide patterns, whose small design residual (below 0.01 rad) sits at the
    carpet's upstream and downstream edges, which the centre row does not see, it can be below
    by up to 0.008 rad: not on the safe side for thresholds under about 0.01 rad. Focusing at
    20 deg, 10 x 10 cilia, spacing 2: estimated 0.076, 0.062, 0.045, 0.014 rad at widths 0.5,
    0.75, 1, 1.5 h, designs 0.066, 0.052, 0.036, 0.014, width_min 1.85 L; spacing 3: 0.082,
    0.068, 0.051, 0.019 against 0.075, 0.061, 0.045, 0.019, width_min 3.02 L; 1024 cilia, spacing
    2: width_min 3.46 L (at 1 and 2 h: 0.070 and 0.040 against 0.063 and 0.035).

    Not above a wall: there the designs miss for another reason (100 cilia, hexagonal, spacing 2,
    wall 0.5 L below the plane: a *uniform* 20 deg deflection 0.17 rad; focusing at 20 deg,
    widths 2 and 8 L, 0.16 and 0.09 rad, where the strip estimated 0.077 and 0.047), so a width
    estimate would be optimistic; width_min is None. With the exact near field (issue 24) those
    designs end the same (0.166, 0.157, 0.091 rad), now with the design model within 2 % of the
    full model's objective: the miss is the target's -- above a wall each control point's flow
    is dominated by the few cilia around it, whose near field does not point along their thrust
    -- not the optimiser's (reachable targets above a wall are met: bench_design.py section 5)."""

    angle_max: float
    angle_floor: float
    pattern_max: float
    line: float = 0.0
    width_min: float | None = None
    width: float | None = None
    width_rms: float | None = None
    widths: tuple = ()
    residual: float | None = None
    seconds: float = 0.0

    @property
    def width_reachable(self) -> bool | None:
        """Whether the target's width is at least the estimated narrowest (None: not estimated)."""
        if self.width_min is None or self.width is None:
            return None
        return self.width >= self.width_min

    def summary(self) -> dict:
        out = {"angle_max_deg": math.degrees(self.angle_max), "angle_floor_deg": math.degrees(self.angle_floor),
               "pattern_max_deg": math.degrees(self.pattern_max), "line": self.line,
               "method": "pattern_max: design model, split layout at the speed floor (an estimate, not a bound)",
               "text": self.describe()}
        if self.width_min is not None:
            out.update({"width_min": self.width_min if math.isfinite(self.width_min) else None,
                        "width": self.width, "width_rms": self.width_rms, "width_reachable": self.width_reachable,
                        "residual_threshold": self.residual,
                        "width_scan": [[w, r] for w, r in self.widths], "width_seconds": self.seconds,
                        "width_method": "design model across the line: curvature constant along each column, "
                                        "the control points of the centre row (an estimate, on the safe side); "
                                        "width_min null: no width up to 8 spacings meets the threshold"})
        return out

    def describe(self) -> str:
        """One sentence for messages and summaries."""
        s = (f"one cilium turns its thrust up to {math.degrees(self.angle_max):.1f} deg "
             f"({math.degrees(self.angle_floor):.1f} at the speed floor); a two-sided pattern holds about "
             f"{math.degrees(self.pattern_max):.1f} deg")
        if self.width_min is not None:
            wm = ("no width up to 8 spacings" if not math.isfinite(self.width_min) else
                  "any width, a step included" if self.width_min == 0 else f"{self.width_min:.3g} L")
            s += (f"; narrowest transition at this amplitude: {wm} (asked {self.width:.3g} L, estimated rms "
                  f"{self.width_rms:.3g} rad against {self.residual:g})")
        return s


def reachability(carpet: Carpet, control, frame: Frame, speed_floor: float | None = None, line: float | None = None,
                 target: Target | None = None) -> Reachability:
    """The :class:`Reachability` of ``carpet`` at the control points (P, 2) with the pattern's
    line at cross-stream offset ``line`` of ``frame`` (one design-model evaluation), and with a
    ``target`` of kind focus, spread or shear the narrowest width at its amplitude and residual
    threshold (:data:`WIDTH_GRID`: ten small solves). ``speed_floor`` and ``line`` default to the
    target's (else 0.3 and 0)."""
    X = np.asarray(control, dtype=float)
    if speed_floor is None:
        speed_floor = target.speed_floor if target is not None else 0.3
    if line is None:
        line = target.line if target is not None else 0.0
    t = carpet.table
    mom = cycle_moments(t)
    grid = np.linspace(0.0, mom.cutoff, 2001)
    keep = np.nonzero(mom.thrust_norm(grid) >= float(speed_floor) * mom.thrust0)[0]
    chi_f = float(grid[keep.max()]) if keep.size else 0.0
    a_f = float(t.scalar("thrust_angle", np.array([chi_f]))[0])
    sgn = 1.0 if a_f >= 0 else -1.0
    chi = -np.sign(frame.cross_coordinate(carpet.centres) - line) * sgn * chi_f  # toward the line on both sides
    u = DesignModel(carpet, X, chi, moments=mom).velocity(chi)
    delta = np.arctan2(u @ frame.cross, u @ frame.flow_direction)
    xi = np.abs(frame.cross_coordinate(X) - line)
    far = xi >= 3.0 * frame.spacing
    if not np.any(far):
        far = xi >= np.median(xi)
    reach = Reachability(angle_max=float(t.thrust_angle_range()[1]), angle_floor=abs(a_f),
                         pattern_max=float(np.median(np.abs(delta[far]))), line=float(line))
    if target is None or target.kind not in WIDTH_PATTERNS:
        return reach
    if carpet.wall is not None:
        logger.info("reachability: the narrowest width is not estimated above a wall (see Reachability)")
        return reach
    clock = _time.perf_counter()
    h = frame.spacing
    w_t = float(target.width) if target.width is not None else h
    strip = _Strip(carpet, X, frame, float(speed_floor), mom)
    ws = [g * h for g in WIDTH_GRID]
    thr = float(target.residual)
    scan: dict[float, float] = {}

    def rms(w: float) -> float:
        if w not in scan:
            scan[w] = strip.rms(replace(target, width=w))
        return scan[w]

    # bisection on the grid (the estimate falls as the width grows): the widest, the narrowest,
    # then halving the bracket; the crossing interpolated linearly between its two ends
    if rms(ws[-1]) > thr:
        w_min = math.inf
    elif rms(ws[0]) <= thr:
        w_min = 0.0
    else:
        lo, hi = 0, len(ws) - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if rms(ws[mid]) <= thr else (mid, hi)
        r0, r1 = scan[ws[lo]], scan[ws[hi]]
        w_min = ws[lo] + (r0 - thr) / max(r0 - r1, 1e-300) * (ws[hi] - ws[lo])
    r_t = rms(w_t)
    sec = _time.perf_counter() - clock
    logger.info("reachability: narrowest %s width at %.1f deg: %.3g L (asked %.3g L, estimated rms %.3g); "
                "%d L-BFGS-B iterations, %.2f s", target.kind, math.degrees(target.amplitude), w_min, w_t, r_t,
                strip.iterations, sec)
    return replace(reach, width_min=float(w_min), width=w_t, width_rms=r_t,
                   widths=tuple((float(w), float(scan[w])) for w in sorted(scan)), residual=thr,
                   seconds=sec)


class _Strip:
    """The design problem across the line on the carpet's centre row (see :class:`Reachability`):
    the control points within half a spacing (along the stream) of the row nearest the centre,
    the cilia binned into columns by their cross-stream coordinate (bins of a quarter spacing),
    one curvature per column; ``W`` (P_row, n_columns, 3, 2, 2) the flow at each row point of a
    unit force (lab axes) on carrier m of every cilium of a column (geometry of straight cilia),
    ``M`` the same as a (2 P_row, 6 n_columns) matrix acting on the flattened carrier forces."""

    def __init__(self, carpet: Carpet, X: np.ndarray, frame: Frame, speed_floor: float, mom: CycleMoments):
        h = frame.spacing
        s = np.abs((X - frame.centre) @ frame.flow_direction)
        self.X = X[s <= s.min() + 0.5 * h * (1 + 1e-9)]
        self.frame, self.mom, self.table = frame, mom, carpet.table
        dm = DesignModel(carpet, self.X, np.zeros(carpet.n), moments=mom)
        cen = dm.pos3[:, :2].reshape(-1, 3, 2).mean(axis=1)
        _, col = np.unique(np.round(frame.cross_coordinate(cen) / (0.25 * h)), return_inverse=True)
        col = col.ravel()
        nc = int(col.max()) + 1
        self.W = np.zeros((self.X.shape[0], nc, 3, 2, 2))
        rep = np.zeros(nc, np.int64)
        with _threads(3 * carpet.n * self.X.shape[0]):
            for b in range(nc):
                j = np.nonzero(col == b)[0]
                rep[b] = j[0]
                for m in range(3):
                    for ax in range(2):
                        f = np.zeros((j.size, 3))
                        f[:, ax] = 1.0
                        self.W[:, b, m, :, ax] = stokeslet_velocity(dm.X3, dm.pos3[3 * j + m], f, carpet.mu,
                                                                    wall=dm.wall, backend=carpet.backend)[:, :2]
        self.M = self.W.transpose(0, 3, 1, 2, 4).reshape(2 * self.X.shape[0], 6 * nc)  # u = M c (flattened)
        self.centres = cen[rep]
        self.delta, self.rot = dm.delta[rep], dm.rot
        self.floor = speed_floor * floor_reference(carpet, self.X, spacing=h, moments=mom)
        self.iterations = 0

    def rms(self, target: Target) -> float:
        """The rms angle residual at the row's points of the best column layout for ``target``:
        the design's objective (:func:`angle_objective`, its speed floor) by L-BFGS-B in chi / chi_c
        in [-1, 1] from the columns' local requests, scaled to 1 there so that its tolerance is
        relative."""
        T = self.frame.directions(target.deflection(self.X, self.frame))
        a_max = self.table.thrust_angle_range()[1] * (1.0 - 1e-9)
        want = np.clip(target.deflection(self.centres, self.frame), -a_max, a_max)
        cut = self.mom.cutoff
        z0 = np.array([self.table.chi_N_for_angle(float(a)) for a in want]) / cut

        def flow(z):
            return (self.M @ _carriers(self.mom, self.rot, self.delta, z * cut).ravel()).reshape(-1, 2)

        scale = 1.0 / max(angle_objective(flow(z0), T, self.floor)[0], 1e-300)

        def fun(z):
            J, g = angle_objective(flow(z), T, self.floor)
            dc = _carriers(self.mom, self.rot, self.delta, z * cut, 1).ravel()
            return scale * J, scale * cut * ((self.M.T @ g.ravel()) * dc).reshape(-1, 6).sum(axis=1)

        with _threads(0):
            res = minimize(fun, z0, jac=True, method="L-BFGS-B", bounds=[(-1.0, 1.0)] * z0.size,
                           options={"ftol": 1e-9, "maxiter": 1000})
        self.iterations += int(res.nit)
        u = flow(res.x)
        r = np.angle((u[:, 0] + 1j * u[:, 1]) * np.conj(T[:, 0] + 1j * T[:, 1]))
        return float(np.sqrt(np.mean(r ** 2)))


# ------------------------------------------------------------------------------ tolerance
@dataclass(frozen=True)
class ToleranceStudy:
    """How a design's residual spreads when the cilia come out with curvature errors.

    Model: chi_j -> chi_j (1 + sigma eps_j), eps_j independent standard normal (a relative
    fabrication error; a perturbed |chi_N| beyond the flutter cutoff stands still). Each sample's
    flow is the design model plus the full model's defect at the design (:class:`DesignModel`),
    one Stokeslet sum per sample. sigma; samples; seed; nominal_rms: the design's residual;
    mean_rms, std_rms, p10_rms, p90_rms: over the samples; sampling_error: std_rms /
    sqrt(samples), the standard error of mean_rms; rms (samples,): every sample's residual.
    Method error: the defect is frozen at the nominal layout, so a sample's flow misses how the
    near field beyond the dipole changes with chi; measured against brute-force full-model
    samples in the tests (well below the sampling error for sigma <= 0.1)."""

    sigma: float
    samples: int
    seed: int
    nominal_rms: float
    mean_rms: float
    std_rms: float
    p10_rms: float
    p90_rms: float
    sampling_error: float
    rms: np.ndarray

    def summary(self) -> dict:
        return {"sigma": self.sigma, "samples": self.samples, "seed": self.seed, "nominal_rms": self.nominal_rms,
                "mean_rms": self.mean_rms, "std_rms": self.std_rms, "p10_rms": self.p10_rms,
                "p90_rms": self.p90_rms, "sampling_error": self.sampling_error,
                "method": "sampled; design model + the full model's defect at the design"}


def tolerance_study(carpet: Carpet, d: Design, sigma: float, samples: int = _as_in_spec("samples"),
                    seed: int = 0) -> ToleranceStudy:
    """The expected residual of design ``d`` on ``carpet`` (its designed carpet) and its spread
    under a relative chi_N error ``sigma`` (see :class:`ToleranceStudy`)."""
    sg = float(sigma)
    if not (math.isfinite(sg) and sg >= 0):
        raise ValueError(f"sigma must be a finite number >= 0 (a relative chi_N error), got {sigma!r}")
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise ValueError(f"samples must be an integer >= 1, got {samples!r}")
    chi = np.asarray(d.chi_N, dtype=float)
    dm = DesignModel(carpet, d.control, chi)
    shift = d.achieved - dm.velocity(chi)
    P = d.control.shape[0]
    if d.kind == "velocity":
        scale = math.sqrt(float(np.sum(d.target ** 2)) / P)
    rng = np.random.default_rng(seed)
    rms = np.empty(int(samples))
    with _threads(3 * carpet.n * P):
        for k in range(int(samples)):
            u = dm.velocity(chi * (1.0 + sg * rng.standard_normal(chi.size))) + shift
            if d.kind == "angle":
                r = np.angle((u[:, 0] + 1j * u[:, 1]) * np.conj(d.target[:, 0] + 1j * d.target[:, 1]))
            else:
                r = np.linalg.norm(u - d.target, axis=1) / scale
            rms[k] = math.sqrt(float(np.mean(r ** 2)))
    sd = float(rms.std(ddof=1)) if rms.size > 1 else 0.0
    return ToleranceStudy(sigma=sg, samples=int(samples), seed=int(seed), nominal_rms=d.residual_rms,
                          mean_rms=float(rms.mean()), std_rms=sd, p10_rms=float(np.percentile(rms, 10)),
                          p90_rms=float(np.percentile(rms, 90)), sampling_error=sd / math.sqrt(rms.size), rms=rms)


def carpet_with(design: Design, carpet: Carpet) -> Carpet:
    """``carpet`` with the designed chi_N (the design's own carpet when it has one)."""
    if design.carpet is not None and np.array_equal(design.carpet.bases, carpet.bases):
        return design.carpet
    return _with_chi(carpet, design.chi_N)


def design(scene, table: ThrustTable | None = None) -> tuple[Design | None, Carpet]:
    """Design the scene's carpet for its target: returns (Design, the designed Carpet), or
    (None, the scene's carpet) when the scene has no target.

    The target's control points and angles (or velocities) come from :mod:`ciliary_carpet.design.target`;
    the per-cilium request is the pattern evaluated at each cilium's force centre. A design whose
    rms residual exceeds ``[target] residual`` returns the closest flow the cilia can make, with
    a warning naming the worst control points; with ``[target] strict = true`` it is a
    DesignError (exit status 3 of the command line) and unreachable angle requests are a
    TargetError instead of being clipped."""
    built = assemble(scene, table)
    table, target, bases, frame = built.table, built.target, built.bases, built.frame
    if target.kind == "none":
        return None, built.carpet()
    strict = target.strict
    kw = dict(tol=scene.tolerance, speed_floor=target.speed_floor, smoothness=target.smoothness,
              spacing=scene.carpet.spacing, robust_sigma=target.sigma if target.robust else 0.0,
              threshold=float(target.residual), inside_swept=target.inside_swept)
    if target.is_angle:
        # the local layout straight away (no carpet of straight cilia is built): the request at
        # each cilium's force centre, the centre of the straight filament
        mom = cycle_moments(table)
        a = scene.field.direction_rad
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        centres0 = bases + mom(np.zeros(1))["offset"] @ rot.T
        want, bad = reachable_check(target.deflection(centres0, frame), table.thrust_angle_range(), not strict,
                                    what="cilium", points=bases)
        chi0 = np.array([table.chi_N_for_angle(x) for x in want])
        carpet = built.carpet(chi0)
        X = control_points(bases, frame, target.control)
        reach = reachability(carpet, X, frame, target=target)  # up front: what this carpet can make
        if target.pattern.two_sided and target.amplitude > reach.pattern_max:
            logger.info("design: the %s amplitude %.1f deg exceeds the estimated reachable %.1f deg of a two-sided "
                        "pattern on this carpet", target.kind, math.degrees(target.amplitude),
                        math.degrees(reach.pattern_max))
        if reach.width_reachable is False:
            logger.info("design: the %s width %.3g L is below the estimated narrowest %.3g L at %.1f deg on this "
                        "carpet (estimated rms %.3g against %g)", target.kind, reach.width, reach.width_min,
                        math.degrees(target.amplitude), reach.width_rms, target.residual)
        d = design_layout(carpet, X, angles=target.deflection(X, frame), cilium_angles=want, clip=not strict,
                          **kw)
        d = _replace(d, reachability=reach.summary(),
                     **({"clipped": tuple(np.nonzero(bad)[0].tolist())} if np.any(bad) else {}))
    else:
        carpet = built.carpet()
        X, U = target.velocities()
        d = design_layout(carpet, X, velocities=U, clip=not strict, **kw)
    if d.residual_rms > target.residual:
        unit = "rad" if d.kind == "angle" else "relative"
        lst = ", ".join(f"#{k} at ({x:.3g}, {y:.3g}): {r:.3g} {unit}" for k, x, y, r in d.worst())
        est, hint = [], "Lower the target angle, widen the pattern, or move the control points away from the cilia"
        r = d.reachability
        if target.pattern.two_sided and r is not None:
            est.append(f"a two-sided pattern holds about {r['pattern_max_deg']:.1f} deg, asked "
                       f"{math.degrees(target.amplitude):.1f} deg")
        if r is not None and "width_min" in r:
            wm = r["width_min"]
            est.append(f"narrowest transition at {math.degrees(target.amplitude):.1f} deg: "
                       + ("none up to 8 spacings" if wm is None else f"{wm:.3g} L") + f", asked {r['width']:.3g} L")
            if wm is not None and r["width"] < wm:
                hint = f"Widen the pattern to about {wm:.3g} L or more, lower the target angle, or move the control " \
                       "points away from the cilia"
        est_s = f" (estimated on this carpet: {'; '.join(est)})" if est else ""
        msg = (f"{scene.source_name}: the cilia cannot make this target: rms residual {d.residual_rms:.3g} "
               f"{unit} exceeds [target] residual = {target.residual:g}{est_s}; worst control points {lst}. {hint}")
        if strict:
            raise DesignError(msg)
        warnings.warn(msg + " (strict = false: returning the closest flow the cilia make)", UserWarning,
                      stacklevel=2)
        d = _replace(d, message=d.message + f"; target NOT met ([target] residual = {target.residual:g}): the "
                     f"closest flow the cilia make; worst control points {lst}")
    else:
        d = _replace(d, message=d.message + f"; target met ([target] residual = {target.residual:g})")
    d = _replace(d, threshold=float(target.residual))
    if target.sigma > 0:
        d = _replace(d, tolerance=tolerance_study(d.carpet, d, target.sigma, target.samples).summary())
    return d, d.carpet


def _replace(d: Design, **kw) -> Design:
    return replace(d, **kw)
