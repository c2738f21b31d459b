"""The main job: a scene file in, a folder of ParaView-ready outputs out.

:func:`render` designs the layout (when the scene has a target), evaluates the flow at the
scene's tolerance and writes, into ``out_dir``:

===========================  ==================================================================
``layout.nc``                the designed layout (chi_N per cilium, control points, residuals)
``layout.vtp``               base points coloured by chi_N (and thrust angle, near_cutoff)
``design.vtp``               control points: target and achieved flow, residual (with a target)
``design.png``               the design at a glance: target vs achieved arrows, residual per
                             control point, the layout coloured by chi_N (with a target)
``mean_field.vti``           the time-averaged velocity (active vectors), speed, vorticity and the
                             error bound on a grid around the carpet
``snapshot_NNN.vti``         instantaneous fields over one beat of the cilia, tied by ``snapshots.pvd``
``cilia_NNN.vtp``            filament shapes over one beat (arc length, drag density), ``cilia.pvd``;
                             both .pvd repeat that beat over the path lines' time range (one clock)
``pathlines.vtp``            tracer path lines (time, IntegrationTime, velocity, speed; SeedIds,
                             TerminationReason with TerminationReasonNames), >= 16 points per beat
``particles.pvd``            the tracers as moving points (``particles_NNNNN.vtp``), as ParticlePath gives
``open_in_paraview.py``      ``paraview --script=DIR/open_in_paraview.py`` (or ``pvpython``/``pvbatch``
                             with its path), from any working folder, opens the whole folder
                             (:mod:`ciliary_carpet.output.paraview`: what shows, what is loaded hidden)
``ftle.vti``                 finite-time Lyapunov exponent over the carpet (mean flow, a quarter of
                             the path-line duration); the mixing number is in the summary
``preview.png``              the mean flow (streamlines) with the layout and path lines, a colour
                             bar for each colour
``summary.json``, ``.md``    residuals, timings, fidelity used, error bounds, path-line outcome
                             (``.md``: the same in words, :mod:`ciliary_carpet.output.report`)
``ciliary-carpet.manifest``  the names of the files above: what the toolkit wrote (JSON)
===========================  ==================================================================

Output-folder safety (:mod:`ciliary_carpet.output.folder`, whose docstring states the guarantees).
Everything is first written into a hidden staging folder on the output's own filesystem (beside
a new ``out_dir``, inside an existing one) and swapped in when complete, or removed on failure.
A render holds a lock on ``out_dir`` (a second render of it is refused at once). A non-empty
``out_dir`` is kept unless ``overwrite=True``, and even then only the files the toolkit wrote and
that are unchanged (output names, regular files, the size and SHA-256 its manifest recorded) are
replaced or removed: files someone else put there are never touched, and a render whose output
would replace one of them is refused before any work. The swap is journalled and signals cannot
split it; a folder is complete (:func:`is_complete`) when it has the manifest and
``summary.json`` and no swap is under way, and current for a scene when it was made with the
same settings (``package_version`` and ``scene_resolved`` in ``summary.json``).
``summary.json`` is strict JSON, and a render whose summary would hold a NaN or an infinity is
a :class:`RenderError` (nothing is written). Before any work, :func:`check_resources` compares a
lower bound of the memory and time the scene needs with what the machine has. Times are in units
of tau, lengths in L
(SI when the scene has ``[units]``). ``[output] periods`` (the path-line duration) counts periods
of the straight filament, T0 = T(chi_N = 0); the snapshots and frames sample one beat of the
cilia themselves (each beats with its own period T(chi_N): their median, ``summary["beat"]``).

Path lines (:func:`pathline_duration`, :func:`pathline_model`): unless the scene sets
``[output] periods``, the duration is long enough for a tracer to cross the whole carpet at the
carpet's median mean speed (1.25 times the carpet's extent along the flow plus three spacings,
divided by that speed). The flow they follow is the time-resolved beat or the long-time mean
flow (``[output] pathline_model``; "auto" takes the mean flow when the scene's tolerance allows
its measured error). The flow uses the regularised Stokeslets of ``[carpet] blob``: it is bounded
everywhere, so the fields are not blanked inside the cilia's swept regions.
"""
from __future__ import annotations

import inspect
import logging
import math
import os
import time as _time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from single_cilium._io import non_finite, strict_json, write_netcdf
from single_cilium._threads import threads_in_use
from single_cilium.progress import Progress

from ciliary_carpet.scenes.assembly import check_table_range
from ciliary_carpet.carpet.carpet import BLOB, Carpet, CycleMean, Instant
from ciliary_carpet.design.inverse import design
from ciliary_carpet.output.figures import _design_picture, _preview
from ciliary_carpet.transport.ftle import ftle_field
from ciliary_carpet.output.folder import MANIFEST, PACKAGE_VERSION, SUMMARY, OutputFolder, RenderError, is_complete, owned_files
from ciliary_carpet.output.folder import usual_mode as _usual_mode
from ciliary_carpet.carpet.omissions import omissions
from ciliary_carpet.output.paraview import SCRIPT, write_script
from ciliary_carpet.transport.flow import MEAN_MODEL_ERROR, MeanFlow, ResolvedFlow
from ciliary_carpet.transport.pathlines import UNDERFLOW, check_output_size, check_seeds, pathlines
from ciliary_carpet.output.report import markdown
from ciliary_carpet.scenes.scene import Scene, SceneError
from ciliary_carpet.stokes.stokeslet import Auto, backend_named
from ciliary_carpet.output.vtkfiles import grid_points, write_cilia, write_field, write_points, write_pvd

logger = logging.getLogger(__name__)

__all__ = ["render", "RenderResult", "RenderError", "ResourceError", "is_complete", "owned_files", "check_resources",
           "check_table_range", "Estimate", "MANIFEST", "pathline_duration", "pathline_model"]

class ResourceError(RenderError):
    """The scene needs more memory or time than the machine has (raised before any work)."""


@dataclass(frozen=True)
class RenderResult:
    """What a render wrote: the folder, its files, and the summary (also in summary.json)."""

    out_dir: Path
    files: tuple
    summary: dict


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
    clear = 2.0 * (carpet.blob or BLOB)
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
    speed = float(np.median(np.linalg.norm(carpet.velocity(probe, CycleMean(), max(scene.tolerance, 1e-3))[:, :2], axis=1)))
    if not (math.isfinite(speed) and speed > 0):
        raise RenderError(f"{scene.source_name}: the carpet makes no mean flow (median speed {speed:g}): set "
                          "[output] periods for the path lines")
    return 1.25 * travel / speed, f"auto: crossing {travel:.3g} L at the median mean speed {speed:.3g} L/tau"


def pathline_model(scene: Scene) -> str:
    """The flow the tracers follow: ``[output] pathline_model``, "auto" resolved to "mean" when
    the scene's tolerance is at least :data:`~ciliary_carpet.transport.flow.MEAN_MODEL_ERROR`."""
    m = scene.output.pathline_model
    if m == "auto":
        return "mean" if scene.tolerance >= MEAN_MODEL_ERROR else "resolved"
    return m


ERROR_SAMPLE = 8
"""Tracers of a render re-integrated to estimate its path lines' end-point error (:func:`pathline_error`)."""


def pathline_error(carpet: Carpet, seeds: np.ndarray, duration: float, pl, model: str, flow, tol: float,
                   spacing: float) -> dict:
    """End-point error estimate of rendered path lines ``pl``: :data:`ERROR_SAMPLE` of its tracers
    (spread evenly over the seeds) integrated again, against a more accurate run.

    For the time-resolved flow the reference is rtol = 1e-8 (atol 1e-6 spacing) with the flow
    tolerance ten times tighter: the estimate covers the integration and the levels of detail.
    For the long-time model (``model == "mean"``, ``flow`` its :class:`MeanFlow`) the reference
    is the time-resolved flow at the render's settings in the same domain (the flow's box): the
    estimate is the model's error. Returns max and median of the end-point distances [L], the
    tracers used and the reference in words."""
    k = min(ERROR_SAMPLE, seeds.shape[0])
    idx = np.unique(np.linspace(0, seeds.shape[0] - 1, k).round().astype(int))
    if model == "mean":
        ref = pathlines(ResolvedFlow(carpet, tol), seeds[idx], (0.0, duration), rtol=1e-6, atol=1e-4 * spacing,
                        samples_per_period=1, domain=tuple(float(v) for v in flow.box))
        what = f"the time-resolved flow (rtol 1e-6, flow tol {tol:g}): the long-time model's error"
    else:
        t_ref = max(tol / 10, 1e-6)
        ref = pathlines(ResolvedFlow(carpet, t_ref), seeds[idx], (0.0, duration), rtol=1e-8, atol=1e-6 * spacing,
                        samples_per_period=1)
        what = f"rtol 1e-8 and flow tol {t_ref:g}: integration and levels of detail"
    e = np.linalg.norm(pl.end_points[idx] - ref.end_points, axis=1)
    return {"max": float(e.max()), "median": float(np.median(e)), "tracers": int(idx.size), "reference": what}


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
        return MeanFlow.from_grid(carpet, *_grid_lines(mean_field), mean_field[4].reshape(shape[1], shape[0], 3))
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


def _beat(carpet: Carpet, T0: float) -> dict:
    """The cilia's beat: the median period of the beating cilia (each beats with the period of
    its own limit cycle, T(chi_N)), their range, and how many beat; T0 when none does."""
    p = carpet.periods
    p = p[np.isfinite(p)]
    if p.size == 0:
        return {"period": T0, "period_min": T0, "period_max": T0, "beating": 0}
    return {"period": float(np.median(p)), "period_min": float(p.min()), "period_max": float(p.max()),
            "beating": int(p.size)}


def _looped(files: list, beat: float, span: float) -> list:
    """(time, file) entries that repeat one beat's ``files`` (at k beat / n) from 0 until
    ``span`` is covered: a .pvd of them plays the beat on over the whole time range."""
    n = len(files)
    count = max(n + 1, int(math.ceil(span / beat * n - 1e-9)) + 1)
    return [(k * beat / n, files[k % n]) for k in range(count)]


# ------------------------------------------------------------------------------ resources
# Lower bounds, far below what was measured (tracemalloc peak of a render: 0.57 MB per cilium;
# path lines: 6 ms per step for 3 tracers over 4 cilia; Stokeslet kernel: 1.5e9 pairs/s on 2
# cores), so that a scene is refused only when it certainly cannot run.
_BYTES_PER_CILIUM = 2048
_BYTES_PER_POINT = 64      # position, velocity, error bound and speed of a field point
_BYTES_PER_TRACER_STEP = 56  # position, velocity, time of a path-line point
_PAIRS_PER_SECOND = 3e9
_SECONDS_PER_STEP = 1e-4
MAX_PATHLINE_STEPS = inspect.signature(pathlines).parameters["max_steps"].default  # what render uses
MAX_COORDINATE = 1e9       # |coordinates| in L beyond which a scene is taken for a typo
SCALE_RANGE = (1e-100, 1e100)  # SI scales of [units] that keep every output finite


@dataclass(frozen=True)
class Estimate:
    """Lower bounds of what a render needs: ``memory_bytes``, Stokeslet ``pairs``, path-line
    ``steps`` (one per period of the flow at least) and ``seconds``; ``parts`` is the memory by
    scene key, ``available_bytes`` what the machine has, ``limit_seconds`` the time allowed."""

    memory_bytes: float
    pairs: float
    steps: float
    seconds: float
    parts: dict
    available_bytes: float
    limit_seconds: float


def _available_memory() -> float:
    """MemAvailable (Linux), or the physical memory, capped by RLIMIT_AS minus what this process
    already maps."""
    avail = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = float(line.split()[1]) * 1024.0
    except OSError:
        pass
    if avail is None:
        try:
            avail = float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            avail = math.inf
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            with open("/proc/self/statm") as fh:
                mapped = float(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
            avail = min(avail, max(float(soft) - mapped, 0.0))
    except (ImportError, OSError, ValueError):
        pass
    return avail


def _gb(x: float) -> str:
    return f"{x / 1e9:.3g} GB"


def check_resources(scene: Scene, *, max_seconds: float = 86400.0) -> Estimate:
    """Check, before any work, that ``scene`` can be rendered: its coordinates and ``[units]``
    scales are sane and lower bounds of the memory and time it needs fit the machine.

    The bounds count only what a render certainly needs (``_BYTES_PER_CILIUM`` etc. are far
    below the measured costs), so a scene is refused only when it certainly cannot finish:
    memory above what is available (MemAvailable, or RLIMIT_AS when set), time above
    ``max_seconds``, or more path-line steps (one per period at least) than the integrator
    allows. Raises :class:`ResourceError` (or :class:`~ciliary_carpet.scenes.scene.SceneError` for a
    coordinate or unit out of range) naming the scene file, the key and the estimate."""
    src = scene.source_name
    c, o = scene.carpet, scene.output
    # coordinates: typos such as 1e300 give NaN deep inside the design; refuse them by key
    coords = {"carpet.origin": [c.origin], "carpet.points": c.points or (), "target.centre":
              [scene.target.centre] if scene.target.centre is not None else (),
              "target.control": c_ if not isinstance((c_ := scene.target.control), str) else (),
              "output.seeds": o.seeds if not isinstance(o.seeds, str) else ()}
    scalars = {"carpet.spacing": c.spacing, "target.line": scene.target.line,
               "output.field_margin": o.field_margin}
    for key, pts in coords.items():
        for i, pt in enumerate(pts):
            if max(abs(pt[0]), abs(pt[1])) > MAX_COORDINATE:
                raise SceneError(f"{src}: {key}{'[%d]' % i if key != 'carpet.origin' else ''} = "
                                 f"[{pt[0]:g}, {pt[1]:g}] is farther than {MAX_COORDINATE:g} L from the origin")
    for key, v in scalars.items():
        if abs(v) > MAX_COORDINATE:
            raise SceneError(f"{src}: {key} = {v:g} is larger than {MAX_COORDINATE:g} L")
    if scene.units is not None:
        u = scene.units
        lo, hi = SCALE_RANGE
        derived = {"units.length_m": u.length_m, "units.time_s": u.time_s, "units.viscosity_Pa_s": u.viscosity_Pa_s,
                   "units.length_m / units.time_s (velocity)": u.length_m / u.time_s,
                   "units.viscosity_Pa_s * length_m / time_s (force per length)": u.viscosity_Pa_s * u.length_m / u.time_s}
        for key, v in derived.items():
            if not (math.isfinite(v) and lo <= v <= hi):
                raise SceneError(f"{src}: {key} = {v:g} is outside [{lo:g}, {hi:g}]: the outputs in SI units would "
                                 f"overflow or vanish; check the [units] section")
    n = float(c.n_cilia)
    p = float(o.field_shape[0]) * float(o.field_shape[1]) if (o.field or o.snapshots > 0) else 0.0
    evals = p * (int(o.field) + o.snapshots)
    k = float(len(o.seeds) if not isinstance(o.seeds, str) else o.n_seeds) if o.pathlines else 0.0
    # periods = None: the duration is chosen later from the carpet's mean speed (pathline_duration);
    # one period is a lower bound, and check_output_size checks the chosen one before any output
    steps = float(max(1.0, math.ceil(o.periods if o.periods is not None else 1.0))) if o.pathlines else 0.0
    parts = {"carpet.points" if c.lattice == "points" else "carpet.shape": n * _BYTES_PER_CILIUM,
             "output.field_shape": p * _BYTES_PER_POINT,
             "output.seeds" if not isinstance(o.seeds, str) else "output.n_seeds":
                 k * (steps + 1.0) * _BYTES_PER_TRACER_STEP}
    mem = sum(parts.values())
    pairs = 3.0 * n * (evals + 7.0 * k * steps)
    seconds = pairs / _PAIRS_PER_SECOND + steps * _SECONDS_PER_STEP
    avail = _available_memory()
    est = Estimate(mem, pairs, steps, seconds, parts, avail, float(max_seconds))
    what = (f"{c.n_cilia:g} cilia, {p:g} field points x {int(o.field) + o.snapshots} field(s), "
            f"{k:g} tracers x {steps:g} steps")
    if steps > MAX_PATHLINE_STEPS:
        raise ResourceError(f"{src}: output.periods = {o.periods:g} needs at least {steps:g} path-line steps (one "
                            f"per period of the flow), more than the integrator's {MAX_PATHLINE_STEPS}; lower "
                            f"output.periods")
    if mem > avail:
        key = max(parts, key=parts.get)
        raise ResourceError(f"{src}: the scene needs at least {_gb(mem)} of memory ({what}; most of it for {key}), "
                            f"more than the {_gb(avail)} available; make {key} smaller")
    if seconds > max_seconds:
        raise ResourceError(f"{src}: the scene needs at least {seconds / 3600:.3g} hours ({pairs:.3g} Stokeslet "
                            f"pairs at {_PAIRS_PER_SECOND:.2g}/s; {what}), more than the {max_seconds / 3600:.3g} "
                            f"hours allowed; make the carpet, the field or the path lines smaller (or raise "
                            f"--max-hours)")
    logger.debug("resource estimate for %s: %s", src, est)
    return est


def render(scene: Scene, out_dir, *, overwrite: bool = False, progress: Progress | None = None,
           max_seconds: float = 86400.0, within=None) -> RenderResult:
    """Render ``scene`` into ``out_dir`` (see the module docstring for what is written and
    :mod:`ciliary_carpet.output.folder` for the output-folder rules). Raises SceneError, TargetError,
    TableError or DesignError for a scene that cannot be rendered, ResourceError when it
    certainly needs more memory than available or more than ``max_seconds``
    (:func:`check_resources`), and RenderError when ``out_dir`` holds files and ``overwrite`` is
    False, when a file it would replace was not written by a render (or was changed since), when
    another render is writing ``out_dir``, when ``out_dir`` resolves outside ``within`` (a
    batch's output root), or when the result is not finite; nothing in ``out_dir`` is changed
    then."""
    with OutputFolder(out_dir, overwrite=overwrite, scene=scene, within=within) as folder:
        return _render(scene, folder, progress=progress, max_seconds=max_seconds)


def _render(scene: Scene, folder: OutputFolder, *, progress: Progress | None, max_seconds: float) -> RenderResult:
    """:func:`render` into the held ``folder``."""
    out_dir = folder.path
    check_resources(scene, max_seconds=max_seconds)
    backend_named(scene.backend)  # backend "cuda" without a GPU: CudaUnavailableError here, before any work
    progress = progress if progress is not None else Progress()
    clock = {}
    t0 = _time.perf_counter()
    d, carpet = design(scene)  # table, range check, target and carpet: assembly.assemble
    table = carpet.table
    clock["design"] = _time.perf_counter() - t0
    o, tol = scene.output, scene.tolerance
    seeds = check_seeds(carpet, _seeds(scene, carpet)) if o.pathlines else None  # SeedError before any output
    T0 = float(table.scalar("period", 0.0))
    if o.pathlines:  # PathLineError (output too large for memory) before any output
        check_output_size(carpet, seeds.shape[0], pathline_duration(scene, carpet, T0)[0], o.samples_per_period)
    sc = carpet.scales
    L, T, V = (sc.length_m, sc.time_s, sc.velocity) if sc is not None else (1.0, 1.0, 1.0)
    stage = folder.stage()  # on the output's filesystem; removed unless placed
    summary = {"scene": scene.name, "source": scene.source_name, "package_version": PACKAGE_VERSION,
               "n_cilia": carpet.n, "tolerance": tol,
               "units": "SI" if sc is not None else "L, tau", "T0": T0 * T,
               "backend": (carpet.backend if carpet.backend is not None else Auto()).describe()}
    steps = 1 + bool(o.field) + (o.snapshots > 0) + (o.frames > 0) + bool(o.pathlines) + bool(o.ftle) + bool(o.preview) + 1
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
            s = carpet.evaluate(pts, CycleMean(), tol=tol)
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
        # one time base for what moves: the snapshots and the cilia's frames sample one beat of the
        # cilia (their median period) and their .pvd repeats it over the path lines' time range
        beat = _beat(carpet, T0)
        Tb = beat["period"]
        span = pathline_duration(scene, carpet, T0)[0] if o.pathlines else Tb
        summary["beat"] = {k: (v * T if k != "beating" else v) for k, v in beat.items()}
        summary["beat"]["loop_until"] = span * T
        summary["layout"] = {"chi_N_min": float(chi.min()), "chi_N_max": float(chi.max())}
        if o.snapshots > 0:
            t1 = _time.perf_counter()
            origin, spacing, shape, pts = _field_grid(scene, carpet)
            entries, fid = [], []
            for k in range(o.snapshots):
                t = k * Tb / o.snapshots
                s = carpet.evaluate(pts, Instant(t), tol=tol)
                u = s.velocity
                f = write_field(stage / f"snapshot_{k:03d}.vti", np.asarray(origin) * L, np.asarray(spacing) * L,
                                shape, {"velocity": u * V, "speed": np.linalg.norm(u, axis=1) * V,
                                        "vorticity": _vorticity(u, spacing, shape) / T,
                                        "error_bound": s.error_bound * V}, time=t * T)
                entries.append(f)
                fid.append(s.fidelity)
            write_pvd(stage / "snapshots.pvd", _looped(entries, Tb * T, span * T))
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
                t = k * Tb / o.frames
                pos, f, ph = carpet.state(t)
                z = np.zeros(pos.shape[:2] + (1,))
                fn = write_cilia(stage / f"cilia_{k:03d}.vtp", np.concatenate([pos * L, z], -1), s_arc * L,
                                 np.arange(carpet.n), chi, ph, drag=np.concatenate([f * f_scale, z], -1), time=t * T)
                entries.append(fn)
            write_pvd(stage / "cilia.pvd", _looped(entries, Tb * T, span * T))
            clock["frames"] = _time.perf_counter() - t1
            done += 1
            progress.update(done)
        pl = None
        if o.pathlines:
            t1 = _time.perf_counter()
            duration, how = pathline_duration(scene, carpet, T0)
            model = pathline_model(scene)
            flow = _mean_flow(scene, carpet, mean_field, tol) if model == "mean" else ResolvedFlow(carpet, tol)
            pl = pathlines(flow, seeds, (0.0, duration), rtol=1e-6, atol=1e-4 * scene.carpet.spacing,
                           samples_per_period=o.samples_per_period)
            pl.write(stage / "pathlines.vtp", scales=sc)
            pl.write_particles(stage / "particles.pvd", scales=sc)
            clock["pathlines"] = _time.perf_counter() - t1
            t1 = _time.perf_counter()
            err = pathline_error(carpet, seeds, duration, pl, model, flow, tol, scene.carpet.spacing)
            clock["pathline_error"] = _time.perf_counter() - t1
            early = int(np.sum(pl.reason == UNDERFLOW))
            summary["pathlines"] = {"tracers": int(seeds.shape[0]), "duration": duration * T, "duration_from": how,
                                    "periods": duration / T0, "beats": duration / Tb, "model": model, "samples_per_period": o.samples_per_period,
                                    "outcome": pl.counts(), "stopped_early": early, "status": pl.status,
                                    "message": pl.message, "work": pl.stats,
                                    "end_point_error": dict(err, max=err["max"] * L, median=err["median"] * L)}
            done += 1
            progress.update(done)
        if o.ftle:
            t1 = _time.perf_counter()
            duration = pathline_duration(scene, carpet, T0)[0] if pl is None else summary["pathlines"]["duration"] / T
            flow = _mean_flow(scene, carpet, mean_field, tol)
            b = carpet.bases
            nx, ny = max(3, o.field_shape[0] // 2), max(3, o.field_shape[1] // 2)
            f = ftle_field(flow, (b[:, 0].min(), b[:, 0].max(), b[:, 1].min(), b[:, 1].max()), (nx, ny),
                           0.25 * duration, rtol=1e-6, atol=1e-4 * scene.carpet.spacing)
            f.write(stage / "ftle.vti", scales=sc)
            clock["ftle"] = _time.perf_counter() - t1
            summary["mixing"] = {"mixing_number": f.mixing_number, "ftle_max": float(np.nanmax(f.ftle)) / T
                                 if np.any(np.isfinite(f.ftle)) else None, "duration": f.duration * T,
                                 "grid": [nx, ny], "model": f.model,
                                 "defined_fraction": float(np.mean(np.isfinite(f.ftle)))}
            done += 1
            progress.update(done)
        # what the model leaves out (interaction between cilia, the wall's drag, the viscosity), sized
        t1 = _time.perf_counter()
        summary["omissions"] = omissions(carpet, tol=min(tol, 1e-3)).summary()
        clock["omissions"] = _time.perf_counter() - t1
        if o.preview:
            t1 = _time.perf_counter()
            _preview(stage / "preview.png", scene, carpet, mean_field, pl, d)
            clock["preview"] = _time.perf_counter() - t1
            done += 1
            progress.update(done)
        write_script(stage / SCRIPT, out_dir, si=sc is not None, scene=scene.name)
        done += 1
        progress.update(done)
        clock["total"] = _time.perf_counter() - t0
        summary["seconds"] = clock
        summary["scene_resolved"] = scene.to_dict()
        summary["threads"] = threads_in_use()  # the numba and BLAS threads (and batch workers) used
        bad = non_finite(summary)
        if bad:
            listed = "; ".join(f"{k} = {v}" for k, v in list(bad.items())[:3])
            raise RenderError(f"{scene.source_name}: the render gave non-finite numbers ({listed}); nothing was "
                              f"written to {out_dir}")
        (stage / "summary.md").write_text(markdown(summary))
        (stage / SUMMARY).write_text(strict_json(summary, indent=2))
        folder.place()  # the manifest (sizes, hashes), then the swap
    finally:
        progress.close()
    files = folder.files()
    logger.info("rendered %s into %s in %.1f s", scene.name, out_dir, clock["total"])
    return RenderResult(out_dir=out_dir, files=files, summary=summary)


def _write_design(stage: Path, d, L: float, V: float) -> None:
    """design.vtp: the control points with the target and achieved flow and the residual."""
    P = d.control.shape[0]
    z = np.zeros((P, 1))
    write_points(stage / "design.vtp", np.column_stack([d.control * L, z]),
                 {"target": np.concatenate([d.target * (V if d.kind == "velocity" else 1.0), z], axis=1),
                  "achieved": np.concatenate([d.achieved * V, z], axis=1), "residual": d.residual,
                  **({"speed_ratio": d.speed_ratio} if d.speed_ratio is not None else {})})
