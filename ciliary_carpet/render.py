"""The main job: a scene file in, a folder of ParaView-ready outputs out.

:func:`render` designs the layout (when the scene has a target), evaluates the flow at the
scene's tolerance and writes, into ``out_dir``:

==========================  ==================================================================
``layout.nc``               the designed layout (chi_N per cilium, control points, residuals)
``layout.vtp``              base points coloured by chi_N (and thrust angle, near_cutoff)
``design.vtp``              control points: target and achieved flow, residual (with a target)
``design.png``              the design at a glance: target vs achieved arrows, residual per
                            control point, the layout coloured by chi_N (with a target)
``mean_field.vti``          the time-averaged velocity on a grid around the carpet (+ error bound)
``snapshot_NNN.vti``        instantaneous fields, tied by ``snapshots.pvd``
``cilia_NNN.vtp``           filament shapes per frame (arc length, drag density), ``cilia.pvd``
``pathlines.vtp``           tracer path lines (time, velocity, speed; SeedIds, ReasonForTermination)
``preview.png``             the mean flow (streamlines) with the layout and path lines
``summary.json``, ``.md``   residuals, timings, fidelity used, error bounds, path-line outcome
==========================  ==================================================================

The whole folder is written atomically: everything goes into a hidden staging folder next to
``out_dir``, which is renamed onto ``out_dir`` only when complete (``summary.json`` last). An
existing ``out_dir`` is kept unless ``overwrite=True``. Times are in units of tau, lengths in L
(SI when the scene has ``[units]``). The periods of the outputs (snapshots, frames, path-line
duration) are counted in periods of the straight filament, T0 = T(chi_N = 0).
"""
from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
import time as _time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from single_cilium._io import write_netcdf
from single_cilium.progress import Progress

from .carpet import Carpet
from .design import design
from .scene import Scene
from .vtkfiles import grid_points, write_cilia, write_field, write_points, write_pvd

logger = logging.getLogger(__name__)

__all__ = ["render", "RenderResult", "RenderError", "is_complete"]

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
        return c + (along.min() - scene.carpet.spacing) * d0 + s[:, None] * cross
    n = max(2, int(round(math.sqrt(o.n_seeds))))  # grid: between the cilia
    a = np.linspace(along.min(), along.max(), n) + 0.5 * scene.carpet.spacing
    s = np.linspace(across.min(), across.max(), n) + 0.5 * scene.carpet.spacing
    A, S = np.meshgrid(a, s)
    return c + A.ravel()[:, None] * d0 + S.ravel()[:, None] * cross


def _field_grid(scene: Scene, carpet: Carpet):
    b = carpet.bases
    m = scene.output.field_margin
    lo, hi = b.min(0) - m - 1.0, b.max(0) + m + 1.0
    nx, ny = scene.output.field_shape
    spacing = ((hi[0] - lo[0]) / max(nx - 1, 1), (hi[1] - lo[1]) / max(ny - 1, 1), 1.0)
    origin = (lo[0], lo[1], 0.0)
    shape = (nx, ny, 1)
    return origin, spacing, shape, grid_points(origin, spacing, shape)


def _blank_inside(carpet: Carpet, pts: np.ndarray) -> np.ndarray:
    inside = np.zeros(pts.shape[0], bool)
    for j in range(carpet.n):
        inside |= carpet.in_swept_region(pts, j)
    return inside


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
    clock["design"] = _time.perf_counter() - t0
    o, tol = scene.output, scene.tolerance
    sc = carpet.scales
    L, T, V = (sc.length_m, sc.time_s, sc.velocity) if sc is not None else (1.0, 1.0, 1.0)
    T0 = float(table.scalar("period", 0.0))
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".partial", dir=out_dir.parent))
    summary = {"scene": scene.name, "source": scene.source_name, "n_cilia": carpet.n, "tolerance": tol,
               "units": "SI" if sc is not None else "L, tau", "T0": T0 * T}
    steps = 1 + bool(o.field) + (o.snapshots > 0) + (o.frames > 0) + bool(o.pathlines) + bool(o.preview)
    progress.start(steps, f"render {scene.name}")
    done = 0
    try:
        # layout
        chi = carpet.chi_N
        th = table.scalar("thrust_angle", chi)
        near = np.zeros(carpet.n, np.uint8)
        if d is not None:
            near[list(d.near_cutoff)] = 1
        write_points(stage / "layout.vtp", np.column_stack([carpet.bases * L, np.zeros(carpet.n)]),
                     {"chi_N": chi, "thrust_angle": th, "cilium_id": np.arange(carpet.n), "flutter":
                      carpet.flutter.astype(np.uint8), "near_cutoff": near})
        if d is not None:
            write_netcdf(d.to_dataset(carpet), stage / "layout.nc")
            _write_design(stage, d, L, V)
            _design_picture(stage / "design.png", scene, carpet, d)
            summary["design"] = d.summary()
        done += 1
        progress.update(done)
        mean_field = None
        if o.field:
            t1 = _time.perf_counter()
            origin, spacing, shape, pts = _field_grid(scene, carpet)
            s = carpet.evaluate_mean(pts, tol=tol)
            u = np.where(_blank_inside(carpet, pts)[:, None], np.nan, s.velocity)
            mean_field = (origin, spacing, shape, pts, u)
            write_field(stage / "mean_field.vti", np.asarray(origin) * L, np.asarray(spacing) * L, shape,
                        {"velocity": u * V, "speed": np.linalg.norm(u, axis=1) * V, "error_bound": s.error_bound * V})
            clock["mean_field"] = _time.perf_counter() - t1
            summary["mean_field"] = {"points": int(pts.shape[0]), "fidelity": s.fidelity,
                                     "max_error_bound": float(s.error_bound.max()),
                                     "max_speed": float(np.nanmax(np.linalg.norm(u, axis=1))) * V}
            done += 1
            progress.update(done)
        if o.snapshots > 0:
            t1 = _time.perf_counter()
            origin, spacing, shape, pts = _field_grid(scene, carpet)
            blank = _blank_inside(carpet, pts)
            entries, fid = [], []
            for k in range(o.snapshots):
                t = k * T0 / o.snapshots
                s = carpet.evaluate(pts, t, tol=tol)
                u = np.where(blank[:, None], np.nan, s.velocity)
                f = write_field(stage / f"snapshot_{k:03d}.vti", np.asarray(origin) * L, np.asarray(spacing) * L,
                                shape, {"velocity": u * V, "speed": np.linalg.norm(u, axis=1) * V,
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
            seeds = _seeds(scene, carpet)
            pl = carpet.pathlines(seeds, (0.0, o.periods * T0), rtol=1e-6, atol=1e-5, tol=tol)
            pl.write(stage / "pathlines.vtp", scales=sc)
            clock["pathlines"] = _time.perf_counter() - t1
            summary["pathlines"] = {"tracers": int(seeds.shape[0]), "duration": o.periods * T0 * T,
                                    "outcome": pl.counts(), "status": pl.status, "message": pl.message,
                                    "work": pl.stats}
            done += 1
            progress.update(done)
        if o.preview:
            t1 = _time.perf_counter()
            _preview(stage / "preview.png", scene, carpet, mean_field, pl, d)
            clock["preview"] = _time.perf_counter() - t1
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
                     f"{dd['residual_rms']:.3g} {dd['residual_unit']} (+- {dd['residual_error']:.1g}), worst "
                     f"{dd['residual_max']:.3g}; local layout {dd['local_rms']:.3g}; returned the {dd['returned']} "
                     f"layout; {dd['cilia_near_cutoff']} of {s['n_cilia']} cilia near the flutter cutoff; "
                     f"{dd['work']['iterations']} L-BFGS-B iterations, {dd['work']['checks']} full-model checks")
        if "tolerance" in dd:
            tt = dd["tolerance"]
            lines.append(f"- fabrication tolerance (relative chi_N error sigma = {tt['sigma']:g}, {tt['samples']} "
                         f"samples): expected rms residual {tt['mean_rms']:.3g} +- {tt['sampling_error']:.1g} "
                         f"(spread {tt['std_rms']:.2g}; 10-90%: {tt['p10_rms']:.3g}..{tt['p90_rms']:.3g}); "
                         f"nominal {tt['nominal_rms']:.3g}")
    if "mean_field" in s:
        m = s["mean_field"]
        fid = ", ".join(f"{k} {v:.1%}" for k, v in m["fidelity"].items())
        lines.append(f"- mean field: {m['points']} points, fidelity {fid}, max error bound {m['max_error_bound']:.2e}")
    if "pathlines" in s:
        p = s["pathlines"]
        out = ", ".join(f"{v} {k}" for k, v in p["outcome"].items() if v)
        lines.append(f"- path lines: {p['tracers']} tracers over {p['duration']:.4g}: {out}")
    lines += ["", "| stage | seconds |", "|---|---|"] + [f"| {k} | {v:.2f} |" for k, v in s["seconds"].items()]
    return "\n".join(lines) + "\n"


def _write_design(stage: Path, d, L: float, V: float) -> None:
    """design.vtp: the control points with the target and achieved flow and the residual."""
    P = d.control.shape[0]
    z = np.zeros((P, 1))
    write_points(stage / "design.vtp", np.column_stack([d.control * L, z]),
                 {"target": np.concatenate([d.target * (V if d.kind == "velocity" else 1.0), z], axis=1),
                  "achieved": np.concatenate([d.achieved * V, z], axis=1), "residual": d.residual,
                  **({"speed_ratio": d.speed_ratio} if d.speed_ratio is not None else {})})


def _savefig(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".png", dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110)
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        Path(tmp).unlink(missing_ok=True)


def _design_picture(path: Path, scene: Scene, carpet: Carpet, d) -> None:
    """Three panels: target (grey) and achieved (blue) flow directions at the control points over
    the layout coloured by chi_N; the residual per control point; the layout with the cilia
    near the flutter cutoff ringed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    X, b = d.control, carpet.bases
    lim = float(carpet.table.flutter_range[1])
    fig, axs = plt.subplots(1, 3, figsize=(17, 6.2))
    h = float(np.median(np.linalg.norm(np.diff(X, axis=0), axis=1))) if len(X) > 1 else 1.0
    scale = 0.8 * max(h, 0.5)

    def arrows(ax, v, **kw):
        n = np.maximum(np.linalg.norm(v, axis=1), 1e-300)[:, None]
        vv = v / n * scale
        ax.quiver(X[:, 0] - 0.5 * vv[:, 0], X[:, 1] - 0.5 * vv[:, 1], vv[:, 0], vv[:, 1], angles="xy",
                  scale_units="xy", scale=1, **kw)

    ax = axs[0]
    ax.scatter(b[:, 0], b[:, 1], c=carpet.chi_N, cmap="coolwarm", vmin=-lim, vmax=lim, s=14, zorder=1)
    arrows(ax, d.target, color="0.6", width=0.009, zorder=2, label="target")
    arrows(ax, d.achieved, color="tab:blue", width=0.0035, zorder=3, label="achieved")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2, fontsize=8)
    ax.set_title("mean-flow direction at the control points\ntarget (grey) vs achieved (blue), over chi_N",
                 fontsize=10)
    ax = axs[1]
    unit = "rad" if d.kind == "angle" else "relative"
    sc = ax.scatter(X[:, 0], X[:, 1], c=d.residual, cmap="magma_r", vmin=0, s=40, marker="s")
    ax.scatter(b[:, 0], b[:, 1], c="0.7", s=6)
    fig.colorbar(sc, ax=ax, label=f"residual [{unit}]", shrink=0.85)
    ax.set_title(f"residual per control point\nrms {d.residual_rms:.3g} {unit} (+- {d.residual_error:.1g}), worst "
                 f"{d.residual.max():.3g}", fontsize=10)
    ax = axs[2]
    sc = ax.scatter(b[:, 0], b[:, 1], c=carpet.chi_N, cmap="coolwarm", vmin=-lim, vmax=lim, s=40)
    nc = list(d.near_cutoff)
    if nc:
        ax.scatter(b[nc, 0], b[nc, 1], facecolors="none", edgecolors="k", s=110, lw=1.2,
                   label=f"{len(nc)} near the flutter cutoff")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), fontsize=8)
    fig.colorbar(sc, ax=ax, label="chi_N", shrink=0.85)
    ax.set_title(f"layout: chi_N (flutter cutoff +-{lim:.5g})\nreturned: the {d.returned} layout", fontsize=10)
    for ax in axs:
        ax.set_aspect("equal")
        ax.set_xlabel("x / L")
        ax.set_ylabel("y / L")
    fig.suptitle(f"{scene.name}: design ({d.kind} target, {len(X)} control points; local layout rms "
                 f"{d.local_rms:.3g})", fontsize=11)
    fig.tight_layout()
    _savefig(fig, path)


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
        for p in pl.points:
            ax.plot(p[:, 0], p[:, 1], color="tab:orange", lw=0.4, alpha=0.6)
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
    _savefig(fig, path)
