"""What a carpet can make under its field, up front: :class:`Reachability` and :func:`reachability`
(the largest deflection of one cilium, the amplitude a two-sided pattern holds, and for a pattern
with a transition width the narrowest width it meets its threshold at)."""
from __future__ import annotations

import logging
import math
import time as _time
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import minimize

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.design.moments import CycleMoments, cycle_moments
from ciliary_carpet.stokes import stokeslet_velocity
from ciliary_carpet.design.model import DesignModel, angle_objective, carrier_forces, floor_reference, solver_threads
from ciliary_carpet.design.target import Frame, Target

logger = logging.getLogger(__name__)

__all__ = ["Reachability", "reachability", "WIDTH_GRID"]

WIDTH_GRID = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
"""The transition widths, in lattice spacings, at which :func:`reachability` estimates a
pattern's residual (the narrowest is a step on the lattice: tanh(4) = 0.9993 one spacing from
the line)."""

@dataclass(frozen=True)
class Reachability:
    """What a carpet can make under its field, up front (angles in radians, lengths in L).

    angle_max: the largest deflection of one cilium's thrust (the table's
    ``thrust_angle_range()``): a uniform target is reachable up to it. angle_floor: the
    deflection of a cilium that keeps ``speed_floor`` of the straight filament's thrust (how far
    the design's floor lets a cilium turn at full weight). pattern_max: the deflection a
    two-sided pattern (focus, spread) holds away from its line: the flow angle of the *split
    layout* -- every cilium on one side of the line turned by angle_floor toward it, on the
    other side away from it -- at the control points 3 spacings or more from the line (median;
    design model, every cilium). Less than angle_floor because each side's cross-stream flow is
    partly cancelled by the other's (Stokeslets decay as 1/r). An estimate, not a bound, and on
    the safe side by up to about 5 degrees; validated against full designs (tests; table 4 of
    benchmarks/results/bench_design.md), focusing of width 4 L, spacing 2: on 10 x 10 cilia
    pattern_max 22.6 deg, 20 and 25 deg meet 0.05 rad (0.006, 0.033), 30 and 40 miss (0.083,
    0.21); on 20 x 12 cilia 26.6 deg, 20 and 25 meet (0.009, 0.023), 30 and 40 miss (0.060,
    0.19).

    Width (patterns with a transition width, :attr:`~ciliary_carpet.design.patterns.Pattern.has_width`:
    focus, spread, shear; on a carpet without a wall; ``None`` otherwise).
    width_min: the narrowest transition width at which the target's pattern (its kind and
    amplitude) meets its residual threshold on this carpet, estimated; 0 when even a step does
    (width h/4, h the spacing), ``inf`` when no width up to 8 h does (the amplitude is beyond
    the carpet: see pattern_max). width: the target's own width; width_rms: the estimated rms
    residual at it; widths: the scan, ((w, estimated rms), ...) at :data:`WIDTH_GRID` x h;
    residual: the threshold; seconds: the cost of the width estimate.

    How: what limits a transition is the kernel's smoothing across the line. A cilium's mean
    flow decays like 1/r, so the flow at a control point one spacing from the line is pushed by
    the column of cilia next to it *and*, the other way, by the columns across the line only two
    or three times as far; the sharper the requested change of angle across the line, the more
    cross-stream force the columns nearest the line need, until they run out of turn (and, near
    the flutter cutoff, of thrust): the smoothing a lattice of spacing h cannot undo is what is
    left. The estimate solves the design problem across the line on a strip: the design model
    of every cilium (:mod:`ciliary_carpet.design.model`), with the curvature constant along each column (cilia
    binned by their cross-stream coordinate in bins of h/4), at the control points of the row
    nearest the carpet's centre (within h/2 of it along the stream), with the design's own
    objective (:func:`~ciliary_carpet.design.model.angle_objective`: angle term and speed floor); L-BFGS-B on one variable per
    column. The Stokeslet sums are done once (a matrix of P_row x n_columns x 3 carriers: 6
    kernel sums per column), so an iteration is two small matrix products (60-120 iterations a
    solve). The row's
    rms residual estimates the design's rms; width_min is where it crosses the threshold, found
    by bisection on :data:`WIDTH_GRID` (the widest and narrowest widths, then halving: about 6
    solves with the target's own width) and linear interpolation between the two widths around
    the crossing. Its cost against a full design's: benchmarks/results/bench_design.md, table 4b.

    Why a strip and not the split layout's profile: the split layout's flow angle reaches 0.76
    of pattern_max only 3.7 L from the line on 100 cilia, 10.6 L on 1000, which would call widths
    the designs meet unreachable: the design concentrates the cross-stream force near the line,
    and so does the strip solve. Why constant along each column: the design's freedom along the
    stream fixes the carpet's upstream and downstream edges, not the transition; on every row of
    the carpet the column solve misses 0.02-0.03 rad more than the design far from the line,
    on the centre row it follows the design. Validated against full designs (table 4b: focusing
    at 10, 20, 40 deg, spreading at 20, shear at 30; spacings 2 and 3; widths 0.5 h to 2 h (6 h
    at 40 deg); 100, 240 and 1024 cilia; 32 designs): the estimate never called a width
    reachable that the design missed, and called 3 unreachable that it met (their estimated rms
    within 0.006 rad of the threshold). Where the rms lies between 0.03 and 0.08 rad the estimate is above the
    design's by 0.004-0.016 rad (so width_min errs on the wide side by up to about a quarter
    spacing); for wide patterns, whose small design residual (below 0.01 rad) sits at the
    carpet's upstream and downstream edges, which the centre row does not see, it can be below
    by up to 0.008 rad: not on the safe side for thresholds under about 0.01 rad. Focusing at
    20 deg, 10 x 10 cilia, spacing 2: estimated 0.076, 0.062, 0.045, 0.014 rad at widths 0.5,
    0.75, 1, 1.5 h, designs 0.066, 0.052, 0.036, 0.014, width_min 1.85 L; spacing 3: 0.082,
    0.068, 0.051, 0.019 against 0.075, 0.061, 0.045, 0.019, width_min 3.02 L; 1024 cilia, spacing
    2: width_min 3.46 L (at 1 and 2 h: 0.070 and 0.040 against 0.063 and 0.035).

    Not above a wall: there the designs miss for another reason (100 cilia, hexagonal, spacing 2,
    wall 0.5 L below the plane: a *uniform* 20 deg deflection 0.17 rad; focusing at 20 deg,
    widths 2 and 8 L, 0.16 and 0.09 rad, where the strip estimated 0.077 and 0.047), so a width
    estimate would be optimistic; width_min is None. Those designs miss with the design model
    within 2 % of the full model's objective (its exact near field): the miss is the target's --
    above a wall each control point's flow is dominated by the few cilia around it, whose near
    field does not point along their thrust -- not the optimiser's (reachable targets above a
    wall are met: bench_design.py section 5)."""

    angle_max: float
    angle_floor: float
    pattern_max: float
    line: float = 0.0
    width_min: float | None = None
    width: float | None = None
    width_rms: float | None = None
    widths: tuple = ()
    residual: float | None = None
    seconds: float = 0.0

    @property
    def width_reachable(self) -> bool | None:
        """Whether the target's width is at least the estimated narrowest (None: not estimated)."""
        if self.width_min is None or self.width is None:
            return None
        return self.width >= self.width_min

    def summary(self) -> dict:
        out = {"angle_max_deg": math.degrees(self.angle_max), "angle_floor_deg": math.degrees(self.angle_floor),
               "pattern_max_deg": math.degrees(self.pattern_max), "line": self.line,
               "method": "pattern_max: design model, split layout at the speed floor (an estimate, not a bound)",
               "text": self.describe()}
        if self.width_min is not None:
            out.update({"width_min": self.width_min if math.isfinite(self.width_min) else None,
                        "width": self.width, "width_rms": self.width_rms, "width_reachable": self.width_reachable,
                        "residual_threshold": self.residual,
                        "width_scan": [[w, r] for w, r in self.widths], "width_seconds": self.seconds,
                        "width_method": "design model across the line: curvature constant along each column, "
                                        "the control points of the centre row (an estimate, on the safe side); "
                                        "width_min null: no width up to 8 spacings meets the threshold"})
        return out

    def describe(self) -> str:
        """One sentence for messages and summaries."""
        s = (f"one cilium turns its thrust up to {math.degrees(self.angle_max):.1f} deg "
             f"({math.degrees(self.angle_floor):.1f} at the speed floor); a two-sided pattern holds about "
             f"{math.degrees(self.pattern_max):.1f} deg")
        if self.width_min is not None:
            wm = ("no width up to 8 spacings" if not math.isfinite(self.width_min) else
                  "any width, a step included" if self.width_min == 0 else f"{self.width_min:.3g} L")
            s += (f"; narrowest transition at this amplitude: {wm} (asked {self.width:.3g} L, estimated rms "
                  f"{self.width_rms:.3g} rad against {self.residual:g})")
        return s


def reachability(carpet: Carpet, control, frame: Frame, speed_floor: float | None = None, line: float | None = None,
                 target: Target | None = None) -> Reachability:
    """The :class:`Reachability` of ``carpet`` at the control points (P, 2) with the pattern's
    line at cross-stream offset ``line`` of ``frame`` (one design-model evaluation), and with a
    ``target`` whose pattern has a transition width the narrowest width at its amplitude and residual
    threshold (:data:`WIDTH_GRID`: ten small solves). ``speed_floor`` and ``line`` default to the
    target's (else 0.3 and 0)."""
    X = np.asarray(control, dtype=float)
    if speed_floor is None:
        speed_floor = target.speed_floor if target is not None else 0.3
    if line is None:
        line = target.line if target is not None else 0.0
    t = carpet.table
    mom = cycle_moments(t)
    grid = np.linspace(0.0, mom.cutoff, 2001)
    keep = np.nonzero(mom.thrust_norm(grid) >= float(speed_floor) * mom.thrust0)[0]
    chi_f = float(grid[keep.max()]) if keep.size else 0.0
    a_f = float(t.scalar("thrust_angle", np.array([chi_f]))[0])
    sgn = 1.0 if a_f >= 0 else -1.0
    chi = -np.sign(frame.cross_coordinate(carpet.centres) - line) * sgn * chi_f  # toward the line on both sides
    u = DesignModel(carpet, X, chi, moments=mom).velocity(chi)
    delta = np.arctan2(u @ frame.cross, u @ frame.flow_direction)
    xi = np.abs(frame.cross_coordinate(X) - line)
    far = xi >= 3.0 * frame.spacing
    if not np.any(far):
        far = xi >= np.median(xi)
    reach = Reachability(angle_max=float(t.thrust_angle_range()[1]), angle_floor=abs(a_f),
                         pattern_max=float(np.median(np.abs(delta[far]))), line=float(line))
    if target is None or not target.pattern.has_width:
        return reach
    if carpet.wall is not None:
        logger.info("reachability: the narrowest width is not estimated above a wall (see Reachability)")
        return reach
    clock = _time.perf_counter()
    h = frame.spacing
    w_t = float(target.width) if target.width is not None else h
    strip = _Strip(carpet, X, frame, float(speed_floor), mom)
    ws = [g * h for g in WIDTH_GRID]
    thr = float(target.residual)
    scan: dict[float, float] = {}

    def rms(w: float) -> float:
        if w not in scan:
            scan[w] = strip.rms(replace(target, width=w))
        return scan[w]

    # bisection on the grid (the estimate falls as the width grows): the widest, the narrowest,
    # then halving the bracket; the crossing interpolated linearly between its two ends
    if rms(ws[-1]) > thr:
        w_min = math.inf
    elif rms(ws[0]) <= thr:
        w_min = 0.0
    else:
        lo, hi = 0, len(ws) - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if rms(ws[mid]) <= thr else (mid, hi)
        r0, r1 = scan[ws[lo]], scan[ws[hi]]
        w_min = ws[lo] + (r0 - thr) / max(r0 - r1, 1e-300) * (ws[hi] - ws[lo])
    r_t = rms(w_t)
    sec = _time.perf_counter() - clock
    logger.info("reachability: narrowest %s width at %.1f deg: %.3g L (asked %.3g L, estimated rms %.3g); "
                "%d L-BFGS-B iterations, %.2f s", target.kind, math.degrees(target.amplitude), w_min, w_t, r_t,
                strip.iterations, sec)
    return replace(reach, width_min=float(w_min), width=w_t, width_rms=r_t,
                   widths=tuple((float(w), float(scan[w])) for w in sorted(scan)), residual=thr,
                   seconds=sec)


class _Strip:
    """The design problem across the line on the carpet's centre row (see :class:`Reachability`):
    the control points within half a spacing (along the stream) of the row nearest the centre,
    the cilia binned into columns by their cross-stream coordinate (bins of a quarter spacing),
    one curvature per column; ``W`` (P_row, n_columns, 3, 2, 2) the flow at each row point of a
    unit force (lab axes) on carrier m of every cilium of a column (geometry of straight cilia),
    ``M`` the same as a (2 P_row, 6 n_columns) matrix acting on the flattened carrier forces."""

    def __init__(self, carpet: Carpet, X: np.ndarray, frame: Frame, speed_floor: float, mom: CycleMoments):
        h = frame.spacing
        s = np.abs((X - frame.centre) @ frame.flow_direction)
        self.X = X[s <= s.min() + 0.5 * h * (1 + 1e-9)]
        self.frame, self.mom, self.table = frame, mom, carpet.table
        dm = DesignModel(carpet, self.X, np.zeros(carpet.n), moments=mom)
        cen = dm.pos3[:, :2].reshape(-1, 3, 2).mean(axis=1)
        _, col = np.unique(np.round(frame.cross_coordinate(cen) / (0.25 * h)), return_inverse=True)
        col = col.ravel()
        nc = int(col.max()) + 1
        self.W = np.zeros((self.X.shape[0], nc, 3, 2, 2))
        rep = np.zeros(nc, np.int64)
        with solver_threads(3 * carpet.n * self.X.shape[0]):
            for b in range(nc):
                j = np.nonzero(col == b)[0]
                rep[b] = j[0]
                for m in range(3):
                    for ax in range(2):
                        f = np.zeros((j.size, 3))
                        f[:, ax] = 1.0
                        self.W[:, b, m, :, ax] = stokeslet_velocity(dm.X3, dm.pos3[3 * j + m], f, carpet.mu,
                                                                    wall=dm.wall, backend=carpet.backend)[:, :2]
        self.M = self.W.transpose(0, 3, 1, 2, 4).reshape(2 * self.X.shape[0], 6 * nc)  # u = M c (flattened)
        self.centres = cen[rep]
        self.delta, self.rot = dm.delta[rep], dm.rot
        self.floor = speed_floor * floor_reference(carpet, self.X, spacing=h, moments=mom)
        self.iterations = 0

    def rms(self, target: Target) -> float:
        """The rms angle residual at the row's points of the best column layout for ``target``:
        the design's objective (:func:`~ciliary_carpet.design.model.angle_objective`, its speed floor) by L-BFGS-B in chi / chi_c
        in [-1, 1] from the columns' local requests, scaled to 1 there so that its tolerance is
        relative."""
        T = self.frame.directions(target.deflection(self.X, self.frame))
        a_max = self.table.thrust_angle_range()[1] * (1.0 - 1e-9)
        want = np.clip(target.deflection(self.centres, self.frame), -a_max, a_max)
        cut = self.mom.cutoff
        z0 = np.asarray(self.table.chi_N_for_angle(np.asarray(want, dtype=float)), dtype=float) / cut

        def flow(z):
            return (self.M @ carrier_forces(self.mom, self.rot, self.delta, z * cut).ravel()).reshape(-1, 2)

        scale = 1.0 / max(angle_objective(flow(z0), T, self.floor)[0], 1e-300)

        def fun(z):
            J, g = angle_objective(flow(z), T, self.floor)
            dc = carrier_forces(self.mom, self.rot, self.delta, z * cut, 1).ravel()
            return scale * J, scale * cut * ((self.M.T @ g.ravel()) * dc).reshape(-1, 6).sum(axis=1)

        with solver_threads(0):
            res = minimize(fun, z0, jac=True, method="L-BFGS-B", bounds=[(-1.0, 1.0)] * z0.size,
                           options={"ftol": 1e-9, "maxiter": 1000})
        self.iterations += int(res.nit)
        u = flow(res.x)
        r = np.angle((u[:, 0] + 1j * u[:, 1]) * np.conj(T[:, 0] + 1j * T[:, 1]))
        return float(np.sqrt(np.mean(r ** 2)))

