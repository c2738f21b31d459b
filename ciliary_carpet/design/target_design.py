"""A carpet designed for a resolved :class:`~ciliary_carpet.design.target.Target`, with the verdict
against its ``residual`` (:func:`design_target` for planar carpets, :func:`design_standing_target`
for standing ones).

The target's control points and angles (or velocities) come from the target itself
(:mod:`~ciliary_carpet.design.control`); a planar angle target's per-cilium request is the pattern
evaluated at each cilium's force centre (the local layout), the solve is
:func:`~ciliary_carpet.design.inverse.design_layout`. A design whose rms residual exceeds the
target's threshold returns the closest flow the cilia can make, with a warning naming the worst
control points; with ``strict`` it is a :class:`~ciliary_carpet.design.result.DesignError` (exit
status 3 of the command line) and unreachable angle requests are a
:class:`~ciliary_carpet.design.errors.TargetError` instead of being clipped. With ``sigma > 0``
the design's summary holds its tolerance study. A scene's door to these is
:func:`ciliary_carpet.scenes.assembly.design`.
"""
from __future__ import annotations

import logging
import math
import warnings
from dataclasses import replace
from typing import Callable

import numpy as np

from single_cilium.table import ThrustTable

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.design.moments import cycle_moments
from ciliary_carpet.design.control import control_points, reachable_check
from ciliary_carpet.design.frame import Frame
from ciliary_carpet.design.inverse import check_control_points, design_layout
from ciliary_carpet.design.reachability import reachability
from ciliary_carpet.design.result import Design, DesignError
from ciliary_carpet.design.target import Target
from ciliary_carpet.design.tolerance import tolerance_study

logger = logging.getLogger(__name__)

__all__ = ["design_target", "design_standing_target"]


def design_target(target: Target, table: ThrustTable, bases: np.ndarray, frame: Frame,
                  carpet_of: Callable[..., Carpet], *, direction: float, spacing: float, tol: float,
                  source: str = "<target>") -> tuple[Design, Carpet]:
    """Design a planar carpet for ``target`` (not kind "none"): returns (Design, the designed
    Carpet).

    ``table``: the carpet's thrust table; ``bases`` (N, 2): its base points; ``frame``: the
    target's frame of those bases; ``carpet_of(chi_N)``: the carpet with curvatures ``chi_N``
    ((N,); None: the carpet's own, the starting guess of a velocity target); ``direction``: the
    field direction [rad, anticlockwise from +y]; ``spacing``: the lattice spacing [L]; ``tol``:
    the flow model's tolerance; ``source`` names the target's origin in messages (the scene
    file). See the module docstring for the verdict."""
    strict = target.strict
    threshold = target.threshold()  # [target] residual, with sampled velocities' own noise
    kw = dict(tol=tol, speed_floor=target.speed_floor, smoothness=target.smoothness,
              spacing=spacing, robust_sigma=target.sigma if target.robust else 0.0,
              threshold=threshold, inside_swept=target.inside_swept)
    if target.is_angle:
        # the local layout straight away (no carpet of straight cilia is built): the request at
        # each cilium's force centre, the centre of the straight filament
        mom = cycle_moments(table)
        a = direction
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        centres0 = bases + mom(np.zeros(1))["offset"] @ rot.T
        want, bad = reachable_check(target.deflection(centres0, frame), table.thrust_angle_range(), not strict,
                                    what="cilium", points=bases)
        chi0 = np.asarray(table.chi_N_for_angle(want), dtype=float)
        carpet = carpet_of(chi0)
        X = control_points(bases, frame, target.control)
        reach = reachability(carpet, X, frame, target=target)  # up front: what this carpet can make
        if target.pattern.two_sided and target.amplitude > reach.pattern_max:
            logger.info("design: the %s amplitude %.1f deg exceeds the estimated reachable %.1f deg of a two-sided "
                        "pattern on this carpet", target.kind, math.degrees(target.amplitude),
                        math.degrees(reach.pattern_max))
        if reach.width_reachable is False:
            logger.info("design: the %s width %.3g L is below the estimated narrowest %.3g L at %.1f deg on this "
                        "carpet (estimated rms %.3g against %g)", target.kind, reach.width, reach.width_min,
                        math.degrees(target.amplitude), reach.width_rms, target.residual)
        d = design_layout(carpet, X, angles=target.deflection(X, frame), cilium_angles=want, clip=not strict,
                          **kw)
        d = _replace(d, reachability=reach.summary(),
                     **({"clipped": tuple(np.nonzero(bad)[0].tolist())} if np.any(bad) else {}))
    else:
        carpet = carpet_of(None)
        X, U = target.velocities()
        d = design_layout(carpet, X, velocities=U, clip=not strict, sample_weights=target.sample_weights(), **kw)
    verdict = _verdict_threshold(target)
    if d.residual_rms > threshold:
        unit = "rad" if d.kind == "angle" else "relative"
        lst = ", ".join(f"#{k} at ({x:.3g}, {y:.3g}): {r:.3g} {unit}" for k, x, y, r in d.worst())
        est, hint = [], ("Lower the target angle, widen the pattern, or move the control points away from the cilia"
                         if target.is_angle else _POINTS_HINT)
        r = d.reachability
        if target.pattern.two_sided and r is not None:
            est.append(f"a two-sided pattern holds about {r['pattern_max_deg']:.1f} deg, asked "
                       f"{math.degrees(target.amplitude):.1f} deg")
        if r is not None and "width_min" in r:
            wm = r["width_min"]
            est.append(f"narrowest transition at {math.degrees(target.amplitude):.1f} deg: "
                       + ("none up to 8 spacings" if wm is None else f"{wm:.3g} L") + f", asked {r['width']:.3g} L")
            if wm is not None and r["width"] < wm:
                hint = f"Widen the pattern to about {wm:.3g} L or more, lower the target angle, or move the control " \
                       "points away from the cilia"
        est_s = f" (estimated on this carpet: {'; '.join(est)})" if est else ""
        msg = (f"{source}: the cilia cannot make this target: rms residual {d.residual_rms:.3g} "
               f"{unit} exceeds {verdict}{est_s}; worst control points {lst}. {hint}")
        if strict:
            raise DesignError(msg)
        warnings.warn(msg + " (strict = false: returning the closest flow the cilia make)", UserWarning,
                      stacklevel=3)
        d = _replace(d, message=d.message + f"; target NOT met ({verdict}): the "
                     f"closest flow the cilia make; worst control points {lst}")
    else:
        d = _replace(d, message=d.message + f"; target met ({verdict})")
    d = _replace(d, threshold=threshold)
    if target.sigma > 0:
        d = _replace(d, tolerance=tolerance_study(d.carpet, d, target.sigma, target.samples).summary())
    return d, d.carpet


def design_standing_target(target: Target, bases: np.ndarray, frame: Frame, carpet: Carpet, *, spacing: float,
                           tol: float, source: str = "<target>") -> tuple[Design, Carpet]:
    """Design a standing carpet for ``target`` (a surface kind or "points"): (chi_N, psi) for its
    surface flow (:func:`~ciliary_carpet.design.surface.design_surface`) on the plane z =
    ``target.height``, the control points the planar rule gives ("cilia": above each base), the
    verdict of :func:`design_target`. ``carpet``: the carpet as built (its own curvatures and
    azimuths); the other arguments as :func:`design_target`'s."""
    from ciliary_carpet.design.surface import design_surface

    threshold = target.threshold()  # [target] residual, with sampled velocities' own noise
    verdict = _verdict_threshold(target)
    kw = dict(height=target.height, tol=tol, speed_floor=target.speed_floor,
              smoothness=target.smoothness, threshold=threshold,
              robust_sigma=target.sigma if target.robust else 0.0,
              robust_sigma_psi=math.radians(target.sigma_psi) if target.robust else 0.0)
    hint = ("Move the pattern's centres apart, raise target.height, or use more cilia" if target.is_surface
            else _POINTS_HINT)
    if target.is_surface:
        X = bases.copy() if target.control == "cilia" else control_points(bases, frame, target.control)
        A, keep = target.surface_directions(X, frame, bases)
        if not np.all(keep):
            logger.info("design: %d control points within half a spacing of the %s pattern's centres left out",
                        int((~keep).sum()), target.kind)
        X = X[keep]
        check_control_points(carpet, X, spacing)
        d = design_surface(carpet, X, directions=A, **kw)
    else:
        X, U = target.velocities()
        check_control_points(carpet, X, spacing)
        d = design_surface(carpet, X, velocities=U, strict=target.strict, **kw)
    unit = "rad" if d.kind == "angle" else "relative"
    if d.residual_rms > threshold:
        lst = ", ".join(f"#{k} at ({x:.3g}, {y:.3g}): {r:.3g} {unit}" for k, x, y, r in d.worst())
        msg = (f"{source}: the cilia cannot make this surface flow: rms residual {d.residual_rms:.3g} "
               f"{unit} exceeds {verdict}; worst control points {lst}. {hint}")
        if target.strict:
            raise DesignError(msg)
        warnings.warn(msg + " (strict = false: returning the closest flow the cilia make)", UserWarning, stacklevel=3)
        d = _replace(d, message=d.message + f"; target NOT met ({verdict}): the closest "
                     f"flow the cilia make; worst control points {lst}")
    else:
        d = _replace(d, message=d.message + f"; target met ({verdict})")
    d = _replace(d, threshold=threshold)
    if target.sigma > 0 or target.sigma_psi > 0:
        d = _replace(d, tolerance=tolerance_study(d.carpet, d, target.sigma, target.samples,
                                                  sigma_psi=math.radians(target.sigma_psi)).summary())
    return d, d.carpet


_POINTS_HINT = ("Lower the target speeds where the residual is largest, check that the samples are in the lab "
                "frame and in L/tau (a scene's [units] convert them), set [target] residual to the samples' own "
                "relative noise if that is larger, or use more cilia")
"""What to change when a "points" target (sampled velocities, e.g. PIV) is not met."""


def _verdict_threshold(target) -> str:
    """The threshold a verdict is given against, in words: ``[target] residual``, and for sampled
    velocities with uncertainties how it combines with their noise."""
    n = target.noise()
    if n == 0.0:
        return f"[target] residual = {target.residual:g}"
    return (f"threshold {target.threshold():.3g} = sqrt(residual^2 + noise^2): [target] residual = "
            f"{target.residual:g} and the samples' own relative rms noise {n:.3g}")


def _replace(d: Design, **kw) -> Design:
    return replace(d, **kw)
