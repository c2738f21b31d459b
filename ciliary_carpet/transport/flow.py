"""Flow models that tracers follow: the contract and its models.

The contract (like ``scipy.integrate.OdeSolver``)
-------------------------------------------------
A flow model is a subclass of :class:`Flow`, registered in :data:`FLOWS` under its name, that
provides

``name`` : str (class attribute)
    Its label in results (``PathLines.model``, ``FTLEField.model``, a render's summary) and its
    key in :data:`FLOWS` (the scene key ``[output] pathline_model`` takes these names).
``carpet`` : Carpet
    The carpet whose flow it is: path lines refuse seeds inside its filaments, sample their
    dense output per its shortest beat period and by default follow tracers within 10 L of its
    bases and of the seeds (:func:`~ciliary_carpet.transport.pathlines.pathlines`).
``velocity(x, t) -> (M, 3)``
    The fluid velocity at points ``x`` (M, 3) at time ``t``: one call for all the tracers a
    stage advances (make it one vectorised sum).

and may override

``domain`` : (6,) array
    (xmin, xmax, ymin, ymax, zmin, zmax) where the model is valid (default: everywhere, inf):
    tracers that leave it stop ("left the domain"); a path-line run intersects it with its own.
``step_cap`` : float
    The largest time step an integrator may take in it (default inf): a flow that changes on a
    time scale the one-step error estimate does not see sets it.
``prepare(times)``
    A hint that ``velocity`` will be called at the few ``times`` next (an integrator's stages;
    default: nothing): a model whose cost per time is shared work may make it for all of them
    at once.

:func:`~ciliary_carpet.transport.pathlines.pathlines` and
:func:`~ciliary_carpet.transport.ftle.ftle_field` ask the flow for these and nothing else, so a new
model is one class here (or in its own module) and its entry in :data:`FLOWS`.

Models
------
* :class:`ResolvedFlow` (``"resolved"``): the time-resolved flow of the beating cilia at the
  tolerance ``tol`` of the levels of detail (:meth:`Carpet.velocity
  <ciliary_carpet.carpet.carpet.Carpet.velocity>` at an ``Instant``). Its steps are capped at a
  sixteenth of the shortest beat period (:data:`STEPS_PER_BEAT`): the one-step error estimate
  does not see the error the beat's oscillation accumulates (a tracer passing a beating
  filament meets a velocity spike shorter than a step). The end-point error over 200 beats of a
  10 x 10 carpet (100 tracers crossing it, flow tol 1e-3, against rtol 1e-8;
  ``benchmarks/bench_flow.py --sections pathlines``, benchmarks/results/bench_pathlines.md): with
  the defaults (rtol 1e-6, cap T/16) at most 7e-4 L, median 1e-6 L; with rtol 1e-4 and the cap
  1.1e-3 L; with a cap of T/24 1e-4 L.
* :class:`MeanFlow` (``"mean"``): the long-time model, the steady time-averaged (Eulerian mean)
  flow (:meth:`Carpet.velocity <ciliary_carpet.carpet.carpet.Carpet.velocity>` of the
  ``CycleMean``) sampled once on a grid of the plane and interpolated by bicubic splines, valid
  on the grid's box. It neglects the Stokes drift of the beat (the difference between the
  Lagrangian and the Eulerian mean): measured for one cilium, at most 1.9 % of its mean flow
  1 L from its force centre, 0.3 % at 2 L, 0.04 % at 4 L (cilia of other periods add no cross
  terms, and a carpet's mean flow adds up over all its cilia), below this model's own error. Its
  end-point error against time-resolved path lines is measured by ``benchmarks/bench_flow.py
  --sections longtime`` (benchmarks/results/bench_longtime.md, with the drift table): across the
  designed 10 x 10 uniform_deflection carpet (156 beats, the render's 100 seeds) at most 2.0 % of
  the distance travelled (median 0.6 %; vortex_turn's 100 seeds over its carpet: 1.6 %, median
  0.3 %), at a small fraction of the cost of the time-resolved flow (the same file). It shows the
  routes of the flow, not where a given tracer is at a given time.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from scipy.interpolate import RectBivariateSpline

from ciliary_carpet.carpet.carpet import CycleMean, Instant

if TYPE_CHECKING:
    from ciliary_carpet.carpet.carpet import Carpet

__all__ = ["Flow", "ResolvedFlow", "MeanFlow", "SteadyMeanFlow", "FLOWS", "above_wall", "MEAN_MODEL_ERROR", "STEPS_PER_BEAT"]

STEPS_PER_BEAT = 16
"""The time-resolved flow caps an integrator's steps at the shortest beat period over this
(:class:`ResolvedFlow`; module docstring for what it buys)."""
AUTO_RESOLVED_BEATS = 300
"""Most beats an "auto" path-line run follows in the time-resolved flow; a longer run follows the
mean flow (the bundled planar scenes run 50-110 beats; a slow standing vortex over 1,600)."""
MEAN_MODEL_ERROR = 0.05
"""End-point error of the long-time model (:class:`MeanFlow`) relative to the distance travelled,
against time-resolved path lines: the largest over 20 of the render's tracers of the designed
10 x 10 uniform_deflection carpet, measured with ``benchmarks/bench_flow.py --sections longtime``
(benchmarks/results/bench_longtime.md): 0.030 (median 0.009) at the carpet's default viscosity
(0.653, from its filaments), a margin of 1.7. The relative error grows like 1 / mu: the drift the
model leaves out is quadratic in the flow, the travel linear. Renders take the model
automatically only when the scene's tolerance is at least this."""
_EVERYWHERE = (-math.inf, math.inf) * 3


def above_wall(carpet: "Carpet", x: np.ndarray) -> np.ndarray:
    """``x`` (M, 3) with the points below a standing carpet's wall moved up onto it (a copy; ``x``
    itself otherwise): the flow there is the wall's, zero (no slip). An integrator's stage may
    land below the wall for a tracer close to it; the tracer itself stops at the wall, where the
    path lines' domain ends (a render's standing domain starts at the substrate). The wall's
    height is the carpet's geometry's :meth:`~ciliary_carpet.carpet.geometry.Geometry.floor`:
    planar carpets, and standing ones in free space, are left alone."""
    placement = getattr(carpet, "placement", None)
    z = None if placement is None else placement.floor(carpet.wall)
    if z is None:
        return x
    if np.all(x[:, 2] >= z):
        return x
    x = np.array(x, dtype=float)
    x[:, 2] = np.maximum(x[:, 2], z)
    return x


class Flow(ABC):
    """Base class of the flow models tracers follow (see the module docstring for the contract)."""

    name: ClassVar[str] = ""
    carpet: "Carpet"

    @abstractmethod
    def velocity(self, x: np.ndarray, t: float) -> np.ndarray:
        """(M, 3) the velocity at points ``x`` (M, 3) at time ``t``."""

    @property
    def domain(self) -> np.ndarray:
        """(6,) (xmin, xmax, ymin, ymax, zmin, zmax) where the model is valid: everywhere."""
        return np.array(_EVERYWHERE)

    @property
    def step_cap(self) -> float:
        """The largest time step an integrator may take: none."""
        return math.inf

    def prepare(self, times: np.ndarray) -> None:
        """A hint: :meth:`velocity` will be called at ``times`` next (default: ignored)."""


@dataclass(frozen=True, eq=False)
class ResolvedFlow(Flow):
    """The time-resolved flow of ``carpet`` at the levels-of-detail tolerance ``tol``, the far
    cilia's carriers summed in ``precision`` (``"fp64"``, or ``"fp32"``: single precision on the
    CPU, more pairs per second, benchmarks/results/bench_evaluation.md; :meth:`Carpet.velocity
    <ciliary_carpet.carpet.carpet.Carpet.velocity>`)."""

    name: ClassVar[str] = "resolved"
    carpet: "Carpet"
    tol: float = 1e-4
    precision: str = "fp64"

    def __post_init__(self) -> None:
        t = float(self.tol)
        if not 0 <= t < 1:
            raise ValueError(f"ResolvedFlow: tol must be in [0, 1), got {self.tol!r}")
        if self.precision not in ("fp64", "fp32"):
            raise ValueError(f"ResolvedFlow: precision must be 'fp64' or 'fp32', got {self.precision!r}")
        object.__setattr__(self, "tol", t)

    def velocity(self, x: np.ndarray, t: float) -> np.ndarray:
        return self.carpet.velocity(above_wall(self.carpet, x), Instant(t), self.tol, self.precision)

    def prepare(self, times: np.ndarray) -> None:
        """The carpet's carriers at ``times`` made together (:meth:`Carpet.prepare
        <ciliary_carpet.carpet.carpet.Carpet.prepare>`; the same numbers, one read of the moments)."""
        if self.tol > 0:
            self.carpet.prepare(times, self.tol, self.precision)

    @property
    def step_cap(self) -> float:
        """The shortest beat period over :data:`STEPS_PER_BEAT` (none when no cilium beats)."""
        p = self.carpet.periods
        p = p[np.isfinite(p)]
        return float(p.min()) / STEPS_PER_BEAT if p.size else math.inf


@dataclass(frozen=True, eq=False)
class MeanFlow(Flow):
    """The long-time model: ``carpet``'s time-averaged flow in the plane z = 0, sampled on a
    regular grid and interpolated with bicubic splines (module docstring for its error).

    Build it with :meth:`from_carpet` (evaluates the mean flow on the grid) or :meth:`from_grid`
    (from an already evaluated grid, e.g. the render's mean field). ``box`` = (xmin, xmax, ymin,
    ymax) is the grid's extent, its :attr:`domain`: tracers that leave it stop ("left the domain")."""

    name: ClassVar[str] = "mean"
    carpet: "Carpet"
    box: tuple
    _ux: object = field(repr=False)
    _uy: object = field(repr=False)

    @classmethod
    def from_grid(cls, carpet: "Carpet", x: np.ndarray, y: np.ndarray, u: np.ndarray) -> "MeanFlow":
        """``x`` (nx,), ``y`` (ny,) increasing grid lines, ``u`` (ny, nx, >= 2) ``carpet``'s mean
        velocity there."""
        x, y, u = np.asarray(x, float), np.asarray(y, float), np.asarray(u, float)
        if x.size < 4 or y.size < 4 or u.shape[:2] != (y.size, x.size):
            raise ValueError(f"MeanFlow needs at least 4 x 4 grid points and u of shape (ny, nx, 2), got "
                             f"x {x.shape}, y {y.shape}, u {u.shape}")
        if not np.all(np.isfinite(u[..., :2])):
            raise ValueError("MeanFlow: the grid velocity has NaN or inf")
        ux = RectBivariateSpline(x, y, u[..., 0].T, kx=3, ky=3)
        uy = RectBivariateSpline(x, y, u[..., 1].T, kx=3, ky=3)
        return cls(carpet, (float(x[0]), float(x[-1]), float(y[0]), float(y[-1])), ux, uy)

    @classmethod
    def from_carpet(cls, carpet: "Carpet", box, spacing: float = 0.25, tol: float = 1e-3) -> "MeanFlow":
        """Sample ``carpet``'s mean flow at tolerance ``tol`` on the grid of ``spacing`` covering ``box``."""
        xmin, xmax, ymin, ymax = (float(v) for v in box)
        nx = max(4, int(math.ceil((xmax - xmin) / spacing)) + 1)
        ny = max(4, int(math.ceil((ymax - ymin) / spacing)) + 1)
        x, y = np.linspace(xmin, xmax, nx), np.linspace(ymin, ymax, ny)
        X, Y = np.meshgrid(x, y)
        u = carpet.velocity(np.column_stack([X.ravel(), Y.ravel()]), CycleMean(), tol)
        return cls.from_grid(carpet, x, y, u.reshape(ny, nx, 3))

    @property
    def domain(self) -> np.ndarray:
        """(6,) the grid's box in the plane, every z."""
        return np.array([*self.box, -math.inf, math.inf])

    def velocity(self, x: np.ndarray, t: float) -> np.ndarray:
        out = np.zeros((x.shape[0], 3))
        out[:, 0] = self._ux.ev(x[:, 0], x[:, 1])
        out[:, 1] = self._uy.ev(x[:, 0], x[:, 1])
        return out


@dataclass(frozen=True, eq=False)
class SteadyMeanFlow(Flow):
    """The long-time model in space: ``carpet``'s time-averaged (cycle-mean) flow evaluated
    directly at the tracers (:meth:`Carpet.velocity <ciliary_carpet.carpet.carpet.Carpet.velocity>`
    of the ``CycleMean`` at the levels-of-detail tolerance ``tol``), valid in ``box`` = (xmin, xmax,
    ymin, ymax, zmin, zmax), its :attr:`domain`. The flow of a standing carpet is three-dimensional
    (it vanishes on the substrate and turns over the carpet's edges), so a sampled plane
    (:class:`MeanFlow`) does not describe it; a render takes this model for a standing carpet's
    path lines where it takes :class:`MeanFlow` for a planar one (same name, ``"mean"``: it is the
    same long-time model, with the same neglected Stokes drift). Steady: no step cap."""

    name: ClassVar[str] = "mean"
    carpet: "Carpet"
    box: tuple
    tol: float = 1e-3

    def __post_init__(self) -> None:
        b = tuple(float(v) for v in self.box)
        if len(b) != 6 or any(hi <= lo for lo, hi in zip(b[0::2], b[1::2])):
            raise ValueError(f"SteadyMeanFlow: box must be (xmin, xmax, ymin, ymax, zmin, zmax), got {self.box!r}")
        object.__setattr__(self, "box", b)
        t = float(self.tol)
        if not 0 <= t < 1:
            raise ValueError(f"SteadyMeanFlow: tol must be in [0, 1), got {self.tol!r}")
        object.__setattr__(self, "tol", t)

    @property
    def domain(self) -> np.ndarray:
        """(6,) the box."""
        return np.array(self.box)

    def velocity(self, x: np.ndarray, t: float) -> np.ndarray:
        return self.carpet.velocity(above_wall(self.carpet, x), CycleMean(), self.tol)


FLOWS: dict[str, type[Flow]] = {m.name: m for m in (ResolvedFlow, MeanFlow)}
"""The flow models by name (the contract: the module docstring); :class:`SteadyMeanFlow` is the
``"mean"`` model of standing carpets (chosen by the geometry, not by name)."""
