"""The sums of one carpet's flow, and what they keep between calls.

A :class:`~ciliary_carpet.carpet.carpet.Carpet` is the model: its cilia, their cycles
(:class:`~ciliary_carpet.carpet.cycles.CycleData`) and the levels of detail with their bounds
(:class:`~ciliary_carpet.carpet.carriers.Carriers`), all fixed when it is made. :class:`FlowSums`
evaluates the model's flow at points,

    u(x, t) = 1/(8 pi mu) sum_j int_0^1 G(x, r_j(s, t)) f_j(s, t) ds,

at an :class:`Instant` or over the :class:`CycleMean`, each (cilium, point) pair at the cheapest
level of detail whose bound meets the tolerance, and keeps what makes the next call cheaper:

* the plans (:class:`~ciliary_carpet.carpet.plan.Plan`, one per kind of flow and tolerance:
  each cilium's order and distances);
* the carriers' forces (the cycle mean's for as long as its plan, a few instants' at a time,
  :meth:`FlowSums.prepare`);
* the resolved line sources of cilia near the points (:class:`~ciliary_carpet.carpet.blocks.MeanBlocks`,
  :class:`~ciliary_carpet.carpet.blocks.InstantBlocks`).

Nothing kept changes a number: an evaluation gives the same velocities to the bit whatever was
kept before. A pickled carpet leaves its sums behind (they are remade where needed).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar, Union

import numpy as np

from ciliary_carpet.carpet.blocks import InstantBlocks, MeanBlocks, ResolvedSources
from ciliary_carpet.carpet.bounds import Bounds
from ciliary_carpet.carpet.carriers import CarrierForces, Carriers
from ciliary_carpet.carpet.cycles import CycleData
from ciliary_carpet.carpet.instants import InstantCarriers, MomentRows, moment_rows
from ciliary_carpet.carpet.plan import Plan, make_plan
from ciliary_carpet.carpet.traversal import Summed, dense_sum, flow_sum
from ciliary_carpet.stokes import Auto, Backend, Direct, Kernel, in_fp32, stokeslet_velocity_ranges

__all__ = ["FlowSums", "FlowSample", "Instant", "CycleMean", "When"]

_AUTO = Auto()
"""The backend of a carpet made without ``backend``."""
_FP32 = Direct("fp32")  # what in_fp32 gives where the sums may run in fp32
_PLANS = 32
"""Plans (one per kind of flow and tolerance) kept before they are all forgotten."""
_INSTANTS = 8
"""Instants whose carrier forces are kept (:meth:`FlowSums.prepare`)."""
_ROWS = 4
"""Plans whose :class:`~ciliary_carpet.carpet.instants.MomentRows` are kept."""
_OWN_CHUNK = 512
"""Cilia whose own cycle-averaged lines are summed at once in :meth:`FlowSums.others_mean_flow`."""


@dataclass(frozen=True)
class FlowSample:
    """Velocities at points with their error bound and the fidelity used.

    velocity (M, 3) in L / tau (the model's units: lengths in cilium lengths L, times in the
    filament's relaxation time tau), lab frame (x, y in the carpet's plane for a planar carpet,
    z up from the substrate for a standing one); error_bound (M,) in L / tau: the rigorous bound
    of the levels of detail on ``|velocity - resolved sum|`` at each point (zero where every pair
    was resolved); pairs: number of (cilium, point) pairs
    evaluated at each level (``point`` or ``mean``, and ``resolved``); tol: the tolerance asked
    for; work: counters of the work done: ``sources``, the (point, source) interactions summed
    (the cost: each is one kernel evaluation), ``ranges``, the source ranges of the sparse sum
    (per point the runs of carriers and one block per resolved pair), and ``orders``, the cheap
    pairs per order (``monopole``, ``dipole``, ``quadrupole``)."""

    velocity: np.ndarray
    error_bound: np.ndarray
    pairs: dict
    tol: float
    work: dict = field(default_factory=dict)

    @property
    def fidelity(self) -> dict:
        """Fraction of the pairs evaluated at each level."""
        n = sum(self.pairs.values())
        return {k: (v / n if n else 0.0) for k, v in self.pairs.items()}


@dataclass(frozen=True)
class Instant:
    """The flow at time ``t`` (units of tau): cilium j at its phase phi_j(t), resolved at its line
    distribution there, its carriers holding its moments at that phase, their orders chosen by
    bounds that hold at every phase (:attr:`Carriers.over_cycle
    <ciliary_carpet.carpet.carriers.Carriers.over_cycle>`). Its cheap pairs count as level
    ``point``; the far cilia's order is chosen by cost."""

    t: float
    level: ClassVar[str] = "point"
    far: ClassVar[int | None] = None

    def __post_init__(self) -> None:
        try:
            t = float(self.t)
        except (TypeError, ValueError):
            raise ValueError(f"Instant.t must be a finite number, got {self.t!r}") from None
        if not math.isfinite(t):
            raise ValueError(f"Instant.t must be a finite number, got {self.t!r}")
        object.__setattr__(self, "t", t)

    def phases(self, cycles: CycleData) -> np.ndarray:
        """(N,) the cilia's phases at t (their resolved sources are taken there)."""
        return cycles.phase_at(self.t)

    def moments(self, cycles: CycleData, phases: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """F, D, T of every cilium at ``phases`` (:meth:`phases`)."""
        return cycles.moments_at(phases)

    def bounds(self, carriers: Carriers) -> Bounds:
        return carriers.over_cycle


@dataclass(frozen=True)
class CycleMean:
    """The cycle-mean (steady, time-averaged) flow: each cilium's flow averaged over its own cycle,
    resolved as the average over the table's phase samples, its carriers holding its cycle-mean
    moments (:attr:`Carriers.of_mean <ciliary_carpet.carpet.carriers.Carriers.of_mean>`). Its cheap
    pairs count as level ``mean``; the far cilia stay quadrupoles (:mod:`~ciliary_carpet.carpet.plan`)."""

    level: ClassVar[str] = "mean"
    far: ClassVar[int | None] = 2

    def phases(self, cycles: CycleData) -> None:
        """None: every phase sample, weighted 1 / n_phase."""
        return None

    def moments(self, cycles: CycleData, phases: None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cycle means of F, D, T."""
        return cycles.F_mean, cycles.D_mean, cycles.T_mean

    def bounds(self, carriers: Carriers) -> Bounds:
        return carriers.of_mean


When = Union[Instant, CycleMean]
"""What :meth:`Carpet.evaluate <ciliary_carpet.carpet.carpet.Carpet.evaluate>` evaluates: the flow
at an :class:`Instant` or the :class:`CycleMean`."""


class FlowSums:
    """The flow of one carpet's model at points, and the plans, carrier forces and resolved blocks
    it keeps between calls (module docstring).

    Parameters
    ----------
    cycles, carriers : the carpet's cycle data and levels of detail.
    kernel : the Green's function of the flow (free space or a wall; regularised or singular).
    backend : the backend of the sums, or None for :class:`~ciliary_carpet.stokes.Auto`.
    mu : the fluid viscosity (model units).

    Targets ``x`` are (M, 3) points in the lab frame, checked by the carpet; ``tol`` is in [0, 1).
    """

    def __init__(self, cycles: CycleData, carriers: Carriers, kernel: Kernel, backend: Backend | None,
                 mu: float) -> None:
        self.cycles, self.carriers, self.kernel, self.backend, self.mu = cycles, carriers, kernel, backend, mu
        self.plans: dict = {}
        self.forces: dict = {}
        self.mean_blocks = MeanBlocks(cycles)
        self.instant_blocks = InstantBlocks(cycles)
        self.rows: dict = {}

    @property
    def n(self) -> int:
        return self.cycles.n

    def evaluate(self, x: np.ndarray, when: When, tol: float) -> FlowSample:
        """The velocity at ``x`` with the rigorous bound of its levels of detail (a
        :class:`FlowSample`; :meth:`Carpet.evaluate <ciliary_carpet.carpet.carpet.Carpet.evaluate>`)."""
        s, plan, car = self.sum(x, when, tol, bound=True)
        bound = np.zeros(x.shape[0])
        if plan is not None and plan.order.size:
            bound = self.carriers.error_bound(x, plan.thresholds, when.bounds(self.carriers), car, self.mu)
        o = s.orders
        return FlowSample(velocity=s.velocity, error_bound=bound, pairs={when.level: int(o.sum()),
                                                                           "resolved": int(s.resolved)},
                          tol=tol, work=dict(sources=int(s.sources), ranges=int(s.ranges),
                                             orders=dict(monopole=int(o[0]), dipole=int(o[1]), quadrupole=int(o[2]))))

    def others_mean_flow(self, js: np.ndarray, tol: float) -> np.ndarray:
        """(len(js), 3) the cycle-mean flow the other cilia make at the force centres of cilia
        ``js`` (:meth:`Carpet.others_mean_flow <ciliary_carpet.carpet.carpet.Carpet.others_mean_flow>`):
        the whole carpet's mean flow there minus each cilium's own resolved mean line, summed
        with the same kernel, weights and blocks (so that the subtraction is exact to rounding)."""
        cen = np.ascontiguousarray(self.cycles.centre3[js])
        u = self.sum(cen, CycleMean(), tol)[0].velocity
        own = ResolvedSources(self.cycles, None, self.mean_blocks)
        blk = own.block
        for lo in range(0, js.size, _OWN_CHUNK):
            jc = js[lo:lo + _OWN_CHUNK]
            src, frc = np.empty((jc.size * blk, 3)), np.empty((jc.size * blk, 3))
            own.fill(jc, src, frc)
            i = np.arange(jc.size, dtype=np.int64)
            u[lo:lo + jc.size] -= stokeslet_velocity_ranges(cen[lo:lo + jc.size], src, frc,
                                                            np.arange(jc.size + 1, dtype=np.int64),
                                                            np.stack([i * blk, (i + 1) * blk], axis=1), self.mu,
                                                            kernel=self.kernel, backend=self.backend)
        return u

    def sum(self, x: np.ndarray, when: When, tol: float, bound: bool = False, precision: str = "fp64"
            ) -> tuple[Summed, Plan | None, CarrierForces | None]:
        """The sum at targets ``x`` (M, 3), its plan and the carriers' forces with the terms of
        the reported bound (``bound``; None for tol = 0 or without ``bound``), the carriers in
        ``precision`` (``"fp32"``: the far carriers in single precision where the sums run on
        the CPU, :meth:`precision`)."""
        if tol > 0 and not bound and isinstance(when, Instant):  # the phases of the cilia resolved only
            ph, sources = None, ResolvedSources(self.cycles, None, t=when.t, prepared=self.instant_blocks)
        else:
            ph = when.phases(self.cycles)
            sources = ResolvedSources(self.cycles, ph, self.mean_blocks)
        backend = self.backend if self.backend is not None else _AUTO
        precision = self.precision(precision)
        if tol == 0:  # the resolved sum itself: every source of every cilium that makes a flow
            js = np.nonzero(when.bounds(self.carriers).S > 0)[0]
            return dense_sum(x, js, sources, self.kernel, self.backend, self.mu), None, None
        key, plan = self.plan(when, tol)
        car = None
        if bound:  # the moments' carriers with the terms of the reported bound
            F, D, T = when.moments(self.cycles, ph)
            car = self.carriers.forces(F, D, T)
            forces = self.carriers.stacked(F, car, plan.order)
        else:
            forces = self._carrier_forces(when, key, plan, precision)
        s = flow_sum(x, plan, forces, sources, self.n, self.kernel, backend, self.mu,
                     grouped=not bound and isinstance(when, Instant), precision=precision)  # (the instants' carriers hold the groups')
        return s, plan, car

    def precision(self, precision: str) -> str:
        """The precision the far carriers' sums run in: ``"fp32"`` where it is asked for and the
        sums run on the CPU (:func:`~ciliary_carpet.stokes.dispatch.in_fp32`), else ``"fp64"``."""
        if precision == "fp32" and in_fp32(self.backend if self.backend is not None else _AUTO) == _FP32:
            return "fp32"
        return "fp64"

    def plan(self, when: When, tol: float) -> tuple[tuple, Plan]:
        """The key and the :class:`~.plan.Plan` of evaluations of ``when`` at ``tol`` (made once)."""
        key = (when.level, tol)
        if key not in self.plans:
            if len(self.plans) > _PLANS:
                self.plans.clear()
                self.forces.clear()
            self.plans[key] = make_plan(when.bounds(self.carriers).thresholds(tol), self.carriers, when.far,
                                        tol=tol if isinstance(when, Instant) else None)
        return key, self.plans[key]

    def instants(self, ph: np.ndarray, key: tuple, plan: Plan, spare: np.ndarray | None = None,
                 precision: str = "fp64") -> InstantCarriers:
        """The carriers of ``plan``'s cilia at the phases ``ph`` ((N,) or (T, N)) of instants (into
        ``spare``, a buffer of instants dropped, when it fits), their forces in ``precision``'s type."""
        kc = self.carriers.harmonics(key[1])
        return InstantCarriers(self.carriers, ph, plan.order, kc, eager=plan.far == 2,
                               out=spare, groups=None if plan.groups is None else (plan.groups, plan.carriers_soa),
                               dtype=np.float32 if precision == "fp32" else np.float64,
                               rows=self._rows(plan.order, kc))

    def _rows(self, js: np.ndarray, kc: int) -> MomentRows:
        """The :class:`~ciliary_carpet.carpet.instants.MomentRows` of cilia ``js`` (a plan's order)
        with ``kc`` harmonics, made once per array ``js`` (kept for the last few plans)."""
        hit = self.rows.get((id(js), kc))
        if hit is not None and hit.js is js:
            return hit
        rows = moment_rows(self.carriers, js, kc)
        if len(self.rows) >= _ROWS:
            self.rows.clear()
        self.rows[(id(js), kc)] = rows
        return rows

    def prepare(self, times: np.ndarray, tol: float, precision: str = "fp64") -> None:
        """Make the carriers' forces of the instants ``times`` (finite, distinct, sorted) together,
        in one read of the moments' coefficients, and have the resolved sources of the cilia near
        the points made for all of them at once when first needed
        (:meth:`Carpet.prepare <ciliary_carpet.carpet.carpet.Carpet.prepare>`). The instants kept
        before are dropped and their buffers reused."""
        precision = self.precision(precision)
        if tol == 0:
            return
        key, plan = self.plan(Instant(0.0), tol)
        kept = [f.group.out for q, f in self.forces.items() if len(q) == 4 and q[:2] == key and q[3] == precision]
        self._drop_instants(0)
        todo = times[:_INSTANTS]
        ph = self.cycles.phase_at(todo)
        group = self.instants(ph, key, plan, spare=kept[0] if kept else None, precision=precision)
        for i, t in enumerate(todo):
            self.forces[key + (float(t), precision)] = group.at(i)
        self.instant_blocks.reset(todo)

    def _carrier_forces(self, when: When, key: tuple, plan: Plan, precision: str = "fp64"):
        """The stacked carrier forces of ``plan`` for ``when``, kept: the cycle-mean's (an array)
        for as long as the plan (its moments do not change), an instant's for its time until other
        instants are prepared (:meth:`prepare`; a Runge-Kutta step evaluates the flow twice at its
        end time). At an instant one compiled pass from the first :meth:`Carriers.harmonics
        <ciliary_carpet.carpet.carriers.Carriers.harmonics>` of the moments' interpolant, the
        quadrupoles made when a sum reads them unless the far cilia are quadrupoles
        (:class:`~ciliary_carpet.carpet.instants.InstantCarriers`), in ``precision``'s type (fp32
        for the CPU's fp32 sums: no conversion per sum)."""
        k = key + ((when.t, precision) if isinstance(when, Instant) else ())
        f = self.forces.get(k)
        if f is None:
            if isinstance(when, Instant):
                f = self.instants(self.cycles.phase_at(when.t), key, plan, precision=precision).at(0)
                self._drop_instants(_INSTANTS - 1)
            else:
                F, D, T = when.moments(self.cycles, when.phases(self.cycles))
                f = self.carriers.stacked(F, self.carriers.forces(F, D, T), plan.order)
            self.forces[k] = f
        return f

    def _drop_instants(self, keep: int) -> None:
        """Forget the instants' carrier forces when more than ``keep`` are kept."""
        inst = [q for q in self.forces if len(q) == 4]
        if len(inst) > keep:
            for q in inst:
                del self.forces[q]
