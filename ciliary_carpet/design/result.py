"""The result of a design: :class:`Design` (the layout, how well its mean flow meets the target,
what it cost) and :class:`DesignError`."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ciliary_carpet.carpet.carpet import Carpet

__all__ = ["Design", "DesignError"]


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
    over the floor's reference speed (:func:`~ciliary_carpet.design.model.floor_reference`; angle targets; NaN for velocity targets); local_rms: the
    rms residual of the local (starting) layout; returned: which iterate is returned ("local"
    or "pass k"); objective, local_objective: the design objective J (:mod:`ciliary_carpet.design.inverse`) on the
    full model's flow of the returned and of the local layout (objective <= local_objective:
    the never-worse guarantee); near_cutoff: indices of cilia whose thrust is below
    :data:`~ciliary_carpet.design.inverse.NEAR_CUTOFF_FRACTION` of the straight filament's; clipped: indices of cilia whose
    request was clipped to the reachable range; status: ``"success"`` (L-BFGS-B converged on the
    design model) or ``"inaccurate"`` (it stopped early: the message says why), the words of the
    other results of the toolkit (:class:`single_cilium.cycle.LimitCycle`); message; work:
    iterations, evaluations, full-model checks, seconds (wall clock; of which seconds_carpets
    building the carpets of the checked layouts, seconds_checks their full-model evaluations,
    seconds_model the L-BFGS-B solves on the design model); tolerance: the fabrication-tolerance
    study (``None`` unless asked, see :func:`~ciliary_carpet.design.tolerance.tolerance_study`); reachability: what the carpet
    can make (:func:`~ciliary_carpet.design.reachability.reachability`; angle targets of :func:`~ciliary_carpet.design.inverse.design`); carpet: the carpet with the
    returned layout, on which the residual was measured; threshold: the target's acceptance
    threshold on residual_rms (``[target] residual``; given to :func:`~ciliary_carpet.design.inverse.design_layout`, which then
    makes residual_error at most half of it by a final full-model check at a tolerance chosen
    for it, ``work["final_tol"]``); inside_swept: the control points that lie inside a cilium's
    swept region (``count``, ``indices`` into the control points as given, ``action`` "use",
    "downweight" or "drop", ``weight``); weights (P,): the control points' weights in the
    objective and in residual_rms (None: all 1; "downweight" gives the inside points
    :data:`~ciliary_carpet.design.inverse.INSIDE_WEIGHT`), residual_rms = sqrt(sum w_k r_k^2 / sum w_k);
    azimuth (N,) and height: a standing carpet's beat-plane azimuths psi [rad] and the height of its
    surface-flow plane (:mod:`~ciliary_carpet.design.surface`; None for a planar carpet), whose
    targets and flows are then absolute directions and velocities in the plane z = height. The
    arrays are copies of those given, read-only."""

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
    azimuth: np.ndarray | None = None
    height: float | None = None

    _ARRAYS = ("chi_N", "control", "target", "achieved", "residual", "speed_ratio", "weights", "azimuth")

    def __post_init__(self) -> None:
        """The arrays are the design's own: copies of what it is given, read-only."""
        for k in self._ARRAYS:
            v = getattr(self, k)
            if v is not None:
                a = np.array(v, dtype=float)
                a.flags.writeable = False
                object.__setattr__(self, k, a)

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
        if self.azimuth is not None:
            out["geometry"] = "standing"
            out["surface_height"] = self.height
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
        if self.azimuth is not None:
            ds["azimuth"] = ("cilium", self.azimuth, {"long_name": "beat-plane azimuth psi of a standing cilium "
                                                      "(anticlockwise from +x)", "units": "rad"})
            ds.attrs["geometry"] = "standing"
            ds.attrs["surface_height"] = float(self.height)
        if self.speed_ratio is not None:
            ds["speed_ratio"] = ("control", self.speed_ratio, {"long_name": "speed along the target over the "
                                                               "local layout's", "units": "1"})
        return ds

