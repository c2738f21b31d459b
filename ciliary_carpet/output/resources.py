"""What a scene needs, checked before any work: :func:`check_resources` compares lower bounds of
the memory and time a render needs (:class:`Estimate`) with what the machine has
(:func:`available_memory`) and the time allowed, and refuses coordinates and ``[units]`` scales
that would overflow."""
from __future__ import annotations

import inspect
import logging
import math
import os
from dataclasses import dataclass

from ciliary_carpet.output import RenderError
from ciliary_carpet.scenes.scene import Scene, SceneError
from ciliary_carpet.transport.pathlines import pathlines

logger = logging.getLogger(__name__)

__all__ = ["ResourceError", "Estimate", "check_resources", "available_memory", "expected_memory", "places_that_fit",
           "MAX_PATHLINE_STEPS", "MAX_COORDINATE", "SCALE_RANGE"]


class ResourceError(RenderError):
    """The scene needs more memory or time than the machine has (raised before any work)."""


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


def available_memory() -> float:
    """MemAvailable (Linux), or the physical memory, capped by RLIMIT_AS minus what this process
    already maps and by what this process's control group can still take (a container's or a
    batch job's memory limit, :func:`cilia_runtime.cgroup.memory_headroom`)."""
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
    from cilia_runtime.cgroup import memory_headroom

    room = memory_headroom()
    if room is not None:
        avail = min(avail, room)
    return avail


# Working-set peaks of whole renders (every process of the render together: the main process, and
# with two places the fork server and its worker; a control group's usage less its inactive file
# pages, polled every 0.1 s; `ciliary-carpet render`, default outputs, 2 cores), MiB, the largest
# of the scenes measured at each size: at 100 cilia the bundled planar scenes (uniform_deflection
# 317 / 566, focusing 390 / 589, shear_layer 402 / 580, vortex_turn 353 / 608), at 900 and 10^4 the
# uniform_deflection scene scaled up (758 / 1149, 1702 / 2691). A standing carpet of 160 cilia
# (standing_mixer) took 631 / 862, 1.46 / 1.33 times a planar one of its size.
_PEAK_MIB = ((100, 402.0, 608.0), (900, 758.0, 1149.0), (10_000, 1702.0, 2691.0))  # cilia, one place, two
_STANDING = 1.46
_PEAK_MARGIN = 1.15
_COUPLED_MIB = (600.0, 100.0, 0.12)
"""What a coupled carpet adds to a render's peak (MiB): the table over the flow in this process,
in each further place (it is sent there as its dataset), and per cilium (the coupled solve's trial
carpets). Measured: a 3 x 3 coupled render 998 / 1313 MB at one / two places against 402 / 623
uncoupled; a 100 x 100 coupled design 3.67 GB against 1.88 (benchmarks/results/bench_coupling.md)."""
_FIELD_BYTES_PER_POINT = 1024
"""Bytes per point of the field grid (``output.field_shape``) at a render's peak: an evaluation of
the mean flow with its error bound takes 860 bytes per point at its peak (tracemalloc, 9 10^4
points over 100 cilia, levels of detail at tol 1e-3), and the render keeps the points, the
velocity and the bound of the grid (56 bytes per point) and the mean flow on it."""


def expected_memory(scene: Scene, places: int = 1) -> float:
    """The memory (bytes) a render of ``scene`` is expected to take at its peak, all its processes
    together, with its path-line stage on ``places`` places
    (:func:`~ciliary_carpet.transport.parallel.pool_for_threads`: this process and ``places - 1``
    workers with their fork server).

    Not a bound (:func:`check_resources` has the certain lower bounds): working-set peaks measured
    on renders at 100, 900 and 10^4 cilia (``_PEAK_MIB``, the largest scene of each size),
    interpolated linearly in the number of cilia and beyond 10^4 by the last slope, times 1.46 for
    a standing carpet, each place after the second adding what the second did; a coupled carpet
    adds its table and trial carpets (:data:`_COUPLED_MIB`); plus the field
    grid's (``output.field_shape``, :data:`_FIELD_BYTES_PER_POINT` per point; the measured renders'
    80 x 80 grids took a few MB of it); all times 1.15 as a margin.
    It sizes a batch's workers and a render's places to a memory limit
    (:func:`places_that_fit`)."""
    import numpy as np

    n = float(scene.carpet.n_cilia)
    sizes = np.array([a[0] for a in _PEAK_MIB], float)
    mib = []
    for col in (1, 2):
        vals = np.array([a[col] for a in _PEAK_MIB])
        if n <= sizes[-1]:
            mib.append(float(np.interp(n, sizes, vals)))  # below 100 cilia: the 100-cilium value
        else:
            mib.append(float(vals[-1] + (n - sizes[-1]) * (vals[-1] - vals[-2]) / (sizes[-1] - sizes[-2])))
    one, two = mib
    total = one + max(0, int(places) - 1) * (two - one)
    if scene.carpet.geometry == "standing":
        total *= _STANDING
    if scene.carpet.coupling == "mean":
        here, per_place, per_cilium = _COUPLED_MIB
        total += here + max(0, int(places) - 1) * per_place + n * per_cilium
    o = scene.output
    field = float(o.field_shape[0]) * float(o.field_shape[1]) * _FIELD_BYTES_PER_POINT if (
        o.field or o.snapshots > 0 or o.ftle) else 0.0
    return (total * 2.0 ** 20 + field) * _PEAK_MARGIN


def places_that_fit(scene: Scene, places: int) -> int:
    """The most places, at most ``places``, whose :func:`expected_memory` fits what is available now
    (:func:`available_memory`: MemAvailable, a control group's limit; and what this process holds
    already, which the estimate counts), at least one. A render
    that does not fit in one place is warned about (it is still tried: the estimate is not a
    bound); one that gets fewer places than asked is logged."""
    places = max(1, int(places))
    avail = available_memory()
    if not math.isfinite(avail):
        return places
    avail += _resident()  # the estimate counts this process's own memory, which it holds already
    p = places
    while p > 1 and expected_memory(scene, p) > avail:
        p -= 1
    need = expected_memory(scene, p)
    if need > avail:
        logger.warning("%s: a render of %d cilia is expected to take about %s of memory at its peak, more than the "
                       "%s available (a container's or a batch job's limit, or the machine's): it may be killed "
                       "for want of memory; give it more, or make the carpet smaller",
                       scene.source_name, scene.carpet.n_cilia, _gb(need), _gb(avail))
    elif p < places:
        logger.warning("%s: path lines on %s instead of %d places: %d would take about %s of memory, more than "
                       "the %s available", scene.source_name, "this process alone" if p == 1 else f"{p} places",
                       places, places, _gb(expected_memory(scene, places)), _gb(avail))
    return p


def _resident() -> float:
    """Bytes of this process's resident anonymous memory (``RssAnon``: what a control group charges
    it for; shared libraries' pages may be charged to whoever read them first), 0 where the
    system does not tell."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("RssAnon:"):
                    return float(line.split()[1]) * 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return 0.0


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
    avail = available_memory()
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
