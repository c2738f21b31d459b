"""The main job: a scene file in, a folder of ParaView-ready outputs out.

:func:`render` designs the layout (when the scene has a target), evaluates the flow at the
scene's tolerance and writes, into ``out_dir``:

==========================  ==================================================================
``layout.nc``               the designed layout (chi_N per cilium, control points, residuals)
``layout.vtp``              base points coloured by chi_N (and thrust angle)
``mean_field.vti``          the time-averaged velocity (active vectors), speed, vorticity and the
                            error bound on a grid around the carpet
``snapshot_NNN.vti``        instantaneous fields, tied by ``snapshots.pvd``
``cilia_NNN.vtp``           filament shapes per frame (arc length, drag density), ``cilia.pvd``
``pathlines.vtp``           tracer path lines (time, IntegrationTime, velocity, speed; SeedIds,
                            TerminationReason with TerminationReasonNames), >= 16 points per beat
``particles.pvd``           the tracers as moving points (``particles/``), as ParticlePath gives
``open_in_paraview.py``     ``pvpython open_in_paraview.py`` (or ``paraview --script=...``) opens
                            the whole scene: fields, cilia, path lines, particles
``ftle.vti``                finite-time Lyapunov exponent over the carpet (mean flow, a quarter of
                            the path-line duration); the mixing number is in the summary
``preview.png``             the mean flow (streamlines) with the layout and path lines
``summary.json``, ``.md``   residuals, timings, fidelity used, error bounds, path-line outcome
==========================  ==================================================================

The whole folder is written atomically: everything goes into a hidden staging folder next to
``out_dir``, which is renamed onto ``out_dir`` only when complete (``summary.json`` last). An
existing ``out_dir`` is kept unless ``overwrite=True``. Times are in units of tau, lengths in L
(SI when the scene has ``[units]``). The periods of the outputs (snapshots, frames, path-line
duration) are counted in periods of the straight filament, T0 = T(chi_N = 0).

Path lines (:func:`pathline_duration`, :func:`pathline_model`): unless the scene sets
``[output] periods``, the duration is long enough for a tracer to cross the whole carpet at the
carpet's median mean speed (1.25 times the carpet's extent along the flow plus three spacings,
divided by that speed). The flow they follow is the time-resolved beat or the long-time mean
flow (``[output] pathline_model``; "auto" takes the mean flow when the scene's tolerance allows
its measured error). The flow uses the regularised Stokeslets of ``[carpet] blob``: it is bounded
everywhere, so the fields are not blanked inside the cilia's swept regions.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import tempfile
import time as _time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from single_cilium._io import write_netcdf
from single_cilium.progress import Progress

from .carpet import Carpet
from .design import design
from .ftle import ftle_field
from .pathlines import MEAN_MODEL_ERROR, UNDERFLOW, MeanFlow, check_output_size, check_seeds
from .scene import Scene
from .vtkfiles import grid_points, write_cilia, write_field, write_points, write_pvd

logger = logging.getLogger(__name__)

__all__ = ["render", "RenderResult", "RenderError", "is_complete", "pathline_duration", "pathline_model"]

SUMMARY = "summary.json"


class RenderError(RuntimeError):
    """The output folder cannot be (re)written as asked."""


@dataclass(frozen=True)
class RenderResult:
    """What a render wrote: the folder, its files, and the summary (also in summary.json)."""

    out_dir: Path
    files: tuple
    summary: dict


def is_complete(out_dir, sources=()) -> bool:
    """Whether ``out_dir`` holds a complete render newer than every file in ``sources``."""
    s = Path(out_dir) / SUMMARY
    if not s.is_file():
        return False
    t = s.stat().st_mtime
    return all(Path(p).stat().st_mtime < t for p in sources if p is not None and Path(p).exists())


def _seeds(scene: Scene, carpet: Carpet) -> np.ndarray:
    o = scene.output
    if not isinstance(o.seeds, str):
        return np.asarray(o.seeds, dtype=float)
    b = carpet.bases
    d0 = scene.field.flow_direction
    cross = np.array([-d0[1], d0[0]])
    c = 0.5 * (b.min(0) + b.max(0))
    along = (b - c) @ d0
    across = (b - c) @ cross
    if o.seeds == "line":  # across the carpet, one spacing upstream of it
        s = np.linspace(across.min(), across.max(), o.n_seeds)
        seeds = c + (along.min() - scene.carpet.spacing) * d0 + s[:, None] * cross
    else:
        n = max(2, int(round(math.sqrt(o.n_seeds))))  # grid: between the cilia
        a = np.linspace(along.min(), along.max(), n) + 0.5 * scene.carpet.spacing
        s = np.linspace(across.min(), across.max(), n) + 0.5 * scene.carpet.spacing
        A, S = np.meshgrid(a, s)
        seeds = c + A.ravel()[:, None] * d0 + S.ravel()[:, None] * cross
    # never inside a filament: nudge a seed across the flow until it is two blob sizes clear
    clear = 2.0 * (carpet.blob or 0.02)
    for _ in range(100):
        bad = carpet.filament_distance(seeds, 0.0) < clear
        if not bad.any():
            break
        seeds[bad] += clear * cross
    return seeds


def pathline_duration(scene: Scene, carpet: Carpet, T0: float) -> tuple[float, str]:
    """Path-line duration and how it was chosen: ``[output] periods * T0`` when the scene sets
    it, else long enough to cross the carpet: 1.25 (extent along the flow + 3 spacings) / U, with
    U the median speed of the mean flow at points between the cilia."""
    o = scene.output
    if o.periods is not None:
        return float(o.periods) * T0, "scene"
    b = carpet.bases
    d0 = np.asarray(scene.field.flow_direction, dtype=float)
    sp = scene.carpet.spacing
    travel = float(np.ptp(b @ d0)) + 3.0 * sp
    probe = b[:: max(1, b.shape[0] // 200)] + 0.5 * sp * (d0 + np.array([-d0[1], d0[0]]))
    speed = float(np.median(np.linalg.norm(carpet.mean_velocity(probe, max(scene.tolerance, 1e-3))[:, :2], axis=1)))
    if not (math.isfinite(speed) and speed > 0):
        raise RenderError(f"{scene.source_name}: the carpet makes no mean flow (median speed {speed:g}): set "
                          "[output] periods for the path lines")
    return 1.25 * travel / speed, f"auto: crossing {travel:.3g} L at the median mean speed {speed:.3g} L/tau"


def pathline_model(scene: Scene) -> str:
    """The flow the tracers follow: ``[output] pathline_model``, "auto" resolved to "mean" when
    the scene's tolerance is at least :data:`~ciliary_carpet.pathlines.MEAN_MODEL_ERROR`."""
    m = scene.output.pathline_model
    if m == "auto":
        return "mean" if scene.tolerance >= MEAN_MODEL_ERROR else "resolved"
    return m


def _field_grid(scene: Scene, carpet: Carpet):
    b = carpet.bases
    m = scene.output.field_margin
    lo, hi = b.min(0) - m - 1.0, b.max(0) + m + 1.0
    nx, ny = scene.output.field_shape
    spacing = ((hi[0] - lo[0]) / max(nx - 1, 1), (hi[1] - lo[1]) / max(ny - 1, 1), 1.0)
    origin = (lo[0], lo[1], 0.0)
    shape = (nx, ny, 1)
    return origin, spacing, shape, grid_points(origin, spacing, shape)


def _field_box(scene: Scene, carpet: Carpet) -> tuple:
    b = carpet.bases
    m = scene.output.field_margin
    lo, hi = b.min(0) - m - 1.0, b.max(0) + m + 1.0
    return (lo[0], hi[0], lo[1], hi[1])


def _mean_flow(scene: Scene, carpet: Carpet, mean_field, tol: float) -> MeanFlow:
    """The long-time model from the render's mean field (or evaluated on the same grid)."""
    if mean_field is not None:
        shape = mean_field[2]
        return MeanFlow.from_grid(*_grid_lines(mean_field), mean_field[4].reshape(shape[1], shape[0], 3))
    box = _field_box(scene, carpet)
    spacing = min((box[1] - box[0]) / (scene.output.field_shape[0] - 1), (box[3] - box[2]) / (scene.output.field_shape[1] - 1))
    return MeanFlow.from_carpet(carpet, box, spacing=spacing, tol=max(tol, 1e-6))


def _grid_lines(mean_field) -> tuple[np.ndarray, np.ndarray]:
    origin, spacing, shape = mean_field[:3]
    return (origin[0] + spacing[0] * np.arange(shape[0]), origin[1] + spacing[1] * np.arange(shape[1]))


def _vorticity(u: np.ndarray, spacing, shape) -> np.ndarray:
    """(n, 3) vorticity (0, 0, dv/dx - du/dy) of an in-plane field on the (nx, ny, 1) grid
    (second-order differences; the plane's own derivatives only)."""
    nx, ny = shape[0], shape[1]
    U = u[:, 0].reshape(ny, nx)
    W = u[:, 1].reshape(ny, nx)
    w = np.zeros((u.shape[0], 3))
    w[:, 2] = (np.gradient(W, spacing[0], axis=1) - np.gradient(U, spacing[1], axis=0)).ravel()
    return w


_PARAVIEW = """# Open this render in ParaView, in one command:  paraview --script=open_in_paraview.py
# (or pvpython open_in_paraview.py to check it loads). Written by ciliary-carpet render; the
# files are found next to this script, so the folder can be moved as a whole.
import os

from paraview.simple import *  # noqa: F401,F403

here = os.path.dirname(os.path.abspath(__file__))
view = GetActiveViewOrCreate("RenderView")


def show(name, reader, color=None, **kw):
    path = os.path.join(here, name)
    if not os.path.exists(path):
        return None
    src = reader(registrationName=name, FileName=path if reader is PVDReader else [path], **kw)
    d = Show(src, view)
    if color:
        ColorBy(d, color)
        d.RescaleTransferFunctionToDataRange(True, False)
    return src


field = show("mean_field.vti", XMLImageDataReader, ("POINTS", "speed"))
if field is not None:
    glyph = Glyph(registrationName="velocity arrows", Input=field, GlyphType="Arrow")
    glyph.OrientationArray = ["POINTS", "velocity"]
    glyph.ScaleArray = ["POINTS", "No scale array"]
    glyph.MaximumNumberOfSamplePoints = 1500
    Show(glyph, view)
show("layout.vtp", XMLPolyDataReader, ("POINTS", "chi_N"))
show("cilia.pvd", PVDReader, ("POINTS", "chi_N"))
show("pathlines.vtp", XMLPolyDataReader, ("POINTS", "IntegrationTime"))
show("particles.pvd", PVDReader, ("POINTS", "speed"))
show("snapshots.pvd", PVDReader)
view.InteractionMode = "2D"
ResetCamera(view)
GetAnimationScene().UpdateAnimationUsingDataTimeSteps()
Render(view)
"""


def _paraview_script(path: Path) -> None:
    """Write the pvpython script that opens every output of the render in ParaView."""
    path.write_text(_PARAVIEW)


def render(scene: Scene, out_dir, *, overwrite: bool = False, progress: Progress | None = None) -> RenderResult:
    """Render ``scene`` into ``out_dir`` (see the module docstring). Raises SceneError,
    TargetError, TableError or DesignError for a scene that cannot be rendered, and RenderError
    when ``out_dir`` holds results and ``overwrite`` is False; nothing is written then."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise RenderError(f"{out_dir} exists and is not a folder")
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise RenderError(f"{out_dir} already holds results ({'complete' if is_complete(out_dir) else 'partial'}); "
                          "they are kept: pass overwrite=True (--overwrite) to replace them")
    progress = progress if progress is not None else Progress()
    clock = {}
    t0 = _time.perf_counter()
    table = scene.load_table()
    d, carpet = design(scene, table)
    if carpet.blob != scene.carpet.blob:
        with warnings.catch_warnings():  # the same bases: overlaps were warned about by design()
            warnings.simplefilter("ignore", UserWarning)
            carpet = dataclasses.replace(carpet, blob=scene.carpet.blob)
    clock["design"] = _time.perf_counter() - t0
    o, tol = scene.output, scene.tolerance
    seeds = check_seeds(carpet, _seeds(scene, carpet)) if o.pathlines else None  # SeedError before any output
    T0 = float(table.scalar("period", 0.0))
    if o.pathlines:  # PathLineError (output too large for memory) before any output
        check_output_size(carpet, seeds.shape[0], pathline_duration(scene, carpet, T0)[0], o.samples_per_period)
    sc = carpet.scales
    L, T, V = (sc.length_m, sc.time_s, sc.velocity) if sc is not None else (1.0, 1.0, 1.0)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".partial", dir=out_dir.parent))
    summary = {"scene": scene.name, "source": scene.source_name, "n_cilia": carpet.n, "tolerance": tol,
               "units": "SI" if sc is not None else "L, tau", "T0": T0 * T}
    steps = 1 + bool(o.field) + (o.snapshots > 0) + (o.frames > 0) + bool(o.pathlines) + bool(o.ftle) + bool(o.preview) + 1
    progress.start(steps, f"render {scene.name}")
    done = 0
    try:
        # layout
        chi = carpet.chi_N
        th = table.scalar("thrust_angle", chi)
        write_points(stage / "layout.vtp", np.column_stack([carpet.bases * L, np.zeros(carpet.n)]),
                     {"chi_N": chi, "thrust_angle": th, "cilium_id": np.arange(carpet.n), "flutter":
                      carpet.flutter.astype(np.uint8)})
        if d is not None:
            write_netcdf(d.to_dataset(carpet), stage / "layout.nc")
            summary["design"] = {"kind": d.kind, "residual_rms": d.residual_rms, "residual_max": float(d.residual.max()),
                                 "residual_unit": "rad" if d.kind == "angle" else "relative",
                                 "control_points": int(d.control.shape[0]), "clipped": list(d.clipped),
                                 "status": d.status, "message": d.message, "work": d.work}
        done += 1
        progress.update(done)
        mean_field = None
        if o.field:
            t1 = _time.perf_counter()
            origin, spacing, shape, pts = _field_grid(scene, carpet)
            s = carpet.evaluate_mean(pts, tol=tol)
            u = s.velocity
            mean_field = (origin, spacing, shape, pts, u)
            write_field(stage / "mean_field.vti", np.asarray(origin) * L, np.asarray(spacing) * L, shape,
                        {"velocity": u * V, "speed": np.linalg.norm(u, axis=1) * V,
                         "vorticity": _vorticity(u, spacing, shape) / T, "error_bound": s.error_bound * V})
            clock["mean_field"] = _time.perf_counter() - t1
            summary["mean_field"] = {"points": int(pts.shape[0]), "fidelity": s.fidelity,
                                     "max_error_bound": float(s.error_bound.max()),
                                     "max_speed": float(np.nanmax(np.linalg.norm(u, axis=1))) * V}
            done += 1
            progress.update(done)
        if o.snapshots > 0:
            t1 = _time.perf_counter()
            origin, spacing, shape, pts = _field_grid(scene, carpet)
            entries, fid = [], []
            for k in range(o.snapshots):
                t = k * T0 / o.snapshots
                s = carpet.evaluate(pts, t, tol=tol)
                u = s.velocity
                f = write_field(stage / f"snapshot_{k:03d}.vti", np.asarray(origin) * L, np.asarray(spacing) * L,
                                shape, {"velocity": u * V, "speed": np.linalg.norm(u, axis=1) * V,
                                        "vorticity": _vorticity(u, spacing, shape) / T,
                                        "error_bound": s.error_bound * V}, time=t * T)
                entries.append((t * T, f))
                fid.append(s.fidelity)
            write_pvd(stage / "snapshots.pvd", entries)
            clock["snapshots"] = _time.perf_counter() - t1
            summary["snapshots"] = {"count": o.snapshots, "fidelity": fid[0]}
            done += 1
            progress.update(done)
        if o.frames > 0:
            t1 = _time.perf_counter()
            entries = []
            s_arc = carpet.s
            f_scale = sc.viscosity_Pa_s * V / carpet.mu if sc is not None else 1.0
            for k in range(o.frames):
                t = k * T0 / o.frames
                pos, f, ph = carpet.state(t)
                z = np.zeros(pos.shape[:2] + (1,))
                fn = write_cilia(stage / f"cilia_{k:03d}.vtp", np.concatenate([pos * L, z], -1), s_arc * L,
                                 np.arange(carpet.n), chi, ph, drag=np.concatenate([f * f_scale, z], -1), time=t * T)
                entries.append((t * T, fn))
            write_pvd(stage / "cilia.pvd", entries)
            clock["frames"] = _time.perf_counter() - t1
            done += 1
            progress.update(done)
        pl = None
        if o.pathlines:
            t1 = _time.perf_counter()
            duration, how = pathline_duration(scene, carpet, T0)
            model = pathline_model(scene)
            flow = _mean_flow(scene, carpet, mean_field, tol) if model == "mean" else "resolved"
            pl = carpet.pathlines(seeds, (0.0, duration), rtol=1e-6, atol=1e-4 * scene.carpet.spacing, tol=tol,
                                  model=flow, samples_per_period=o.samples_per_period)
            pl.write(stage / "pathlines.vtp", scales=sc)
            pl.write_particles(stage / "particles.pvd", scales=sc)
            clock["pathlines"] = _time.perf_counter() - t1
            early = int(np.sum(pl.reason == UNDERFLOW))
            summary["pathlines"] = {"tracers": int(seeds.shape[0]), "duration": duration * T, "duration_from": how,
                                    "periods": duration / T0, "model": model, "samples_per_period": o.samples_per_period,
                                    "outcome": pl.counts(), "stopped_early": early, "status": pl.status,
                                    "message": pl.message, "work": pl.stats}
            done += 1
            progress.update(done)
        if o.ftle:
            t1 = _time.perf_counter()
            duration = pathline_duration(scene, carpet, T0)[0] if pl is None else summary["pathlines"]["duration"] / T
            flow = _mean_flow(scene, carpet, mean_field, tol)
            b = carpet.bases
            nx, ny = max(3, o.field_shape[0] // 2), max(3, o.field_shape[1] // 2)
            f = ftle_field(carpet, (b[:, 0].min(), b[:, 0].max(), b[:, 1].min(), b[:, 1].max()), (nx, ny),
                           0.25 * duration, model=flow, rtol=1e-6, atol=1e-4 * scene.carpet.spacing)
            f.write(stage / "ftle.vti", scales=sc)
            clock["ftle"] = _time.perf_counter() - t1
            summary["mixing"] = {"mixing_number": f.mixing_number, "ftle_max": float(np.nanmax(f.ftle)) / T
                                 if np.any(np.isfinite(f.ftle)) else None, "duration": f.duration * T,
                                 "grid": [nx, ny], "model": f.model,
                                 "defined_fraction": float(np.mean(np.isfinite(f.ftle)))}
            done += 1
            progress.update(done)
        if o.preview:
            t1 = _time.perf_counter()
            _preview(stage / "preview.png", scene, carpet, mean_field, pl, d)
            clock["preview"] = _time.perf_counter() - t1
            done += 1
            progress.update(done)
        _paraview_script(stage / "open_in_paraview.py")
        done += 1
        progress.update(done)
        clock["total"] = _time.perf_counter() - t0
        summary["seconds"] = clock
        summary["scene_resolved"] = scene.to_dict()
        (stage / "summary.md").write_text(_markdown(summary))
        (stage / SUMMARY).write_text(json.dumps(summary, indent=2, default=_json_default))
        os.chmod(stage, 0o755)
        if out_dir.exists():
            old = out_dir.parent / f".{out_dir.name}.old-{os.getpid()}"
            os.replace(out_dir, old)
            os.replace(stage, out_dir)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(stage, out_dir)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    finally:
        progress.close()
    files = tuple(sorted(p.name for p in out_dir.iterdir()))
    logger.info("rendered %s into %s in %.1f s", scene.name, out_dir, clock["total"])
    return RenderResult(out_dir=out_dir, files=files, summary=summary)


def _json_default(v):
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return float(v)
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")


def _markdown(s: dict) -> str:
    lines = [f"# {s['scene']}", "", f"- source: `{s['source']}`", f"- cilia: {s['n_cilia']}",
             f"- flow tolerance: {s['tolerance']:g}", f"- units: {s['units']}"]
    if "design" in s:
        dd = s["design"]
        lines.append(f"- design ({dd['kind']} target, {dd['control_points']} control points): rms residual "
                     f"{dd['residual_rms']:.3g} {dd['residual_unit']}, worst {dd['residual_max']:.3g}; "
                     f"{dd['work']['iterations']} L-BFGS-B iterations")
    if "mean_field" in s:
        m = s["mean_field"]
        fid = ", ".join(f"{k} {v:.1%}" for k, v in m["fidelity"].items())
        lines.append(f"- mean field: {m['points']} points, fidelity {fid}, max error bound {m['max_error_bound']:.2e}")
    if "pathlines" in s:
        p = s["pathlines"]
        out = ", ".join(f"{v} {k}" for k, v in p["outcome"].items() if v)
        lines.append(f"- path lines: {p['tracers']} tracers, {p['model']} flow, over {p['duration']:.4g} "
                     f"({p['periods']:.3g} beats; {p['duration_from']}): {out}; {p['stopped_early']} stopped early")
    if "mixing" in s:
        mx = s["mixing"]
        top = "n/a" if mx["ftle_max"] is None else f"{mx['ftle_max']:.3g}"
        lines.append(f"- mixing: number {mx['mixing_number']:.3g} (mean log-stretching over {mx['duration']:.4g}, "
                     f"{mx['model']} flow; FTLE max {top}, defined on {mx['defined_fraction']:.0%} of the grid)")
    lines += ["", "| stage | seconds |", "|---|---|"] + [f"| {k} | {v:.2f} |" for k, v in s["seconds"].items()]
    return "\n".join(lines) + "\n"


def _preview(path: Path, scene: Scene, carpet: Carpet, mean_field, pl, d) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6.5))
    if mean_field is not None:
        origin, spacing, shape, pts, u = mean_field
        X = pts[:, 0].reshape(shape[1], shape[0])
        Y = pts[:, 1].reshape(shape[1], shape[0])
        U = np.nan_to_num(u[:, 0]).reshape(X.shape)
        W = np.nan_to_num(u[:, 1]).reshape(X.shape)
        sp = np.hypot(U, W)
        ax.streamplot(X, Y, U, W, color=sp, cmap="Blues", density=1.4, linewidth=0.6, arrowsize=0.7)
    if pl is not None:
        cmap = plt.cm.autumn
        for k, p in enumerate(pl.points):
            ax.plot(p[:, 0], p[:, 1], color=cmap(k / max(1, len(pl.points) - 1)), lw=0.5, alpha=0.8)
        e = pl.end_points
        ax.plot(e[:, 0], e[:, 1], ".", color="k", ms=2)
    pos, _, _ = carpet.state(0.0)
    lim = max(float(np.abs(carpet.chi_N).max()), 1e-9)
    for j in range(carpet.n):
        ax.plot(pos[j, :, 0], pos[j, :, 1], color=plt.cm.coolwarm(0.5 + 0.5 * carpet.chi_N[j] / lim), lw=1.2)
    sc = ax.scatter(carpet.bases[:, 0], carpet.bases[:, 1], c=carpet.chi_N, cmap="coolwarm", vmin=-lim, vmax=lim,
                    s=12, zorder=3)
    fig.colorbar(sc, ax=ax, label="chi_N", shrink=0.8)
    title = scene.name
    if d is not None:
        title += f"  (design rms residual {d.residual_rms:.3g}{' rad' if d.kind == 'angle' else ''})"
    ax.set_title(title)
    ax.set_aspect("equal")
    ax.set_xlabel("x / L")
    ax.set_ylabel("y / L")
    fig.tight_layout()
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".png", dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110)
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        Path(tmp).unlink(missing_ok=True)
