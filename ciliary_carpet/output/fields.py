"""The flow and the cilia over time: the time-averaged flow on the field grid (``mean_field``), the
instantaneous flow over one beat (``snapshots``) and the cilia over one beat (``frames``), whose
``.pvd`` collections play that beat on over the render's time range.
"""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from cilia_runtime.threads import threads_in_use

from ciliary_carpet.carpet.carpet import CycleMean, Instant
from ciliary_carpet.output.contract import MeanField, Output
from ciliary_carpet.output.plan import ANIMATION_STEPS, FieldGrid, RenderPlan
from ciliary_carpet.output.vtkfiles import write_cilia, write_field, write_pvd

__all__ = ["MeanFieldOutput", "SnapshotsOutput", "FramesOutput"]


def _vorticity(u: np.ndarray, spacing, shape) -> np.ndarray:
    """(n, 3) vorticity of a field on a grid of ``shape`` (nx, ny, nz), from the grid's own
    derivatives (second-order differences): (0, du/dz - dw/dx, 0) on a vertical x-z section
    (nx, 1, nz), else (0, 0, dv/dx - du/dy) on an in-plane (nx, ny, 1) grid."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    if ny == 1 and nz > 1:
        U, W = u[:, 0].reshape(nz, nx), u[:, 2].reshape(nz, nx)
        axis, curl = 1, np.gradient(U, spacing[2], axis=0) - np.gradient(W, spacing[0], axis=1)
    else:
        U, V = u[:, 0].reshape(ny, nx), u[:, 1].reshape(ny, nx)
        axis, curl = 2, np.gradient(V, spacing[0], axis=1) - np.gradient(U, spacing[1], axis=0)
    w = np.zeros((u.shape[0], 3))
    w[:, axis] = curl.ravel()
    return w


def _write_flow(path: Path, grid: FieldGrid, sample, plan: RenderPlan, time: float | None = None) -> Path:
    """A field file of a flow ``sample`` on ``grid``: velocity, speed, vorticity (:func:`_vorticity`),
    error bound."""
    L, T, V = plan.units
    u = sample.velocity
    return write_field(path, np.asarray(grid.origin) * L, np.asarray(grid.spacing) * L, grid.shape,
                       {"velocity": u * V, "speed": np.linalg.norm(u, axis=1) * V,
                        "vorticity": _vorticity(u, grid.spacing, grid.shape) / T,
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


class MeanFieldOutput(Output):
    """``mean_field.vti``: the time-averaged flow on the field grid (leaves ``ctx.mean_field``); a
    standing carpet's also ``mean_field_section.vti`` on its vertical section (``ctx.section_field``)."""

    name = "mean_field"
    files = (r"mean_field\.vti", r"mean_field_section\.vti")

    def wanted(self, plan):
        return bool(plan.settings.output.field)

    def write(self, ctx):
        grid, V = ctx.plan.grid, ctx.plan.units[2]
        with ctx.timed("mean_field"):
            pts = grid.points()
            s = ctx.carpet.evaluate(pts, CycleMean(), tol=ctx.plan.settings.tolerance)
            ctx.mean_field = MeanField(grid, pts, s.velocity)
            _write_flow(ctx.stage / "mean_field.vti", grid, s, ctx.plan)
            sec = ctx.plan.section
            if sec is not None:  # a standing carpet: the vertical section, down to the wall
                sp = sec.points()
                ss = ctx.carpet.evaluate(sp, CycleMean(), tol=ctx.plan.settings.tolerance)
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
        return plan.settings.output.snapshots > 0

    def write(self, ctx):
        plan = ctx.plan
        n, Tb, T = plan.settings.output.snapshots, plan.beat.period, plan.units[1]
        with ctx.timed("snapshots"):
            pts = plan.grid.points()
            entries, fid = [], []
            for k in range(n):
                t = k * Tb / n
                s = ctx.carpet.evaluate(pts, Instant(t), tol=plan.settings.tolerance)
                entries.append(_write_flow(ctx.stage / f"snapshot_{k:03d}.vti", plan.grid, s, plan, time=t * T))
                fid.append(s.fidelity)
            write_pvd(ctx.stage / "snapshots.pvd", _looped(entries, Tb * T, plan.span * T))
            sec = plan.section
            if sec is not None:  # a standing carpet: its vertical section too
                sp, entries = sec.points(), []
                for k in range(n):
                    t = k * Tb / n
                    s = ctx.carpet.evaluate(sp, Instant(t), tol=plan.settings.tolerance)
                    entries.append(_write_flow(ctx.stage / f"snapshot_section_{k:03d}.vti", sec, s, plan, time=t * T))
                write_pvd(ctx.stage / "snapshots_section.pvd", _looped(entries, Tb * T, plan.span * T))
        ctx.summary["snapshots"] = {"count": n, "fidelity": fid[0]}


class FramesOutput(Output):
    """``cilia_NNN.vtp``: the filaments over one beat (arc length, drag density), ``cilia.pvd`` (a
    standing carpet's in space, 3D polylines)."""

    name = "frames"
    files = (r"cilia_\d+\.vtp", r"cilia\.pvd")

    def wanted(self, plan):
        return plan.settings.output.frames > 0

    def write(self, ctx):
        plan, c = ctx.plan, ctx.carpet
        n, Tb, (L, T, V), sc = plan.settings.output.frames, plan.beat.period, plan.units, plan.scales
        f_scale = sc.viscosity_Pa_s * V / c.mu if sc is not None else 1.0
        # The shapes are made here, one frame after the other; the files are written by the
        # render's threads (VTK's writer and the disk let go of the interpreter: two threads write
        # 40 frames of 10^4 cilia in 0.6 of the time of one), at most one frame ahead of each.
        writers = max(1, threads_in_use()["numba"])
        with ctx.timed("frames"), ThreadPoolExecutor(max_workers=writers) as pool:
            jobs, pending = [], []
            for k in range(n):
                t = k * Tb / n
                pos, f, ph = c.placement.shapes(c, t)  # in space (a standing beat plane turned by its azimuth)
                args = (pos * L, c.s * L, np.arange(c.n), c.chi_N, ph)
                kw = dict(drag=f * f_scale, time=t * T)
                if len(pending) > writers:
                    pending.pop(0).result()
                pending.append(pool.submit(write_cilia, ctx.stage / f"cilia_{k:03d}.vtp", *args, **kw))
                jobs.append(pending[-1])
            entries = [j.result() for j in jobs]  # the first error of a write, raised here
            write_pvd(ctx.stage / "cilia.pvd", _looped(entries, Tb * T, plan.span * T))
