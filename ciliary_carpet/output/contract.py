"""The contract of a render's outputs: the base class :class:`Output`, the :class:`RenderContext`
the outputs of one render share, the render's time-averaged field (:class:`MeanField`) and the
summary's file name (:data:`SUMMARY`). The contract in words, and the outputs a render writes, are
in :mod:`ciliary_carpet.output.outputs` (their registry).
"""
from __future__ import annotations

import time as _time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cilia_runtime.progress import Progress

from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.design import Design
from ciliary_carpet.output.plan import FieldGrid, RenderPlan
from ciliary_carpet.transport.flow import MeanFlow, SteadyMeanFlow
from ciliary_carpet.transport.pathlines import PathLines

__all__ = ["Output", "RenderContext", "MeanField", "StageProgress", "SUMMARY"]

SUMMARY = "summary.json"
"""The summary's name in a render folder (with the manifest, what makes a folder complete)."""


@dataclass(frozen=True, eq=False)
class MeanField:
    """The time-averaged velocity on the field grid: ``points`` (n, 3) in VTK order [L] and
    ``velocity`` (n, 3) [L/tau], n = nx ny."""

    grid: FieldGrid
    points: np.ndarray
    velocity: np.ndarray


@dataclass(eq=False)
class RenderContext:
    """What the outputs of one render share, handed to each :meth:`Output.write` in turn.

    ``plan``, ``carpet`` (designed) and ``design`` (None without a target) are fixed; ``stage`` is
    the staging folder to write into and ``out_dir`` the folder as it will be once placed;
    ``scene_resolved`` is the scene as a dict (``Scene.to_dict``: the summary's copy);
    ``summary`` and ``clock`` (seconds by stage, from ``started``) grow as outputs are written;
    ``mean_field`` and ``pathlines`` are left by their outputs for later ones (and a standing
    carpet's ``section_field``, its vertical section). ``pool`` says where the path lines' chunks
    and their error estimate's reference run (:mod:`~cilia_runtime.pool`; None: in this process).
    ``beside``: the summary's computations that ran in the path lines' pool
    (:func:`~ciliary_carpet.output.summary.summary_tasks`), by name, as
    :class:`~cilia_runtime.pool.TaskResult` s. ``progress`` reports the running output's own steps
    (the render sets a :class:`StageProgress` for each; silent by default).
    """

    plan: RenderPlan
    carpet: Carpet
    design: Design | None
    stage: Path
    out_dir: Path
    summary: dict
    clock: dict
    started: float
    scene_resolved: dict
    mean_field: MeanField | None = None
    pathlines: PathLines | None = None
    section_field: MeanField | None = None
    pool: object = None
    beside: dict = field(default_factory=dict)
    progress: Progress = field(default_factory=Progress)
    _mean_flow: MeanFlow | None = field(default=None, init=False, repr=False)

    @contextmanager
    def timed(self, key: str) -> Iterator[None]:
        """Record the seconds the block takes as ``clock[key]``."""
        t = _time.perf_counter()
        yield
        self.clock[key] = _time.perf_counter() - t

    def mean_flow(self) -> MeanFlow:
        """The long-time flow model (made once): from the render's mean field, or the carpet's
        mean flow evaluated on a grid of the same box and spacing. For a standing carpet, the
        in-plane mean flow of its target plane z = h (what its FTLE takes; its path lines follow
        the 3D flow, :meth:`standing_mean_flow`)."""
        if self._mean_flow is None:
            mf, tol = self.mean_field, self.plan.settings.tolerance
            if self.carpet.geometry == "standing":
                g = self.plan.grid
                if mf is None:
                    sample = self.carpet.velocity(g.points(), CycleMean(), tol)
                    mf = MeanField(g, g.points(), sample)
                nx, ny = g.shape[:2]
                self._mean_flow = MeanFlow.from_grid(self.carpet, *g.lines(), mf.velocity.reshape(ny, nx, 3))
            elif mf is not None:
                nx, ny = mf.grid.shape[:2]
                self._mean_flow = MeanFlow.from_grid(self.carpet, *mf.grid.lines(), mf.velocity.reshape(ny, nx, 3))
            else:
                g = self.plan.grid
                self._mean_flow = MeanFlow.from_carpet(self.carpet, g.box, spacing=min(g.spacing[:2]),
                                                       tol=max(tol, 1e-6))
        return self._mean_flow


    def standing_mean_flow(self) -> SteadyMeanFlow:
        """A standing carpet's long-time flow in space: its cycle-mean flow evaluated directly at
        the scene's tolerance, in the path lines' domain (``plan.domain``)."""
        return SteadyMeanFlow(self.carpet, self.plan.domain, tol=self.plan.settings.tolerance)


class StageProgress(Progress):
    """One output's own progress, shown as part of the render's: the output's ``total`` steps
    move ``render``'s count from ``before`` to ``before + 1`` (its ``start`` and ``close`` leave
    the render's bar as it is; a note goes to the render's)."""

    def __init__(self, render: Progress, before: float) -> None:
        self.render, self.before, self.total = render, float(before), 0.0

    def start(self, total: float, desc: str = "", uniform: bool = True) -> None:
        self.total = float(total)

    def update(self, done: float) -> None:
        if self.total > 0:
            self.render.update(self.before + min(float(done) / self.total, 1.0))

    def note(self, message: str) -> None:
        self.render.note(message)


class Output(ABC):
    """Base class of the outputs (the contract: :mod:`ciliary_carpet.output.outputs`)."""

    name = ""
    files: tuple[str, ...] = ()

    @abstractmethod
    def wanted(self, plan: RenderPlan) -> bool:
        """Whether a render with ``plan`` writes this output."""

    @abstractmethod
    def write(self, ctx: RenderContext) -> None:
        """Write the files into ``ctx.stage`` and the summary's section."""
