"""Path lines of massless tracers in a carpet's flow: dx/dt = u(x(t), t) (MODEL.md section 6).

:func:`pathlines` integrates tracers in any flow model (:class:`~ciliary_carpet.transport.flow.Flow`:
the time-resolved beat, the long-time mean flow, or a new one), asking the flow for its name,
the domain where it is valid, the largest step it allows and its velocity; the carpet it
belongs to (``flow.carpet``) gives the seeds' check, the dense output's time scale (its
shortest beat period) and the default domain.

Integration: one embedded Runge-Kutta pair (Dormand-Prince 5(4)) for all tracers together, with
a common step ``H`` chosen so that most tracers (90 %) meet their local error test
``|err| <= atol + rtol |x|``; the tracers that fail it (those close to a filament, where the
flow changes within a blob size) re-integrate the same interval with smaller steps of their own
(recursively, at most :data:`MAX_DEPTH` levels), so that one tracer near a filament does not slow
down all others. Those smaller steps split what is left of the interval into equal parts no
longer than the step the error test asks for (:func:`_next_step`), never a short remainder: each
step of a few tracers costs a whole instant of the carpet's state (:meth:`Flow.prepare
<ciliary_carpet.transport.flow.Flow.prepare>`), so a remainder cost as much as a full step, and
the equal parts, each within the error test's step, fail less often. The step is also capped by
the flow (``flow.step_cap``; for the time-resolved flow a sixteenth of the beat period, see
:mod:`~ciliary_carpet.transport.flow` for what that buys) or by ``max_step``. Every stage evaluates the flow
once for all the tracers it advances (one vectorised sum). A tracer that leaves the domain ends
on its boundary, at the crossing time found by bisection on the continuous extension. Output is
dense: positions at the common times ``t0 + k dt`` with at least
``samples_per_period`` samples per (shortest) beat period, by the pair's continuous extension of
order 4 (Shampine 1986) within the accepted steps, plus the final point.

Termination (:data:`REASONS`): the end time, leaving the domain, or a step size underflow (the
flow is not resolved). With the regularised kernel the velocity is bounded everywhere, so
tracers pass between and through the filaments' swept regions; nothing stops them there.
Seeds closer than one blob size to a filament at the start time are refused (:class:`SeedError`).

Chunks: ``pathlines(..., chunk_size=n, pool=...)`` integrates the tracers in independent chunks of
about ``n`` (:func:`chunks`: consecutive seeds, the membership fixed by the number of seeds and
``n`` alone), each its own integration with its own steps (:func:`pathline_tasks`), joined in seed
order (:func:`join_pathlines`); ``pool`` (:mod:`~cilia_runtime.pool`) says where
they run, in this process or in worker processes, with the same numbers. Each chunk pays the
per-time overhead of its own flow evaluations (:data:`CHUNK_SIZE` for what that costs).

One concept over 500 lines: the path-line integrator, its chunks and its result.
"""
from __future__ import annotations

import logging
import math
import time as _time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from cilia_runtime.progress import Progress

from ciliary_carpet.transport.flow import Flow
from cilia_runtime.pool import adjust_threads

if TYPE_CHECKING:
    from ciliary_carpet.carpet.carpet import Carpet

logger = logging.getLogger(__name__)

__all__ = ["PathLines", "pathlines", "check_seeds", "check_output_size", "REASONS", "SeedError", "PathLineError",
           "MAX_DEPTH", "MAX_OUTPUT_BYTES", "chunks", "pathline_tasks", "join_pathlines", "task_cost", "CHUNK_SIZE"]

REASONS = ("reached end time", "left the domain", "step size underflow")
END, DOMAIN, UNDERFLOW = range(3)
MAX_DEPTH = 12
"""Most levels of step halving a tracer may take below the common step (H / 4096)."""
MAX_OUTPUT_BYTES = 2 * 1024 ** 3
"""Largest dense output (positions and velocities, float64) a run may allocate."""

# Dormand-Prince 5(4) tableau
_C = np.array([0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1, 1])
_A = [[], [1 / 5], [3 / 40, 9 / 40], [44 / 45, -56 / 15, 32 / 9],
      [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729],
      [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656],
      [35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84]]
_A_ROWS = [np.array(r, dtype=float) for r in _A]
_B = np.array([35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0])
_E = _B - np.array([5179 / 57600, 0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40])
# its continuous extension of order 4 (Shampine 1986; the coefficients of scipy's RK45 and
# Hairer-Norsett-Wanner's DOPRI5): x(t + s h) = x + h sum_i k_i sum_q _P[i, q] s^(q+1)
_P = np.array([
    [1, -8048581381 / 2820520608, 8663915743 / 2820520608, -12715105075 / 11282082432],
    [0, 0, 0, 0],
    [0, 131558114200 / 32700410799, -68118460800 / 10900136933, 87487479700 / 32700410799],
    [0, -1754552775 / 470086768, 14199869525 / 1410260304, -10690763975 / 1880347072],
    [0, 127303824393 / 49829197408, -318862633887 / 49829197408, 701980252875 / 199316789632],
    [0, -282668133 / 205662961, 2019193451 / 616988883, -1453857185 / 822651844],
    [0, 40617522 / 29380423, -110615467 / 29380423, 69997945 / 29380423]])


class SeedError(ValueError):
    """Seeds that cannot be integrated (inside a filament, outside the domain, malformed)."""


class PathLineError(ValueError):
    """A path-line request that cannot run as asked (e.g. its output would not fit in memory)."""


@dataclass(frozen=True)
class PathLines:
    """Tracer trajectories: one polyline per seed.

    points[k] (n_k, 3), times[k] (n_k,), velocities[k] (n_k, 3): tracer k at the dense output
    times (every ``dt``) up to where it stopped, and its last point; seed_ids (K,); reason (K,)
    codes into :data:`REASONS`; model: the flow's name (``"resolved"``, ``"mean"``, ...:
    :data:`~ciliary_carpet.transport.flow.FLOWS`); stats: work counters (steps,
    rejected, evaluations, substeps, seconds); status ``"success"`` when every tracer reached its
    end time or left the domain, ``"inaccurate"`` when some tracers' step size underflowed (the
    words of the other results of the toolkit); message says what happened and what to change."""

    points: list
    times: list
    velocities: list
    seed_ids: np.ndarray
    reason: np.ndarray
    rtol: float
    atol: float
    dt: float = 0.0
    model: str = "resolved"
    stats: dict = field(default_factory=dict)
    status: str = "success"
    message: str = ""

    @property
    def end_points(self) -> np.ndarray:
        """(K, 3) last position of every tracer."""
        return np.array([p[-1] for p in self.points])

    def counts(self) -> dict:
        """Number of tracers per termination reason."""
        return {REASONS[k]: int(np.sum(self.reason == k)) for k in range(len(REASONS))}

    def thinned(self, max_points: int | None) -> list:
        """Per tracer, the indices of its samples a file of at most ``max_points`` points per line
        keeps: every k-th, the last one always (all of them when ``max_points`` is None or 0, or
        the line is short enough)."""
        out = []
        for t in self.times:
            n = t.size
            if not max_points or n <= max_points:
                out.append(np.arange(n))
            else:
                step = int(math.ceil((n - 1) / (max_points - 1))) if max_points > 1 else n
                out.append(np.unique(np.append(np.arange(0, n, step), n - 1)))
        return out


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


def check_seeds(carpet: "Carpet", seeds, t0: float = 0.0) -> np.ndarray:
    """``seeds`` as a (K, 3) array, or :class:`SeedError` naming the seeds that are malformed or
    closer than one blob size (the filament radius) to a filament at time ``t0``."""
    x0 = np.asarray(seeds, dtype=float)
    if x0.ndim != 2 or x0.shape[1] not in (2, 3) or x0.shape[0] < 1:
        raise SeedError(f"seeds must have shape (K, 2) or (K, 3) with K >= 1, got {x0.shape}")
    if not np.all(np.isfinite(x0)):
        raise SeedError("seeds contain NaN or inf")
    if x0.shape[1] == 2:
        x0 = np.concatenate([x0, np.zeros((x0.shape[0], 1))], axis=1)
    radius = carpet.blob if carpet.blob is not None else 0.0
    if radius > 0:
        d = carpet.filament_distance(x0, t0)
        bad = np.nonzero((d < radius) & (np.abs(x0[:, 2]) < radius))[0]
        if bad.size:
            k = int(bad[0])
            raise SeedError(f"{bad.size} seed(s) lie inside a filament at t = {t0:g} (closer than the blob size "
                            f"{radius:g} L to its centre line), e.g. seed {k} at ({x0[k, 0]:.4g}, {x0[k, 1]:.4g}) "
                            f"at distance {d[k]:.3g} L; move them")
    return x0


def check_output_size(carpet: "Carpet", n_tracers: int, duration: float, samples_per_period: int
                      ) -> tuple[int, float]:
    """The number of dense output times and the shortest beat period of a run, or
    :class:`PathLineError` if its output would exceed :data:`MAX_OUTPUT_BYTES`."""
    periods = carpet.periods[np.isfinite(carpet.periods)]
    t_beat = float(periods.min()) if periods.size else float(duration)
    n_out = int(math.ceil(duration / t_beat * int(samples_per_period))) + 1
    need = 2 * n_out * int(n_tracers) * 3 * 8
    if need > MAX_OUTPUT_BYTES:
        raise PathLineError(f"path lines: {n_tracers} tracers over {duration:.4g} time units with "
                            f"{samples_per_period} samples per period need {need / 2 ** 30:.1f} GiB of output "
                            f"(limit {MAX_OUTPUT_BYTES / 2 ** 30:.0f} GiB): shorten the duration, use fewer "
                            "seeds or fewer samples per period")
    return n_out, t_beat


def _sq(x: np.ndarray) -> np.ndarray:
    """(M,) the squared norms of the rows of ``x`` (M, 3)."""
    return np.einsum("ij,ij->i", x, x)


def _dense(x0, k, h, s):
    """Positions and velocities at fractions ``s`` (J,) of a step from ``x0`` (M, 3) with stages
    ``k`` (7, M, 3), by the order-4 continuous extension: (J, M, 3) each."""
    Q = np.tensordot(_P.T, k, axes=1)  # (4, M, 3)
    pw = np.stack([s, s ** 2, s ** 3, s ** 4], axis=1)  # (J, 4)
    dpw = np.stack([np.ones_like(s), 2 * s, 3 * s ** 2, 4 * s ** 3], axis=1)
    p = x0[None] + h * np.tensordot(pw, Q, axes=1)
    v = np.tensordot(dpw, Q, axes=1)
    return p, v


class _Run:
    """State of one integration: positions, velocities, dense output, counters."""

    def __init__(self, flow: Flow, x0: np.ndarray, t0: float, t1: float, t_out: np.ndarray, dom: np.ndarray,
                 rtol: float, atol: float, max_steps: int, progress: Progress):
        self.flow, self.rtol, self.atol, self.dom = flow, rtol, atol, dom
        self.t0, self.t1, self.t_out = t0, t1, t_out
        K = x0.shape[0]
        self.x = x0.copy()
        self.reason = np.full(K, END, dtype=np.int64)
        self.active = np.ones(K, bool)
        self.t_end = np.full(K, t1)
        self.x_end = x0.copy()
        self.u_end = np.zeros_like(x0)
        # dense output, tracer-major so that each tracer's samples are contiguous; sample j of
        # tracer k is valid while t_out[j] <= t_end[k] (steps fill it in time order)
        self.out_x = np.empty((K, t_out.size, 3))
        self.out_u = np.empty((K, t_out.size, 3))
        self.n_eval = self.n_steps = self.n_rej = self.n_sub = 0
        self.max_steps = max_steps
        self.max_h = np.inf
        self.progress = progress
        outside = self._outside(self.x)
        self.reason[outside] = DOMAIN
        self.t_end[outside] = t0
        self.active &= ~outside
        self.u = self.velocity(self.x, t0)
        self.u_end[:] = self.u
        self.out_x[:, 0] = self.x
        self.out_u[:, 0] = self.u

    def velocity(self, x: np.ndarray, t: float) -> np.ndarray:
        self.n_eval += 1
        adjust_threads(x.shape[0])  # in a process pool: idle places' cores while they pay (cilia_runtime.pool)
        u = self.flow.velocity(x, t)
        if not np.all(np.isfinite(u)):
            raise FloatingPointError(f"path lines: non-finite velocity at t = {t:.6g}")
        return u

    def _outside(self, x: np.ndarray) -> np.ndarray:
        return np.any((x < self.dom[0::2]) | (x > self.dom[1::2]), axis=1)

    def step(self, idx: np.ndarray, t: float, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One Dormand-Prince step of tracers ``idx`` from ``t``: new positions, stages (7, M, 3)
        (the last is the end velocity, FSAL) and error norms."""
        if self.n_steps + self.n_rej >= self.max_steps:
            raise RuntimeError(f"path lines: max_steps = {self.max_steps} reached at t = {t:.6g} of {self.t1:.6g}; "
                               "raise max_steps or loosen rtol/atol")
        xa = self.x[idx]
        k = np.empty((7,) + xa.shape)
        k[0] = self.u[idx]
        self.flow.prepare(t + _C[1:] * h)  # the stages' times, for a flow whose cost per time is shared
        kf = k.reshape(7, -1)  # a view: stage combinations as one small matrix product each
        for i in range(1, 7):
            k[i] = self.velocity(xa + h * (_A_ROWS[i] @ kf[:i]).reshape(xa.shape), t + _C[i] * h)
        x_new = xa + h * (_B[:6] @ kf[:6]).reshape(xa.shape)
        err = h * (_E @ kf).reshape(xa.shape)
        scale = self.atol + self.rtol * np.sqrt(np.maximum(_sq(xa), _sq(x_new)))
        return x_new, k, np.sqrt(_sq(err)) / scale

    def accept(self, idx: np.ndarray, t: float, h: float, x_new: np.ndarray, k: np.ndarray) -> None:
        """Record the accepted step of tracers ``idx`` over (t, t + h]: dense output, domain test."""
        u_new = k[6]
        lo = int(np.searchsorted(self.t_out, t, side="right"))
        hi = int(np.searchsorted(self.t_out, t + h + 1e-12 * max(abs(t), h), side="right"))
        if hi > lo:
            s = np.clip((self.t_out[lo:hi] - t) / h, 0.0, 1.0)
            p, v = _dense(self.x[idx], k, h, s)
            self.out_x[idx, lo:hi] = p.transpose(1, 0, 2)
            self.out_u[idx, lo:hi] = v.transpose(1, 0, 2)
        out = self._outside(x_new)
        x_old = self.x[idx[out]]
        self.x[idx] = x_new
        self.u[idx] = u_new
        if np.any(out):
            gone = idx[out]
            s_exit, p, v = self._exit(x_old, k[:, out], h)
            self.reason[gone] = DOMAIN
            self.active[gone] = False
            self.t_end[gone] = t + s_exit * h
            self.x_end[gone] = p
            self.u_end[gone] = v

    def _exit(self, x0: np.ndarray, k: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fractions s (J,) of a step at which tracers ``x0`` (J, 3) with stages ``k`` (7, J, 3),
        inside the domain at s = 0 and outside at s = 1, leave it, and their positions and
        velocities there (J, 3): by bisection on the continuous extension to 1e-12 of the step
        (the crossing lies on the domain's boundary, not up to a step beyond it)."""
        Q = h * np.tensordot(_P.T, k, axes=1)  # (4, J, 3): p(s) = x0 + sum_n Q[n] s^(n+1)
        lo_b, hi_b = self.dom[0::2], self.dom[1::2]
        lo = np.zeros(x0.shape[0])
        hi = np.ones(x0.shape[0])
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            s = mid[:, None]
            p = x0 + s * (Q[0] + s * (Q[1] + s * (Q[2] + s * Q[3])))
            out = np.any((p < lo_b) | (p > hi_b), axis=1)
            hi = np.where(out, mid, hi)
            lo = np.where(out, lo, mid)
        s = hi[:, None]
        p = x0 + s * (Q[0] + s * (Q[1] + s * (Q[2] + s * Q[3])))
        v = (Q[0] + s * (2 * Q[1] + s * (3 * Q[2] + s * 4 * Q[3]))) / h
        return hi, p, v

    def advance(self, idx: np.ndarray, ta: float, tb: float, h: float, depth: int) -> float:
        """Integrate tracers ``idx`` from ``ta`` to ``tb``; returns the next step size guess."""
        t = ta
        span = tb - ta
        while idx.size and tb - t > 1e-13 * max(abs(tb), span):
            h = _next_step(tb - t, min(h, self.max_h), equal=depth > 0)
            x_new, k, en = self.step(idx, t, h)
            ok = en <= 1.0
            i90 = (9 * (en.size - 1)) // 10  # the 90 % best (numpy's "lower" quantile): one outlier cannot set H
            q = float(np.partition(en, i90)[i90])
            if not math.isfinite(q):
                raise FloatingPointError(f"path lines: non-finite error estimate at t = {t:.6g}")
            if ok.all() or (q <= 1.0 and depth < MAX_DEPTH):
                self.n_steps += 1
                if depth:
                    self.n_sub += 1
                self.accept(idx[ok], t, h, x_new[ok], k[:, ok])
                bad = idx[~ok]
                if bad.size:
                    hb = h * max(0.1, 0.9 * float(en[~ok].max()) ** -0.2)
                    self.advance(bad, t, t + h, hb, depth + 1)
                t += h
                idx = idx[self.active[idx]]
                if depth == 0:
                    self.progress.update(t - self.t0)
                h *= min(5.0, max(0.2, 0.9 * q ** -0.2)) if q > 0 else 5.0
            else:
                self.n_rej += 1
                h *= max(0.1, 0.9 * q ** -0.2)
                if h <= 1e-12 * max(abs(t), self.t1 - self.t0):
                    self.reason[idx] = UNDERFLOW
                    self.active[idx] = False
                    self.t_end[idx] = t
                    self.x_end[idx] = self.x[idx]
                    self.u_end[idx] = self.u[idx]
                    return h
        return h


def _next_step(left: float, h: float, equal: bool) -> float:
    """The next step toward an end ``left`` ahead, given the step ``h`` the error test allows:
    all that is left when it is within ``h`` (up to 1e-9 h), else ``h``, or, with ``equal`` (the
    smaller steps of the tracers that failed a step, :meth:`_Run.advance`), what is left split
    into the fewest equal parts no longer than ``h`` (at least h / 2: no short remainder), which
    saves rejected steps (``benchmarks/bench_evaluation.py --pathlines 0.1``,
    benchmarks/results/bench_evaluation.md)."""
    if left - h < 1e-9 * h:
        return left
    if equal:
        return left / math.ceil(left / h - 1e-9)
    return h


def _prepare(flow: Flow, seeds, t_span, rtol, atol, samples_per_period, domain, max_step=None):
    """Check a run's input before any work: the seeds (K, 3), (t0, t1), the dense output's
    size and time scale, and the domain (6,) within the flow's."""
    if not isinstance(flow, Flow):
        raise TypeError(f"flow must be a Flow (ciliary_carpet.transport.flow), got {type(flow).__name__}")
    carpet = flow.carpet
    t0, t1 = (float(v) for v in t_span)
    if not (math.isfinite(t0) and math.isfinite(t1) and t1 > t0):
        raise ValueError(f"t_span must be finite with t1 > t0, got {t_span!r}")
    x0 = check_seeds(carpet, seeds, t0)
    for k, v in (("rtol", rtol), ("atol", atol)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{k} must be a non-negative number, got {v!r}")
    if rtol == 0 and atol == 0:
        raise ValueError("rtol and atol cannot both be 0")
    if int(samples_per_period) < 1:
        raise ValueError(f"samples_per_period must be >= 1, got {samples_per_period!r}")
    if max_step is not None and not (math.isfinite(max_step) and max_step > 0):
        raise ValueError(f"max_step must be > 0, got {max_step!r}")
    n_out, t_beat = check_output_size(carpet, x0.shape[0], t1 - t0, samples_per_period)
    dom = _domain(domain, carpet, x0)
    valid = np.asarray(flow.domain, dtype=float)  # within the flow's own domain
    dom = np.concatenate([np.maximum(dom[0::2], valid[0::2])[:, None], np.minimum(dom[1::2], valid[1::2])[:, None]],
                         axis=1).ravel()
    return x0, (t0, t1), n_out, t_beat, dom


def pathlines(flow: Flow, seeds, t_span, *, rtol: float = 1e-6, atol: float = 1e-6, samples_per_period: int = 16,
              domain=None, h0: float | None = None, max_step: float | None = None, max_steps: int = 1_000_000,
              progress: Progress | None = None, chunk_size: int | None = None, pool=None) -> PathLines:
    """Integrate tracers from ``seeds`` (K, 2) or (K, 3) over ``t_span = (t0, t1)`` in ``flow``.

    Parameters
    ----------
    flow : Flow
        The flow model (:mod:`ciliary_carpet.transport.flow`: e.g. ``ResolvedFlow(carpet, tol)``,
        ``MeanFlow.from_carpet(carpet, box)``); its carpet checks the seeds and sets the output's
        time scale.
    seeds : (K, 2) or (K, 3) array_like
        Start points, none inside a filament at ``t0`` (:class:`SeedError`).
    t_span : (t0, t1), t1 > t0
    rtol, atol : float
        Local error tolerances of the positions (units of L).
    samples_per_period : int >= 1
        Dense output: samples per shortest beat period (``dt = T_min / samples_per_period``).
    domain : (xmin, xmax, ymin, ymax[, zmin, zmax]), optional
        Tracers leaving it stop; default the bounding box of bases and seeds grown by 10 L. Always
        within ``flow.domain``.
    h0 : float, optional
        First step (default from the speed scale).
    max_step : float, optional
        Largest step; default ``flow.step_cap`` (for the time-resolved flow a sixteenth of the
        shortest beat period: :mod:`~ciliary_carpet.transport.flow`).
    chunk_size : int, optional
        Integrate the tracers in independent chunks of about this many (:func:`chunks`: the
        membership depends on the number of seeds and ``chunk_size`` only), each its own
        integration with its own steps, joined into one result (:func:`join_pathlines`); default
        all together (one chunk). ``max_steps`` then holds per chunk.
    pool : InProcess or ProcessPool, optional
        Where the chunks run (:mod:`~cilia_runtime.pool`); default in this
        process, one after another. The numbers are the same wherever they run.

    Returns
    -------
    PathLines

    Raises
    ------
    SeedError, PathLineError, ValueError, TypeError
        Before any work: malformed or in-filament seeds; an output that would exceed
        :data:`MAX_OUTPUT_BYTES`; bad tolerances, span or domain; a ``flow`` that is not a Flow.
    """
    if chunk_size is not None or pool is not None:
        tasks = pathline_tasks(flow, seeds, t_span, chunk_size=chunk_size, rtol=rtol, atol=atol,
                               samples_per_period=samples_per_period, domain=domain, h0=h0, max_step=max_step,
                               max_steps=max_steps)
        if pool is None:
            from cilia_runtime.pool import InProcess

            pool = InProcess()
        clock = _time.perf_counter()
        results = pool.run(tasks, shared=[flow.carpet], progress=progress)
        return join_pathlines([r.value for r in results], t_end=float(t_span[1]), wall=_time.perf_counter() - clock,
                              where=[r.where for r in results], workers=pool.workers)
    x0, (t0, t1), n_out, t_beat, dom = _prepare(flow, seeds, t_span, rtol, atol, samples_per_period, domain,
                                                max_step)
    t_out = np.linspace(t0, t1, n_out)
    name = flow.name
    progress = progress if progress is not None else Progress()
    clock = _time.perf_counter()
    progress.start(t1 - t0, "path lines")
    try:
        run = _Run(flow, x0, t0, t1, t_out, dom, float(rtol), float(atol), int(max_steps), progress)
        if max_step is not None:
            run.max_h = float(max_step)
        else:
            run.max_h = float(flow.step_cap)
        if h0 is None:  # a first guess from the speed scale, corrected by the controller
            vmax = float(np.max(np.linalg.norm(run.u[run.active], axis=1))) if np.any(run.active) else 1.0
            h = min(t1 - t0, 0.05 * t_beat, (atol + rtol) ** 0.2 / max(vmax, 1e-300))
        else:
            h = float(h0)
        run.advance(np.nonzero(run.active)[0], t0, t1, h, 0)
    finally:
        progress.close()
    seconds = _time.perf_counter() - clock
    K = x0.shape[0]
    done = run.reason == END
    run.x_end[done] = run.x[done]
    run.u_end[done] = run.u[done]
    pts, tms, vel = [], [], []
    n_valid = np.searchsorted(t_out, run.t_end, side="right")
    n_valid[run.t_end <= t0] = 0
    for k in range(K):
        n = int(n_valid[k])
        p, v, tt = run.out_x[k, :n], run.out_u[k, :n], t_out[:n]
        if tt.size == 0 or run.t_end[k] > tt[-1]:
            p = np.concatenate([p, run.x_end[k][None]])
            v = np.concatenate([v, run.u_end[k][None]])
            tt = np.concatenate([tt, [run.t_end[k]]])
        pts.append(p)
        tms.append(tt)
        vel.append(v)
    reason = run.reason
    status, message = _outcome(reason, name, t1)
    if status != "success":
        logger.warning(message)
    stats = {"steps": run.n_steps, "rejected": run.n_rej, "substeps": run.n_sub, "evaluations": run.n_eval,
             "seconds": seconds}
    logger.info("path lines: %s (%d steps, %d substeps, %d rejected, %.2f s)", message, run.n_steps, run.n_sub,
                run.n_rej, seconds)
    return PathLines(points=pts, times=tms, velocities=vel, seed_ids=np.arange(K), reason=reason,
                     rtol=float(rtol), atol=float(atol), dt=float(t_out[1] - t_out[0]),
                     model=name, stats=stats, status=status, message=message)


def _outcome(reason: np.ndarray, name: str, t1: float) -> tuple[str, str]:
    """The status and message of a run whose tracers ended for ``reason``."""
    status = "inaccurate" if np.any(reason == UNDERFLOW) else "success"
    counts = ", ".join(f"{int(np.sum(reason == k))} {r}" for k, r in enumerate(REASONS) if np.any(reason == k))
    message = f"integrated {reason.size} tracers ({name} flow) to t = {t1:.6g}: {counts}"
    if status != "success":
        message += ("; the step size underflowed for some tracers: the flow is not resolved there (raise the "
                    "blob size or loosen rtol/atol)")
    return status, message


def chunks(n_tracers: int, chunk_size: int | None) -> list[np.ndarray]:
    """The tracer indices of each chunk: ``ceil(n / chunk_size)`` chunks of consecutive tracers,
    as equal in size as they can be (sizes differ by at most one). The membership depends on
    ``n_tracers`` and ``chunk_size`` only (not on where the chunks run), so the numbers do not
    change with the number of workers. None: one chunk."""
    n = int(n_tracers)
    if chunk_size is None:
        return [np.arange(n)]
    if not (int(chunk_size) == chunk_size and chunk_size >= 1):
        raise ValueError(f"chunk_size must be an integer >= 1, got {chunk_size!r}")
    return np.array_split(np.arange(n), max(1, -(-n // int(chunk_size))))


CHUNK_SIZE = 200
"""Tracers per chunk of a render's path lines (:func:`chunks`; ``ciliary_carpet.output.tracers``).
Each chunk pays the per-time overhead of its own steps (and its tracers lose the substeps they
shared): measured on the 30 x 30 uniform_deflection carpet (the render's 100 tracers over 23.5 time
units, flow tol 1e-4, one thread, benchmarks/results/bench_pathlines_parallel.md) the work is
39.5 s in one chunk, 49.4 s (x 1.25) in chunks of 50 and 65.0 s (x 1.65) in chunks of 25: about
10 s per chunk plus 0.3 s per tracer there. A render's 100 tracers therefore run as one chunk,
beside the error estimate's reference run on another core
(:func:`~ciliary_carpet.transport.accuracy.pathline_error`); more than 200 are split into chunks of
100 to 200, which cost about 10-15 % more work than one run of all (by that estimate) and run on
as many cores as the render has."""
PER_POINT_COST = 1 / 50
"""A flow evaluation's cost per point relative to its per-time overhead (measured on the 30 x 30
uniform_deflection carpet at flow tol 1e-4, one thread: about 0.85 ms per time plus 15-20 us per
point): sets :attr:`Task.cost <cilia_runtime.pool.Task.cost>`, which orders tasks."""


def task_cost(n_tracers: int, rtol: float, atol: float, duration: float) -> float:
    """An estimate (arbitrary unit) of the work of integrating ``n_tracers`` together for
    ``duration``: steps grow as ``tol^(-1/5)`` and with the duration, each evaluation costs its
    per-time overhead plus :data:`PER_POINT_COST` per tracer."""
    return float(duration) * max(float(rtol) + float(atol), 1e-300) ** -0.2 * (1.0 + PER_POINT_COST * int(n_tracers))


def pathline_tasks(flow: Flow, seeds, t_span, *, chunk_size: int | None = CHUNK_SIZE, label: str = "path lines",
                   rtol: float = 1e-6, atol: float = 1e-6, samples_per_period: int = 16, domain=None,
                   h0: float | None = None, max_step: float | None = None, max_steps: int = 1_000_000) -> list:
    """The chunks of a path-line run (the arguments of :func:`pathlines`) as
    :class:`~cilia_runtime.pool.Task` s, checked as :func:`pathlines` checks them
    before any work: each ``pathlines(flow, seeds[chunk], t_span, ...)`` over the tracers of
    one of :func:`chunks`, all in the domain of the whole run (the default: from all seeds);
    join their results with :func:`join_pathlines`. ``label`` names them in errors."""
    from cilia_runtime.pool import Task

    x0, (t0, t1), _, _, dom = _prepare(flow, seeds, t_span, rtol, atol, samples_per_period, domain, max_step)
    parts = chunks(x0.shape[0], chunk_size)
    kwargs = dict(rtol=rtol, atol=atol, samples_per_period=samples_per_period, domain=tuple(float(v) for v in dom),
                  h0=h0, max_step=max_step, max_steps=max_steps)
    scale = 1.0 if flow.name == "resolved" else 0.01  # the other models are far cheaper per evaluation
    def name(k, p):
        what = f"tracers {int(p[0])}-{int(p[-1])}" if p.size > 1 else f"tracer {int(p[0])}"
        return f"{label}: chunk {k + 1} of {len(parts)} ({what})" if len(parts) > 1 else f"{label} ({what})"

    return [Task(name(k, p), pathlines,
                 (flow, x0[p], (t0, t1)), kwargs, cost=scale * task_cost(p.size, rtol, atol, t1 - t0))
            for k, p in enumerate(parts)]


def join_pathlines(parts: list, *, t_end: float | None = None, wall: float | None = None, where: list | None = None,
                   workers: int = 1) -> PathLines:
    """One :class:`PathLines` from the runs of consecutive chunks of seeds (:func:`pathline_tasks`),
    in their order (``t_end``: the runs' end time, for the message): tracers in seed order
    (``seed_ids`` 0..K-1), work counters summed
    (``seconds`` is the work of all chunks; ``wall`` the elapsed time, if given), ``chunks`` and
    ``workers`` counted and, given ``where`` (each chunk's place: "parent", "worker N"), the
    chunks by place; status ``"inaccurate"`` if any chunk's is, the message for all tracers."""
    if not parts:
        raise ValueError("join_pathlines: no parts")
    first = parts[0]
    reason = np.concatenate([p.reason for p in parts])
    t1 = float(t_end) if t_end is not None else max(float(t[-1]) for p in parts for t in p.times if t.size)
    status, message = _outcome(reason, first.model, t1)
    if any(p.status != "success" for p in parts):
        status = "inaccurate"
    stats: dict = {}
    for p in parts:
        for k, v in p.stats.items():
            stats[k] = stats.get(k, 0) + v
    stats["chunks"] = len(parts)
    stats["workers"] = int(workers)
    if wall is not None:
        stats["wall_seconds"] = float(wall)
    if where is not None:
        by: dict = {}
        for w in where:
            by[w] = by.get(w, 0) + 1
        stats["chunks_by_place"] = by
    return PathLines(points=[x for p in parts for x in p.points], times=[x for p in parts for x in p.times],
                     velocities=[x for p in parts for x in p.velocities], seed_ids=np.arange(reason.size),
                     reason=reason, rtol=first.rtol, atol=first.atol, dt=first.dt, model=first.model, stats=stats,
                     status=status, message=message)
