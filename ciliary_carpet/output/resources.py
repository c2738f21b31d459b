"""What a render needs, from numbers: :func:`lower_bounds` compares lower bounds of the memory
and time a render needs (:class:`Estimate`) with what the machine has (:func:`available_memory`)
and the time allowed; :func:`expected_memory` is its expected peak (:class:`Needs`), and
:func:`places_that_fit` the places that memory allows. The scene's side -- its keys read, its
coordinates and ``[units]`` scales checked -- is :mod:`ciliary_carpet.scenes.resources`."""
from __future__ import annotations

import inspect
import logging
import math
import os
from dataclasses import dataclass

from ciliary_carpet.output import RenderError
from ciliary_carpet.transport.pathlines import pathlines

logger = logging.getLogger(__name__)

__all__ = ["ResourceError", "Estimate", "Needs", "lower_bounds", "available_memory", "expected_memory",
           "places_that_fit", "MAX_PATHLINE_STEPS", "MAX_COORDINATE", "SCALE_RANGE"]


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
    part (named by the scene key that sets it), ``available_bytes`` what the machine has,
    ``limit_seconds`` the time allowed."""

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


@dataclass(frozen=True)
class Needs:
    """What a render's peak memory depends on, as numbers (a scene's: ``Scene.needs()``).

    Attributes
    ----------
    source : str
        What warnings name the render by (its scene file).
    n_cilia : int
        The carpet's cilia.
    standing : bool
        Whether the carpet is a standing one.
    coupled : bool
        Whether the cilia are coupled through their mean flow.
    field_points : float
        The field grid's points when the render evaluates a field on it (the mean field, the
        snapshots or the FTLE), else 0.
    """

    source: str
    n_cilia: int
    standing: bool
    coupled: bool
    field_points: float


def expected_memory(needs: Needs, places: int = 1) -> float:
    """The memory (bytes) a render is expected to take at its peak, all its processes together,
    with its path lines run in ``places`` processes
    (:func:`~cilia_runtime.pool.pool_for_threads`: this process and ``places - 1``
    workers with their fork server). ``needs``: the render's :class:`Needs`
    (:meth:`Scene.needs <ciliary_carpet.scenes.scene.Scene.needs>`).

    Not a bound (:func:`lower_bounds` has the certain lower bounds): working-set peaks measured
    on renders at 100, 900 and 10^4 cilia (``_PEAK_MIB``, the largest scene of each size),
    interpolated linearly in the number of cilia and beyond 10^4 by the last slope, times 1.46 for
    a standing carpet, each place after the second adding what the second did; a coupled carpet
    adds its table and trial carpets (:data:`_COUPLED_MIB`); plus the field
    grid's (``Needs.field_points``, :data:`_FIELD_BYTES_PER_POINT` per point; the measured renders'
    80 x 80 grids took a few MB of it); all times 1.15 as a margin.
    It sizes a batch's workers and a render's places to a memory limit
    (:func:`places_that_fit`)."""
    import numpy as np

    n = float(needs.n_cilia)
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
    if needs.standing:
        total *= _STANDING
    if needs.coupled:
        here, per_place, per_cilium = _COUPLED_MIB
        total += here + max(0, int(places) - 1) * per_place + n * per_cilium
    return (total * 2.0 ** 20 + float(needs.field_points) * _FIELD_BYTES_PER_POINT) * _PEAK_MARGIN


def places_that_fit(needs: Needs, places: int) -> int:
    """The most processes for the path lines, at most ``places``, whose :func:`expected_memory`
    fits what is available now (:func:`available_memory`: MemAvailable, a control group's limit;
    and what this process holds already, which the estimate counts), at least one. ``needs``: the
    render's :class:`Needs`. A render that does not fit in one process is warned about (it is
    still tried: the estimate is not a bound); one that gets fewer processes than asked is logged."""
    places = max(1, int(places))
    avail = available_memory()
    if not math.isfinite(avail):
        return places
    avail += _resident()  # the estimate counts this process's own memory, which it holds already
    p = places
    while p > 1 and expected_memory(needs, p) > avail:
        p -= 1
    need = expected_memory(needs, p)
    if need > avail:
        logger.warning("%s: a render of %d cilia is expected to take about %s of memory at its peak, more than the "
                       "%s available (a container's or a batch job's limit, or the machine's): it may be killed "
                       "for want of memory; give it more, or make the carpet smaller",
                       needs.source, needs.n_cilia, _gb(need), _gb(avail))
    elif p < places:
        logger.warning("%s: path lines in %s instead of %d processes: %d would take about %s of memory, more "
                       "than the %s available", needs.source, "this process alone" if p == 1 else f"{p} processes",
                       places, places, _gb(expected_memory(needs, places)), _gb(avail))
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


def lower_bounds(source: str, parts: tuple, *, cilia: float, field_points: float, fields: int, tracers: float,
                 steps: float, max_seconds: float = 86400.0) -> Estimate:
    """Lower bounds of what a render needs (:class:`Estimate`), checked against the machine and the
    time allowed: ``cilia``, ``field_points`` (of each of ``fields`` field evaluations),
    ``tracers`` followed for ``steps`` steps; ``parts`` names the memory's three parts -- the
    cilia's, the field's and the tracers' -- in that order (the scene keys that set them).

    The bounds count only what a render certainly needs (``_BYTES_PER_CILIUM`` etc. are far
    below the measured costs), so a render is refused only when it certainly cannot finish:
    memory above what is available (:func:`available_memory`), or time above ``max_seconds``.
    Raises :class:`ResourceError` naming ``source``, the part that takes most memory and the
    estimate."""
    memory = dict(zip(parts, (cilia * _BYTES_PER_CILIUM, field_points * _BYTES_PER_POINT,
                             tracers * (steps + 1.0) * _BYTES_PER_TRACER_STEP)))
    mem = sum(memory.values())
    pairs = 3.0 * cilia * (field_points * fields + 7.0 * tracers * steps)
    seconds = pairs / _PAIRS_PER_SECOND + steps * _SECONDS_PER_STEP
    avail = available_memory()
    est = Estimate(mem, pairs, steps, seconds, memory, avail, float(max_seconds))
    what = (f"{cilia:g} cilia, {field_points:g} field points x {fields} field(s), "
            f"{tracers:g} tracers x {steps:g} steps")
    if mem > avail:
        key = max(memory, key=memory.get)
        raise ResourceError(f"{source}: the scene needs at least {_gb(mem)} of memory ({what}; most of it for {key}), "
                            f"more than the {_gb(avail)} available; make {key} smaller")
    if seconds > max_seconds:
        raise ResourceError(f"{source}: the scene needs at least {seconds / 3600:.3g} hours ({pairs:.3g} Stokeslet "
                            f"pairs at {_PAIRS_PER_SECOND:.2g}/s; {what}), more than the {max_seconds / 3600:.3g} "
                            f"hours allowed; make the carpet, the field or the path lines smaller (or raise "
                            f"--max-hours)")
    logger.debug("resource estimate for %s: %s", source, est)
    return est
