"""Mixing: the finite-time Lyapunov exponent (FTLE) field of a carpet's flow, and a mixing number.

Tracers start on a regular grid of the plane, ``X0``, and are advected for a time ``T`` by a
flow model (:mod:`ciliary_carpet.transport.flow`: the time-resolved beat, the long-time mean flow,
...; :func:`~ciliary_carpet.transport.pathlines.pathlines`). With
the flow map ``Phi(X0) = x(T)`` and its gradient ``J = dPhi/dX0`` (second-order differences on
the grid), the right Cauchy-Green tensor ``C = J^T J`` and its largest eigenvalue
``lambda_max``, the FTLE is

.. math::

    \\sigma(X_0) = \\frac{1}{|T|} \\ln \\sqrt{\\lambda_{max}(C)},

the exponential rate at which neighbouring tracers separate (ridges of ``sigma`` are the
Lagrangian coherent structures that organise transport). The mixing number is the grid average
of the total log-stretching, ``M = <sigma> |T| = <ln sqrt(lambda_max)>`` (dimensionless; 0 for a
translation or rotation, growing with stretching and folding), so that layouts can be compared at
equal duration. Grid points inside a filament at the start, and tracers that leave the domain
before ``T``, get NaN and are left out of the averages. Exact for a linear flow ``u = A x``:
``sigma`` is the largest singular value's log rate of ``exp(A T)`` (tested with a hyperbolic
flow, where ``sigma = a``).
"""
from __future__ import annotations

import logging
import math
import time as _time
from dataclasses import dataclass, field
import numpy as np

from ciliary_carpet.transport.flow import Flow
from ciliary_carpet.transport.pathlines import END, pathlines

logger = logging.getLogger(__name__)

__all__ = ["FTLEField", "ftle_field", "FTLEError"]


class FTLEError(ValueError):
    """An FTLE request that cannot be computed as asked (grid, box or duration)."""


@dataclass(frozen=True)
class FTLEField:
    """FTLE on a grid of start points: ``ftle`` (ny, nx) in 1/time (NaN where undefined),
    ``origin`` (x0, y0), ``spacing`` (dx, dy), ``duration`` T, ``model`` of the flow, the mixing
    number (module docstring), work counters, and the ``height`` z of the grid's plane (0: the
    plane of a planar carpet)."""

    ftle: np.ndarray
    origin: tuple
    spacing: tuple
    duration: float
    model: str
    mixing_number: float
    stats: dict = field(default_factory=dict)
    height: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        """(nx, ny)."""
        return (self.ftle.shape[1], self.ftle.shape[0])


def ftle_field(flow: Flow, box, shape, duration: float, *, rtol: float = 1e-6, atol: float = 1e-6,
               t0: float = 0.0, height: float = 0.0) -> FTLEField:
    """FTLE of ``flow`` (a :class:`~ciliary_carpet.transport.flow.Flow`, e.g. the long-time
    ``MeanFlow.from_carpet(carpet, box)``) on the ``shape = (nx, ny)`` grid spanning
    ``box = (xmin, xmax, ymin, ymax)``, over ``duration`` (> 0) from ``t0``; the grid points inside
    a filament of ``flow.carpet`` at ``t0`` are left out. The grid lies in the plane z = ``height``
    (0: a planar carpet's own plane; a standing carpet's target plane above its cilia, where
    ``flow`` is the plane's in-plane flow: 2D tracers, :class:`~ciliary_carpet.transport.flow.MeanFlow`
    of that plane). Raises :class:`FTLEError` before any work
    for a grid with fewer than 3 points per side, an empty box or a duration that is not positive."""
    try:
        nx, ny = (int(v) for v in shape)
    except (TypeError, ValueError):
        raise FTLEError(f"FTLE grid shape must be two integers (nx, ny), got {shape!r}") from None
    if nx < 3 or ny < 3:
        raise FTLEError(f"FTLE grid shape must be at least 3 x 3 (differences need neighbours), got {nx} x {ny}")
    b = np.asarray(box, dtype=float).reshape(-1)
    if b.size != 4 or not np.all(np.isfinite(b)) or b[1] <= b[0] or b[3] <= b[2]:
        raise FTLEError(f"FTLE box must be (xmin, xmax, ymin, ymax) with min < max, got {box!r}")
    if not (math.isfinite(duration) and duration > 0):
        raise FTLEError(f"FTLE duration must be finite and > 0, got {duration!r}")
    clock = _time.perf_counter()
    x = np.linspace(b[0], b[1], nx)
    y = np.linspace(b[2], b[3], ny)
    X, Y = np.meshgrid(x, y)
    pts = np.column_stack([X.ravel(), Y.ravel()])
    if height != 0.0:  # the grid's plane in space (a standing carpet's flow takes 3D points only)
        pts = np.column_stack([pts, np.full(pts.shape[0], float(height))])
    carpet = flow.carpet
    blob = carpet.blob if carpet.blob is not None else 0.0
    ok = carpet.filament_distance(pts, t0) >= blob if blob > 0 else np.ones(len(pts), bool)
    pl = pathlines(flow, pts[ok], (t0, t0 + duration), rtol=rtol, atol=atol, samples_per_period=1)
    end = np.full((len(pts), 2), np.nan)
    good = np.zeros(len(pts), bool)
    good[np.nonzero(ok)[0]] = pl.reason == END
    end[np.nonzero(ok)[0]] = pl.end_points[:, :2]
    end[~good] = np.nan
    ex = end[:, 0].reshape(ny, nx)
    ey = end[:, 1].reshape(ny, nx)
    dx, dy = x[1] - x[0], y[1] - y[0]
    J11, J12 = np.gradient(ex, dx, axis=1), np.gradient(ex, dy, axis=0)
    J21, J22 = np.gradient(ey, dx, axis=1), np.gradient(ey, dy, axis=0)
    c11 = J11 ** 2 + J21 ** 2
    c22 = J12 ** 2 + J22 ** 2
    c12 = J11 * J12 + J21 * J22
    lam = 0.5 * (c11 + c22) + np.sqrt(0.25 * (c11 - c22) ** 2 + c12 ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = np.log(np.sqrt(lam)) / duration
    sigma[~np.isfinite(sigma)] = np.nan
    mixing = float(np.nanmean(sigma) * duration) if np.any(np.isfinite(sigma)) else float("nan")
    stats = {"tracers": int(ok.sum()), "defined": int(np.isfinite(sigma).sum()), "seconds":
             _time.perf_counter() - clock, "pathlines": pl.stats}
    logger.info("FTLE on %d x %d over %.4g: mixing number %.3g (%.2f s)", nx, ny, duration, mixing, stats["seconds"])
    return FTLEField(ftle=sigma, origin=(float(x[0]), float(y[0])), spacing=(float(dx), float(dy)),
                     duration=float(duration), model=pl.model, mixing_number=mixing, stats=stats, height=float(height))
