"""Inverse design: a signed chi_N for every cilium so that the carpet's mean flow matches a target.

Model. The design works on the steady (cycle-averaged) flow at control points x_k, represented
by one Stokeslet of the mean thrust per cilium at its force centre c_j (the ``mean`` level of
:mod:`ciliary_carpet.carpet` without its dipole; the control points lie between the cilia, where
that is what dominates):

    u_k(chi) = 1/(8 pi mu) sum_j G(x_k - c_j) Rot Fbar(chi_j),

linear in the thrusts, and the thrusts smooth in chi_N through the table's cubic splines
(:meth:`~single_cilium.table.ThrustTable.scalar`, with their analytic chi_N derivatives). The
objective is

* angle targets (a deflection angle delta_k at each control point; desired flow direction
  t_k = d0 rotated by delta_k, d0 the straight filaments' flow direction):
  J = 1/(2P) sum_k |u_k/|u_k| - t_k|^2  (scale-free: only directions are asked for);
* velocity targets U_k: J = 1/2 sum_k |u_k - U_k|^2 / sum_k |U_k|^2.

Its gradient is exact: dJ/dchi_j = sum_k (dJ/du_k) . G(x_k - c_j) Rot Fbar'(chi_j) / (8 pi mu),
evaluated matrix-free as one more Stokeslet sum with sources and targets swapped (G, and Blake's
tensor by the reciprocal theorem, are symmetric under that swap), so each evaluation costs two
O(P N) kernel sums and no P x N matrix is formed. scipy.optimize's L-BFGS-B solves it with
|chi_j| bounded by the flutter branch. The force centres depend weakly on chi_N; they are frozen
during one solve and updated between solves (``outer`` passes). The reported residual is
measured on the full carpet's mean flow (:meth:`Carpet.evaluate_mean`, all levels of detail
within ``tol``), not on the design model.
"""
from __future__ import annotations

import logging
import math
import time as _time
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize

from single_cilium.table import ThrustTable

from .carpet import Carpet
from .stokeslet import Wall, stokeslet_velocity
from .target import Frame, Target, control_points, reachable_check

logger = logging.getLogger(__name__)

__all__ = ["design", "design_layout", "carpet_with", "Design", "DesignError"]


class DesignError(ValueError):
    """A target the cilia cannot make (listed in the message), or a design that did not converge."""


@dataclass(frozen=True)
class Design:
    """A designed curvature layout and how well its mean flow meets the target.

    chi_N (N,): signed natural curvatures; control (P, 2): control points; target (P, 2): target
    flow direction (unit vectors, angle targets) or velocity; achieved (P, 2): the carpet's mean
    flow there (measured with the full flow model); residual (P,): per control point, the angle
    error in radians (angle targets) or |u - U| / rms|U| (velocity targets); residual_rms:
    the root mean square of those; kind: "angle" or "velocity"; clipped: indices of cilia
    whose request was clipped to the reachable range; status 0 converged, 1 not; message;
    work: iterations, evaluations, seconds."""

    chi_N: np.ndarray
    control: np.ndarray
    target: np.ndarray
    achieved: np.ndarray
    residual: np.ndarray
    residual_rms: float
    kind: str
    clipped: tuple = ()
    status: int = 0
    message: str = ""
    work: dict = field(default_factory=dict)

    def to_dataset(self, carpet: Carpet):
        """The layout as an xarray Dataset (dims cilium, control; CF attributes)."""
        import xarray as xr

        th = carpet.table.scalar("thrust_angle", self.chi_N)
        ds = xr.Dataset(
            {"x": ("cilium", carpet.bases[:, 0], {"long_name": "base point x", "units": "L"}),
             "y": ("cilium", carpet.bases[:, 1], {"long_name": "base point y", "units": "L"}),
             "chi_N": ("cilium", self.chi_N, {"long_name": "natural curvature chi_N = L kappa_N", "units": "1"}),
             "thrust_angle": ("cilium", th, {"long_name": "deflection of the mean thrust from the straight "
                                             "filament's (anticlockwise)", "units": "rad"}),
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
                   "target_kind": self.kind, "residual_rms": self.residual_rms, "status": self.status,
                   "message": self.message, "clipped": np.asarray(self.clipped, dtype=np.int64)})
        return ds


def _unit(a: np.ndarray) -> np.ndarray:
    return np.column_stack([np.cos(a), np.sin(a)])


def design_layout(carpet: Carpet, control, *, angles=None, velocities=None, cilium_angles=None, clip: bool = False,
                  tol: float = 1e-3, regularization: float = 1e-2, outer: int = 4, gtol: float = 1e-10,
                  maxiter: int = 500) -> Design:
    """Choose chi_N for the cilia of ``carpet`` (its bases, phases, field and table are kept;
    its chi_N is only the starting guess when ``angles`` is None) so that the mean flow at
    ``control`` (P, 2) points along the deflection ``angles`` (P,) [rad, anticlockwise from the
    straight filaments' flow direction] or equals ``velocities`` (P, 2) (lab frame).

    With angle targets, each cilium starts from the chi_N whose own thrust has the deflection
    ``cilium_angles`` (default: the angle asked at the control point nearest its force centre);
    a cilium whose request lies outside the table's reachable angles is an error (TargetError
    listing them) or, with ``clip=True``, clipped to the range with a warning. ``regularization`` adds
    lambda/N sum_j ((chi_j - chi0_j)/chi_max)^2 to J: the problem is not unique (many layouts
    make nearly the same directions), and this keeps the design near the local one, each cilium
    pointing where it is asked, unless departing from it buys a better match.
    Returns a :class:`Design`; the carpet with the designed chi_N is ``carpet_with(design, carpet)``."""
    clock = _time.perf_counter()
    t: ThrustTable = carpet.table
    X = np.asarray(control, dtype=float)
    if X.ndim != 2 or X.shape[1] != 2 or X.shape[0] < 1:
        raise ValueError(f"control points must have shape (P, 2), got {X.shape}")
    if not np.all(np.isfinite(X)):
        raise ValueError("control points contain NaN or inf")
    if (angles is None) == (velocities is None):
        raise ValueError("give exactly one of angles (P,) or velocities (P, 2)")
    rot = carpet.rotation
    d0 = rot @ np.array([0.0, -1.0])  # the straight filaments' flow direction, lab frame
    base_angle = math.atan2(d0[1], d0[0])
    b0, b1 = t.flutter_range
    lo_a, hi_a = t.thrust_angle_range()
    clipped: list[int] = []
    if angles is not None:
        A = np.broadcast_to(np.asarray(angles, dtype=float), (X.shape[0],)).copy()
        if not np.all(np.isfinite(A)):
            raise ValueError("target angles contain NaN or inf")
        kind = "angle"
        target = _unit(base_angle + A)
        # starting guess: each cilium takes the angle asked at its nearest control point
        from scipy.spatial import cKDTree

        want = A[cKDTree(X).query(carpet.centres)[1]] if cilium_angles is None else \
            np.broadcast_to(np.asarray(cilium_angles, dtype=float), (carpet.n,)).copy()
        want, bad = reachable_check(want, (lo_a, hi_a), clip, what="cilium", points=carpet.bases)
        clipped = np.nonzero(bad)[0].tolist()
        chi0 = np.array([t.chi_N_for_angle(a) for a in want])
    else:
        U = np.asarray(velocities, dtype=float)
        if U.shape != X.shape:
            raise ValueError(f"velocities must have shape {X.shape}, got {U.shape}")
        if not np.all(np.isfinite(U)):
            raise ValueError("target velocities contain NaN or inf")
        kind = "velocity"
        target = U
        chi0 = np.clip(carpet.chi_N, -b1, b1)
    X3 = np.column_stack([X, np.zeros(X.shape[0])])
    wall = None if carpet.wall is None else Wall(z=-float(carpet.wall))
    mu, backend = carpet.mu, carpet.backend
    P = X.shape[0]
    scaleU = float(np.sum(target ** 2)) if kind == "velocity" else 1.0
    if kind == "velocity" and scaleU == 0:
        raise ValueError("target velocities are all zero")
    n_eval = n_iter = 0
    chi = chi0.copy()
    res = None

    def thrust(c, nu=0):
        F = np.column_stack([t.scalar("thrust_x", c, nu), t.scalar("thrust_y", c, nu)])
        return F @ rot.T

    def model(c, C3):
        F = thrust(c)
        return stokeslet_velocity(X3, C3, np.column_stack([F, np.zeros(len(c))]), mu, wall=wall,
                                  backend=backend)[:, :2]

    def residual(u):
        if kind == "angle":
            return np.abs(np.angle((u[:, 0] + 1j * u[:, 1]) * np.conj(target[:, 0] + 1j * target[:, 1])))
        return np.linalg.norm(u - target, axis=1) / math.sqrt(scaleU / P)

    goal = target.copy()
    best = None
    for _ in range(max(1, outer)):
        C3 = np.column_stack([_centres(carpet, chi), np.zeros(len(chi))])

        def fun(c):
            nonlocal n_eval
            n_eval += 1
            u = model(c, C3)
            if kind == "angle":
                nrm = np.maximum(np.linalg.norm(u, axis=1), 1e-300)
                uh = u / nrm[:, None]
                r = uh - goal
                J = 0.5 * float(np.sum(r ** 2)) / P
                g_u = (r - uh * np.sum(uh * r, axis=1)[:, None]) / nrm[:, None] / P
            else:
                r = u - goal
                J = 0.5 * float(np.sum(r ** 2)) / scaleU
                g_u = r / scaleU
            # adjoint: sum_k G(x_k - c_j)^T g_k = Stokeslet sum from the control points to the centres
            gF = stokeslet_velocity(C3, X3, np.column_stack([g_u, np.zeros(P)]), mu, wall=wall,
                                    backend=backend)[:, :2]
            dc = (c - chi0) / b1
            J += regularization * float(np.sum(dc ** 2)) / len(c)
            return J, np.sum(gF * thrust(c, 1), axis=1) + 2 * regularization * dc / (b1 * len(c))

        res = minimize(fun, chi, jac=True, method="L-BFGS-B", bounds=[(-b1, b1)] * len(chi),
                       options={"gtol": gtol, "ftol": 1e-15, "maxiter": maxiter})
        n_iter += int(res.nit)
        chi = res.x
        # defect correction: measure the full flow model, shift the design model's goal by its error
        u_full = _with_chi(carpet, chi).evaluate_mean(X, tol=tol, error=False).velocity[:, :2]
        resid = residual(u_full)
        rms = float(np.sqrt(np.mean(resid ** 2)))
        if best is None or rms < best[0]:
            best = (rms, chi.copy(), u_full, resid, res)
        u_mod = model(chi, C3)
        if kind == "angle":
            shift = np.angle((u_mod[:, 0] + 1j * u_mod[:, 1]) * np.conj(u_full[:, 0] + 1j * u_full[:, 1]))
            g = (goal[:, 0] + 1j * goal[:, 1]) * np.exp(1j * shift)
            goal = np.column_stack([g.real, g.imag])
        else:
            goal = goal + (u_mod - u_full)
    rms, chi, u, resid, res = best
    status = 0 if res.success else 1
    message = (f"{kind} target at {P} control points: rms residual {rms:.3g}"
               f"{' rad' if kind == 'angle' else ' (relative)'}, worst {float(resid.max()):.3g}; "
               f"L-BFGS-B {'converged' if res.success else 'stopped: ' + str(res.message)}")
    logger.info("design: %s", message)
    return Design(chi_N=chi, control=X, target=target, achieved=u, residual=resid, residual_rms=rms, kind=kind,
                  clipped=tuple(clipped), status=status, message=message,
                  work={"iterations": n_iter, "evaluations": n_eval, "seconds": _time.perf_counter() - clock})


def _centres(carpet: Carpet, chi: np.ndarray) -> np.ndarray:
    """Force centres (N, 2) of the carpet's cilia if they had curvatures ``chi``: the centroid of
    the swept samples, from the table in chunks (no Carpet is built)."""
    out = np.empty((len(chi), 2))
    for lo in range(0, len(chi), 512):
        sl = slice(lo, lo + 512)
        cyc = carpet.table.cycles(chi[sl])
        xy = np.stack([np.nanmean(cyc["x"], axis=(1, 2)), np.nanmean(cyc["y"], axis=(1, 2))], axis=-1)
        xy = np.where(np.isfinite(xy), xy, 0.0)  # still filaments: their base (they make no flow)
        out[sl] = carpet.bases[sl] + xy @ carpet.rotation.T
    return out


def _with_chi(carpet: Carpet, chi: np.ndarray) -> Carpet:
    """The same carpet with other curvatures (no overlap warning: the bases did not move)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return Carpet(carpet.bases, chi, carpet.table, carpet.phases, carpet.direction, carpet.mu, carpet.wall,
                      carpet.scales, carpet.backend)


def carpet_with(design: Design, carpet: Carpet) -> Carpet:
    """``carpet`` with the designed chi_N."""
    return _with_chi(carpet, design.chi_N)


def scene_carpet(scene, table: ThrustTable | None = None, chi_N=None) -> Carpet:
    """The carpet a scene describes (its own chi_N unless ``chi_N`` is given)."""
    table = table if table is not None else scene.load_table()
    bases = scene.carpet.bases()
    return Carpet(bases, scene.carpet.chi_N if chi_N is None else chi_N, table,
                  scene.carpet.initial_phases(bases), direction=scene.field.direction_rad, wall=scene.carpet.wall,
                  scales=None if scene.units is None else scene.units.scales())


def design(scene, table: ThrustTable | None = None) -> tuple[Design | None, Carpet]:
    """Design the scene's carpet for its target: returns (Design, the designed Carpet), or
    (None, the scene's carpet) when the scene has no target.

    The target's control points and angles (or velocities) come from :mod:`ciliary_carpet.target`;
    the per-cilium request is the pattern evaluated at each cilium. A design whose rms residual
    exceeds ``[target] residual`` is a DesignError listing the worst control points (with
    ``clip = true``: a warning, and the best design is returned)."""
    table = table if table is not None else scene.load_table()
    carpet = scene_carpet(scene, table)
    target = Target.from_scene(scene, table)
    if target.kind == "none":
        return None, carpet
    frame = Frame.from_scene(scene, carpet.bases)
    if target.is_angle:
        X = control_points(carpet.bases, frame, target.control)
        d = design_layout(carpet, X, angles=target.deflection(X, frame),
                          cilium_angles=target.deflection(carpet.centres, frame), clip=target.clip,
                          tol=scene.tolerance)
    else:
        X, U = target.velocities()
        d = design_layout(carpet, X, velocities=U, clip=target.clip, tol=scene.tolerance)
    if d.residual_rms > target.residual:
        worst = np.argsort(d.residual)[::-1][:5]
        unit = "rad" if d.kind == "angle" else "relative"
        lst = ", ".join(f"#{k} at ({X[k, 0]:.3g}, {X[k, 1]:.3g}): {d.residual[k]:.3g} {unit}" for k in worst)
        msg = (f"{scene.source_name}: the cilia cannot make this target: rms residual {d.residual_rms:.3g} "
               f"{unit} exceeds [target] residual = {target.residual:g}; worst control points {lst}. "
               "Lower the target angle, widen the pattern, or move the control points away from the cilia")
        if not target.clip:
            raise DesignError(msg)
        warnings.warn(msg + " (clip = true: keeping the best design)", UserWarning, stacklevel=2)
    return d, carpet_with(d, carpet)
