"""One layout, several programs: what a chip's cilia do under each of several field strengths,
and how long they take to settle after the field is switched.

A chip's cilia are fabricated once, each with its natural curvature chi_N; the field strength
chi_E that drives them can be switched. chi_E sets each cilium's beat: whether it beats at all
(its flutter range in ``|chi_N|``), its period, the angle of its mean thrust and its size. So one
layout makes a different flow under each field, and the flows are tied together: a cilium's chi_N
fixes its beat under every field at once.

:func:`program_reachability` answers, before a program is asked for, which pairs of flows one
layout can make: per state (a field, given by its thrust table) the thrust angles its cilia reach,
and per pair of states the curve of (angle under a, angle under b) that the cilia beating under
both trace over chi_N, the largest change of angle a switch makes, the thrust ratio, and the
on/off switches (cilia that beat under one field and rest under the other).

:func:`switch_transient` says how many beats a cilium takes to settle onto its new beat after the
field switches to a state: from the largest non-trivial Floquet multiplier modulus ``|mu|`` of its
limit cycle (the table's ``floquet`` column: a deviation from the cycle shrinks by ``|mu|`` per
period), ``ln(0.01) / ln|mu|`` beats to 1 %; for a cilium that rests under the field, from the
leading eigenvalue ``alpha + i beta`` of its steady state, ``ln(100) / |alpha|`` tau.

Units: lengths in L, times in tau (the relaxation time), forces in B / L^2, angles in radians
(thrust angles as the table's ``thrust_angle``: the mean thrust's angle from the straight
filament's, anticlockwise, odd in chi_N).

What the ``floquet`` column is (:mod:`single_cilium.cycle`): ``max(|mu_1|, exp(-T))``, ``|mu_1|``
the largest modulus among the monodromy's eigenvalues other than the trivial one (the flow
direction, 1), ``T`` the period. ``exp(-T)`` is an exact multiplier of the discrete system: the
curvature at the clamp relaxes as ``d_t kappa = -kappa`` whatever the shape, and the curvature's
other short-wave modes relax at about the same rate. Over most of a branch ``floquet = exp(-T)``
exactly (chi_E = 200: ``|chi_N|`` below about 130; chi_E = 150: below about 20): there the
settling is set by the curvature's relaxation, 4.6 tau to 1 % whatever the period; near the
flutter cutoff the amplitude mode takes over, ``1 - |mu| ~ 2 alpha T`` falls linearly to 0 at the
cutoff (a supercritical Hopf bifurcation) and the transient slows as ``1 / (cutoff - |chi_N|)``.
Likewise for a resting cilium the leading eigenvalue is at least -1 (the same curvature mode).

The check against the nonlinear dynamics (``tests/test_program_reach.py``,
``test_floquet_multiplier_matches_a_direct_simulation``): chi_E = 200, eta = 1, chi_N = 146.5,
mesh ``Mesh.for_params(p, 8)`` (41 nodes), 64 steps per period.
:func:`~single_cilium.cycle.limit_cycle` gives T = 0.32670 tau and the multipliers 1, 0.83434,
0.72130 (= exp(-T)), 0.6969 (a complex pair), ...; the shipped table's ``floquet`` there is
0.8345. The state on the cycle at phase 0, its deviation from the equilibrium scaled by 1.02,
integrated by :func:`~single_cilium.dynamics.simulate` (rtol 1e-10, 128 outputs per period) for
25 periods: the per-beat maximum of the tip angle (parabola through the three samples around the
largest) approaches the cycle's, successive changes shrinking by 0.8342, 0.8342, 0.8341 over the
last three beats, and by 0.8338 on a least-squares fit of their logarithm over beats 14 to 23
(0.8336 over beats 10 to 23: the next multiplier, 0.7213, contaminates the early beats as
(0.7213 / 0.8343)^k). The measured rate agrees with the Floquet multiplier to 5e-4 and is far
from the curvature floor exp(-T) = 0.7213. The test asserts agreement within 3e-3 (six times the
measured gap, a fortieth of the distance to the floor).

A switch itself, measured the same way (not a test: 13 s): the cilium of chi_N = 81.26 on its
chi_E = 200 cycle, switched to chi_E = 150 (``floquet`` 0.91417, T = 0.33862 tau) and followed
for 60 beats. The tip angle's per-beat maximum falls from 1.355 (first beat) to 0.8169 (the
cycle's, extrapolated). Successive changes shrink irregularly over the first 20 beats, then by
0.896 to 0.907 (beats 20 to 30), 0.907 to 0.911 (30 to 40) and 0.9115 to 0.9136 (40 to 58),
converging on the Floquet multiplier 0.9142 from below. The large deviation at first collapses
much faster than the linear rate (the weakly stable cycle's amplitude equation is nonlinear):
it fell to e^-1 of its start in 2 beats and to 1 % in 32, where the Floquet count,
``-1 / ln|mu|`` and ``ln(0.01) / ln|mu|``, gives 11 and 51. So the Floquet count is the
asymptotic rate and, for a cilium switched between two beats, an upper estimate. A cilium switched
on from rest (beating only under the new field) first grows from its old steady state, which takes
longer than the Floquet count says; that growth is not estimated here.

One concept: what the programs of one layout can make, and how fast a switch between them settles.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from single_cilium.lookup import ThrustTable
from single_cilium.tablefile import TableError

logger = logging.getLogger(__name__)

__all__ = ["program_reachability", "ProgramReach", "PairReach", "Switch", "switch_transient", "SwitchTransient",
           "REGIMES"]

#: what a cilium does under a field: beats (inside the table's flutter range), rests (its straight
#: steady state is stable), or rests coiled (``|chi_N| > |chi_E|``: the filament curls up; stable,
#: but the table has no row for it)
REGIMES = ("beats", "rests", "coiled")
_BEATS, _RESTS, _COILED = range(3)
#: a thrust below this fraction of its state's reference is "vanishing" (the thrust ratio between
#: states is reported only where both thrusts are above it)
THRUST_FLOOR = 0.01
_LN100 = math.log(100.0)


# ------------------------------------------------------------------------------------------ helpers
def _one_field(table, what: str) -> ThrustTable:
    """The still-fluid, one-field table of ``table`` (a table over the background flow gives its
    U = 0 grid flow); a clear error for anything else."""
    if not isinstance(table, ThrustTable):
        raise TypeError(f"{what} must be a ThrustTable, got {type(table).__name__}")
    if "chi_E" in table.ds.dims:
        raise ValueError(f"{what} is a table over a grid of chi_E: give one table per field (a state is one "
                         "field strength)")
    return table.in_still_fluid()


def _edges(table: ThrustTable) -> tuple[float, float] | None:
    """The |chi_N| interval where the table's cilia beat, or None (no flutter branch)."""
    try:
        return table.flutter_range
    except TableError:
        return None


def _regimes(table: ThrustTable, edges, a: np.ndarray) -> np.ndarray:
    """:data:`REGIMES` codes at ``|chi_N| = a``."""
    out = np.full(a.shape, _RESTS, dtype=np.int8)
    out[a > abs(table.chi_E)] = _COILED
    if edges is not None:
        out[(a >= edges[0]) & (a <= edges[1])] = _BEATS
    return out


def _num(x, digits: int = 4):
    """``x`` rounded to ``digits`` significant digits, as a plain float; None for NaN or inf (strict
    JSON)."""
    x = float(x)
    if not math.isfinite(x):
        return None
    if x == 0.0:
        return 0.0
    return float(f"{x:.{digits}g}")


def _chi(x) -> float | None:
    """A chi_N for a summary: two decimals."""
    x = float(x)
    return round(x, 2) if math.isfinite(x) else None


def _deg(x) -> float | None:
    x = float(x)
    return round(math.degrees(x), 2) if math.isfinite(x) else None


def _frozen(a) -> np.ndarray:
    a = np.array(a)
    a.setflags(write=False)
    return a


def _angle_error(table: ThrustTable, chi_N) -> np.ndarray:
    """An error estimate of ``scalar("thrust_angle", chi_N)`` (rad): the interpolation error
    estimate plus the rows' own discretisation error (``thrust_angle_error``, interpolated; 0
    where the table has none)."""
    c = np.asarray(chi_N, dtype=float)
    interp = table.interpolation_error("thrust_angle", c)
    rows = np.abs(np.nan_to_num(table.scalar("thrust_angle_error", c), nan=0.0))
    return interp + rows


def _thrust_error(table: ThrustTable, chi_N) -> float:
    """A relative error estimate of ``scalar("thrust_norm", chi_N)``: the interpolation error
    estimate over the value plus the row's ``thrust_norm_error`` (relative; 0 where the table has
    none)."""
    v = float(table.scalar("thrust_norm", chi_N))
    interp = float(table.interpolation_error("thrust_norm", chi_N))
    rows = abs(float(np.nan_to_num(table.scalar("thrust_norm_error", chi_N), nan=0.0)))
    return (interp / v if v > 0 else math.inf) + rows


def _refine(f, x: np.ndarray, v: np.ndarray, i: int, sign: float) -> tuple[float, float]:
    """The extreme (``sign`` +1: maximum, -1: minimum) of ``f`` near the grid point ``x[i]`` where
    the samples ``v`` have theirs: a bounded 1-d search between its neighbours when both are
    finite, else the grid value."""
    best = (float(x[i]), float(v[i]))
    if 0 < i < x.size - 1 and np.isfinite(v[i - 1]) and np.isfinite(v[i + 1]):
        r = minimize_scalar(lambda t: -sign * float(f(t)), bounds=(float(x[i - 1]), float(x[i + 1])),
                            method="bounded", options={"xatol": 1e-10 * max(1.0, abs(float(x[i])))})
        if r.success and sign * (-sign * r.fun) > sign * best[1]:
            best = (float(r.x), float(-sign * r.fun))
    return best


def _intervals_minus(on: tuple[float, float], off: tuple[float, float] | None) -> list[tuple[float, float]]:
    """The parts of the |chi_N| interval ``on`` outside ``off`` (None: nothing removed)."""
    if off is None:
        return [on]
    out = []
    if on[0] < off[0]:
        out.append((on[0], min(on[1], off[0])))
    if on[1] > off[1]:
        out.append((max(on[0], off[1]), on[1]))
    return [(a, b) for a, b in out if b > a]


# ------------------------------------------------------------------------------------------ reachability
@dataclass(frozen=True)
class Switch:
    """An on/off switch between two states: for ``lo < |chi_N| <= hi`` (``0 <= |chi_N|`` when
    ``lo = 0``; the mirror image too) a
    cilium beats under state ``beats`` and does not under ``still``, where it ``rests`` (straight
    steady state) or rests ``coiled`` (``|chi_N| > |chi_E|`` of ``still``).

    The ends are the tables' flutter edges (:attr:`ThrustTable.flutter_range`: the upper one is
    the table's computed cutoff ``chi_N_cutoff``) and the ``still`` field's ``|chi_E|``."""

    beats: str
    still: str
    how: str  # "rests" or "coiled"
    lo: float
    hi: float

    def text(self) -> str:
        how = "rests" if self.how == "rests" else "rests coiled up (|chi_N| > chi_E)"
        where = f"|chi_N| <= {self.hi:.2f}" if self.lo == 0.0 else f"{self.lo:.2f} < |chi_N| <= {self.hi:.2f}"
        return f"{where}: beats under '{self.beats}', {how} under '{self.still}'"

    def summary(self) -> dict:
        return {"beats_under": self.beats, "still_under": self.still, "how": self.how,
                "abs_chi_N": [_chi(self.lo), _chi(self.hi)], "text": self.text()}


@dataclass(frozen=True, eq=False)
class PairReach:
    """What a switch between two states ``a`` and ``b`` does to the cilia (angles in rad, chi_N
    signed, thrust in B / L^2).

    Attributes
    ----------
    a, b : str
        The states' names.
    both : (float, float) or None
        The |chi_N| interval where a cilium beats under both (the intersection of the flutter
        ranges), None if there is none.
    chi_N, angle_a, angle_b : (m,) arrays
        The curve: the grid's chi_N where the cilium beats under both, and its thrust angle under
        each. A layout fixes chi_N, so each cilium sits at one point of this curve: the pair
        (angle_a, angle_b) a program can ask of a cilium lies on it, one angle_b for each angle_a
        wherever angle_a is monotone in chi_N (:attr:`monotone`).
    thrust_ratio : (m,) array
        ``thrust_b / thrust_a`` along the curve (NaN where ``thrust_a`` is 0, at a's cutoff).
    monotone : bool
        angle_a is strictly monotone in chi_N along the curve: angle_b is a function of angle_a.
    largest, smallest : dict
        The largest and the smallest ``angle_b - angle_a`` over the cilia beating under both:
        ``delta`` (rad), ``chi_N`` (where), ``angle_a``, ``angle_b`` there, ``error`` (the sum of
        both angles' error estimates there: interpolation plus the rows' ``thrust_angle_error``);
        refined between grid points. By mirror symmetry
        ``smallest = -largest`` at ``-chi_N``.
    ratio : dict
        The thrust ratio b / a: at the straight filament (``at_straight``; None if it does not
        beat under both), its ``min`` and ``max`` (``value``, ``chi_N``, ``error``: the ratio
        times the sum of both thrusts' relative error estimates) over the cilia whose thrust is
        at least :data:`THRUST_FLOOR` of their state's reference under both; ``vanishes``, pairs
        ``(|chi_N|, name)``: where the state ``name`` stops beating (its flutter edge, where its
        thrust falls to 0) inside the other's range, so the ratio runs to 0 or infinity there.
    switches : tuple of Switch
        The on/off intervals, both ways.
    """

    a: str
    b: str
    both: tuple[float, float] | None
    chi_N: np.ndarray
    angle_a: np.ndarray
    angle_b: np.ndarray
    thrust_ratio: np.ndarray
    monotone: bool
    largest: dict
    smallest: dict
    ratio: dict
    switches: tuple[Switch, ...]

    def summary(self) -> dict:
        def ext(d):
            return {"delta_rad": _num(d["delta"]), "delta_deg": _deg(d["delta"]), "chi_N": _chi(d["chi_N"]),
                    "angle_a_rad": _num(d["angle_a"]), "angle_b_rad": _num(d["angle_b"]),
                    "error_rad": _num(d["error"], 2)} if d else None

        def val(d):
            return {"value": _num(d["value"]), "chi_N": _chi(d["chi_N"]), "error": _num(d["error"], 2)} if d else None

        return {
            "states": [self.a, self.b],
            "beat_under_both_abs_chi_N": [_chi(self.both[0]), _chi(self.both[1])] if self.both else None,
            "angle_b_given_angle_a": (
                "one value: the cilia's (angle_a, angle_b) lie on a curve parametrised by chi_N, and angle_a is "
                "monotone in chi_N on it" if self.monotone else
                "angle_a is not monotone in chi_N: the same angle_a can come with more than one angle_b (still a "
                "curve over chi_N, not a region)") if self.both else None,
            "largest_angle_change": ext(self.largest), "smallest_angle_change": ext(self.smallest),
            "thrust_ratio_b_over_a": {"at_straight": _num(self.ratio.get("at_straight", math.nan)),
                                      "min": val(self.ratio.get("min")), "max": val(self.ratio.get("max")),
                                      "over": f"cilia whose thrust is at least {THRUST_FLOOR:g} of their state's "
                                              "reference under both",
                                      "runs_to_0_or_infinity_at": [
                                          {"abs_chi_N": _chi(x), "where_stops_beating": who}
                                          for x, who in self.ratio.get("vanishes", ())]}
            if self.both else None,
            "switches": [s.summary() for s in self.switches],
        }


@dataclass(frozen=True, eq=False)
class ProgramReach:
    """What one layout can make under each of several fields, and pairwise (see
    :func:`program_reachability`). Angles in rad, thrust in B / L^2, chi_N signed.

    Attributes
    ----------
    names, chi_E : tuple
        The states, in the order given, and their fields.
    eta : float
        The drag ratio (the same for every state: a program switches the field only).
    chi_N : (m,) array
        The grid: symmetric about 0 (exactly: the negative half is the mirror image of the
        positive), covering the union of the states' flutter ranges, with every state's flutter
        edges on it.
    regime : (k, m) int8 array
        :data:`REGIMES` code of each cilium under each state.
    beats : (k, m) bool array
        ``regime == "beats"``.
    angle : (k, m) array
        The thrust angle (the table's ``thrust_angle``: from the straight filament's thrust,
        anticlockwise, odd in chi_N); NaN where the cilium does not beat.
    angle_error : (k, m) array
        Its error estimate (interpolation error plus the rows' ``thrust_angle_error``); NaN where
        it does not beat.
    thrust : (k, m) array
        ``|mean thrust|`` (0 where it does not beat: a still filament in still fluid exerts no
        mean force).
    thrust_rel : (k, m) array
        ``thrust / thrust_reference`` of the same state.
    thrust_reference : tuple of float
        Per state: the straight filament's thrust (``chi_N = 0``) where it beats, else the
        state's largest thrust on the grid (:attr:`reference_is`).
    reference_is : tuple of str
        ``"straight"`` or ``"largest"``, per state.
    edges : tuple
        Per state the |chi_N| flutter interval ``(lo, hi)`` (the table's ``flutter_range``), or
        None (the field makes no cilium beat).
    angle_range : tuple of dict
        Per state the reachable thrust angles: ``min``, ``max`` (rad) with their ``chi_N`` and
        ``error``; None for a state where nothing beats.
    pairs : tuple of PairReach
        Every pair of states ``(names[i], names[j])``, ``i < j``.
    """

    names: tuple[str, ...]
    chi_E: tuple[float, ...]
    eta: float
    chi_N: np.ndarray
    regime: np.ndarray
    beats: np.ndarray
    angle: np.ndarray
    angle_error: np.ndarray
    thrust: np.ndarray
    thrust_rel: np.ndarray
    thrust_reference: tuple[float, ...]
    reference_is: tuple[str, ...]
    edges: tuple
    angle_range: tuple
    pairs: tuple[PairReach, ...]

    def pair(self, a: str, b: str) -> PairReach:
        """The pair of states ``a``, ``b`` (in either order; swapped, the angles are too)."""
        for p in self.pairs:
            if (p.a, p.b) == (a, b):
                return p
        for p in self.pairs:
            if (p.a, p.b) == (b, a):
                return _swapped(p)
        raise ValueError(f"no pair of states ({a!r}, {b!r}): the states are {list(self.names)}")

    def summary(self) -> dict:
        """Everything above in strict JSON (no NaN: None), numbers rounded to 4 significant
        digits, chi_N to 0.01, degrees next to radians."""
        states = []
        for i, name in enumerate(self.names):
            r = self.angle_range[i]
            e = self.edges[i]
            states.append({
                "name": name, "chi_E": _num(self.chi_E[i], 6),
                "beats_for_abs_chi_N": [_chi(e[0]), _chi(e[1])] if e else None,
                "angle_range": None if r is None else {
                    k: {"rad": _num(r[k]["angle"]), "deg": _deg(r[k]["angle"]), "chi_N": _chi(r[k]["chi_N"]),
                        "error_rad": _num(r[k]["error"], 2)} for k in ("min", "max")},
                "thrust_reference": _num(self.thrust_reference[i]), "reference_is": self.reference_is[i],
                "thrust_max_rel": _num(np.nanmax(self.thrust_rel[i])) if e else None,
            })
        return {"eta": _num(self.eta, 6), "states": states, "pairs": [p.summary() for p in self.pairs],
                "grid": {"points": int(self.chi_N.size), "abs_chi_N_max": _chi(self.chi_N[-1])},
                "units": "angles rad (deg alongside), thrust B/L^2, chi_N = L kappa_N"}

    def describe(self) -> str:
        """A few plain lines: what each field makes, and which pairs of flows one layout can make."""
        lines = [f"{len(self.names)} program state(s) at eta = {self.eta:g}: "
                 + ", ".join(f"'{n}' chi_E = {e:g}" for n, e in zip(self.names, self.chi_E)) + "."]
        for i, name in enumerate(self.names):
            e, r = self.edges[i], self.angle_range[i]
            if e is None:
                lines.append(f"'{name}': no cilium beats under this field (no flutter branch): the carpet is still.")
                continue
            where = f"|chi_N| <= {e[1]:.2f}" if e[0] == 0 else f"{e[0]:.2f} <= |chi_N| <= {e[1]:.2f}"
            hi = r["max"]
            ref = ("the straight filament's" if self.reference_is[i] == "straight"
                   else "the largest")
            lines.append(f"'{name}': cilia beat for {where}; thrust angle within +-{hi['angle']:.3f} rad "
                         f"(+-{math.degrees(hi['angle']):.1f} deg, reached at |chi_N| = {abs(hi['chi_N']):.2f}, "
                         f"error {hi['error']:.0e} rad); {ref} thrust {self.thrust_reference[i]:.3g}.")
        for p in self.pairs:
            if p.both is None:
                lines.append(f"'{p.a}' -> '{p.b}': no cilium beats under both; a cilium beats under one or none.")
            else:
                lg = max((p.largest, p.smallest), key=lambda d: (abs(d["delta"]), d["chi_N"]))
                way = ("further from" if abs(lg["angle_b"]) > abs(lg["angle_a"]) else "closer to")
                r = p.ratio
                ratio = ""
                if r.get("min") and r.get("max"):
                    ratio = (f"; thrust '{p.b}'/'{p.a}' from {r['min']['value']:.3g} (|chi_N| = "
                             f"{abs(r['min']['chi_N']):.1f}) to {r['max']['value']:.3g} (|chi_N| = "
                             f"{abs(r['max']['chi_N']):.1f})")
                    for x, who in r.get("vanishes", ()):
                        ratio += f", running to 0 or infinity toward |chi_N| = {x:.2f} where '{who}' stops beating"
                curve = ("one angle under '%s' for each angle under '%s' (a curve over chi_N)" % (p.b, p.a)
                         if p.monotone else "a curve over chi_N (angle under '%s' not monotone)" % p.a)
                lines.append(f"'{p.a}' -> '{p.b}': cilia beating under both ({p.both[0]:.2f} <= |chi_N| <= "
                             f"{p.both[1]:.2f}) move on {curve}; the largest change is {abs(lg['delta']):.3f} rad "
                             f"({math.degrees(abs(lg['delta'])):.1f} deg) at |chi_N| = {abs(lg['chi_N']):.2f}, from "
                             f"{abs(lg['angle_a']):.3f} to {abs(lg['angle_b']):.3f} rad off the straight direction "
                             f"({way} it){ratio}.")
            for s in p.switches:
                lines.append("  on/off: " + s.text() + ".")
        lines.append("A layout fixes each cilium's chi_N, so its beat under every field at once: a flow chosen for "
                     "one state fixes the other's along these curves, except that on/off switches choose beat or rest.")
        return "\n".join(lines)


def _swapped(p: PairReach) -> PairReach:
    def neg(d):
        return {**d, "delta": -d["delta"]} if d else d

    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(p.thrust_ratio != 0, 1.0 / p.thrust_ratio, np.nan)
    r = p.ratio
    ratio = {"vanishes": r.get("vanishes", ())}
    if "at_straight" in r:
        ratio["at_straight"] = 1.0 / r["at_straight"] if r["at_straight"] else math.nan
    if r.get("min") and r.get("max"):
        for key, other in (("min", "max"), ("max", "min")):
            o = r[other]
            ratio[key] = {"value": 1.0 / o["value"], "chi_N": o["chi_N"], "error": o["error"] / o["value"] ** 2}
    mono = bool(np.all(np.diff(p.angle_b) > 0) or np.all(np.diff(p.angle_b) < 0)) if p.angle_b.size > 1 else True
    return PairReach(p.b, p.a, p.both, p.chi_N, p.angle_b, p.angle_a, _frozen(inv), mono, neg(p.smallest),
                     neg(p.largest), ratio, p.switches)


def _grid(edges: list, n: int) -> np.ndarray:
    """Symmetric chi_N grid over [-top, top], top the largest flutter edge: ``(n + 1) // 2``
    uniform points on [0, top] plus every edge, mirrored exactly."""
    top = max(e[1] for e in edges if e is not None)
    pos = np.linspace(0.0, top, (n + 1) // 2)
    pos = np.unique(np.concatenate([pos, [x for e in edges if e is not None for x in e]]))
    return np.concatenate([-pos[:0:-1], pos])


def program_reachability(tables: Sequence[ThrustTable], names: Sequence[str], n: int = 401) -> ProgramReach:
    """Which flows one layout makes under each field of a program, and which pairs of them.

    Parameters
    ----------
    tables : sequence of ThrustTable
        One table per state (one field chi_E each, same eta), in still fluid: a table over the
        background flow is used at its grid flow U = 0 (:meth:`ThrustTable.in_still_fluid`); a
        table over a chi_E grid is refused (give one table per field).
    names : sequence of str
        The states' names (distinct, non-empty), one per table.
    n : int
        Grid points over ``[-top, top]`` (``top`` the largest flutter edge; rounded up to odd, so
        the straight filament is on the grid), >= 3; each state's flutter edges are added.

    Returns
    -------
    ProgramReach
        Per state and grid chi_N: regime, thrust angle and its error estimate, thrust (absolute
        and relative to the same state's straight filament); per state the reachable angle range;
        per pair the curve of angle pairs, the largest change of angle, the thrust ratio and the
        on/off switches. :meth:`ProgramReach.describe` reads it out.

    Raises
    ------
    ValueError
        No tables, names that do not match the tables (count, duplicates, empty), tables of
        different eta, a table over a chi_E grid, ``n`` not an integer >= 3, or no state whose
        field makes any cilium beat.
    TypeError
        A table that is not a ThrustTable.
    """
    tables = list(tables) if tables is not None else []
    names = [names] if isinstance(names, str) else list(names) if names is not None else []
    if not tables:
        raise ValueError("program_reachability: no tables: give one ThrustTable per program state")
    if len(names) != len(tables):
        raise ValueError(f"program_reachability: {len(tables)} table(s) but {len(names)} name(s): give one name per "
                         "table")
    for nm in names:
        if not isinstance(nm, str) or not nm.strip():
            raise ValueError(f"program_reachability: state names must be non-empty strings, got {nm!r}")
    if len(set(names)) != len(names):
        dup = sorted({x for x in names if names.count(x) > 1})
        raise ValueError(f"program_reachability: state names must be distinct, {dup} repeat")
    if isinstance(n, bool) or int(n) != n or n < 3:
        raise ValueError(f"program_reachability: n must be an integer >= 3, got {n!r}")
    tabs = [_one_field(t, f"tables[{i}] ('{names[i]}')") for i, t in enumerate(tables)]
    etas = [t.eta for t in tabs]
    if any(abs(e - etas[0]) > 1e-12 * abs(etas[0]) for e in etas):
        raise ValueError(f"program_reachability: the tables have different eta {etas}: a program switches the "
                         "field chi_E of one chip in one fluid (one eta)")
    edges = [_edges(t) for t in tabs]
    if all(e is None for e in edges):
        raise ValueError("program_reachability: no state's field makes any cilium beat (no table has a flutter "
                         "branch): there is nothing to program")
    c = _grid(edges, int(n) + (1 - int(n) % 2))
    a = np.abs(c)
    k, m = len(tabs), c.size
    regime = np.empty((k, m), np.int8)
    angle = np.full((k, m), np.nan)
    err = np.full((k, m), np.nan)
    thrust = np.zeros((k, m))
    refs, ref_is, ranges = [], [], []
    for i, (t, e) in enumerate(zip(tabs, edges)):
        regime[i] = _regimes(t, e, a)
        on = regime[i] == _BEATS
        if np.any(on):
            angle[i, on] = t.scalar("thrust_angle", c[on])
            err[i, on] = _angle_error(t, c[on])
            thrust[i, on] = t.scalar("thrust_norm", c[on])
        if e is not None and e[0] == 0.0:
            refs.append(float(t.scalar("thrust_norm", 0.0)))
            ref_is.append("straight")
        else:
            refs.append(float(thrust[i].max()))
            ref_is.append("largest")
        ranges.append(_angle_range(t, c, angle[i]) if np.any(on) else None)
        logger.info("program state %r (chi_E = %g): beats for |chi_N| in %s, thrust reference %.4g (%s)", names[i],
                    t.chi_E, e, refs[-1], ref_is[-1])
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(np.array(refs)[:, None] > 0, thrust / np.array(refs)[:, None], np.nan)
    beats = regime == _BEATS
    pairs = tuple(_pair(names[i], names[j], tabs[i], tabs[j], edges[i], edges[j], c, beats[i] & beats[j],
                        angle[i], angle[j], thrust[i], thrust[j], refs[i], refs[j])
                  for i in range(k) for j in range(i + 1, k))
    return ProgramReach(tuple(names), tuple(t.chi_E for t in tabs), etas[0], _frozen(c), _frozen(regime),
                        _frozen(beats), _frozen(angle), _frozen(err), _frozen(thrust), _frozen(rel), tuple(refs),
                        tuple(ref_is), tuple(edges), tuple(ranges), pairs)


def _angle_range(t: ThrustTable, c: np.ndarray, ang: np.ndarray) -> dict:
    """The smallest and largest thrust angle over the beating cilia, refined between grid points,
    with the error estimate there."""
    out = {}
    for key, sign in (("min", -1.0), ("max", 1.0)):
        v = np.where(np.isfinite(ang), ang, -sign * np.inf)
        i = int(np.argmax(sign * v))
        lo, hi = t.flutter_range

        def f(x):
            return t.scalar("thrust_angle", x) if lo <= abs(x) <= hi else -sign * np.inf

        x, val = _refine(f, c, np.where(np.isfinite(ang), ang, np.nan), i, sign)
        out[key] = {"angle": val, "chi_N": x, "error": float(_angle_error(t, x))}
    return out


def _pair(na, nb, ta, tb, ea, eb, c, both, ang_a, ang_b, thr_a, thr_b, ref_a, ref_b) -> PairReach:
    """The :class:`PairReach` of states a and b on the grid ``c``."""
    switches = []
    for on_name, off_name, e_on, e_off, t_off in ((nb, na, eb, ea, ta), (na, nb, ea, eb, tb)):
        if e_on is None:
            continue
        E = abs(t_off.chi_E)
        for lo, hi in _intervals_minus(e_on, e_off):
            if lo < E:
                switches.append(Switch(on_name, off_name, "rests", lo, min(hi, E)))
            if hi > E:
                switches.append(Switch(on_name, off_name, "coiled", max(lo, E), hi))
    if ea is None or eb is None or max(ea[0], eb[0]) > min(ea[1], eb[1]):
        empty = _frozen(np.zeros(0))
        return PairReach(na, nb, None, empty, empty, empty, empty, True, {}, {}, {}, tuple(switches))
    span = (max(ea[0], eb[0]), min(ea[1], eb[1]))
    x, pa, pb = c[both], ang_a[both], ang_b[both]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(thr_a[both] > 0, thr_b[both] / thr_a[both], np.nan)
    d = pb - pa

    def delta(t):
        if not span[0] <= abs(t) <= span[1]:
            return np.nan
        return float(tb.scalar("thrust_angle", t) - ta.scalar("thrust_angle", t))

    ext = {}
    for key, sign in (("largest", 1.0), ("smallest", -1.0)):
        i = int(np.argmax(sign * d))
        xe, de = _refine(delta, x, d, i, sign)
        ext[key] = {"delta": de, "chi_N": xe, "angle_a": float(ta.scalar("thrust_angle", xe)),
                    "angle_b": float(tb.scalar("thrust_angle", xe)),
                    "error": float(_angle_error(ta, xe) + _angle_error(tb, xe))}
    dx = np.diff(pa)
    monotone = bool(np.all(dx > 0) or np.all(dx < 0)) if pa.size > 1 else True
    # where one state's beat vanishes (a Hopf edge) inside the other's range, the ratio runs to 0 or infinity
    stops = [(float(ea[j]), na) for j in (0, 1) if ea[j] != eb[j] and ea[j] == span[j]]
    stops += [(float(eb[j]), nb) for j in (0, 1) if ea[j] != eb[j] and eb[j] == span[j]]
    rinfo: dict = {"vanishes": tuple(sorted(s for s in stops if s[0] > 0.0))}
    if span[0] == 0.0:
        ta0, tb0 = float(ta.scalar("thrust_norm", 0.0)), float(tb.scalar("thrust_norm", 0.0))
        rinfo["at_straight"] = tb0 / ta0 if ta0 > 0 else math.nan
    ok = (thr_a[both] >= THRUST_FLOOR * ref_a) & (thr_b[both] >= THRUST_FLOOR * ref_b) & np.isfinite(ratio)
    if np.any(ok):
        rv = np.where(ok, ratio, np.nan)
        for key, f in (("min", np.nanargmin), ("max", np.nanargmax)):
            j = int(f(rv))
            rinfo[key] = {"value": float(rv[j]), "chi_N": float(x[j]),
                          "error": float(rv[j] * (_thrust_error(ta, x[j]) + _thrust_error(tb, x[j])))}
    return PairReach(na, nb, span, _frozen(x), _frozen(pa), _frozen(pb), _frozen(ratio), monotone, ext["largest"],
                     ext["smallest"], rinfo, tuple(switches))


# ------------------------------------------------------------------------------------------ the switch's transient
@dataclass(frozen=True, eq=False)
class SwitchTransient:
    """How long the cilia take to settle after the field switches to one state (times in tau).

    A deviation from a stable limit cycle shrinks by the largest non-trivial Floquet multiplier
    modulus ``|mu|`` per period ``T``: to ``e^-1`` in ``-1 / ln|mu|`` beats, to 1 % in
    ``ln(0.01) / ln|mu|`` beats (times ``T`` in tau); its decay rate is ``-ln|mu| / T`` per tau.
    A deviation from a stable steady state decays as ``exp(alpha t)``, ``alpha`` the real part of
    its leading eigenvalue: ``1 / |alpha|`` tau to ``e^-1``, ``ln(100) / |alpha|`` to 1 %, ringing
    at period ``2 pi / beta``. Both are the asymptotic (linear) rates.

    Attributes
    ----------
    chi_E, eta, cutoff : float
        The state's field, drag ratio and computed flutter cutoff (``chi_N_cutoff``).
    edges : (float, float) or None
        The |chi_N| interval where cilia beat under this field.
    chi_N : (m,) array
        The cilia.
    regime : (m,) int8 array
        :data:`REGIMES` code of each.
    known : (m,) bool array
        The table covers it (beating; or resting with |chi_N| inside the rows that have a steady
        state). A coiled cilium is never known (the table has no row for it).
    period : (m,) array
        ``T`` of a beating cilium (NaN otherwise).
    multiplier, multiplier_error : (m,) arrays
        ``|mu|`` of a beating cilium, the table's ``floquet`` interpolated in chi_N and raised to
        its exact floor ``exp(-T)`` where the spline dips below it (the column has a kink where
        the amplitude mode overtakes the floor), and its error estimate (the interpolation error
        estimate plus the row's ``floquet_trivial_error``, the distance of the computed trivial
        multiplier from 1); NaN otherwise.
    curvature_limited : (m,) bool array
        ``|mu| = exp(-T)`` within ``multiplier_error``: the settling is the curvature's
        relaxation, about ``ln(100)`` = 4.6 tau to 1 %.
    alpha, beta : (m,) arrays
        The leading eigenvalue of a resting cilium's steady state; NaN otherwise.
    rate : (m,) array
        The decay rate per tau (``-ln|mu| / T`` or ``-alpha``); 0 where it does not settle at
        this resolution, NaN where not known.
    settles : (m,) bool array
        Known and ``rate > 0`` beyond the error: ``1 - |mu| > multiplier_error`` (a cilium at
        or next to the cutoff, ``|mu| -> 1``, does not settle at this resolution), or
        ``alpha < 0``.
    beats_e, beats_1pct : (m,) arrays
        Beats to ``e^-1`` and to 1 % of a beating cilium (inf where it does not settle, NaN for a
        resting or unknown one).
    tau_e, tau_1pct : (m,) arrays
        The same in tau, for every known cilium (inf where it does not settle, NaN where unknown).
    """

    chi_E: float
    eta: float
    cutoff: float
    edges: tuple[float, float] | None
    chi_N: np.ndarray
    regime: np.ndarray
    known: np.ndarray
    period: np.ndarray
    multiplier: np.ndarray
    multiplier_error: np.ndarray
    curvature_limited: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    rate: np.ndarray
    settles: np.ndarray
    beats_e: np.ndarray
    beats_1pct: np.ndarray
    tau_e: np.ndarray
    tau_1pct: np.ndarray

    def _worst(self, mask: np.ndarray, key: np.ndarray) -> int | None:
        """The index of the slowest cilium among ``mask`` (one that does not settle first)."""
        idx = np.flatnonzero(mask)
        if idx.size == 0:
            return None
        return int(idx[np.argmax(np.where(np.isfinite(key[idx]) | np.isinf(key[idx]), key[idx], -1.0))])

    def summary(self) -> dict:
        """Counts, the slowest cilium (overall by tau to 1 %, and among the beating by beats to
        1 %), medians over the settling cilia, the cilia that do not settle at this resolution,
        and :meth:`statement`; strict JSON (None for NaN or inf)."""
        beating = (self.regime == _BEATS)
        known_rest = self.known & (self.regime == _RESTS)
        unsettled = self.known & ~self.settles

        def one(i):
            if i is None:
                return None
            d = {"chi_N": _chi(self.chi_N[i]), "regime": REGIMES[int(self.regime[i])], "settles": bool(self.settles[i]),
                 "tau_1pct": _num(self.tau_1pct[i]), "tau_e": _num(self.tau_e[i])}
            if beating[i]:
                d.update(beats_1pct=_num(self.beats_1pct[i]), beats_e=_num(self.beats_e[i]),
                         multiplier=_num(self.multiplier[i], 6), multiplier_error=_num(self.multiplier_error[i], 2),
                         period=_num(self.period[i]), curvature_limited=bool(self.curvature_limited[i]))
            else:
                d.update(alpha=_num(self.alpha[i]), ringing_period=_num(2 * math.pi / abs(self.beta[i]))
                         if self.beta[i] else None)
            return d

        ok_b = beating & self.settles
        return {
            "chi_E": _num(self.chi_E, 6), "eta": _num(self.eta, 6), "cutoff": _chi(self.cutoff),
            "cilia": int(self.chi_N.size), "beating": int(beating.sum()), "resting": int((self.regime == _RESTS).sum()),
            "coiled": int((self.regime == _COILED).sum()), "unknown": int((~self.known).sum()),
            "curvature_limited": int((beating & self.curvature_limited).sum()),
            "worst": one(self._worst(self.known, self.tau_1pct)),
            "worst_beating": one(self._worst(beating & self.known, self.beats_1pct)),
            "worst_resting": one(self._worst(known_rest, self.tau_1pct)),
            "median": {"beats_1pct": _num(np.median(self.beats_1pct[ok_b])) if ok_b.any() else None,
                       "tau_1pct": _num(np.median(self.tau_1pct[self.settles])) if self.settles.any() else None},
            "not_settling": {"count": int(unsettled.sum()), "chi_N": [_chi(x) for x in self.chi_N[unsettled][:10]]},
            "statement": self.statement(),
        }

    def statement(self) -> str:
        """One sentence: how long the cilia take to settle after a switch to this field."""
        head = f"after a switch to chi_E = {self.chi_E:g}"
        parts = []
        beating = self.regime == _BEATS
        un = self.known & ~self.settles
        if un.any():
            x = self.chi_N[un]
            parts.append(f"{int(un.sum())} cilium(s) (e.g. chi_N = {x[0]:.2f}, at or next to the flutter cutoff "
                         f"{self.cutoff:.2f} where |mu| -> 1) do not settle at this resolution (|mu| = 1 within the "
                         "table's error)")
        ok = beating & self.settles
        if ok.any():
            i = self._worst(ok, self.beats_1pct)
            c = float(self.chi_N[i])
            why = ""
            if self.curvature_limited[i]:
                why = ", set by the curvature's relaxation (|mu| = exp(-T))"
            elif self.edges is not None and self.edges[1] - abs(c) <= 0.2 * self.edges[1]:
                why = (f", near the flutter cutoff {self.edges[1]:.2f} where the transient slows as "
                       "1/(cutoff - |chi_N|)")
            parts.append(f"the beating cilia settle within {math.ceil(self.beats_1pct[i])} beats "
                         f"({self.tau_1pct[i]:.3g} tau; 1 %, worst cilium chi_N = {c:.2f}{why}; median "
                         f"{np.median(self.beats_1pct[ok]):.3g} beats)")
        rest = self.settles & (self.regime == _RESTS)
        if rest.any():
            i = self._worst(rest, self.tau_1pct)
            parts.append(f"the resting cilia come to rest within {self.tau_1pct[i]:.3g} tau (1 %, slowest chi_N = "
                         f"{self.chi_N[i]:.2f}, leading eigenvalue {self.alpha[i]:.3g}"
                         f"{' + %.3gi' % abs(self.beta[i]) if self.beta[i] else ''})")
        unknown = ~self.known
        if unknown.any():
            co = int((unknown & (self.regime == _COILED)).sum())
            parts.append(f"{int(unknown.sum())} cilium(s) have no estimate ({co} coiled, |chi_N| > chi_E; the rest "
                         "beyond the table's rows)")
        return head + ": " + ("; ".join(parts) if parts else "no cilia") + "."


def switch_transient(table: ThrustTable, chi_N) -> SwitchTransient:
    """How long each cilium takes to settle after the field switches to ``table``'s state.

    Parameters
    ----------
    table : ThrustTable
        The state's table (one field; a table over the background flow is used in still fluid).
    chi_N : float or array_like
        The cilia's natural curvatures (signed; 1-d or a number), finite.

    Returns
    -------
    SwitchTransient
        Per cilium the multiplier or leading eigenvalue, the decay rate, beats and tau to
        ``e^-1`` and to 1 %, and whether it settles at the table's resolution.

    Raises
    ------
    ValueError
        ``chi_N`` empty, not 1-d, or not finite (naming the first bad index); a table over a
        chi_E grid.
    TypeError
        ``table`` not a ThrustTable.
    """
    t = _one_field(table, "table")
    try:
        c = np.atleast_1d(np.asarray(chi_N, dtype=float))
    except (TypeError, ValueError):
        raise ValueError(f"switch_transient: chi_N must be numbers, got {chi_N!r}") from None
    if c.ndim != 1 or c.size == 0:
        raise ValueError(f"switch_transient: chi_N must be a number or a non-empty 1-d array, got shape {c.shape}")
    bad = np.flatnonzero(~np.isfinite(c))
    if bad.size:
        raise ValueError(f"switch_transient: chi_N must be finite: chi_N[{bad[0]}] = {c[bad[0]]}")
    edges = _edges(t)
    a = np.abs(c)
    regime = _regimes(t, edges, a)
    m = c.size
    nan = np.full(m, np.nan)
    period, mult, merr, alpha, beta = nan.copy(), nan.copy(), nan.copy(), nan.copy(), nan.copy()
    beat = regime == _BEATS
    known = beat.copy()
    curv = np.zeros(m, bool)
    if beat.any():
        cb = c[beat]
        period[beat] = t.scalar("period", cb)
        merr[beat] = (t.interpolation_error("floquet", cb)
                      + np.abs(np.nan_to_num(t.scalar("floquet_trivial_error", cb), nan=0.0)))
        floor = np.exp(-period[beat])
        spline = t.scalar("floquet", cb)
        mult[beat] = np.maximum(spline, floor)  # the floor is exact; a spline across its kink dips below
        curv[beat] = spline - floor <= merr[beat]
    rest = regime == _RESTS
    if rest.any():
        lo, hi = t.chi_N_range
        have = rest & (a >= lo) & (a <= hi)
        if have.any():
            try:
                alpha[have] = t.rest("alpha", c[have])
                beta[have] = np.abs(t.rest("beta", c[have]))
                known |= have
            except TableError as exc:  # rows without a steady state: leave them unknown
                logger.warning("switch_transient: no steady state for some resting cilia: %s", exc)
    with np.errstate(divide="ignore", invalid="ignore"):
        settles_b = beat & (1.0 - mult > merr)
        rate = np.where(beat, np.where(settles_b, -np.log(mult) / period, 0.0), nan)
        settles_r = rest & known & (alpha < 0)
        rate = np.where(rest & known, np.where(settles_r, np.minimum(-alpha, 1.0), 0.0), rate)
        settles = settles_b | settles_r
        beats_e = np.where(beat, np.where(settles_b, -1.0 / np.log(mult), np.inf), np.nan)
        beats_1 = np.where(beat, np.where(settles_b, _LN100 / -np.log(mult), np.inf), np.nan)
        tau_e = np.where(known, np.where(settles, 1.0 / rate, np.inf), np.nan)
        tau_1 = np.where(known, np.where(settles, _LN100 / rate, np.inf), np.nan)
    cutoff = float(t.ds.attrs.get("chi_N_cutoff", np.nan))
    out = SwitchTransient(t.chi_E, t.eta, cutoff, edges, _frozen(c), _frozen(regime), _frozen(known), _frozen(period),
                          _frozen(mult), _frozen(merr), _frozen(curv), _frozen(alpha), _frozen(beta), _frozen(rate),
                          _frozen(settles), _frozen(beats_e), _frozen(beats_1), _frozen(tau_e), _frozen(tau_1))
    logger.info("switch_transient: %s", out.statement())
    return out
