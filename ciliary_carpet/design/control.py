"""Control points, where a design compares the carpet's mean flow with its target
(:func:`control_points`), and the check of requested deflections against the thrust table's
reachable range (:func:`reachable_check`).

Control points: "cilia" = every base point moved half a spacing downstream (along d0); "cells" =
the centres of the lattice cells: the circumcentres of the Delaunay triangles of the base points
(the Voronoi vertices: the points farthest from every base), merged where two triangles share one
(the cell centres of a square lattice, the triangle centres of a hexagonal one), and for a carpet
whose base points lie on a line (a row) the "cilia" rule; or an explicit list.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from ciliary_carpet.design.errors import TargetError, UnreachableTargetError
from ciliary_carpet.design.frame import Frame, checked_points

__all__ = ["control_points", "reachable_check"]


def control_points(bases, frame: Frame, control="cells") -> np.ndarray:
    """(P, 2) points where the designed mean flow is compared with the target.

    ``control``: "cilia" (each base point moved half a spacing along d0, just downstream of its
    cilium), "cells" (the circumcentres of the Delaunay triangles of the base points, duplicates
    merged: the cell centres; for collinear base points, a row, the "cilia" rule), a list
    of points (P, 2), or anything with a ``control`` attribute holding one of these (a Target or
    a TargetSpec)."""
    if hasattr(control, "control"):
        control = control.control
    b = checked_points("bases", bases)
    h, d0, cr = frame.spacing, frame.flow_direction, frame.cross
    if not isinstance(control, str):
        return checked_points("control points", control).copy()
    if control not in ("cells", "cilia"):
        raise TargetError(f"control must be 'cells', 'cilia' or a list of points, got {control!r}")
    down = b + 0.5 * h * d0
    if control == "cilia" or b.shape[0] < 3:
        return down
    sv = np.linalg.svd(b - b.mean(axis=0), compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], h):  # collinear: a row
        return down
    from scipy.spatial import ConvexHull, Delaunay

    tri = Delaunay(b)
    cand = _circumcentres(b[tri.simplices])
    # the two triangles of a square cell share their circumcentre: keep one
    key = np.round((cand - b.min(axis=0)) / (1e-6 * h)).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    cand = cand[np.sort(first)]
    # inside the triangulation = inside the bases' convex hull (its unit-normal half-planes; a
    # point search in a square lattice's degenerate triangulation took 2 s for 100 x 100 cilia)
    eq = ConvexHull(b).equations
    inside = np.all(cand @ eq[:, :2].T + eq[:, 2] <= 1e-9 * h, axis=1)
    if not np.any(inside):
        raise TargetError("no cell centre lies inside the carpet (too few cilia for control = \"cells\"); "
                          "use control = \"cilia\" or a list of points")
    cand = cand[inside]
    return cand[np.lexsort((cand[:, 0], cand[:, 1]))]


def _circumcentres(t: np.ndarray) -> np.ndarray:
    """(T, 2) circumcentres of the triangles t (T, 3, 2)."""
    a, bb, c = t[:, 0], t[:, 1], t[:, 2]
    d = 2.0 * (a[:, 0] * (bb[:, 1] - c[:, 1]) + bb[:, 0] * (c[:, 1] - a[:, 1]) + c[:, 0] * (a[:, 1] - bb[:, 1]))
    sa, sb, sc = (a ** 2).sum(1), (bb ** 2).sum(1), (c ** 2).sum(1)
    ux = (sa * (bb[:, 1] - c[:, 1]) + sb * (c[:, 1] - a[:, 1]) + sc * (a[:, 1] - bb[:, 1])) / d
    uy = (sa * (c[:, 0] - bb[:, 0]) + sb * (a[:, 0] - c[:, 0]) + sc * (bb[:, 0] - a[:, 0])) / d
    return np.column_stack([ux, uy])


# ------------------------------------------------------------------------------ reachability
def reachable_check(angles, angle_range, clip: bool = False, *, what: str = "control point",
                    points=None) -> tuple[np.ndarray, np.ndarray]:
    """Check requested deflections against the table's reachable range.

    ``angles`` (P,) rad; ``angle_range`` = ``table.thrust_angle_range()`` (only its maximum is
    used: |delta| <= max, negative angles by mirror symmetry); ``what`` names the items in the
    message ("control point", "cilium") and ``points`` (P, 2), if given, their positions.

    Returns ``(angles, unreachable)``: a copy of the angles (clipped to [-max, max] with
    ``clip=True``) and the (P,) boolean mask of the unreachable ones. Without ``clip`` any
    unreachable angle is a :class:`TargetError` listing the indices, positions and requested
    angles (the first 10) and the reachable range; with ``clip`` the same list is a
    ``UserWarning``."""
    a = np.atleast_1d(np.asarray(angles, dtype=float)).copy()
    if not np.all(np.isfinite(a)):
        raise TargetError("target angles contain NaN or inf")
    hi = float(angle_range[1])
    bad = np.abs(a) > hi * (1 + 1e-12)
    if np.any(bad):
        idx = np.nonzero(bad)[0]
        pts = None if points is None else checked_points("points", points)
        items = []
        for i in idx[:10]:
            at = f" at ({pts[i, 0]:.4g}, {pts[i, 1]:.4g})" if pts is not None else ""
            items.append(f"{what} {i}{at} asks {math.degrees(a[i]):.2f} deg")
        more = f" (and {idx.size - 10} more)" if idx.size > 10 else ""
        items_name = "cilia" if what == "cilium" else f"{what}s"
        msg = (f"{idx.size} of {a.size} {items_name} ask for a deflection outside the reachable range "
               f"|angle| <= {math.degrees(hi):.2f} deg ({hi:.4f} rad) of this field: {'; '.join(items)}{more}")
        if not clip:
            raise UnreachableTargetError(msg + "; lower target.angle, or set target.strict = false to clip them")
        warnings.warn(msg + "; clipped to the reachable range", UserWarning, stacklevel=2)
        a = np.clip(a, -hi, hi)
    return a, bad

