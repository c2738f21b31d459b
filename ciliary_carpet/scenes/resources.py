"""What a scene needs, checked before any work: :func:`check_resources` refuses coordinates and
``[units]`` scales that would overflow, and compares lower bounds of the memory and time a render
of the scene needs with what the machine has and the time allowed
(:func:`~ciliary_carpet.output.resources.lower_bounds`); :func:`needs` gives what its expected
peak memory depends on (:class:`~ciliary_carpet.output.resources.Needs`). Errors name the scene
file and the scene keys."""
from __future__ import annotations

import math

from ciliary_carpet.output.resources import (MAX_COORDINATE, MAX_PATHLINE_STEPS, SCALE_RANGE, Estimate, Needs,
                                             ResourceError, lower_bounds)
from ciliary_carpet.scenes.schema import SceneError

__all__ = ["check_resources", "needs"]


def needs(scene) -> Needs:
    """What the peak memory of a render of ``scene`` (a :class:`~ciliary_carpet.scenes.scene.Scene`)
    depends on: its cilia, geometry and coupling, and the points of its field grid when the
    render evaluates a field there (``[output] field``, ``snapshots`` or ``ftle``)."""
    o = scene.output
    points = float(o.field_shape[0]) * float(o.field_shape[1]) if (o.field or o.snapshots > 0 or o.ftle) else 0.0
    return Needs(source=scene.source_name, n_cilia=scene.carpet.n_cilia, standing=scene.carpet.geometry == "standing",
                 coupled=scene.carpet.coupling == "mean", field_points=points)


def check_resources(scene, *, max_seconds: float = 86400.0) -> Estimate:
    """Check, before any work, that ``scene`` can be rendered: its coordinates and ``[units]``
    scales are sane and lower bounds of the memory and time it needs fit the machine
    (:func:`~ciliary_carpet.output.resources.lower_bounds`: memory above what is available, time
    above ``max_seconds``), and its path lines need no more steps (one per period at least) than
    the integrator allows. Raises :class:`~ciliary_carpet.output.resources.ResourceError` (or
    :class:`~ciliary_carpet.scenes.schema.SceneError` for a coordinate or unit out of range)
    naming the scene file, the key and the estimate."""
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
    p = float(o.field_shape[0]) * float(o.field_shape[1]) if (o.field or o.snapshots > 0) else 0.0
    k = float(len(o.seeds) if not isinstance(o.seeds, str) else o.n_seeds) if o.pathlines else 0.0
    # periods = None: the duration is chosen later from the carpet's mean speed (pathline_duration);
    # one period is a lower bound, and check_output_size checks the chosen one before any output
    steps = float(max(1.0, math.ceil(o.periods if o.periods is not None else 1.0))) if o.pathlines else 0.0
    if steps > MAX_PATHLINE_STEPS:
        raise ResourceError(f"{src}: output.periods = {o.periods:g} needs at least {steps:g} path-line steps (one "
                            f"per period of the flow), more than the integrator's {MAX_PATHLINE_STEPS}; lower "
                            f"output.periods")
    parts = ("carpet.points" if c.lattice == "points" else "carpet.shape", "output.field_shape",
             "output.seeds" if not isinstance(o.seeds, str) else "output.n_seeds")
    return lower_bounds(src, parts, cilia=float(c.n_cilia), field_points=p,
                        fields=int(o.field) + o.snapshots, tracers=k, steps=steps, max_seconds=max_seconds)
