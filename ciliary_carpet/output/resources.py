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

__all__ = ["ResourceError", "Estimate", "check_resources", "available_memory", "MAX_PATHLINE_STEPS",
           "MAX_COORDINATE", "SCALE_RANGE"]


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
    batch job's memory limit, :func:`single_cilium.cgroup.memory_headroom`)."""
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
    from single_cilium.cgroup import memory_headroom

    room = memory_headroom()
    if room is not None:
        avail = min(avail, room)
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
