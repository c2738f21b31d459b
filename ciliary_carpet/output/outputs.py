"""The outputs of a render: the contract, one class per output, and their registry.

The contract
------------
An output is a subclass of :class:`Output`, registered in :data:`OUTPUTS` under its ``name``.
The registry's order is the order a render writes them in (an output may use what an earlier
one left on the context; the summary is last). An output provides

``name`` : str
    Its key in :data:`OUTPUTS`.
``files`` : tuple of str
    Regular expressions (matched in full) of the names of the files it may write into the render
    folder. Their union over the registry is what the output folder counts as the toolkit's
    (:mod:`ciliary_carpet.output.folder`): only files with such names are ever replaced or
    removed by a later render, and a render that writes any other name fails before placing it.
``wanted(plan) -> bool``
    Whether a render with this :class:`~ciliary_carpet.output.plan.RenderPlan` writes it
    (usually a key of the scene's ``[output]``).
``write(ctx) -> None``
    Write its files into ``ctx.stage`` (the staging folder, in the units ``ctx.plan.units``) and
    its section of ``ctx.summary``; time its stages with ``ctx.timed(key)``. It may use
    ``ctx.mean_field`` (left by :class:`MeanFieldOutput`), ``ctx.pathlines`` (left by
    :class:`PathLinesOutput`) and the long-time flow model ``ctx.mean_flow()``.

:func:`~ciliary_carpet.render.render` does everything else once: the resource check, the design,
the plan, the progress bar, the output folder and its manifest.

Outputs
-------
===========================  ==================================================================
``layout``                   ``layout.vtp``: base points coloured by chi_N (and thrust angle,
                             near_cutoff); a standing carpet's also azimuth and the mean thrust
                             in space
``design``                   with a target: ``layout.nc`` (the designed layout: chi_N per cilium,
                             control points, residuals), ``design.vtp`` (control points: target and
                             achieved flow, residual), ``design.png`` (target vs achieved arrows,
                             residual per control point, the layout coloured by chi_N); a standing
                             carpet: ``layout.nc`` (its given layout: chi_N and azimuth per cilium)
``mean_field``               ``mean_field.vti``: the time-averaged velocity (active vectors),
                             speed, vorticity and the error bound on the field grid (a standing
                             carpet: the target plane z = h, and ``mean_field_section.vti`` on
                             the vertical x-z section through its centre, down to the wall)
``snapshots``                ``snapshot_NNN.vti``: instantaneous fields over one beat of the cilia,
                             tied by ``snapshots.pvd`` (a standing carpet: also on the section,
                             ``snapshot_section_NNN.vti``, ``snapshots_section.pvd``)
``frames``                   ``cilia_NNN.vtp``: filament shapes over one beat (arc length, drag
                             density), ``cilia.pvd``; both .pvd repeat that beat over the path
                             lines' time range (one clock)
``pathlines``                ``pathlines.vtp``: tracer path lines (time, IntegrationTime, velocity,
                             speed; SeedIds, TerminationReason with TerminationReasonNames), >= 16
                             points per beat; ``particles.pvd``: the tracers as moving points
                             (``particles_NNNNN.vtp``), as ParticlePath gives
``ftle``                     ``ftle.vti``: finite-time Lyapunov exponent over the carpet (mean
                             flow, a quarter of the path-line duration); the mixing number is in
                             the summary
``preview``                  ``preview.png``: the mean flow (streamlines) with the layout and path
                             lines, a colour bar for each colour
``paraview``                 ``open_in_paraview.py`` (:mod:`ciliary_carpet.output.paraview`)
``summary``                  ``summary.json``, ``summary.md``: residuals, timings, fidelity used,
                             error bounds, path-line outcome, what the model leaves out (``.md``:
                             the same in words, :mod:`ciliary_carpet.output.report`)
===========================  ==================================================================

Standing carpets (``[carpet] geometry = "standing"``, :mod:`ciliary_carpet.carpet.geometry`) write
the same files in space: the cilia's frames and the path lines are 3D polylines; the fields lie
on the target plane z = h above the cilia (``[output] height``) plus the vertical section; the
path lines follow the 3D flow (the time-resolved flow, or the cycle-mean flow evaluated directly,
:class:`~ciliary_carpet.transport.flow.SteadyMeanFlow`) from the substrate up, and a tracer that
reaches the wall ends there ("left the domain"). The FTLE and the mixing number are those of the
target plane's in-plane mean flow (2D tracers that stay in the plane z = h: the stretching along
the surface flow, not the fluid's 3D stretching). The preview looks down on the target plane.
The summary gives the geometry and the azimuths; the coupling estimate (a planar carpet's) is
left out.
"""
from __future__ import annotations

import logging
import math
import re
import time as _time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from cilia_runtime.files import non_finite, strict_json, write_netcdf
from cilia_runtime.threads import threads_in_use

from ciliary_carpet.carpet.carpet import Carpet, CycleMean, Instant
from ciliary_carpet.carpet.coupling import coupling_estimate
from ciliary_carpet.carpet.omissions import omissions
from ciliary_carpet.design import Design
from ciliary_carpet.output import RenderError
from ciliary_carpet.output.figures import design_picture, preview, standing_preview
from ciliary_carpet.output.paraview import SCRIPT, write_script
from ciliary_carpet.output.plan import ANIMATION_STEPS, FieldGrid, RenderPlan
from ciliary_carpet.output.report import markdown
from ciliary_carpet.output.vtkfiles import write_cilia, write_field, write_points, write_pvd
from ciliary_carpet.transport.ftle import ftle_field
from ciliary_carpet.transport.flow import MeanFlow, ResolvedFlow, SteadyMeanFlow
from cilia_runtime.pool import InProcess
from ciliary_carpet.transport.pathlines import CHUNK_SIZE, UNDERFLOW, PathLines, join_pathlines, pathline_tasks

logger = logging.getLogger(__name__)

__all__ = ["Output", "OUTPUTS", "RenderContext", "MeanField", "SUMMARY", "pathline_error", "error_tracers", "summary_tasks",
           "error_reference", "end_point_error",
           "ERROR_SAMPLE", "PATHLINE_TOL", "PATHLINE_RTOL", "PATHLINE_ATOL", "REFERENCE_TIGHTER",
           "LayoutOutput", "DesignOutput", "MeanFieldOutput", "SnapshotsOutput", "FramesOutput",
           "PathLinesOutput", "FtleOutput", "PreviewOutput", "ParaViewOutput", "SummaryOutput"]

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
    ``summary`` and ``clock`` (seconds by stage, from ``started``) grow as outputs are written;
    ``mean_field`` and ``pathlines`` are left by their outputs for later ones (and a standing
    carpet's ``section_field``, its vertical section). ``pool`` says where the path lines' chunks
    and their error estimate's reference run (:mod:`~ciliary_carpet.transport.parallel`; None:
    in this process). ``beside``: the summary's computations that ran in the path lines' pool
    (:func:`summary_tasks`), by name, as :class:`~ciliary_carpet.transport.parallel.TaskResult` s.
    """

    plan: RenderPlan
    carpet: Carpet
    design: Design | None
    stage: Path
    out_dir: Path
    summary: dict
    clock: dict
    started: float
    mean_field: MeanField | None = None
    pathlines: PathLines | None = None
    section_field: MeanField | None = None
    pool: object = None
    beside: dict = field(default_factory=dict)
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
            mf, tol = self.mean_field, self.plan.scene.tolerance
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
        return SteadyMeanFlow(self.carpet, self.plan.domain, tol=self.plan.scene.tolerance)


class Output(ABC):
    """Base class of the outputs (see the module docstring for the contract)."""

    name = ""
    files: tuple[str, ...] = ()

    @abstractmethod
    def wanted(self, plan: RenderPlan) -> bool:
        """Whether a render with ``plan`` writes this output."""

    @abstractmethod
    def write(self, ctx: RenderContext) -> None:
        """Write the files into ``ctx.stage`` and the summary's section."""


def _vorticity(u: np.ndarray, spacing, shape) -> np.ndarray:
    """(n, 3) vorticity (0, 0, dv/dx - du/dy) of an in-plane field on the (nx, ny, 1) grid
    (second-order differences; the plane's own derivatives only)."""
    nx, ny = shape[0], shape[1]
    U = u[:, 0].reshape(ny, nx)
    W = u[:, 1].reshape(ny, nx)
    w = np.zeros((u.shape[0], 3))
    w[:, 2] = (np.gradient(W, spacing[0], axis=1) - np.gradient(U, spacing[1], axis=0)).ravel()
    return w


def _vorticity_section(u: np.ndarray, spacing, shape) -> np.ndarray:
    """(n, 3) vorticity (0, du/dz - dw/dx, 0) of a field on a vertical x-z section, the
    (nx, 1, nz) grid (second-order differences; the section's own derivatives only)."""
    nx, nz = shape[0], shape[2]
    U = u[:, 0].reshape(nz, nx)
    W = u[:, 2].reshape(nz, nx)
    w = np.zeros((u.shape[0], 3))
    w[:, 1] = (np.gradient(U, spacing[2], axis=0) - np.gradient(W, spacing[0], axis=1)).ravel()
    return w


def _write_flow(path: Path, grid: FieldGrid, sample, plan: RenderPlan, time: float | None = None) -> Path:
    """A field file of a flow ``sample`` on ``grid``: velocity, speed, vorticity, error bound
    (a vertical section, shape (nx, 1, nz): its y vorticity)."""
    L, T, V = plan.units
    u = sample.velocity
    vort = _vorticity_section(u, grid.spacing, grid.shape) if grid.shape[1] == 1 and grid.shape[2] > 1 \
        else _vorticity(u, grid.spacing, grid.shape)
    return write_field(path, np.asarray(grid.origin) * L, np.asarray(grid.spacing) * L, grid.shape,
                       {"velocity": u * V, "speed": np.linalg.norm(u, axis=1) * V,
                        "vorticity": vort / T,
                        "error_bound": sample.error_bound * V}, time=time)


def _looped(files: list, beat: float, span: float) -> list:
    """(time, file) entries that repeat one beat's ``files`` (at k beat / n) from 0 until
    ``span`` is covered: a .pvd of them plays the beat on over the whole time range. Beyond
    :data:`~ciliary_carpet.output.plan.ANIMATION_STEPS` entries, that many at equal steps over ``span`` instead, each showing
    the frame of its phase in the beat (a stroboscope: the clock stays right, the beat is sampled)."""
    n = len(files)
    count = max(n + 1, int(math.ceil(span / beat * n - 1e-9)) + 1)
    if count <= ANIMATION_STEPS:
        return [(k * beat / n, files[k % n]) for k in range(count)]
    times = np.linspace(0.0, span, ANIMATION_STEPS)
    return [(float(t), files[int(round(t / beat * n)) % n]) for t in times]


class LayoutOutput(Output):
    """``layout.vtp``: the cilia's base points with chi_N, thrust angle (in the flow each beats in),
    flutter and near_cutoff; for a coupled carpet also ``background_flow``, the others' mean flow
    at each cilium. A standing carpet's also has ``azimuth`` [deg] and ``mean_thrust`` (the
    cycle-mean force on the fluid in space, force per length units x L) with its force centres'
    height ``centre_z`` (its ``layout.nc`` is the ``design`` output's file)."""

    name = "layout"
    files = (r"layout\.vtp",)

    def wanted(self, plan):
        return True

    def write(self, ctx):
        if ctx.carpet.geometry == "standing":
            self._standing(ctx)
            return
        c, d = ctx.carpet, ctx.design
        L, _, V = ctx.plan.units
        near = np.zeros(c.n, np.uint8)
        if d is not None:
            near[list(d.near_cutoff)] = 1
        flow = {}
        if c.background is not None:  # each cilium's thrust in the flow it beats in (field frame)
            u = c.background @ c.rotation
            flow = {"U_perp": u[:, 0], "U_par": u[:, 1]}
        data = {"chi_N": c.chi_N, "thrust_angle": c.table.scalar("thrust_angle", c.chi_N, **flow),
                "cilium_id": np.arange(c.n), "flutter": c.flutter.astype(np.uint8), "near_cutoff": near}
        if c.background is not None:  # a coupled carpet: the others' mean flow at each cilium
            data["background_flow"] = np.column_stack([c.background * V, np.zeros(c.n)])
        write_points(ctx.stage / "layout.vtp", np.column_stack([c.bases * L, np.zeros(c.n)]), data)
        ctx.summary["layout"] = {"chi_N_min": float(c.chi_N.min()), "chi_N_max": float(c.chi_N.max())}

    @staticmethod
    def _standing(ctx):
        c = ctx.carpet
        L = ctx.plan.units[0]
        f_scale = _force_scale(ctx.plan, c)
        psi = np.round(np.degrees(c.azimuth), 9)
        data = {"chi_N": c.chi_N, "azimuth": psi, "thrust_angle": c.table.scalar("thrust_angle", c.chi_N),
                "cilium_id": np.arange(c.n), "flutter": c.flutter.astype(np.uint8), "near_cutoff": np.zeros(c.n, np.uint8),
                "mean_thrust": c.in_space("mean_thrust") * f_scale * L, "centre_z": c.in_space("centres")[:, 2] * L}
        write_points(ctx.stage / "layout.vtp", np.column_stack([c.bases * L, np.zeros(c.n)]), data)
        ctx.summary["layout"] = {"chi_N_min": float(c.chi_N.min()), "chi_N_max": float(c.chi_N.max()),
                                 "azimuth_min_deg": float(psi.min()), "azimuth_max_deg": float(psi.max())}


def _force_scale(plan: RenderPlan, c: Carpet) -> float:
    """The factor from the model's force per length to the files' (1 without SI units)."""
    sc = plan.scales
    return sc.viscosity_Pa_s * plan.units[2] / c.mu if sc is not None else 1.0


def standing_layout_dataset(c: Carpet):
    """A standing carpet's layout as an xarray Dataset (dim ``cilium``, CF attributes; what
    ``layout.nc`` holds): base point x, y [L], chi_N, azimuth psi [degrees anticlockwise from +x],
    thrust angle [rad], beat phase at t = 0, the cycle-mean force on the fluid in space
    (``mean_thrust_x``, ``_y``, ``_z``; force per length x L, model units) and the force centre's
    height ``centre_z`` [L]; attributes: geometry, chi_E, eta, wall (distance below the clamps,
    -1 for none)."""
    import xarray as xr

    F = c.in_space("mean_thrust")
    return xr.Dataset(
        {"x": ("cilium", c.bases[:, 0], {"long_name": "base point x", "units": "L"}),
         "y": ("cilium", c.bases[:, 1], {"long_name": "base point y", "units": "L"}),
         "chi_N": ("cilium", c.chi_N, {"long_name": "natural curvature chi_N = L kappa_N", "units": "1"}),
         "azimuth": ("cilium", np.round(np.degrees(c.azimuth), 9),  # (to 1e-9 deg: 30, not 29.999999999999996)
                     {"long_name": "beat-plane azimuth psi, anticlockwise from +x", "units": "degree"}),
         "thrust_angle": ("cilium", c.table.scalar("thrust_angle", c.chi_N),
                          {"long_name": "lean of the mean thrust from the normal towards e_psi", "units": "rad"}),
         "phase": ("cilium", c.phases, {"long_name": "beat phase at t = 0", "units": "1"}),
         "mean_thrust_x": ("cilium", F[:, 0], {"long_name": "cycle-mean force on the fluid, x", "units": "B/L^2"}),
         "mean_thrust_y": ("cilium", F[:, 1], {"long_name": "cycle-mean force on the fluid, y", "units": "B/L^2"}),
         "mean_thrust_z": ("cilium", F[:, 2], {"long_name": "cycle-mean force on the fluid, z", "units": "B/L^2"}),
         "centre_z": ("cilium", c.in_space("centres")[:, 2], {"long_name": "height of the force centre",
                                                              "units": "L"})},
        attrs={"geometry": c.geometry, "chi_E": c.table.chi_E, "eta": c.table.eta,
               "wall": -1.0 if c.wall is None else float(c.wall)})


class DesignOutput(Output):
    """With a target: ``layout.nc``, ``design.vtp`` (control points: target, achieved flow,
    residual) and ``design.png``. A standing carpet (given its layout, no target): ``layout.nc``
    alone, chi_N and azimuth per cilium (:func:`standing_layout_dataset`)."""

    name = "design"
    files = (r"layout\.nc", r"design\.vtp", r"design\.png")

    def wanted(self, plan):
        return plan.designed or plan.scene.carpet.geometry == "standing"

    def write(self, ctx):
        if ctx.design is None:  # a standing carpet's given layout
            write_netcdf(standing_layout_dataset(ctx.carpet), ctx.stage / "layout.nc")
            return
        d, stage = ctx.design, ctx.stage
        L, _, V = ctx.plan.units
        write_netcdf(d.to_dataset(ctx.carpet), stage / "layout.nc")
        z = np.zeros((d.control.shape[0], 1))
        write_points(stage / "design.vtp", np.column_stack([d.control * L, z]),
                     {"target": np.concatenate([d.target * (V if d.kind == "velocity" else 1.0), z], axis=1),
                      "achieved": np.concatenate([d.achieved * V, z], axis=1), "residual": d.residual,
                      **({"speed_ratio": d.speed_ratio} if d.speed_ratio is not None else {})})
        design_picture(stage / "design.png", ctx.plan.scene, ctx.carpet, d)
        ctx.summary["design"] = design_summary(d, L)


def design_summary(d, length: float) -> dict:
    """The design's summary (:meth:`Design.summary <ciliary_carpet.design.result.Design.summary>`,
    lengths in L) with its lengths times ``length`` (the summary's unit of length: 1, or
    ``[units] length_m``): the worst control points' x, y, a standing design's surface height and
    the reachability's line, widths and width scan. Its residuals are angles or relative."""
    out = d.summary()
    out["worst"] = [dict(w, x=w["x"] * length, y=w["y"] * length) for w in out["worst"]]
    if out.get("surface_height") is not None:
        out["surface_height"] = out["surface_height"] * length
    r = out.get("reachability")
    if r is not None:
        r = dict(r)
        for k in ("line", "width", "width_min"):
            if r.get(k) is not None:
                r[k] = r[k] * length
        if "width_scan" in r:
            r["width_scan"] = [[w * length, res] for w, res in r["width_scan"]]
        out["reachability"] = r
    return out


_COUPLING_SPEEDS = ("median_speed_coupled", "median_speed_uncoupled")
"""The speeds (L/tau in the model) of the summary's ``coupling`` section."""
OMISSIONS_UNITS = "L, tau: model units, as the key names say (viscosities in B tau / L^4)"
"""The summary's ``omissions`` section is in model units whatever ``[units]`` says (its keys
name their unit: ``spacing_L``, ``mean_flow_others_median_L_per_tau``); its ``units`` key says so."""


class MeanFieldOutput(Output):
    """``mean_field.vti``: the time-averaged flow on the field grid (leaves ``ctx.mean_field``); a
    standing carpet's also ``mean_field_section.vti`` on its vertical section (``ctx.section_field``)."""

    name = "mean_field"
    files = (r"mean_field\.vti", r"mean_field_section\.vti")

    def wanted(self, plan):
        return bool(plan.scene.output.field)

    def write(self, ctx):
        grid, V = ctx.plan.grid, ctx.plan.units[2]
        with ctx.timed("mean_field"):
            pts = grid.points()
            s = ctx.carpet.evaluate(pts, CycleMean(), tol=ctx.plan.scene.tolerance)
            ctx.mean_field = MeanField(grid, pts, s.velocity)
            _write_flow(ctx.stage / "mean_field.vti", grid, s, ctx.plan)
            sec = ctx.plan.section
            if sec is not None:  # a standing carpet: the vertical section, down to the wall
                sp = sec.points()
                ss = ctx.carpet.evaluate(sp, CycleMean(), tol=ctx.plan.scene.tolerance)
                ctx.section_field = MeanField(sec, sp, ss.velocity)
                _write_flow(ctx.stage / "mean_field_section.vti", sec, ss, ctx.plan)
        ctx.summary["mean_field"] = {"points": int(pts.shape[0]), "fidelity": s.fidelity,
                                     "max_error_bound": float(s.error_bound.max()) * V,
                                     "max_speed": float(np.nanmax(np.linalg.norm(s.velocity, axis=1))) * V}
        if sec is not None:
            L = ctx.plan.units[0]
            ctx.summary["mean_field"].update(
                height=float(grid.origin[2]) * L,
                section={"points": int(sp.shape[0]), "y": float(sec.origin[1]) * L, "top": float(sec.box[3]) * L,
                         "max_error_bound": float(ss.error_bound.max()) * V,
                         "max_speed": float(np.nanmax(np.linalg.norm(ss.velocity, axis=1))) * V})


class SnapshotsOutput(Output):
    """``snapshot_NNN.vti`` over one beat of the cilia, ``snapshots.pvd`` repeating it (a standing
    carpet: also ``snapshot_section_NNN.vti`` on its vertical section, ``snapshots_section.pvd``)."""

    name = "snapshots"
    files = (r"snapshot_\d+\.vti", r"snapshots\.pvd", r"snapshot_section_\d+\.vti", r"snapshots_section\.pvd")

    def wanted(self, plan):
        return plan.scene.output.snapshots > 0

    def write(self, ctx):
        plan = ctx.plan
        n, Tb, T = plan.scene.output.snapshots, plan.beat.period, plan.units[1]
        with ctx.timed("snapshots"):
            pts = plan.grid.points()
            entries, fid = [], []
            for k in range(n):
                t = k * Tb / n
                s = ctx.carpet.evaluate(pts, Instant(t), tol=plan.scene.tolerance)
                entries.append(_write_flow(ctx.stage / f"snapshot_{k:03d}.vti", plan.grid, s, plan, time=t * T))
                fid.append(s.fidelity)
            write_pvd(ctx.stage / "snapshots.pvd", _looped(entries, Tb * T, plan.span * T))
            sec = plan.section
            if sec is not None:  # a standing carpet: its vertical section too
                sp, entries = sec.points(), []
                for k in range(n):
                    t = k * Tb / n
                    s = ctx.carpet.evaluate(sp, Instant(t), tol=plan.scene.tolerance)
                    entries.append(_write_flow(ctx.stage / f"snapshot_section_{k:03d}.vti", sec, s, plan, time=t * T))
                write_pvd(ctx.stage / "snapshots_section.pvd", _looped(entries, Tb * T, plan.span * T))
        ctx.summary["snapshots"] = {"count": n, "fidelity": fid[0]}


class FramesOutput(Output):
    """``cilia_NNN.vtp``: the filaments over one beat (arc length, drag density), ``cilia.pvd`` (a
    standing carpet's in space, 3D polylines)."""

    name = "frames"
    files = (r"cilia_\d+\.vtp", r"cilia\.pvd")

    def wanted(self, plan):
        return plan.scene.output.frames > 0

    def write(self, ctx):
        plan, c = ctx.plan, ctx.carpet
        n, Tb, (L, T, V), sc = plan.scene.output.frames, plan.beat.period, plan.units, plan.scales
        f_scale = sc.viscosity_Pa_s * V / c.mu if sc is not None else 1.0
        # The shapes are made here, one frame after the other; the files are written by the
        # render's threads (VTK's writer and the disk let go of the interpreter: two threads write
        # 40 frames of 10^4 cilia in 0.6 of the time of one), at most one frame ahead of each.
        writers = max(1, threads_in_use()["numba"])
        with ctx.timed("frames"), ThreadPoolExecutor(max_workers=writers) as pool:
            jobs, pending = [], []
            for k in range(n):
                t = k * Tb / n
                if c.geometry == "standing":  # in space: each beat plane turned by its azimuth
                    pos, f, ph = c.state_in_space(t)
                    args = (pos * L, c.s * L, np.arange(c.n), c.chi_N, ph)
                    kw = dict(drag=f * f_scale, time=t * T)
                else:
                    pos, f, ph = c.state(t)
                    z = np.zeros(pos.shape[:2] + (1,))
                    args = (np.concatenate([pos * L, z], -1), c.s * L, np.arange(c.n), c.chi_N, ph)
                    kw = dict(drag=np.concatenate([f * f_scale, z], -1), time=t * T)
                if len(pending) > writers:
                    pending.pop(0).result()
                pending.append(pool.submit(write_cilia, ctx.stage / f"cilia_{k:03d}.vtp", *args, **kw))
                jobs.append(pending[-1])
            entries = [j.result() for j in jobs]  # the first error of a write, raised here
            write_pvd(ctx.stage / "cilia.pvd", _looped(entries, Tb * T, plan.span * T))


ERROR_SAMPLE = 8
"""Tracers of a render re-integrated to estimate its path lines' end-point error (:func:`pathline_error`)."""
PATHLINE_TOL = 1e-4
"""Largest flow tolerance (levels of detail) of a render's time-resolved path lines: the scene's
tolerance when tighter. The tracers' end points are far more sensitive to the flow's error than
the fields are: measured on the designed uniform_deflection carpet at 30 x 30 (8 tracers over 142
beats, against flow tol 1e-5, rtol 1e-9, atol 2e-7 L with the step cap halved;
``benchmarks/bench_large.py --decompose``, benchmarks/results/bench_large.md), with the integration tight (rtol 1e-9, atol 2e-7 L) the end
points are off by up to 2.1e-3 L at flow tol 1e-3, 9.5e-4 L at 3e-4 and 5e-5 L at 1e-4. On 100 x 100
the render's 100 tracers end up to 1.4e-3 L from the check run (the estimate said 6.4e-4 L: the fine
runs themselves differ by that much there)."""
PATHLINE_RTOL = 1e-9
PATHLINE_ATOL = 1e-7
"""Local error test of a render's time-resolved path lines: rtol :data:`PATHLINE_RTOL`, atol this
times the carpet's spacing [L]. The test is per step, the end-point error accumulates over the
thousands of steps of a render (about 16 per beat): measured as above at flow tol 1e-4, atol
2e-4 L (the settings before, rtol 1e-6) ends up to 4e-3 L off, 2e-6 L 1.1e-3 L, 2e-7 L 5e-5 L,
for 22 % more steps than the first."""
PATHLINE_PRECISION = "fp32"
"""The precision of the far cilia's carriers in a render's time-resolved path lines
(:class:`~ciliary_carpet.transport.flow.ResolvedFlow`; the near field and everything else in fp64).
Their rounding (:func:`~ciliary_carpet.stokes.precision.fp32_error_bound`) is some 1e-7 of the
velocity, far inside the levels of detail's tolerance; the end-point error estimate's reference
run (:func:`pathline_error`) sums in fp64, so the estimate covers it. Measured with
``benchmarks/bench_evaluation.py --pathlines 0.1`` (the render's 100 tracers over a tenth of the
duration, one thread, benchmarks/results/bench_evaluation.md): 30 x 30 1.82 s in fp64, 1.37 s in
fp32, end points 4.4e-6 L apart, 3.5e-6 and 2.9e-6 L from the reference run; 100 x 100 13.1 s and
11.1 s, 6.9e-5 L apart (the two runs take different steps), 5.1e-5 and 4.5e-5 L from the
reference."""
REFERENCE_TIGHTER = (3.0, 10.0)
"""The reference of a render's end-point error estimate (:func:`pathline_error`): the flow
tolerance divided by the first, rtol and atol by the second (the step cap unchanged: at these
tolerances the local error test, not the cap, sets the steps; measured as above, halving the
cap too moves the reference's end points by at most 4e-5 L)."""


def error_tracers(k: int) -> np.ndarray:
    """The indices of the :data:`ERROR_SAMPLE` tracers (spread evenly over ``k`` seeds) that
    :func:`pathline_error` re-integrates."""
    n = min(ERROR_SAMPLE, int(k))
    return np.unique(np.linspace(0, int(k) - 1, n).round().astype(int))


def pathline_error(carpet: Carpet, seeds: np.ndarray, duration: float, pl, model: str, flow, tol: float,
                   spacing: float, domain=None, pool=None) -> dict:
    """End-point error estimate of rendered path lines ``pl`` in ``flow``: :data:`ERROR_SAMPLE` of
    its tracers (:func:`error_tracers`) integrated again, against a more accurate run.

    For the time-resolved flow (``flow`` a :class:`ResolvedFlow`) the reference is the same
    integration with every tolerance tightened (:data:`REFERENCE_TIGHTER`: the flow tolerance
    ``flow.tol`` / 3, ``pl.rtol`` and ``pl.atol`` / 10): the estimate covers the integration and
    the levels of detail. For the long-time model (``model == "mean"``, ``flow`` its
    :class:`MeanFlow`) the reference is the time-resolved flow at the scene's tolerance ``tol``
    in the same domain (the flow's box): the estimate is the model's error. Returns max and
    median of the end-point distances [L], the tracers used and the reference in words.
    ``domain`` (6,), where given (a standing carpet's, from the substrate up), bounds the time-resolved
    reference too. The reference run is one task (:func:`error_reference`), in this process
    unless ``pool`` says where (a render runs it beside its path lines' chunks)."""
    task, idx, what = error_reference(carpet, seeds, duration, pl.rtol, pl.atol, model, flow, tol, spacing,
                                      domain=domain)
    if pool is None:
        from cilia_runtime.pool import InProcess

        pool = InProcess()
    ref = pool.run([task], shared=[carpet])[0].value
    return end_point_error(pl, ref, idx, what)


def error_reference(carpet: Carpet, seeds: np.ndarray, duration: float, rtol: float, atol: float, model: str, flow,
                    tol: float, spacing: float, domain=None):
    """The reference run of :func:`pathline_error` for path lines integrated with ``rtol`` and
    ``atol`` in ``flow``, as one :class:`~ciliary_carpet.transport.parallel.Task` (its
    :data:`ERROR_SAMPLE` tracers integrated together): ``(task, tracer indices, the reference in
    words)``; :func:`end_point_error` compares its result with the path lines."""
    idx = error_tracers(seeds.shape[0])
    label = "path lines' error estimate: the reference run"
    if model == "mean":
        (task,) = pathline_tasks(ResolvedFlow(carpet, tol), seeds[idx], (0.0, duration), chunk_size=None, label=label,
                                 rtol=1e-6, atol=1e-4 * spacing, samples_per_period=1,
                                 domain=tuple(float(v) for v in flow.box))
        what = f"the time-resolved flow (rtol 1e-6, flow tol {tol:g}): the long-time model's error"
    else:
        ft, ti = REFERENCE_TIGHTER
        t_ref, r_rtol, r_atol = flow.tol / ft, rtol / ti, atol / ti
        (task,) = pathline_tasks(ResolvedFlow(carpet, t_ref), seeds[idx], (0.0, duration), chunk_size=None,
                                 label=label, rtol=r_rtol, atol=r_atol, samples_per_period=1, domain=domain)
        what = (f"flow tol {t_ref:.3g}, rtol {r_rtol:.3g}, atol {r_atol:.3g} L (the render's path lines: flow tol "
                f"{flow.tol:.3g}, rtol {rtol:.3g}, atol {atol:.3g} L): integration and levels of detail")
    return task, idx, what


def end_point_error(pl, ref, idx: np.ndarray, what: str) -> dict:
    """The estimate of :func:`pathline_error` from its reference run ``ref`` of tracers ``idx``."""
    e = np.linalg.norm(pl.end_points[idx] - ref.end_points, axis=1)
    return {"max": float(e.max()), "median": float(np.median(e)), "tracers": int(idx.size), "reference": what}


class PathLinesOutput(Output):
    """``pathlines.vtp`` and ``particles.pvd`` (``particles_NNNNN.vtp``): the tracers from the plan's
    seeds in the plan's path-line model, with an end-point error estimate (leaves ``ctx.pathlines``).
    A standing carpet's tracers move in space, in the plan's domain (from the substrate up).
    The tracers' chunks (:data:`~ciliary_carpet.transport.pathlines.CHUNK_SIZE`) and the estimate's
    reference run (:func:`error_reference`) go to ``ctx.pool`` together, biggest first, and the
    summary's own computations after them (:func:`summary_tasks`): on two cores the reference, then
    those, run beside the path lines (the numbers do not depend on the pool; the timings are in
    benchmarks/results/bench_pathlines_parallel.md)."""

    name = "pathlines"
    files = (r"pathlines\.vtp", r"particles_\d+\.vtp", r"particles\.pvd")

    def wanted(self, plan):
        return bool(plan.scene.output.pathlines)

    def write(self, ctx):
        plan, c = ctx.plan, ctx.carpet
        o, tol, spacing = plan.scene.output, plan.scene.tolerance, plan.scene.carpet.spacing
        seeds, duration, model = plan.seeds, plan.duration, plan.pathline_model
        L, T, _ = plan.units
        pool = ctx.pool if ctx.pool is not None else InProcess()
        with ctx.timed("pathlines"):
            if model == "mean":  # the model's own error (MEAN_MODEL_ERROR) is far above the integration's
                flow = ctx.standing_mean_flow() if c.geometry == "standing" else ctx.mean_flow()
                rtol, atol = 1e-6, 1e-4 * spacing
            else:
                flow = ResolvedFlow(c, min(tol, PATHLINE_TOL), precision=PATHLINE_PRECISION)
                rtol, atol = PATHLINE_RTOL, PATHLINE_ATOL * spacing
            # the path lines' chunks and the error estimate's reference run, together, biggest first
            tasks = pathline_tasks(flow, seeds, (0.0, duration), chunk_size=CHUNK_SIZE, rtol=rtol, atol=atol,
                                   samples_per_period=o.samples_per_period, domain=plan.domain)
            ref_task, idx, what = error_reference(c, seeds, duration, rtol, atol, model, flow, tol, spacing,
                                                  domain=plan.domain)
            # and the summary's own computations, last: a worker takes them once the reference is done
            side = summary_tasks(ctx)
            clock = _time.perf_counter()
            results = pool.run(tasks + [ref_task] + [t for _, t in side], shared=[c])
            wall = _time.perf_counter() - clock
            n = len(tasks)
            ctx.beside.update({name: r for (name, _), r in zip(side, results[n + 1:])})
            pl = join_pathlines([r.value for r in results[:n]], t_end=duration, wall=wall,
                                where=[r.where for r in results[:n]], workers=pool.workers)
            ref = results[n]
            pl.write(ctx.stage / "pathlines.vtp", scales=plan.scales, max_points=o.pathline_points or None)
            pl.write_particles(ctx.stage / "particles.pvd", scales=plan.scales)
        with ctx.timed("pathline_error"):  # (its reference ran with the path lines above)
            err = end_point_error(pl, ref.value, idx, what)
        err["work"] = {**ref.value.stats, "where": ref.where}
        ctx.pathlines = pl
        ctx.summary["pathlines"] = {
            "tracers": int(seeds.shape[0]), "duration": duration * T, "duration_from": plan.duration_from,
            "periods": duration / plan.T0, "beats": duration / plan.beat.period, "model": model,
            "model_from": plan.model_from,
            "flow_tol": flow.tol if model != "mean" else None, "rtol": rtol, "atol": atol * L,
            "samples_per_period": o.samples_per_period, "outcome": pl.counts(),
            "points": int(sum(t.size for t in pl.times)),
            "points_written": int(sum(k.size for k in pl.thinned(o.pathline_points or None))),
            "stopped_early": int(np.sum(pl.reason == UNDERFLOW)), "status": pl.status, "message": pl.message,
            "work": pl.stats, "end_point_error": dict(err, max=err["max"] * L, median=err["median"] * L),
            "parallel": {"where": repr(pool), "places": pool.workers,
                         "threads": (pool.budget.as_dict() if pool.budget is not None else threads_in_use()),
                         "startup_seconds": dict(getattr(pool, "startup", {})), "wall_seconds": wall}}


def _omissions_summary(carpet: Carpet, tol: float) -> dict:
    """The summary's ``omissions`` section (:func:`~ciliary_carpet.carpet.omissions.omissions`)."""
    return omissions(carpet, tol=tol).summary()


def _coupling_summary(carpet: Carpet, tol: float) -> dict:
    """The summary's ``coupling`` section of an uncoupled planar carpet (its size estimated)."""
    return {**coupling_estimate(carpet, tol=tol), "status": "not solved"}


def summary_tasks(ctx: RenderContext, pool_only: bool = True) -> list:
    """The summary's computations that need only the carpet, as ``(name, Task)``: what the model
    leaves out (``omissions``) and, for an uncoupled planar carpet, the size of the coupling
    (``coupling``). The path lines run them in their pool after their own tasks (cost 0: last),
    so that on two cores a worker takes them once the error estimate's reference is done, beside
    the path lines' main run; the numbers are the same wherever they run (one BLAS thread in a
    worker; the sums give the same numbers on any numba thread count). ``pool_only``: none unless
    the render's pool has worker processes (in this process they run where the summary is made)."""
    from cilia_runtime.pool import Task

    if pool_only and getattr(ctx.pool, "workers", 1) < 2:
        return []
    c, tol = ctx.carpet, min(ctx.plan.scene.tolerance, 1e-3)
    out = [("omissions", Task("the summary: what the model leaves out", _omissions_summary, (c, tol), cost=0.0))]
    if c.coupled is None:  # uncoupled: the linear estimate of the coupling's size (each cilium's frame)
        out.append(("coupling", Task("the summary: the size of the coupling", _coupling_summary, (c, tol), cost=0.0)))
    return out


class FtleOutput(Output):
    """``ftle.vti``: the FTLE over the carpet in the long-time flow, for a quarter of the path-line
    duration; the mixing number in the summary. A standing carpet's: over its footprint in the
    target plane z = h, 2D tracers in that plane's in-plane mean flow (:meth:`RenderContext.mean_flow`)."""

    name = "ftle"
    files = (r"ftle\.vti",)

    def wanted(self, plan):
        return bool(plan.scene.output.ftle)

    def write(self, ctx):
        plan, b = ctx.plan, ctx.carpet.bases
        fs, T = plan.scene.output.field_shape, plan.units[1]
        nx, ny = max(3, fs[0] // 2), max(3, fs[1] // 2)
        with ctx.timed("ftle"):
            f = ftle_field(ctx.mean_flow(), (b[:, 0].min(), b[:, 0].max(), b[:, 1].min(), b[:, 1].max()), (nx, ny),
                           0.25 * plan.duration, rtol=1e-6,
                           atol=1e-4 * plan.scene.carpet.spacing,
                           **({"height": float(plan.grid.origin[2])} if ctx.carpet.geometry == "standing" else {}))
            f.write(ctx.stage / "ftle.vti", scales=plan.scales)
        defined = np.isfinite(f.ftle)
        ctx.summary["mixing"] = {"mixing_number": f.mixing_number,
                                 "ftle_max": float(np.nanmax(f.ftle)) / T if np.any(defined) else None,
                                 "duration": f.duration * T, "grid": [nx, ny], "model": f.model,
                                 "defined_fraction": float(np.mean(defined))}
        d = ctx.design
        if ctx.carpet.geometry == "standing" and d is not None and d.azimuth is not None:
            with ctx.timed("ftle_pump"):
                ctx.summary["mixing"]["uniform_pump"] = self._uniform_pump(ctx, (nx, ny), f.duration)

    @staticmethod
    def _uniform_pump(ctx, shape, duration) -> dict:
        """The mixing number of the same standing carpet pumping uniformly -- every cilium at the
        pumping maximum chi_hi, every beat plane along the designed layout's mean azimuth (the
        direction of the sum of the cilia's pumping vectors) -- over the same grid and duration:
        what the design adds to the mixing a carpet gives by carrying the fluid along."""
        from ciliary_carpet.design.surface import pumping_curvature

        c, d, plan = ctx.carpet, ctx.design, ctx.plan
        chi_hi, _ = pumping_curvature(c.table)
        psi = float(np.angle(np.sum(np.exp(1j * d.azimuth) * np.abs(d.chi_N))))
        pump = replace(c, chi_N=np.full(c.n, chi_hi), azimuth=np.full(c.n, psi))
        g = plan.grid
        mf = MeanField(g, g.points(), pump.velocity(g.points(), CycleMean(), plan.scene.tolerance))
        nx, ny = g.shape[:2]
        flow = MeanFlow.from_grid(pump, *g.lines(), mf.velocity.reshape(ny, nx, 3))
        b = c.bases
        f = ftle_field(flow, (b[:, 0].min(), b[:, 0].max(), b[:, 1].min(), b[:, 1].max()), shape, duration,
                       rtol=1e-6, atol=1e-4 * plan.scene.carpet.spacing, height=float(g.origin[2]))
        return {"mixing_number": f.mixing_number, "chi_N": chi_hi, "azimuth_deg": math.degrees(psi) % 360.0,
                "defined_fraction": float(np.mean(np.isfinite(f.ftle)))}


class PreviewOutput(Output):
    """``preview.png``: the mean flow's streamlines, the path lines and the layout."""

    name = "preview"
    files = (r"preview\.png",)

    def wanted(self, plan):
        return bool(plan.scene.output.preview)

    def write(self, ctx):
        with ctx.timed("preview"):
            if ctx.carpet.geometry == "standing":
                standing_preview(ctx.stage / "preview.png", ctx.plan.scene, ctx.carpet, ctx.mean_field, ctx.pathlines)
            else:
                preview(ctx.stage / "preview.png", ctx.plan.scene, ctx.carpet, ctx.mean_field, ctx.pathlines, ctx.design)


class ParaViewOutput(Output):
    """``open_in_paraview.py``: the script that opens the render folder in ParaView."""

    name = "paraview"
    files = (re.escape(SCRIPT),)

    def wanted(self, plan):
        return True

    def write(self, ctx):
        write_script(ctx.stage / SCRIPT, ctx.out_dir, si=ctx.plan.scales is not None, scene=ctx.plan.scene.name,
                     geometry=ctx.carpet.geometry)


class SummaryOutput(Output):
    """``summary.json`` (strict JSON) and ``summary.md``: the summary, with what the model leaves
    out, the seconds by stage, the resolved scene and the threads used. Last: a summary with a
    NaN or an infinity is a :class:`~ciliary_carpet.output.RenderError` (nothing is placed)."""

    name = "summary"
    files = (re.escape(SUMMARY), r"summary\.md")

    def wanted(self, plan):
        return True

    def write(self, ctx):
        scene, summary = ctx.plan.scene, ctx.summary
        # what the model leaves out (interaction between cilia, the wall's drag, the viscosity), sized,
        # and the cilia's coupling through their mean flow: solved ("mean"), or its size estimated
        # ("none"); computed here, or beside the path lines (summary_tasks), then timed there
        todo = dict(summary_tasks(ctx, pool_only=False))
        for name in ("omissions", "coupling"):
            got = ctx.beside.get(name)
            if got is not None:
                summary[name] = got.value
                ctx.clock[name] = 0.0
                ctx.clock[f"{name}_beside_pathlines"] = got.seconds
            elif name in todo:
                with ctx.timed(name):
                    task = todo[name]
                    summary[name] = task.func(*task.args, **task.kwargs)
        c = ctx.carpet
        if c.coupled is not None:  # solved: the carpet says how
            summary["coupling"] = c.coupled.summary()
        if "coupling" in summary:  # its speeds in the summary's units
            V = ctx.plan.units[2]
            summary["coupling"] = {k: (v * V if k in _COUPLING_SPEEDS and v is not None else v)
                                   for k, v in summary["coupling"].items()}
        if "omissions" in summary:
            summary["omissions"]["units"] = OMISSIONS_UNITS
        ctx.clock["total"] = _time.perf_counter() - ctx.started
        summary["seconds"] = ctx.clock
        summary["scene_resolved"] = scene.to_dict()
        summary["threads"] = threads_in_use()  # the numba and BLAS threads (and batch workers) used
        bad = non_finite(summary)
        if bad:
            listed = "; ".join(f"{k} = {v}" for k, v in list(bad.items())[:3])
            raise RenderError(f"{scene.source_name}: the render gave non-finite numbers ({listed}); nothing was "
                              f"written to {ctx.out_dir}")
        (ctx.stage / "summary.md").write_text(markdown(summary))
        (ctx.stage / SUMMARY).write_text(strict_json(summary, indent=2))


OUTPUTS: dict[str, type[Output]] = {o.name: o for o in (
    LayoutOutput, DesignOutput, MeanFieldOutput, SnapshotsOutput, FramesOutput, PathLinesOutput, FtleOutput,
    PreviewOutput, ParaViewOutput, SummaryOutput)}
"""The outputs by name, in the order a render writes them."""
