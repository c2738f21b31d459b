"""A carpet of cilia under one uniform field, and the Stokes flow it drives.

Model (MODEL.md section 6)
--------------------------
Every cilium j is clamped at its base point b_j in the plane z = 0 and beats on the limit cycle
of its natural curvature chi_N_j, read from the :class:`~single_cilium.table.ThrustTable` of the
field (chi_E, eta). The field points along ``direction`` (radians, anticlockwise from +y); the
whole single-filament picture (field along e2) is rotated by it. Cilium j is at phase
``phi_j(t) = phases[j] + t / T(chi_N_j)`` (mod 1): each beats at its own period, so the carpet's
flow is in general quasi-periodic, and nothing here assumes a common period. The fluid velocity
is the superposition of the filaments' line distributions of Stokeslets,

    u(x, t) = 1/(8 pi mu) sum_j int_0^1 G(x, r_j(s, t)) f_j(s, t) ds,

with f = -d the force per length on the fluid (the table's fx, fy) and G the regularised
Stokeslet of blob size ``blob`` (the filament radius; :mod:`ciliary_carpet.stokes.kernel`), so that the
velocity stays bounded on and between the filaments and tracers pass through the carpet; away
from a filament it differs from the singular Stokeslet I/|R| + R R^T/|R|^3 by O(blob^2/|R|^3). The arc length integral is
the composite Simpson rule on the table's uniform s grid; the phase dependence is the
trigonometric interpolant of the table's uniform phase samples (spectral: the cycle is smooth).
With ``wall=h`` a no-slip plane lies at z = -h (the regularised image system of Ainley et al.
2008; Blake's for ``blob=None``). The model ignores
contact and hydrodynamic interaction between filaments (each beats as if alone); a base point
within the reach of another cilium's beat (:attr:`Carpet.reach`: the cilia can touch) is a
ValueError.

Evaluating the flow
-------------------
One front door: :meth:`Carpet.evaluate` ``(points, when, tol)`` with ``when`` an
:class:`Instant` ``(t)`` (the flow at time t) or :class:`CycleMean` ``()`` (each cilium's flow
averaged over its own cycle: the steady, time-averaged flow), returning a :class:`FlowSample`
(velocity, rigorous error bound, fidelity); :meth:`Carpet.velocity` is the same velocity
without the bound, for integrators that evaluate the flow many times. Per (cilium, point) pair
the cheapest representation whose error bound meets ``tol`` is summed (DESIGN.md "flow
fidelity"): point-force carriers of the cilium's moments (level ``point`` at an instant,
``mean`` for the cycle mean) or its resolved line distribution (``resolved``; for the mean flow
averaged over the phase samples); ``tol = 0`` sums everything resolved. The pieces, each built
once per carpet:

* :mod:`~ciliary_carpet.carpet.cycles` (:attr:`Carpet.cycles`): the cycle data, its interpolation
  in phase and its moments about the force centres;
* :mod:`~ciliary_carpet.carpet.carriers` (:attr:`Carpet.carriers`): the carriers of the cheap
  orders and their rigorous bounds (the bound, the calibration ``LOD_SLACK`` and what was measured);
* :mod:`~ciliary_carpet.carpet.plan` and :mod:`~ciliary_carpet.carpet.traversal`: the cost model, the grid and the ranged sums of each
  evaluation.

One concept over 500 lines: the carpet model, its checks and its front door to the flow.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from functools import cached_property


import numpy as np
from scipy.spatial import cKDTree

from single_cilium.checks import finite, positive
from single_cilium.table import TableError, ThrustTable

from ciliary_carpet.carpet.carriers import Carriers
from ciliary_carpet.carpet.coupling import COUPLINGS, couple
from ciliary_carpet.carpet.cycles import CycleData
from ciliary_carpet.carpet.geometry import GEOMETRIES, Embedding, Geometry
from ciliary_carpet.carpet.sums import CycleMean, FlowSample, FlowSums, Instant, When
from ciliary_carpet.stokes import Backend, Kernel, Wall, make_kernel

logger = logging.getLogger(__name__)

__all__ = ["Carpet", "Scales", "BLOB", "sbt_viscosity", "CycleMean", "FlowSample", "Instant", "When"]

BLOB = 0.02
"""Default blob size eps of the regularised Stokeslets, in units of L: the filament radius of a
slender filament of aspect ratio L / (2 a) = 25 (scene key ``[carpet] blob``)."""


def _frozen(a: np.ndarray | None) -> np.ndarray | None:
    """``a`` (an array the carpet owns) made read-only: a carpet's arrays are its model."""
    if a is not None:
        a.flags.writeable = False
    return a


def sbt_viscosity(eta: float, a: float, length: float = 1.0) -> float:
    """The fluid viscosity that slender-body theory assigns to the tangential resistive
    coefficient ``eta`` of a filament of radius ``a`` and length ``length`` (Gray & Hancock 1955,
    the filament's length as the cut-off; MODEL.md section 2 writes eta = mu_par L^4 / (tau B)):

        c_par = 2 pi mu / (ln(2 L / a) - 1/2)   =>   mu = eta (ln(2 L / a) - 1/2) / (2 pi),

    in the same units as eta (B tau / L^4): 0.653 eta for a = 0.02 L. A carpet's default
    viscosity (its flow then moves at the speed its filaments' drag implies)."""
    eta, a, length = float(eta), float(a), float(length)
    if not (math.isfinite(eta) and eta > 0 and math.isfinite(a) and 0 < a < length / 2):
        raise ValueError(f"sbt_viscosity needs eta > 0 and 0 < a < L / 2, got eta = {eta!r}, a = {a!r}, L = {length!r}")
    return eta * (math.log(2.0 * length / a) - 0.5) / (2.0 * math.pi)


@dataclass(frozen=True)
class Scales:
    """Physical scales for output in SI units: the filament length L [m], the relaxation time
    tau [s] and the fluid viscosity [Pa s]. Positions scale by L, times by tau, velocities by
    L/tau; a force per length f (model units B/L^3) by ``viscosity * L / (tau * mu)`` where
    ``mu`` is the carpet's dimensionless viscosity."""

    length_m: float
    time_s: float
    viscosity_Pa_s: float

    def __post_init__(self) -> None:
        for k in ("length_m", "time_s", "viscosity_Pa_s"):
            object.__setattr__(self, k, positive(f"Scales.{k}", getattr(self, k)))

    @property
    def velocity(self) -> float:
        return self.length_m / self.time_s


@dataclass(frozen=True, eq=False)
class Carpet:
    """Cilia clamped at ``bases`` under one uniform field, with the flow they make.

    Parameters
    ----------
    bases : (N, 2) base points in the plane z = 0 (units of L); see :mod:`ciliary_carpet.carpet.layout`.
    chi_N : (N,) signed natural curvatures, each within the table's range.
    table : the ThrustTable of the field (chi_E, eta).
    phases : (N,) phases at t = 0 in [0, 1) (default all 0); see :mod:`ciliary_carpet.carpet.layout`.
    direction : field direction, radians anticlockwise from +y (the scene rotates with it).
    viscosity : fluid viscosity of the Stokeslets in model units (B tau / L^4), or None (default):
        the one the filaments' drag implies, :func:`sbt_viscosity` ``(table.eta, blob or BLOB)``
        (0.653 eta for the default blob). The value used is :attr:`mu`; :attr:`mu_source` says
        where it came from (``"filaments"`` or ``"given"``).
    wall : distance h > 0 of a no-slip wall z = -h below the plane, or None (free space).
    scales : optional :class:`Scales` for output in SI units.
    backend : backend of the sums (:mod:`ciliary_carpet.stokes`); default Auto.
    blob : regularisation length eps of the Stokeslets (:data:`BLOB`, the filament radius), > 0
        and at most half the smallest distance between base points; None: singular Stokeslets
        (the flow is then unbounded at the filaments).
    background : (N, 2) or None: the uniform flow U_j each cilium beats in (L / tau), in each
        cilium's 2D frame, read from a table over the background flow
        (:class:`~ciliary_carpet.carpet.cycles.CycleData`; the table's ``U_perp`` across the field,
        ``U_par`` along it); None: each beats as in still fluid (the uncoupled model). Planar
        carpet: the lab frame's (x, y) in the plane z = 0 (the table reads ``rotation^T U_j``).
        Standing carpet: cilium j's beat plane, U_j = (u . e_psi_j, u . e_z) for a flow u in
        space, so that ``U_perp = U_j[0]`` (horizontal, along e_psi_j) and ``U_par = U_j[1]``
        (up, along the field); the flow's component along e_z x e_psi_j, normal to the beat
        plane, does not enter. A coupled carpet (:func:`~ciliary_carpet.carpet.coupling.couple`)
        sets it to the mean flow the other cilia make at each one, in the same frames; given
        with ``coupling = "mean"`` it is the solve's first guess (a solution for nearby
        curvatures: fewer Newton steps), replaced by the solution.
    geometry : ``"planar"`` (default: every filament in the plane z = 0, the field in it along
        ``direction``) or ``"standing"``: cilium j clamped at ``bases[j]`` on the substrate z = 0,
        the field along +z, its beat plane turned about the normal by ``azimuth[j]``
        (:mod:`~ciliary_carpet.carpet.geometry`). A standing carpet's ``wall`` is the distance
        h >= 0 of the no-slip wall below the clamps: 0 (the substrate itself, the device), or
        None for free space (cilia on a substrate the flow does not see: the comparison with a
        planar carpet).
    azimuth : (N,) beat-plane azimuths psi_j of a standing carpet (radians anticlockwise from +x;
        default all 0): cilium j's tangential thrust points along (cos psi_j, sin psi_j) for
        chi_N > 0, the other way for chi_N < 0. Planar carpets take none.
    coupling : ``"none"`` (default: each cilium beats in ``background``, still fluid when None) or
        ``"mean"``: each beats in the mean flow the other cilia make at it, solved self-consistently
        when the carpet is made (:func:`~ciliary_carpet.carpet.coupling.couple` at its default
        tolerances; needs a table over the background flow); ``background`` is then that solution
        (a given one is ignored: the same carpet with other curvatures is solved afresh) and
        :attr:`coupled` the solve's :class:`~ciliary_carpet.carpet.coupling.Coupling` (status,
        residual, history).

    The carpet keeps copies of the arrays it is given, read-only (``bases``, ``chi_N``,
    ``phases``, ``azimuth``, ``background``): changing the caller's arrays afterwards changes
    nothing here, and a carpet's own arrays cannot be changed in place. Cilia closer than the
    reach of their beat (:attr:`reach`) are a ValueError.

    Built once with it: :attr:`cycles` (:class:`~ciliary_carpet.carpet.cycles.CycleData`, the
    cilia's cycles and moments) and :attr:`carriers` (:class:`~ciliary_carpet.carpet.carriers.Carriers`,
    the levels of detail and their bounds). Cilia whose chi_N does not flutter stand still in
    their equilibrium shape and make no flow.
    """

    bases: np.ndarray
    chi_N: np.ndarray
    table: ThrustTable
    phases: np.ndarray | None = None
    direction: float = 0.0
    viscosity: float | None = None
    wall: float | None = None
    scales: Scales | None = None
    backend: Backend | None = None
    blob: float | None = BLOB
    background: np.ndarray | None = None
    coupling: str = "none"
    geometry: str = "planar"
    azimuth: np.ndarray | None = None
    cycles: CycleData = field(default=None, init=False, repr=False)
    carriers: Carriers = field(default=None, init=False, repr=False)
    sums: FlowSums = field(default=None, init=False, repr=False)
    mu: float = field(default=None, init=False)
    mu_source: str = field(default=None, init=False)
    coupled: object = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        b = np.array(self.bases, dtype=float)  # copies: the caller's arrays stay the caller's
        if b.ndim != 2 or b.shape[1] != 2 or b.shape[0] < 1:
            raise ValueError(f"bases must have shape (N, 2) with N >= 1, got {b.shape}")
        if not np.all(np.isfinite(b)):
            raise ValueError("bases contain NaN or inf")
        n = b.shape[0]
        c = np.broadcast_to(np.asarray(self.chi_N, dtype=float), (n,)).copy() if np.ndim(self.chi_N) == 0 \
            else np.array(self.chi_N, dtype=float)
        if c.shape != (n,):
            raise ValueError(f"chi_N must have shape ({n},) to match bases, got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("chi_N contains NaN or inf")
        p = np.zeros(n) if self.phases is None else np.array(self.phases, dtype=float)
        if p.shape != (n,) or not np.all(np.isfinite(p)):
            raise ValueError(f"phases must be {n} finite numbers, got shape {p.shape}")
        if not isinstance(self.table, ThrustTable):
            raise TypeError(f"table must be a ThrustTable, got {type(self.table).__name__}")
        object.__setattr__(self, "direction", finite("direction", self.direction))
        if self.viscosity is not None:  # None: from the filaments' drag
            object.__setattr__(self, "viscosity", positive("viscosity", self.viscosity))
        if self.geometry not in GEOMETRIES:
            raise ValueError(f"geometry must be one of {', '.join(GEOMETRIES)}, got {self.geometry!r}")
        where = self.placement
        psi = where.azimuths(self.azimuth, self.direction, n)
        if self.blob is not None:
            try:
                e = float(self.blob)
            except (TypeError, ValueError):
                raise ValueError(f"blob must be a positive length (or None), got {self.blob!r}") from None
            if not (math.isfinite(e) and e > 0):
                raise ValueError(f"blob must be a positive length in units of L (the filament radius), got {e}")
            if n > 1:
                gap = float(cKDTree(b).query(b, k=2)[0][:, 1].min())
                if e > 0.5 * gap:
                    raise ValueError(f"blob = {e:g} is larger than half the smallest spacing of the base points "
                                     f"({gap:g} L): the blobs of neighbouring filaments would overlap")
            object.__setattr__(self, "blob", e)
        where.check_wall(self.wall, self.filament_radius)
        if self.coupling not in COUPLINGS:
            raise ValueError(f"coupling must be one of {', '.join(COUPLINGS)}, got {self.coupling!r}")
        u = None
        if self.coupling == "mean":
            start = None if self.background is None else np.array(self.background, dtype=float)
            if start is not None and (start.shape != (n, 2) or not np.all(np.isfinite(start))):
                raise ValueError(f"background (the coupled solve's first guess) must be {n} finite flows, shape "
                                 f"({n}, 2), got shape {start.shape}")
            res = couple(self._first_guess(start))  # (its bases checked there; no reference kept here)
            for k in ("background", "mu", "mu_source", "blob", "cycles", "carriers", "sums", "bases", "chi_N",
                      "phases", "direction", "azimuth"):
                object.__setattr__(self, k, getattr(res.carpet, k))
            object.__setattr__(self, "coupled", res)
            return
        if self.background is not None:
            u = np.array(self.background, dtype=float)
            if u.shape != (n, 2) or not np.all(np.isfinite(u)):
                frame = "in each cilium's beat plane (along e_psi, e_z)" if psi is not None else "in the plane"
                raise ValueError(f"background must be {n} finite flows {frame}, shape ({n}, 2), got shape {u.shape}")
        object.__setattr__(self, "background", _frozen(u))
        object.__setattr__(self, "bases", _frozen(b))
        object.__setattr__(self, "chi_N", _frozen(c))
        object.__setattr__(self, "phases", _frozen(np.mod(p, 1.0)))
        object.__setattr__(self, "mu_source", "filaments" if self.viscosity is None else "given")
        object.__setattr__(self, "mu", sbt_viscosity(self.table.eta, self.filament_radius) if self.viscosity is None
                           else float(self.viscosity))
        object.__setattr__(self, "azimuth", _frozen(psi))
        fb, rot, emb = where.frames(self.bases, psi, self.rotation)
        cycles = CycleData(self.table, self.chi_N, fb, self.phases, rot, u, **({} if emb is None else {"embedding": emb}))
        where.check_cycles(cycles, self.chi_N)
        object.__setattr__(self, "cycles", cycles)
        object.__setattr__(self, "carriers", Carriers(cycles, self.kernel))
        object.__setattr__(self, "sums", FlowSums(cycles, self.carriers, self.kernel, self.backend, self.mu))
        self._check_spacing()

    def __getstate__(self) -> dict:
        """A pickled carpet (sent to a worker process) leaves what its sums kept behind (plans,
        carrier forces, blocks that can take hundreds of MB): they are remade where needed."""
        state = dict(self.__dict__)
        if self.cycles is not None:
            state["sums"] = FlowSums(self.cycles, self.carriers, self.kernel, self.backend, self.mu)
        return state

    @property
    def reach(self) -> np.ndarray:
        """(N,) how far each cilium's filament reaches from its base over its beat (L; in the plane
        for a planar carpet, horizontally for a standing one): its swept region's radius plus its
        centre's distance from the base (horizontal), at most the filament length 1."""
        c = self.cycles
        return self.placement.reach(c.centre, c.bases, c.radius)

    def _check_spacing(self) -> None:
        """ValueError when a base point lies within the reach of another cilium's beat
        (:attr:`reach`): those cilia can touch, which the model does not describe."""
        if self.n < 2:
            return
        reach = self.reach
        pairs = cKDTree(self.bases).query_pairs(float(reach.max()), output_type="ndarray")
        if pairs.size == 0:
            return
        d = np.linalg.norm(self.bases[pairs[:, 0]] - self.bases[pairs[:, 1]], axis=1)
        r = np.maximum(reach[pairs[:, 0]], reach[pairs[:, 1]])
        bad = np.nonzero(d < r)[0]
        if bad.size:
            k = bad[np.argmin(d[bad] - r[bad])]
            i, j = (int(x) for x in pairs[k])
            raise ValueError(f"cilia {i} and {j} stand {d[k]:.3g} L apart, within the {r[k]:.3g} L that their beat "
                             f"reaches from the base: their filaments can touch, which the model does not describe; "
                             f"the smallest spacing allowed is {float(reach.max()):.3g} L (the farthest reach of "
                             f"these cilia; the filament length 1 L is always enough)")

    # ------------------------------------------------------------------ geometry and state
    @property
    def placement(self) -> Geometry:
        """The carpet's geometry as an object (:data:`~ciliary_carpet.carpet.geometry.GEOMETRIES`
        of :attr:`geometry`): what differs between planar and standing carpets."""
        return GEOMETRIES[self.geometry]

    @property
    def n(self) -> int:
        """Number of cilia."""
        return self.bases.shape[0]

    @property
    def filament_radius(self) -> float:
        """The filaments' radius a (L): the blob, or :data:`BLOB` for singular Stokeslets (what
        the default viscosity and the omissions' slender-body formulas use)."""
        return float(self.blob) if self.blob is not None else BLOB

    @property
    def rotation(self) -> np.ndarray:
        """2x2 rotation from the field frame (field along e2) to the lab frame."""
        a = self.direction
        return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])

    @property
    def periods(self) -> np.ndarray:
        """(N,) beat period of each cilium (NaN for still ones)."""
        return self.cycles.period.copy()

    @property
    def flutter(self) -> np.ndarray:
        """(N,) whether each cilium beats (chi_N on the flutter branch)."""
        return self.cycles.flutter.copy()

    @property
    def centres(self) -> np.ndarray:
        """(N, 2) force centres c_j (centroid of the swept samples)."""
        return self.cycles.centre.copy()

    @property
    def radii(self) -> np.ndarray:
        """(N,) radius a_j of the swept region about c_j."""
        return self.cycles.radius.copy()

    @property
    def mean_thrust(self) -> np.ndarray:
        """(N, 2) cycle-mean force on the fluid in each cilium's 2D frame: the lab plane of a
        planar carpet (the table's thrust, rotated), the beat plane of a standing one (along
        e_psi, e_z); :attr:`embedding` maps it into space (:meth:`in_space`)."""
        return self.cycles.F_mean.copy()

    @property
    def embedding(self) -> Embedding:
        """The map of each cilium's 2D frame into space (:mod:`~ciliary_carpet.carpet.geometry`)."""
        return self.cycles.embedding

    def in_space(self, what: str, js=None) -> np.ndarray:
        """``"centres"`` (N, 3): the force centres, or ``"mean_thrust"`` (N, 3): the cycle-mean
        forces on the fluid, of cilia ``js`` (default all), in space."""
        js = np.arange(self.n) if js is None else np.asarray(js, dtype=np.int64).reshape(-1)
        if what == "centres":
            return self.cycles.centre3[js].copy()
        if what == "mean_thrust":
            return self.embedding.vectors(self.cycles.F_mean[js], js)
        raise ValueError(f"in_space knows 'centres' and 'mean_thrust', got {what!r}")

    def state_in_space(self, t: float, js=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`state` mapped into space: positions (N, n_s, 3), forces per length on the fluid
        (N, n_s, 3) and phases (N,) at time t (of cilia ``js``)."""
        pos, frc, ph = self.cycles.state(t, js)
        return self.embedding.points(pos, js), self.embedding.vectors(frc, js), ph

    @property
    def s(self) -> np.ndarray:
        """(n_s,) the arc-length samples of the filaments."""
        return self.cycles.s.copy()

    @cached_property
    def kernel(self) -> Kernel:
        """The Green's function of the flow: regularised (blob) or singular, free or with the wall."""
        return make_kernel(None if self.wall is None else Wall(z=-float(self.wall)), self.blob or 0.0)

    def filament_distance(self, points, t: float) -> np.ndarray:
        """(M,) distance of ``points`` (M, 2) or (M, 3) from the nearest filament at time ``t``
        (to the sampled centre lines, the table's s grid; in-plane for a planar carpet, in
        space for a standing one)."""
        return self.placement.filament_distance(self, points, t)

    def phase_at(self, t: float) -> np.ndarray:
        """(N,) phase of every cilium at time t, in [0, 1)."""
        return self.cycles.phase_at(t)

    def state(self, t: float, js=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shapes and forces of all cilia (or of cilia ``js``) at time t.

        Returns positions (N, n_s, 2) (lab frame), force per length on the fluid (N, n_s, 2),
        and the phases (N,) (N = len(js) with ``js``)."""
        return self.cycles.state(t, js)

    def beat_velocity(self, t, js=None) -> np.ndarray:
        """Velocity d r_j / dt (s, t) of the filaments ``js`` (default all) at time ``t`` (a
        number, or one per cilium of ``js``): (len(js), n_s, 2), lab frame, in L / tau. The
        exact time derivative of the phase interpolant that :meth:`state` evaluates (its
        harmonics times 2 pi k / T_j); zero for still cilia."""
        return self.cycles.beat_velocity(t, js)

    def cycle_samples(self, js) -> tuple[np.ndarray, np.ndarray]:
        """Positions and forces per length of cilia ``js`` at the table's phase samples:
        (len(js), n_phase, n_s, 2) each, lab frame."""
        return self.cycles.samples(js)

    def in_swept_region(self, points, j: int, margin: float = 0.0) -> np.ndarray:
        """Whether points (M, 2) (planar carpets: in the plane) or (M, 3) (in space: within
        ``margin`` of cilium j's frame and, projected on it, in the region) lie in the convex
        hull of cilium j's swept region grown by ``margin`` (conservative: the hull covers the
        region)."""
        p = np.asarray(points, dtype=float)
        if p.ndim == 2 and p.shape[1] == 3:
            e = self.embedding
            rel = p - e.origin[j]
            q = rel @ e.axes[j]  # (M, 2) in cilium j's frame
            off = np.linalg.norm(rel - q @ e.axes[j].T, axis=1)
            return (off <= margin) & self.cycles.in_swept_region(q, j, margin)
        return self.cycles.in_swept_region(p, j, margin)

    # ------------------------------------------------------------------ flow
    def evaluate(self, points, when: When, tol: float = 1e-3) -> FlowSample:
        """Fluid velocity at ``points`` (M, 2) or (M, 3) [L; (M, 2) means z = 0], at an
        :class:`Instant` ``(t)`` [tau] or the :class:`CycleMean` ``()``, each pair of a cilium and
        a point summed at the cheapest level of detail whose bound meets ``tol`` (relative to the
        carpet's far-field flow; 0: everything resolved), with the rigorous bound of the result
        (module docstring; :mod:`~ciliary_carpet.carpet.carriers`). Returns a :class:`FlowSample`
        (velocities and bounds in L / tau)."""
        return self.sums.evaluate(self.targets(points), when, self._tol(tol))

    def velocity(self, points, when: When, tol: float = 1e-3, precision: str = "fp64") -> np.ndarray:
        """(M, 3) the velocity of :meth:`evaluate` without its error bound (which costs a pass over
        every pair of a point and a cilium): for integrators that evaluate the flow many times.
        ``precision="fp32"`` sums the far cilia's carriers in single precision on the CPU
        (:func:`~ciliary_carpet.stokes.dispatch.in_fp32`; their rounding error,
        :func:`~ciliary_carpet.stokes.precision.fp32_error_bound`, is some 1e-7 of the velocity, far
        inside the levels of detail's ``tol``); the resolved near field stays in fp64."""
        if precision not in ("fp64", "fp32"):
            raise ValueError(f"precision must be 'fp64' or 'fp32', got {precision!r}")
        return self.sums.sum(self.targets(points), when, self._tol(tol), precision=precision)[0].velocity

    def _first_guess(self, start: np.ndarray | None) -> "Carpet":
        """The uncoupled carpet in the flows ``start`` (the coupled solve's first guess), or in
        still fluid when there is none or the table does not serve it."""
        try:
            return replace(self, coupling="none", background=start)
        except TableError:
            return replace(self, coupling="none", background=None)

    def others_mean_flow(self, js=None, tol: float = 1e-4) -> np.ndarray:
        """(len(js), 3) the cycle-mean flow that all the *other* cilia make at the force centres
        c_j of cilia ``js`` (default all), in space (lab frame, L / tau): the carpet's
        :class:`CycleMean` flow at c_j (:meth:`velocity` at ``tol``) minus cilium j's own
        cycle-averaged resolved line (the same kernel, blob, wall and weights as the carpet's
        resolved mean: the carpet resolves a cilium at its own centre, so the subtraction removes
        exactly that term, to rounding). The centres are :attr:`CycleData.centre3
        <ciliary_carpet.carpet.cycles.CycleData.centre3>`: in the plane z = 0 for a planar carpet,
        in each beat plane above the substrate for a standing one. The background flow a coupled
        cilium feels is its in-frame part (:mod:`~ciliary_carpet.carpet.coupling`)."""
        js = np.arange(self.n) if js is None else np.asarray(js, dtype=np.int64).ravel()
        return self.sums.others_mean_flow(js, self._tol(tol))

    def prepare(self, times, tol: float = 1e-3, precision: str = "fp64") -> None:
        """Say that the flow will be evaluated at the instants ``times`` (a few) with ``tol``
        (:meth:`velocity`): their carriers' forces are made together, in one read of the moments'
        coefficients for all of them (an integrator's stages); the resolved sources of a cilium near the points are made the first
        time an evaluation at one of these instants needs them, for all of them at once, and kept
        (:class:`~ciliary_carpet.carpet.blocks.InstantBlocks`: reading a cilium's coefficients is
        most of what making its sources costs). The instants kept before are dropped and their
        buffers reused. Optional: an evaluation at an instant not prepared makes its own; the
        velocities are the same to the bit either way. ``precision``: that of the evaluations
        (:meth:`velocity`)."""
        tol = self._tol(tol)
        if tol == 0:
            return
        ts = np.unique(np.asarray(times, dtype=float).ravel())
        if not np.all(np.isfinite(ts)):
            raise ValueError("prepare: times must be finite")
        self.sums.prepare(ts, tol, precision)

    def targets(self, points) -> np.ndarray:
        """(M, 3) the points ``points`` (M, 2) or (M, 3) [L] checked (finite, above the wall) and
        placed in space (:meth:`Geometry.targets <ciliary_carpet.carpet.geometry.Geometry.targets>`):
        where :meth:`evaluate` and :meth:`velocity` take the flow."""
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] not in (2, 3):
            raise ValueError(f"points must have shape (M, 2) or (M, 3), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("points contain NaN or inf")
        p = self.placement.targets(p)
        if self.wall is not None and np.any(p[:, 2] < -self.wall):
            raise ValueError(f"points lie below the wall at z = {-self.wall:g}")
        return np.ascontiguousarray(p)

    @staticmethod
    def _tol(tol) -> float:
        t = float(tol)
        if not 0 <= t < 1:
            raise ValueError(f"tol must be in [0, 1), got {tol!r}")
        return t
