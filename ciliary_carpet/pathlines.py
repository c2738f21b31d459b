"""Path lines of massless tracers in a carpet's flow: dx/dt = u(x(t), t) (MODEL.md section 6).

All tracers are integrated together by one embedded Runge-Kutta pair (Dormand-Prince 5(4)) with a
common adaptive step: every step evaluates the carpet's velocity once per stage for all active
tracers (one vectorised sum), and a step is accepted only when every active tracer's local error
estimate meets ``atol + rtol |x|`` (max norm over tracers; the published work used an adaptive
multistep solver). A tracer stops when it enters a cilium's swept region (the convex hull of
the positions the filament takes over its cycle, grown by ``margin``), when it leaves the domain,
or at the end time; the reason is recorded per tracer with the codes of :data:`REASONS`.
The flow is quasi-periodic in general (each cilium beats at its own period): the integrator
makes no assumption of periodicity.
"""
from __future__ import annotations

import logging
import math
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from single_cilium.progress import Progress

if TYPE_CHECKING:
    from .carpet import Carpet

logger = logging.getLogger(__name__)

__all__ = ["PathLines", "pathlines", "REASONS"]

REASONS = ("reached end time", "entered a cilium's swept region", "left the domain", "step size underflow")
END, SWEPT, DOMAIN, UNDERFLOW = range(4)

# Dormand-Prince 5(4) tableau
_C = np.array([0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1, 1])
_A = [[], [1 / 5], [3 / 40, 9 / 40], [44 / 45, -56 / 15, 32 / 9],
      [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729],
      [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656],
      [35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84]]
_B = np.array([35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0])
_E = _B - np.array([5179 / 57600, 0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40])


@dataclass(frozen=True)
class PathLines:
    """Tracer trajectories: one polyline per seed.

    points[k] (n_k, 3), times[k] (n_k,), velocities[k] (n_k, 3) at every accepted step of
    tracer k; seed_ids (K,); reason (K,) codes into :data:`REASONS`; stats: work counters
    (steps, rejected, evaluations, seconds); status 0 when the run reached its end time
    (tracers may still have stopped early for physical reasons), 1 on step size underflow;
    message says what happened and what to change."""

    points: list
    times: list
    velocities: list
    seed_ids: np.ndarray
    reason: np.ndarray
    rtol: float
    atol: float
    tol: float
    stats: dict = field(default_factory=dict)
    status: int = 0
    message: str = ""

    @property
    def end_points(self) -> np.ndarray:
        """(K, 3) last position of every tracer."""
        return np.array([p[-1] for p in self.points])

    def counts(self) -> dict:
        """Number of tracers per termination reason."""
        return {REASONS[k]: int(np.sum(self.reason == k)) for k in range(len(REASONS))}

    def write(self, path, scales=None) -> Path:
        """Write as a .vtp (one polyline per tracer; point data time, velocity, speed; cell data
        SeedIds, ReasonForTermination), in SI units when ``scales`` (a Scales) is given."""
        from .vtkfiles import write_pathlines

        L, T = (scales.length_m, scales.time_s) if scales is not None else (1.0, 1.0)
        return write_pathlines(path, [p * L for p in self.points], [t * T for t in self.times],
                               [v * (L / T) for v in self.velocities], self.seed_ids, self.reason, REASONS)


def _domain(domain, carpet: "Carpet", seeds: np.ndarray) -> np.ndarray:
    if domain is None:
        pts = np.concatenate([carpet.bases, seeds[:, :2]])
        lo, hi = pts.min(axis=0) - 10.0, pts.max(axis=0) + 10.0
        return np.array([lo[0], hi[0], lo[1], hi[1], -np.inf, np.inf])
    d = np.asarray(domain, dtype=float).reshape(-1)
    if d.size == 4:
        d = np.concatenate([d, [-np.inf, np.inf]])
    if d.size != 6 or np.any(np.isnan(d)) or np.any(d[1::2] <= d[0::2]):
        raise ValueError(f"domain must be (xmin, xmax, ymin, ymax[, zmin, zmax]) with min < max, got {domain!r}")
    return d


class _Swept:
    """Vectorised test of tracers against the cilia's grown swept hulls."""

    def __init__(self, carpet: "Carpet", margin: float):
        c = carpet._c
        self.centre = c["centre"]
        self.reach = c["radius"] + margin
        self.tree = cKDTree(self.centre)
        eqs = [h if h is not None else np.zeros((0, 3)) for h in c["hulls"]]
        nf = max(1, max(e.shape[0] for e in eqs))
        self.eq = np.zeros((len(eqs), nf, 3))
        self.eq[:, :, 2] = -1.0  # padding facets: always satisfied
        for j, e in enumerate(eqs):
            self.eq[j, :e.shape[0]] = e
        self.round = np.array([h is None for h in c["hulls"]])
        self.margin = margin
        self.k = min(4, carpet.n)

    def inside(self, x: np.ndarray) -> np.ndarray:
        if x.shape[0] == 0:
            return np.zeros(0, bool)
        d, j = self.tree.query(x[:, :2], k=self.k)
        d, j = d.reshape(x.shape[0], -1), j.reshape(x.shape[0], -1)
        near = d <= self.reach[j]
        val = np.einsum("mkfa,ma->mkf", self.eq[j][..., :2], x[:, :2]) + self.eq[j][..., 2]
        hull = np.all(val <= self.margin, axis=-1) & ~self.round[j]
        disc = self.round[j]
        return np.any(near & (hull | disc), axis=1)


def pathlines(carpet: "Carpet", seeds, t_span, *, rtol: float = 1e-6, atol: float = 1e-6, tol: float = 1e-4,
              margin: float = 0.02, domain=None, h0: float | None = None, max_steps: int = 100_000,
              progress: Progress | None = None) -> PathLines:
    """Integrate tracers from ``seeds`` (K, 2) or (K, 3) over ``t_span = (t0, t1)``.

    rtol, atol: local error tolerances of the positions (units of L); tol: the flow model's
    tolerance (levels of detail, see :mod:`ciliary_carpet.carpet`); margin: how far outside
    a swept region a tracer is stopped; domain: (xmin, xmax, ymin, ymax[, zmin, zmax]) (default
    the bounding box of bases and seeds grown by 10 L). Returns :class:`PathLines`."""
    x0 = np.asarray(seeds, dtype=float)
    if x0.ndim != 2 or x0.shape[1] not in (2, 3) or x0.shape[0] < 1:
        raise ValueError(f"seeds must have shape (K, 2) or (K, 3), got {x0.shape}")
    if not np.all(np.isfinite(x0)):
        raise ValueError("seeds contain NaN or inf")
    if x0.shape[1] == 2:
        x0 = np.concatenate([x0, np.zeros((x0.shape[0], 1))], axis=1)
    t0, t1 = (float(v) for v in t_span)
    if not (math.isfinite(t0) and math.isfinite(t1) and t1 > t0):
        raise ValueError(f"t_span must be finite with t1 > t0, got {t_span!r}")
    for k, v in (("rtol", rtol), ("atol", atol)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{k} must be a non-negative number, got {v!r}")
    if rtol == 0 and atol == 0:
        raise ValueError("rtol and atol cannot both be 0")
    if not (math.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin must be >= 0, got {margin!r}")
    dom = _domain(domain, carpet, x0)
    swept = _Swept(carpet, margin)
    progress = progress if progress is not None else Progress()
    clock = _time.perf_counter()

    K = x0.shape[0]
    x = x0.copy()
    reason = np.full(K, END, dtype=np.int64)
    active = np.ones(K, bool)
    start_in = swept.inside(x)
    outside = np.any((x[:, :3] < dom[0::2]) | (x[:, :3] > dom[1::2]), axis=1)
    reason[start_in] = SWEPT
    reason[outside & ~start_in] = DOMAIN
    active &= ~(start_in | outside)
    u = carpet.velocity(x, t0, tol)
    rec_x = [[x[k].copy()] for k in range(K)]
    rec_t = [[t0] for _ in range(K)]
    rec_u = [[u[k].copy()] for k in range(K)]
    n_eval, n_steps, n_rej = 1, 0, 0
    t = t0
    span = t1 - t0
    if h0 is None:  # a first guess from the speed scale, corrected by the controller
        vmax = float(np.max(np.linalg.norm(u[active], axis=1))) if np.any(active) else 1.0
        periods = carpet.periods[np.isfinite(carpet.periods)]
        h = min(span, 0.01 * float(periods.min()) if periods.size else span,
                (atol + rtol) ** 0.2 / max(vmax, 1e-300))
    else:
        h = float(h0)
    status, message = 0, ""
    progress.start(span, "path lines")
    k_stage = np.empty((7,) + x.shape)
    try:
        while t < t1 and np.any(active):
            if n_steps + n_rej >= max_steps:
                raise RuntimeError(f"path lines: max_steps = {max_steps} reached at t = {t:.6g} of {t1:.6g}; "
                                   "raise max_steps or loosen rtol/atol")
            h = min(h, t1 - t)
            if h <= 1e-12 * max(abs(t), span):
                reason[active] = UNDERFLOW
                active[:] = False
                status = 1
                message = (f"step size underflow at t = {t:.6g}: the flow is not resolved (a tracer too close "
                           "to a cilium?); raise margin or loosen rtol/atol")
                logger.warning(message)
                break
            idx = np.nonzero(active)[0]
            xa = x[idx]
            k_stage[0, idx] = u[idx]
            for i in range(1, 7):
                xi = xa + h * np.tensordot(_A[i], k_stage[:i, idx], axes=1)
                k_stage[i, idx] = carpet.velocity(xi, t + _C[i] * h, tol)
            n_eval += 6
            x_new = xa + h * np.tensordot(_B[:6], k_stage[:6, idx], axes=1)
            err = h * np.tensordot(_E, k_stage[:, idx], axes=1)
            scale = atol + rtol * np.maximum(np.linalg.norm(xa, axis=1), np.linalg.norm(x_new, axis=1))
            en = float(np.max(np.linalg.norm(err, axis=1) / scale))
            if not math.isfinite(en):
                raise FloatingPointError(f"path lines: non-finite velocity at t = {t:.6g}")
            if en <= 1.0:
                t += h
                n_steps += 1
                x[idx] = x_new
                u[idx] = k_stage[6, idx]  # FSAL
                for m, k in enumerate(idx):
                    rec_x[k].append(x_new[m].copy())
                    rec_t[k].append(t)
                    rec_u[k].append(u[k].copy())
                hit = swept.inside(x_new)
                out = np.any((x_new < dom[0::2]) | (x_new > dom[1::2]), axis=1)
                reason[idx[hit]] = SWEPT
                reason[idx[out & ~hit]] = DOMAIN
                active[idx[hit | out]] = False
                progress.update(t - t0)
                h *= min(5.0, max(0.2, 0.9 * en ** -0.2)) if en > 0 else 5.0
            else:
                n_rej += 1
                h *= max(0.2, 0.9 * en ** -0.2)
    finally:
        progress.close()
    seconds = _time.perf_counter() - clock
    if not message:
        counts = ", ".join(f"{int(np.sum(reason == k))} {r}" for k, r in enumerate(REASONS) if np.any(reason == k))
        message = f"integrated {K} tracers to t = {t:.6g}: {counts}"
    stats = {"steps": n_steps, "rejected": n_rej, "evaluations": n_eval, "seconds": seconds}
    logger.info("path lines: %s (%d steps, %d rejected, %.2f s)", message, n_steps, n_rej, seconds)
    return PathLines(points=[np.array(p) for p in rec_x], times=[np.array(v) for v in rec_t],
                     velocities=[np.array(v) for v in rec_u], seed_ids=np.arange(K), reason=reason,
                     rtol=float(rtol), atol=float(atol), tol=float(tol), stats=stats, status=status, message=message)
