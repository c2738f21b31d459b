"""The tracers' outputs: the path lines (``pathlines``: ``pathlines.vtp`` and the tracers as moving
points, ``particles.pvd``) and the FTLE (``ftle``: ``ftle.vti``), and the VTK files of the transport
layer's results they write (:func:`pathlines_to_vtp`, :func:`particles_to_pvd`, :func:`ftle_to_vti`).
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import replace
from pathlib import Path

import numpy as np

from cilia_runtime.pool import InProcess
from cilia_runtime.threads import threads_in_use

from ciliary_carpet.carpet.carpet import CycleMean
from ciliary_carpet.design.surface_model import pumping_curvature
from ciliary_carpet.output.contract import MeanField, Output
from ciliary_carpet.output.summary import summary_tasks
from ciliary_carpet.output.vtkfiles import write_field, write_pathlines, write_points, write_pvd
from ciliary_carpet.transport.accuracy import (
    PATHLINE_ATOL,
    PATHLINE_PRECISION,
    PATHLINE_RTOL,
    PATHLINE_TOL,
    end_point_error,
    error_reference,
)
from ciliary_carpet.transport.flow import MeanFlow, ResolvedFlow
from ciliary_carpet.transport.ftle import FTLEField, ftle_field
from ciliary_carpet.transport.pathlines import (
    CHUNK_SIZE,
    REASONS,
    UNDERFLOW,
    PathLines,
    join_pathlines,
    pathline_tasks,
)

__all__ = ["PathLinesOutput", "FtleOutput", "pathlines_to_vtp", "particles_to_pvd", "ftle_to_vti"]


def _units(scales) -> tuple[float, float]:
    """The length and time units [m, s] of ``scales`` (a Scales), or (1, 1) in model units."""
    return (scales.length_m, scales.time_s) if scales is not None else (1.0, 1.0)


def pathlines_to_vtp(pl: PathLines, path, scales=None, max_points: int | None = None) -> Path:
    """Write path lines ``pl`` as a ``.vtp`` (:func:`~ciliary_carpet.output.vtkfiles.write_pathlines`:
    one polyline per tracer; point data time, IntegrationTime, velocity, speed; cell data SeedIds,
    TerminationReason with its names in field data), in SI units when ``scales`` (a Scales) is
    given; with ``max_points``, at most that many points of each tracer
    (:meth:`PathLines.thinned <ciliary_carpet.transport.pathlines.PathLines.thinned>`). Returns ``path``."""
    L, T = _units(scales)
    keep = pl.thinned(max_points)
    return write_pathlines(path, [p[k] * L for p, k in zip(pl.points, keep)],
                           [t[k] * T for t, k in zip(pl.times, keep)],
                           [v[k] * (L / T) for v, k in zip(pl.velocities, keep)], pl.seed_ids, pl.reason,
                           REASONS)


def particles_to_pvd(pl: PathLines, path, scales=None, max_frames: int = 200) -> Path:
    """Write the tracers of ``pl`` over time as ParaView's ParticlePath gives them: a ``.pvd`` at
    ``path`` over point sets ``<stem>_NNNNN.vtp`` beside it (point data SeedIds, velocity, speed),
    at most ``max_frames`` of the dense output times (evenly strided), in SI units when ``scales``
    is given. The frames sit in the same folder (no subfolder), like the other time series of a
    render, so that a render's manifest lists every file it wrote. Returns ``path``."""
    path = Path(path)
    folder = path.parent
    L, T = _units(scales)
    grid = pl.times[int(np.argmax([t.size for t in pl.times]))]
    stride = max(1, int(math.ceil(grid.size / max(1, int(max_frames)))))
    entries = []
    for j in range(0, grid.size, stride):
        t = grid[j]
        alive = [k for k, tk in enumerate(pl.times) if j < tk.size and tk[j] == t]
        if not alive:
            continue
        p = np.array([pl.points[k][j] for k in alive]) * L
        v = np.array([pl.velocities[k][j] for k in alive]) * (L / T)
        f = write_points(folder / f"{path.stem}_{j:05d}.vtp", p,
                         {"SeedIds": pl.seed_ids[alive].astype(np.int32), "velocity": v,
                          "speed": np.linalg.norm(v, axis=1)})
        entries.append((float(t) * T, f))
    return write_pvd(path, entries)


def ftle_to_vti(f: FTLEField, path, scales=None) -> Path:
    """Write the FTLE field ``f`` as a ``.vti`` on its grid in the plane z = ``f.height`` (point
    data "FTLE", in 1/s when ``scales`` is given). Returns ``path``."""
    L, T = _units(scales)
    nx, ny = f.shape
    return write_field(path, (f.origin[0] * L, f.origin[1] * L, f.height * L),
                       (f.spacing[0] * L, f.spacing[1] * L, 1.0), (nx, ny, 1),
                       {"FTLE": f.ftle.ravel() / T})


class PathLinesOutput(Output):
    """``pathlines.vtp`` and ``particles.pvd`` (``particles_NNNNN.vtp``): the tracers from the plan's
    seeds in the plan's path-line model, with an end-point error estimate (leaves ``ctx.pathlines``).
    A standing carpet's tracers move in space, in the plan's domain (from the substrate up).
    The tracers' chunks (:data:`~ciliary_carpet.transport.pathlines.CHUNK_SIZE`) and the estimate's
    reference run (:func:`~ciliary_carpet.transport.accuracy.error_reference`) go to ``ctx.pool``
    together, biggest first, and the summary's own computations after them
    (:func:`~ciliary_carpet.output.summary.summary_tasks`): on two cores the reference, then those,
    run beside the path lines (the numbers do not depend on the pool; the timings are in
    benchmarks/results/bench_pathlines_parallel.md). Each task finished advances
    ``ctx.progress``, so that the render's progress shows the path lines' share done."""

    name = "pathlines"
    files = (r"pathlines\.vtp", r"particles_\d+\.vtp", r"particles\.pvd")

    def wanted(self, plan):
        return bool(plan.settings.output.pathlines)

    def write(self, ctx):
        plan, c = ctx.plan, ctx.carpet
        o, tol, spacing = plan.settings.output, plan.settings.tolerance, plan.settings.spacing
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
            results = pool.run(tasks + [ref_task] + [t for _, t in side], shared=[c], progress=ctx.progress)
            wall = _time.perf_counter() - clock
            n = len(tasks)
            ctx.beside.update({name: r for (name, _), r in zip(side, results[n + 1:])})
            pl = join_pathlines([r.value for r in results[:n]], t_end=duration, wall=wall,
                                where=[r.where for r in results[:n]], workers=pool.workers)
            ref = results[n]
            pathlines_to_vtp(pl, ctx.stage / "pathlines.vtp", scales=plan.scales, max_points=o.pathline_points or None)
            particles_to_pvd(pl, ctx.stage / "particles.pvd", scales=plan.scales)
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



class FtleOutput(Output):
    """``ftle.vti``: the FTLE over the carpet in the long-time flow, for a quarter of the path-line
    duration; the mixing number in the summary. A standing carpet's: over its footprint in the
    target plane z = h, 2D tracers in that plane's in-plane mean flow
    (:meth:`RenderContext.mean_flow <ciliary_carpet.output.contract.RenderContext.mean_flow>`)."""

    name = "ftle"
    files = (r"ftle\.vti",)

    def wanted(self, plan):
        return bool(plan.settings.output.ftle)

    def write(self, ctx):
        plan, b = ctx.plan, ctx.carpet.bases
        fs, T = plan.settings.output.field_shape, plan.units[1]
        nx, ny = max(3, fs[0] // 2), max(3, fs[1] // 2)
        with ctx.timed("ftle"):
            f = ftle_field(ctx.mean_flow(), (b[:, 0].min(), b[:, 0].max(), b[:, 1].min(), b[:, 1].max()), (nx, ny),
                           0.25 * plan.duration, rtol=1e-6,
                           atol=1e-4 * plan.settings.spacing,
                           **plan.settings.outputs.ftle_options(plan))
            ftle_to_vti(f, ctx.stage / "ftle.vti", scales=plan.scales)
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
        c, d, plan = ctx.carpet, ctx.design, ctx.plan
        chi_hi, _ = pumping_curvature(c.table)
        psi = float(np.angle(np.sum(np.exp(1j * d.azimuth) * np.abs(d.chi_N))))
        pump = replace(c, chi_N=np.full(c.n, chi_hi), azimuth=np.full(c.n, psi))
        g = plan.grid
        mf = MeanField(g, g.points(), pump.velocity(g.points(), CycleMean(), plan.settings.tolerance))
        nx, ny = g.shape[:2]
        flow = MeanFlow.from_grid(pump, *g.lines(), mf.velocity.reshape(ny, nx, 3))
        b = c.bases
        f = ftle_field(flow, (b[:, 0].min(), b[:, 0].max(), b[:, 1].min(), b[:, 1].max()), shape, duration,
                       rtol=1e-6, atol=1e-4 * plan.settings.spacing, height=float(g.origin[2]))
        return {"mixing_number": f.mixing_number, "chi_N": chi_hi, "azimuth_deg": math.degrees(psi) % 360.0,
                "defined_fraction": float(np.mean(np.isfinite(f.ftle)))}
