"""Surface-flow targets of standing carpets: the direction the mean flow on the plane z = h should
take at each control point (:mod:`ciliary_carpet.design.surface`).

Each kind of :data:`SURFACE_KINDS` is a model velocity field v(x) in the plane whose direction is
asked for (its magnitude is not: the design keeps a speed floor instead), written with the
carpet's ``centre`` c, an ``angle`` a (radians anticlockwise from +x; e_a = (cos a, sin a), n =
e_z x e_a) and a ``separation`` d:

* ``pump``: v = e_a, uniform pumping along a;
* ``vortex``: v = s e_z x (x - c) / |x - c|^2, a vortex about c (s = +1 anticlockwise, -1
  clockwise: ``sense``);
* ``mixer``: two counter-rotating vortices at c -+ (d/2) e_a, v = sum_i s_i e_z x (x - c_i) /
  (|x - c_i|^2 + d^2 / 16) with s_i = (+s, -s): a jet between them along s n, the flow returning
  around them;
* ``u_turn``: a flow that comes in along +e_a on the side -n of the axis through c, turns about c
  and goes back along -e_a on the side +n (anticlockwise for s = +1): v = s e_z x (x - q) / |x - q|
  with q the point of the half-line c - t e_a (t >= 0) nearest x;
* ``source_sink``: a source at c - (d/2) e_a and a sink at c + (d/2) e_a, v = (x - c_1) / |x -
  c_1|^2 - (x - c_2) / |x - c_2|^2.

Where v vanishes or is singular (a vortex's centre, a source) the direction is undefined: control
points closer than :data:`SINGULAR_RADIUS` times the spacing to such a point are left out (the
design says how many).
"""
from __future__ import annotations

import math

import numpy as np

from ciliary_carpet.design.errors import TargetError

__all__ = ["SURFACE_KINDS", "SINGULAR_RADIUS", "surface_field", "surface_directions"]

SURFACE_KINDS = ("pump", "vortex", "mixer", "u_turn", "source_sink")
"""The surface-flow targets (``[target] kind`` of a standing scene; ``"points"`` reads velocities from a file)."""
SINGULAR_RADIUS = 0.5
"""Control points within this many spacings of a pattern's singular points are left out."""


def _rot90(v: np.ndarray) -> np.ndarray:
    return np.column_stack([-v[:, 1], v[:, 0]])


def surface_field(kind: str, X: np.ndarray, centre, angle: float = 0.0, separation: float = 4.0,
                  sense: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(v (P, 2), singular points (S, 2)): the model field of ``kind`` at ``X`` (P, 2) (module
    docstring) and the points where its direction is undefined."""
    if kind not in SURFACE_KINDS:
        raise TargetError(f"a standing carpet's target kind must be one of {', '.join(SURFACE_KINDS)} or 'points', "
                          f"got {kind!r}")
    X = np.asarray(X, dtype=float)
    c = np.asarray(centre, dtype=float).reshape(2)
    for name, v in (("angle", angle), ("separation", separation)):
        if not math.isfinite(float(v)):
            raise TargetError(f"target {name} must be finite, got {v!r}")
    if sense not in (1, -1):
        raise TargetError(f"target sense must be +1 (anticlockwise) or -1 (clockwise), got {sense!r}")
    d = float(separation)
    if kind in ("mixer", "source_sink") and not d > 0:
        raise TargetError(f"a {kind} target needs separation > 0, got {separation!r}")
    ea = np.array([math.cos(angle), math.sin(angle)])
    if kind == "pump":
        return np.broadcast_to(ea, X.shape).copy(), np.zeros((0, 2))
    if kind == "vortex":
        r = X - c
        return sense * _rot90(r) / np.maximum(np.sum(r * r, axis=1), 1e-300)[:, None], c[None]
    if kind == "mixer":
        cs = np.array([c - 0.5 * d * ea, c + 0.5 * d * ea])
        v = np.zeros_like(X)
        for ci, si in zip(cs, (sense, -sense)):
            r = X - ci
            v += si * _rot90(r) / (np.sum(r * r, axis=1) + d * d / 16.0)[:, None]
        return v, cs
    if kind == "u_turn":
        t = np.minimum(0.0, (X - c) @ ea)
        q = c + t[:, None] * ea
        r = X - q
        return sense * _rot90(r) / np.maximum(np.linalg.norm(r, axis=1), 1e-300)[:, None], c[None]
    cs = np.array([c - 0.5 * d * ea, c + 0.5 * d * ea])
    r1, r2 = X - cs[0], X - cs[1]
    v = r1 / np.maximum(np.sum(r1 * r1, axis=1), 1e-300)[:, None] - r2 / np.maximum(np.sum(r2 * r2, axis=1),
                                                                                     1e-300)[:, None]
    return v, cs


def surface_directions(kind: str, X: np.ndarray, centre, spacing: float, angle: float = 0.0,
                       separation: float = 4.0, sense: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(directions (P',) [rad, anticlockwise from +x], keep (P,) bool): the target directions at
    the control points ``X`` (P, 2) that are kept, those farther than :data:`SINGULAR_RADIUS`
    ``spacing`` from the pattern's singular points."""
    v, sing = surface_field(kind, X, centre, angle, separation, sense)
    keep = np.ones(X.shape[0], bool)
    for s in sing:
        keep &= np.linalg.norm(X - s, axis=1) > SINGULAR_RADIUS * float(spacing)
    keep &= np.linalg.norm(v, axis=1) > 0
    if not np.any(keep):
        raise TargetError(f"every control point lies within {SINGULAR_RADIUS:g} spacings of the {kind} pattern's "
                          "singular points: no direction to design for")
    return np.arctan2(v[keep, 1], v[keep, 0]), keep
