"""What the carpet model leaves out, sized for a given carpet (MODEL.md section 6, last bullet).

The carpet's flow superposes filaments that each beat on their own limit cycle, computed for a
single filament in fluid at rest, far from any wall, with resistive coefficients that fix a
viscosity of their own. :func:`omissions` measures, for any :class:`~ciliary_carpet.carpet.carpet.Carpet`,
how large the three neglected effects are, and :class:`Omissions` says it in numbers (with units)
and in one plain sentence each (:meth:`Omissions.lines`, :meth:`Omissions.summary`).

(b) Hydrodynamic interaction between cilia
------------------------------------------
For a sampled cilium j, a point s on it (mid-length s = 1/2 and the tip s = 1) and an instant t,

    induced_j(s, t) = |u_others(x_j(s, t), t)|,   u_others = u_carpet - u_j,

the flow that all the *other* cilia make at the filament point: the carpet's flow
(:meth:`Carpet.evaluate <ciliary_carpet.carpet.carpet.Carpet.evaluate>` at tolerance ``tol``) minus
cilium j's own resolved line of Stokeslets (the same kernel, blob, wall and Simpson weights as the
carpet's sum, at the same phase; the carpet resolves a cilium at its own points, so the
subtraction removes exactly that term, to rounding). Its error is the evaluation's
``FlowSample.error_bound`` (the rigorous bound of the levels of detail, ``tol``-relative to the
sum of the cilia's far fields), reported as ``interaction_error`` in the units of the ratios below.

The cilium's own speed there is |dx_j/dt (s, t)|, the exact time derivative of the phase
interpolant the carpet evaluates (:meth:`Carpet.beat_velocity
<ciliary_carpet.carpet.carpet.Carpet.beat_velocity>`). It passes through (nearly) zero twice a beat, at
the stroke's turning points, where a pointwise ratio is meaningless; the reported ratio is
therefore normalised by the cilium's **r.m.s. beat speed at that s over its cycle**,

    ratio_j(s, t) = induced_j(s, t) / v_rms,j(s),   v_rms,j(s)^2 = <|dx_j/dt (s)|^2>_cycle,

(the cycle average by the uniform rule on 2 n_phase phases: exact for the interpolant's
trigonometric polynomial), and its median, 90th percentile and maximum over the sampled
cilia and instants are given for s = 1/2 and s = 1. The pointwise ratio induced / |dx/dt| is
given too (median and 90th percentile only: its maximum is unbounded at the turning points); it
is what an independent check measured (uniform_deflection: 18 % at mid-length, 32 % at the tip, 90th
percentile 66-69 %, 12 cilia x 6 instants); here, 64 cilia x 6 instants, 19 %, 29 % and 65 %, and
the r.m.s.-normalised medians 18 % and 28 % (the two differ little in the median, by design).
A standing carpet's filament points, forces and force centres are taken in space (each cilium's
beat plane, :meth:`Carpet.state_in_space <ciliary_carpet.carpet.carpet.Carpet.state_in_space>`);
the beat speeds are the same in either frame.

Sampling: at most ``n_cilia`` (default 64) fluttering cilia, drawn without replacement by
``numpy.random.default_rng(seed)`` (all of them when there are fewer; still cilia neither beat
nor push and are not sampled), and ``n_instants`` (default 6) instants t_k = k T / n_instants,
k = 0 .. n_instants - 1, T the median period of the fluttering cilia. Each instant is one carpet
evaluation at 2 x n_cilia points, plus one mean-flow evaluation at the sampled force centres
and the spread carpet's direct sums (below): measured on 2 shared cores, about 1.5 s for 10 x 10
and 6 s for 100 x 100 (``spacing=False``: about 1 s and 4.5 s), after the carpet is built.

The mean push of the neighbours. A filament held in a uniform stream U feels about eta U per
unit length (eta the model's tangential resistive coefficient, MODEL.md section 2; 2 eta across
the stream), so the stream that would cancel cilium j's mean thrust |Fbar_j| has the speed
U_cancel,j = |Fbar_j| / (eta L). The others' cycle-mean flow at j's force centre c_j,
|u_mean_others(c_j)| (:meth:`Carpet.velocity` of the :class:`CycleMean` minus j's own cycle-averaged resolved line),
over U_cancel,j is the ``pushback`` ratio: 1 means the neighbours' mean flow would stall the
cilium (the tangential coefficient makes it a lower bound, by up to 2, of that push; the flow's
magnitude is used, not its component along Fbar_j: in a carpet whose cilia push the same way the
two agree). The mean flow does not depend on the phases: carpets of the same lattice and
curvatures give the same pushback.

Spacing. The induced flow falls with the carpet's spacing d. The same carpet with its base
points spread by a factor 2 (same layout shape, curvatures, phases, wall) is summed directly
(every pair resolved) at the same points, giving a local power law median ~ d^-p; the spacing
at which the median tip ratio would fall to 10 % is d (median / 0.1)^(1 / p) (an extrapolation
of that power law; for a carpet whose median is already under 10 % it is not extrapolated
downwards: the carpet's own spacing is given). Measured: p = 1.00 in free space (10 x 10 to
100 x 100: the coupling is the far fields' 1 / R sum, which the spread scales by 1 / 2 exactly),
2.2 to 3.1 with a wall 1 to 0.05 L below (the wall screens the far field). This is the same
cilia spread apart; on a fixed footprint (fewer cilia) the far-field sum falls faster, like the
density n ~ d^-2.

(a) The wall's effect on each cilium's own drag
-----------------------------------------------
The limit cycles use free-space resistive coefficients, in slender-body form (Gray & Hancock
1955, with the filament's length as the cut-off; MODEL.md section 2
takes the slender limit c_perp = 2 c_par)

    c_par = 2 pi mu / (ln(2 L / a) - 1/2),   c_perp = 2 c_par,

for a filament of length L and radius a. A slender filament parallel to a no-slip plane at
height h, a << h << L, has instead (Katz, Blake & Paveri-Fontana 1975, J. Fluid Mech. 72, 529;
reviewed by Brennen & Winet 1977, Annu. Rev. Fluid Mech. 9, 339)

    c_par = 2 pi mu / ln(2 h / a),   c_perp = 4 pi mu / ln(2 h / a)   (normal, parallel to the wall),
    c_z = 4 pi mu / (ln(2 h / a) - 1)                                  (normal to the wall):

the wall's image system cuts the Stokeslet's logarithm off at 2 h instead of the filament's
length. These constants are checked against this package's Blake kernel (the velocity averaged
round the surface of a long singular Stokeslet line, tests/test_neglected.py: to 0.2 % at
h = 20 a, L = 1000 a). A planar carpet beats parallel to the wall, and its anisotropy stays 2,
so the wall scales the model's eta by one factor, the **closed form**

    ratio = (ln(2 L / a) - 1/2) / ln(2 h / a)     (``wall_drag_formula``),

taken as 1 where it falls below 1 (h >= L e^{-1/2} = 0.61 L). Its O(1) constants matter at
the modest logarithms of a real cilium (L / a = 50), so the reported ratios are the same theory
evaluated for the finite filament (:func:`wall_drag_ratios`): a straight filament of length L
at height h, uniform force density along it or across it (parallel to the wall), its velocity
averaged round its surface (radius a) and along its length, with the singular Blake kernel, over
the same in free space. They tend to the closed form for a << h << L and to 1 smoothly as
h -> infinity (measured: a = 0.02 L, h = 0.05, 0.1, 0.2, 0.5, 1 L: along 2.12, 1.55, 1.28, 1.12,
1.06, across 2.59, 1.85, 1.46, 1.19, 1.10; the closed form 2.55, 1.78, 1.37, 1.05, 1); the
uniform force density (not a rigid rod's) makes them an O(1 / ln^2) estimate. NaN where
ln(2 h / a) <= 1 (h < 1.36 a: the filament touches the wall, lubrication, outside the theory);
``wall_regime`` says whether h lies in a << h << L (taken as 5 a <= h <= L / 2).

For a planar carpet every filament point lies at the wall depth h = ``carpet.wall`` above the
wall, so that is the cilia's mean height; with no wall the ratios are 1. A standing carpet's
filaments rise from the wall (clamped on it, or ``carpet.wall`` above it): the same formulas are
evaluated at each cilium's mean height, its force centre's height above the wall
(``centre_z + wall``), as the estimate of the wall's effect on the filament as a whole; the
ratios are reported at the median of those heights and, the largest, at the lowest. The theory
is for a filament parallel to the wall, so for a standing one it is an order-of-magnitude
estimate (its base, at the wall, is slowed more; its tip less). A ratio of 1.5 means
the filament near the wall is 1.5 times as hard to move as its cycle assumes: it beats more
slowly than modelled, by what the single-cilium model with eta scaled by that factor gives
(MODEL.md section 4: the frequency falls as eta grows).

The viscosity. The Stokeslets use the carpet's viscosity ``mu`` (in B tau / L^4, the model's
unit: MODEL.md section 2 writes eta = mu_par L^4 / (tau B), so eta and mu are in the same units).
The filaments' tangential coefficient eta already implies, through the free-space c_par above,

    mu_sbt = eta (ln(2 L / a) - 1/2) / (2 pi)

(0.653 eta for a = 0.02 L; :func:`~ciliary_carpet.carpet.carpet.sbt_viscosity`), which is the
carpet's default (``mu_source = "filaments"``). A carpet given another viscosity
(``mu_source = "given"``, scene key ``[carpet] viscosity``) has flows mu_sbt / mu - 1 too fast
(negative: too slow) against the filaments' own drag (``flow_speed_error``; -35 % for mu = 1 = eta).

The filament radius a is the carpet's blob (its filament radius, :data:`~ciliary_carpet.carpet.carpet.BLOB`
when the carpet uses singular Stokeslets).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ciliary_carpet.carpet.carpet import Carpet, CycleMean, Instant, sbt_viscosity
from ciliary_carpet.carpet.cycles import simpson
from ciliary_carpet.stokes import Wall, make_kernel, stokeslet_velocity, stokeslet_velocity_ranges

__all__ = ["Omissions", "omissions", "wall_drag_ratios", "wall_drag_formula", "N_CILIA", "N_INSTANTS",
           "TARGET_RATIO", "SPREAD", "SPREAD_SOURCES"]

N_CILIA = 64
"""Default largest number of sampled cilia."""
N_INSTANTS = 6
"""Default number of instants over one (median) beat period."""
TARGET_RATIO = 0.1
"""The interaction level at which :attr:`Omissions.spacing_10` is given (median tip ratio)."""
SPREAD = 2.0
"""Factor by which the base points are spread to measure the spacing power law."""
SPREAD_SOURCES = 1_500_000
"""The spread carpet (:data:`SPREAD`) is summed directly at m of the instants, evenly spaced, with
m x N x n_s (its sources over those instants) at most this: all six instants up to about 3,800
cilia, two at 100 x 100 (about 1 s an instant there: every cilium's state and the direct sum)."""


def wall_drag_formula(h: float | None, a: float, length: float = 1.0) -> float:
    """The closed-form ratio of a slender filament's resistive coefficients at height ``h``
    above a no-slip plane (parallel to it, a << h << L) to the free-space ones the model uses,
    (ln(2L/a) - 1/2) / ln(2h/a), at least 1 (module docstring; Katz, Blake & Paveri-Fontana
    1975); 1 for ``h`` None (no wall); NaN where ln(2h/a) <= 1 (touching the wall)."""
    if h is None:
        return 1.0
    h, a = float(h), float(a)
    if not (h > 0 and a > 0):
        raise ValueError(f"need h > 0 and a > 0, got h = {h!r}, a = {a!r}")
    lg = math.log(2.0 * h / a)
    if lg <= 1.0:
        return math.nan
    return max(1.0, (math.log(2.0 * length / a) - 0.5) / lg)


def wall_drag_ratios(h: float | None, a: float, length: float = 1.0) -> tuple[float, float]:
    """(along, across) ratios of the resistance of a straight filament of length ``length`` and
    radius ``a`` parallel to a no-slip plane at height ``h`` to its resistance in free space, for
    motion along itself and across itself parallel to the wall (module docstring): a uniform
    force density on a line of singular Stokeslets, the velocity averaged round the surface and
    along the length, with and without Blake's image system. (1, 1) for ``h`` None; NaN where
    ln(2h/a) <= 1 (touching the wall). About 10 ms for a = 0.02 L."""
    if h is None:
        return 1.0, 1.0
    if math.isnan(wall_drag_formula(h, a, length)):
        return math.nan, math.nan
    h, a, L = float(h), float(a), float(length)
    n = int(min(max(2001, 40 * L / a), 400_001)) | 1  # 40 sources per radius: the surface is resolved
    x = np.linspace(0.0, L, n)
    w = np.full(n, L / (n - 1))
    w[[0, -1]] *= 0.5
    src = np.stack([x, np.zeros(n), np.zeros(n)], axis=1)
    phi = 2.0 * np.pi * np.arange(8) / 8
    xs = L * (0.05 + 0.9 * np.arange(19) / 18)  # along the length, clear of the ends' 5 %
    tg = np.stack([np.repeat(xs, phi.size), np.tile(a * np.cos(phi), xs.size), np.tile(a * np.sin(phi), xs.size)],
                  axis=1)
    free, wall = make_kernel(None, 0.0), make_kernel(Wall(z=-h), 0.0)
    out = []
    for e in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        f = w[:, None] * e[None]
        uf = float((stokeslet_velocity(tg, src, f, kernel=free) @ e).mean())
        uw = float((stokeslet_velocity(tg, src, f, kernel=wall) @ e).mean())
        out.append(uf / uw)
    return out[0], out[1]


@dataclass(frozen=True, eq=False)
class Omissions:
    """The neglected effects of a carpet, sized (see the module docstring for the definitions).

    Hydrodynamic interaction (ratios, dimensionless; median, 90th percentile, max over the
    sampled cilia and instants): ``mid_median``, ``mid_p90``, ``mid_max`` at s = 1/2 and
    ``tip_median``, ``tip_p90``, ``tip_max`` at s = 1, the others' flow over the cilium's r.m.s.
    beat speed there; ``mid_pointwise_median``, ``tip_pointwise_median``, ``tip_pointwise_p90``:
    the same over the instantaneous own speed; ``interaction_error``: the largest error bound of
    a ratio from the evaluation's tolerance; ``ratio_mid``, ``ratio_tip`` (n_instants, n_sampled):
    the ratios themselves; ``beat_speed_mid``, ``beat_speed_tip`` (n_sampled,): the r.m.s. beat
    speeds [L / tau].

    Mean push: ``pushback_median``, ``pushback_max`` (dimensionless): |mean flow of the others at
    the force centre| * eta / |Fbar|; ``mean_flow_others_median`` [L / tau]; ``coupled``: whether
    the carpet's cilia already beat in that mean flow (``coupling = "mean"``), so that the push is
    modelled rather than left out.

    Spacing: ``spacing`` [L], the median nearest-neighbour distance of the base points (NaN for
    one cilium); ``spacing_exponent`` p of median tip ratio ~ spacing^-p (NaN when not measured);
    ``spacing_10`` [L], the spacing at which the median tip ratio falls to
    :data:`TARGET_RATIO` (NaN when not measured).

    Wall: ``wall_height`` [L] (None without a wall), ``filament_radius`` a [L],
    ``wall_drag_along``, ``wall_drag_across`` (dimensionless, 1 without a wall): the filaments'
    resistance near the wall over the free-space one the model uses, for motion along and across
    them (:func:`wall_drag_ratios`), ``wall_drag_formula``: the closed form (:func:`wall_drag_formula`),
    ``wall_regime`` (text).

    A standing carpet (``geometry = "standing"``): ``wall_height`` is the median of the cilia's
    mean heights above the wall (force centre's z plus the wall's distance below the clamps),
    ``wall_height_min``, ``wall_height_max`` their range, the drag ratios are at the median
    height and ``wall_drag_along_max``, ``wall_drag_across_max`` at the lowest.

    Viscosity: ``mu`` (the carpet's, B tau / L^4), ``mu_source`` (``"filaments"``: the default,
    from eta and the radius; ``"given"``: set by the user), ``mu_sbt`` (slender-body theory's from eta and
    a, same units), ``flow_speed_error`` = mu_sbt / mu - 1 (dimensionless: the carpet's flow
    speeds relative to consistent ones, minus 1).

    Sampling: ``n_cilia`` (carpet), ``cilia`` (the sampled indices), ``instants`` [tau], ``tol``,
    ``seed``."""

    n_cilia: int
    cilia: np.ndarray
    instants: np.ndarray
    tol: float
    seed: int
    ratio_mid: np.ndarray
    ratio_tip: np.ndarray
    beat_speed_mid: np.ndarray
    beat_speed_tip: np.ndarray
    mid_median: float
    mid_p90: float
    mid_max: float
    tip_median: float
    tip_p90: float
    tip_max: float
    mid_pointwise_median: float
    tip_pointwise_median: float
    tip_pointwise_p90: float
    interaction_error: float
    pushback_median: float
    pushback_max: float
    mean_flow_others_median: float
    spacing: float
    spacing_exponent: float
    spacing_10: float
    wall_height: float | None
    filament_radius: float
    wall_drag_along: float
    wall_drag_across: float
    wall_drag_formula: float
    wall_regime: str
    mu: float
    mu_source: str
    mu_sbt: float
    flow_speed_error: float
    geometry: str = "planar"
    coupled: bool = False
    wall_height_min: float | None = None
    wall_height_max: float | None = None
    wall_drag_along_max: float = math.nan
    wall_drag_across_max: float = math.nan

    def summary(self) -> dict:
        """Strict-JSON-safe dict (floats, ints, strings; NaN as None) of the scalar results and
        the sampling, with ``lines`` the plain-English sentences of :meth:`lines`."""
        def f(v):
            return None if v is None or not math.isfinite(float(v)) else float(v)

        return {
            "interaction": {
                "definition": "|flow of all other cilia at the filament point| / r.m.s. beat speed of the "
                              "filament at that point over its cycle",
                "mid_length": {"median": f(self.mid_median), "p90": f(self.mid_p90), "max": f(self.mid_max),
                               "pointwise_median": f(self.mid_pointwise_median)},
                "tip": {"median": f(self.tip_median), "p90": f(self.tip_p90), "max": f(self.tip_max),
                        "pointwise_median": f(self.tip_pointwise_median),
                        "pointwise_p90": f(self.tip_pointwise_p90)},
                "error_bound": f(self.interaction_error),
                "sampled_cilia": int(len(self.cilia)), "instants": int(len(self.instants)),
                "carpet_cilia": int(self.n_cilia), "tol": float(self.tol), "seed": int(self.seed),
            },
            "pushback": {
                "definition": "|mean flow of the other cilia at the force centre| / (|Fbar| / (eta L))",
                "median": f(self.pushback_median), "max": f(self.pushback_max),
                "mean_flow_others_median_L_per_tau": f(self.mean_flow_others_median),
            },
            "spacing": {"spacing_L": f(self.spacing), "exponent": f(self.spacing_exponent),
                        "spacing_for_10pct_L": f(self.spacing_10)},
            "wall": {"height_L": f(self.wall_height), "filament_radius_L": f(self.filament_radius),
                     "drag_ratio_along": f(self.wall_drag_along), "drag_ratio_across": f(self.wall_drag_across),
                     "drag_ratio_formula": f(self.wall_drag_formula), "regime": self.wall_regime,
                     **({"geometry": "standing", "height_is": "median mean height (force centre) above the wall",
                         "height_min_L": f(self.wall_height_min), "height_max_L": f(self.wall_height_max),
                         "drag_ratio_along_lowest": f(self.wall_drag_along_max),
                         "drag_ratio_across_lowest": f(self.wall_drag_across_max)}
                        if self.geometry == "standing" else {})},
            "viscosity": {"mu": f(self.mu), "source": self.mu_source, "mu_sbt": f(self.mu_sbt), "flow_speed_error": f(self.flow_speed_error)},
            "lines": self.lines(),
        }

    def lines(self) -> list[str]:
        """One plain-English sentence per neglected effect, with what it means for the design."""
        out = []
        if math.isfinite(self.tip_median):
            head = (f"The other cilia's flow at a cilium is {_pct(self.tip_median)} % of its own r.m.s. tip speed "
                    f"(median; 90th percentile {_pct(self.tip_p90)} %, max {_pct(self.tip_max)} %) and "
                    f"{_pct(self.mid_median)} % at mid-length (median; max {_pct(self.mid_max)} %; "
                    f"{len(self.cilia)} of {self.n_cilia} cilia x {len(self.instants)} instants)")
            if self.tip_median < TARGET_RATIO:
                tail = ": the model's cilia beat as if alone, and that holds to about this fraction"
            elif self.tip_median < 1.0:
                tail = (": the model's cilia beat as if alone, so their beats, and the flow, are uncertain at "
                        "about this level")
            else:
                tail = (": the neighbours' flow outruns the cilia's own beat, so the superposed flow of cilia "
                        "that beat as if alone is not a prediction")
            if math.isfinite(self.spacing_10) and self.tip_median >= TARGET_RATIO:
                tail += (f"; it falls like spacing^-{self.spacing_exponent:.2g}, so spreading these cilia to a "
                         f"spacing of about {self.spacing_10:.2g} L (now {self.spacing:.2g} L) would bring the median "
                         f"under {100 * TARGET_RATIO:.0f} %")
            out.append(head + tail + ".")
        else:
            out.append("No cilium flutters: there is no interaction to size.")
        if math.isfinite(self.pushback_median) and self.coupled:
            out.append(f"The other cilia's mean flow at a cilium is {_pct(self.pushback_median)} % (median; max "
                       f"{_pct(self.pushback_max)} %) of the stream that would cancel its mean thrust (|Fbar| / eta): "
                       "the coupling models it (each cilium's cycle and thrust are the table's in that flow), so "
                       "it is not left out.")
        elif math.isfinite(self.pushback_median):
            verdict = ("small: the table's thrusts stand" if self.pushback_max < TARGET_RATIO else
                       "the table's thrusts overstate what the cilia push against it" if self.pushback_max < 1 else
                       "the neighbours' mean flow would stall some cilia: the superposed mean flow is not one "
                       "the cilia can sustain")
            out.append(f"The other cilia's mean flow at a cilium is {_pct(self.pushback_median)} % (median; max "
                       f"{_pct(self.pushback_max)} %) of the stream that would cancel its own mean thrust "
                       f"(|Fbar| / eta): {verdict}.")
        if self.geometry == "standing" and self.wall_height is not None:
            out.append(self._standing_wall_line())
        elif self.wall_height is None:
            out.append("No wall: the filaments' free-space drag coefficients are the right ones.")
        elif max(self.wall_drag_along, self.wall_drag_across) < 1.05:
            out.append(f"The wall {self.wall_height:.3g} L below the filaments changes their own drag by less than "
                       f"5 % ({self.wall_drag_across:.3f} across, {self.wall_drag_along:.3f} along; slender-body "
                       "theory): their free-space cycles stand.")
        elif math.isfinite(self.wall_drag_across):
            out.append(f"The wall {self.wall_height:.3g} L below the filaments makes them "
                       f"{self.wall_drag_across:.2f} times as hard to move across and {self.wall_drag_along:.2f} "
                       f"times along themselves as their free-space cycles assume (slender-body theory, "
                       f"{self.wall_regime}; the closed form gives {self.wall_drag_formula:.2f} for both): they beat "
                       "more slowly than modelled (the single-cilium model with eta scaled by about this factor "
                       "says by how much).")
        else:
            out.append(f"The wall {self.wall_height:.3g} L below the filaments is within a few radii of them: "
                       "slender-body theory does not apply (lubrication), their drag is far above the model's.")
        direction = "slow" if self.flow_speed_error < 0 else "fast"
        if abs(self.flow_speed_error) < 0.005:
            how = "set to" if self.mu_source == "filaments" else "given as"
            out.append(f"The flow's viscosity mu = {self.mu:.3g} is {how} the one the filaments' drag eta implies "
                       f"(slender-body theory, radius {self.filament_radius:.3g} L): flow and filaments agree.")
            return out
        out.append(f"The flow's viscosity mu = {self.mu:.3g} (given) differs from the {self.mu_sbt:.3g} that the filaments' "
                   f"drag eta implies (slender-body theory, radius {self.filament_radius:.3g} L): the flow speeds are "
                   f"{100 * abs(self.flow_speed_error):.0f} % too {direction} against the filaments' own drag.")
        return out


    def _standing_wall_line(self) -> str:
        """The wall's sentence for standing cilia (their mean heights above it)."""
        where = (f"The cilia stand on the wall: their force centres lie {self.wall_height:.3g} L above it (median; "
                 f"{self.wall_height_min:.3g} to {self.wall_height_max:.3g} L)")
        if not math.isfinite(self.wall_drag_across):
            return (where + ", within a few radii of it: slender-body theory does not apply (lubrication), their "
                    "drag is far above the model's.")
        if max(self.wall_drag_along_max, self.wall_drag_across_max) < 1.05:
            return (where + f"; at those heights the wall changes their drag by less than 5 % (slender-body theory, "
                    f"{self.wall_drag_across:.3f} across, {self.wall_drag_along:.3f} along): their free-space cycles "
                    "stand.")
        return (where + f"; slender-body theory at that mean height makes them {self.wall_drag_across:.2f} times as "
                f"hard to move across and {self.wall_drag_along:.2f} times along themselves as their free-space "
                f"cycles assume (up to {self.wall_drag_across_max:.2f} and {self.wall_drag_along_max:.2f} for the "
                f"lowest; {self.wall_regime}; the theory is for filaments parallel to the wall, so for standing ones "
                "it is an estimate, larger near the base and smaller at the tip): they beat more slowly than "
                "modelled.")


def _others_mean_flow_in_space(carpet: Carpet, js: np.ndarray, tol: float) -> np.ndarray:
    """(len(js), 3) the others' cycle-mean flow at the force centres of a standing carpet's cilia
    ``js``, in space: the carpet's :class:`CycleMean` flow at each centre minus the cilium's own
    cycle-averaged resolved line (the same weights as the carpet's resolved mean, as
    :meth:`Carpet.others_mean_flow <ciliary_carpet.carpet.carpet.Carpet.others_mean_flow>` does in a
    planar carpet's plane)."""
    cen = carpet.in_space("centres", js)
    u = carpet.velocity(cen, CycleMean(), tol)
    w = carpet.cycles.weights
    xs, fs = carpet.cycle_samples(js)  # (m, n_phase, n_s, 2) in each beat plane
    m, n_p, n_s = xs.shape[:3]
    src = carpet.embedding.points(xs.reshape(m, -1, 2), js).reshape(-1, 3)
    frc = carpet.embedding.vectors((fs * (w / n_p)[None, None, :, None]).reshape(m, -1, 2), js).reshape(-1, 3)
    return u - _own(carpet, cen, np.ascontiguousarray(src), np.ascontiguousarray(frc), 1, n_p * n_s)


def _pct(x: float) -> str:
    """A fraction as a percentage: whole percent from 10 % on, two significant digits below."""
    return f"{100 * x:.0f}" if 100 * x >= 9.5 else f"{100 * x:.2g}"


def _stats(r: np.ndarray) -> tuple[float, float, float]:
    r = r[np.isfinite(r)]
    if r.size == 0:
        return math.nan, math.nan, math.nan
    return float(np.median(r)), float(np.percentile(r, 90)), float(r.max())


def _own(carpet: Carpet, targets: np.ndarray, src: np.ndarray, frc: np.ndarray, per: int, blk: int) -> np.ndarray:
    """Velocity at ``targets`` ((len(js) * per, 3), ``per`` consecutive targets per cilium) of
    each cilium's own sources only (block i of ``blk`` rows of ``src``, ``frc``)."""
    m = targets.shape[0]
    i = np.arange(m) // per
    ranges = np.stack([i * blk, (i + 1) * blk], axis=1).astype(np.int64)
    ptr = np.arange(m + 1, dtype=np.int64)
    return stokeslet_velocity_ranges(targets, src, frc, ptr, ranges, carpet.mu, kernel=carpet.kernel,
                                     backend=carpet.backend)


def _pad(a: np.ndarray) -> np.ndarray:
    return np.concatenate([a, np.zeros(a.shape[:-1] + (1,))], axis=-1)


def omissions(carpet: Carpet, tol: float = 1e-4, n_cilia: int = N_CILIA, n_instants: int = N_INSTANTS,
              seed: int = 0, spacing: bool = True) -> Omissions:
    """Size what ``carpet``'s model leaves out (module docstring): the cilia's hydrodynamic
    interaction at ``n_instants`` instants of a beat on at most ``n_cilia`` fluttering cilia
    drawn with ``seed``, the carpet's flow evaluated at tolerance ``tol``; the neighbours' mean
    push; with ``spacing`` the spacing power law (a direct sum of the carpet spread by
    :data:`SPREAD`); the wall's effect on the filaments' drag; the viscosity's consistency."""
    if not isinstance(carpet, Carpet):
        raise TypeError(f"carpet must be a Carpet, got {type(carpet).__name__}")
    if int(n_cilia) < 1 or int(n_instants) < 1:
        raise ValueError(f"n_cilia and n_instants must be >= 1, got {n_cilia!r}, {n_instants!r}")
    tol = float(tol)
    standing = carpet.geometry == "standing"
    s = carpet.s
    n_s = s.size
    w = simpson(n_s)
    pts = np.array([int(np.argmin(np.abs(s - 0.5))), n_s - 1])
    fl = np.flatnonzero(carpet.flutter)
    if fl.size > n_cilia:
        js = np.sort(np.random.default_rng(seed).choice(fl, size=int(n_cilia), replace=False))
    else:
        js = fl
    nj = js.size
    periods = carpet.periods
    T = float(np.median(periods[fl])) if fl.size else 1.0
    instants = T * np.arange(int(n_instants)) / int(n_instants)
    eta = float(carpet.table.eta)
    a = carpet.filament_radius
    bases = carpet.bases
    if carpet.n > 1:
        from scipy.spatial import cKDTree

        d_nn = float(np.median(cKDTree(bases).query(bases, k=2)[0][:, 1]))
    else:
        d_nn = math.nan

    ratio = np.full((2, instants.size, nj), np.nan)
    pointwise = np.full((2, instants.size, nj), np.nan)
    err = 0.0
    pushback = np.full(nj, np.nan)
    mean_others = np.full(nj, np.nan)
    exponent = spacing_10 = math.nan
    if nj:
        # r.m.s. beat speed at s = 1/2 and 1 over each cilium's own cycle (phases m / M)
        xs, fs = carpet.cycle_samples(js)  # (nj, n_phase, n_s, 2): the table's phase samples
        n_p = xs.shape[1]
        M = 2 * n_p
        ph0, Tj = carpet.phases[js], periods[js]
        v2 = np.zeros((nj, 2))
        for m in range(M):
            v = carpet.beat_velocity((m / M - ph0) * Tj, js)[:, pts]
            v2 += (v ** 2).sum(-1)
        vrms = np.sqrt(v2 / M)  # (nj, 2)

        spread = SPREAD if spacing and carpet.n > 1 else None
        # the spread carpet needs every cilium's state: at most SPREAD_SOURCES sources x instants
        n_spread = max(1, min(instants.size, SPREAD_SOURCES // (carpet.n * n_s))) if spread else 0
        spread_k = set(np.unique(np.linspace(0, instants.size, n_spread, endpoint=False).astype(int)).tolist())
        near, far = [], []
        for k, t in enumerate(instants):
            if standing:  # in space: each cilium in its beat plane
                pos3, frc3, _ = carpet.state_in_space(t, js)
                targets = np.ascontiguousarray(pos3[:, pts].reshape(-1, 3))
                src = np.ascontiguousarray(pos3.reshape(-1, 3))
                force = np.ascontiguousarray((frc3 * w[None, :, None]).reshape(-1, 3))
            else:
                pos, frc, _ = carpet.state(t, js)
                targets = _pad(pos[:, pts].reshape(-1, 2))  # (nj * 2, 3)
                src = _pad(pos.reshape(-1, 2))
                force = _pad((frc * w[None, :, None]).reshape(-1, 2))
            sample = carpet.evaluate(targets, Instant(t), tol)
            u = sample.velocity - _own(carpet, targets, src, force, 2, n_s)
            ind = np.linalg.norm(u, axis=1).reshape(nj, 2)
            ratio[:, k] = (ind / vrms).T
            own = np.linalg.norm(carpet.beat_velocity(t, js)[:, pts], axis=-1)
            with np.errstate(divide="ignore", invalid="ignore"):
                pointwise[:, k] = (ind / own).T
            err = max(err, float(np.max(sample.error_bound.reshape(nj, 2) / vrms)))
            if k in spread_k and standing:  # the same, in space
                shift = _pad((spread - 1.0) * bases)
                p_all, f_all, _ = carpet.state_in_space(t)
                all_src = (p_all + shift[:, None, :]).reshape(-1, 3)
                all_frc = (f_all * w[None, :, None]).reshape(-1, 3)
                tg = (pos3[:, pts] + shift[js][:, None, :]).reshape(-1, 3)
                own_src = (pos3 + shift[js][:, None, :]).reshape(-1, 3)
                u2 = stokeslet_velocity(tg, all_src, all_frc, carpet.mu, kernel=carpet.kernel, backend=carpet.backend) \
                    - _own(carpet, tg, own_src, force, 2, n_s)
                far.append(np.linalg.norm(u2, axis=1).reshape(nj, 2)[:, 1] / vrms[:, 1])
                near.append(ratio[1, k])
            elif k in spread_k:  # the same carpet, bases spread by SPREAD: every pair resolved
                shift = (spread - 1.0) * bases
                p_all, f_all, _ = carpet.state(t)
                all_src = _pad((p_all + shift[:, None, :]).reshape(-1, 2))
                all_frc = _pad((f_all * w[None, :, None]).reshape(-1, 2))
                tg = _pad((pos[:, pts] + shift[js][:, None, :]).reshape(-1, 2))
                own_src = _pad((pos + shift[js][:, None, :]).reshape(-1, 2))
                u2 = stokeslet_velocity(tg, all_src, all_frc, carpet.mu, kernel=carpet.kernel, backend=carpet.backend) \
                    - _own(carpet, tg, own_src, force, 2, n_s)
                far.append(np.linalg.norm(u2, axis=1).reshape(nj, 2)[:, 1] / vrms[:, 1])
                near.append(ratio[1, k])
        if far:
            r1, r2 = float(np.median(np.concatenate(near))), float(np.median(np.concatenate(far)))
            if r1 > 0 and r2 > 0 and r1 > r2:
                exponent = math.log(r1 / r2) / math.log(spread)
                spacing_10 = d_nn * max(1.0, (float(np.median(ratio[1])) / TARGET_RATIO) ** (1.0 / exponent))

        # the others' mean flow at the force centres against the stream that cancels the thrust
        um = _others_mean_flow_in_space(carpet, js, tol) if standing else carpet.others_mean_flow(js, tol)
        mean_others = np.linalg.norm(um, axis=1)
        fbar = np.linalg.norm(carpet.mean_thrust[js], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            pushback = np.where(fbar > 0, mean_others * eta / fbar, np.nan)

    mid, tip = _stats(ratio[0].ravel()), _stats(ratio[1].ravel())
    pw_mid, pw_tip = _stats(pointwise[0].ravel()), _stats(pointwise[1].ravel())
    pb = _stats(pushback)
    h = None if carpet.wall is None else float(carpet.wall)
    heights = None
    if standing and h is not None:  # each cilium's mean height above the wall: its force centre's
        heights = carpet.in_space("centres")[:, 2] + h
        h = float(np.median(heights))
    along, across = wall_drag_ratios(h, a)
    low = wall_drag_ratios(float(heights.min()), a) if heights is not None else (math.nan, math.nan)
    if h is None:
        regime = "no wall"
    elif not math.isfinite(across):
        regime = "h within a few filament radii: lubrication, outside slender-body theory"
    elif 5 * a <= h <= 0.5:
        regime = "a << h << L"
    elif h < 5 * a:
        regime = "h only a few radii: slender-body theory at its edge, the drag likely higher still"
    else:
        regime = "h comparable to L: the wall's effect is weak and only estimated"
    mu_sbt = sbt_viscosity(eta, a)
    return Omissions(
        n_cilia=carpet.n, cilia=js, instants=instants, tol=tol, seed=int(seed),
        ratio_mid=ratio[0], ratio_tip=ratio[1],
        beat_speed_mid=vrms[:, 0] if nj else np.zeros(0), beat_speed_tip=vrms[:, 1] if nj else np.zeros(0),
        mid_median=mid[0], mid_p90=mid[1], mid_max=mid[2], tip_median=tip[0], tip_p90=tip[1], tip_max=tip[2],
        mid_pointwise_median=pw_mid[0], tip_pointwise_median=pw_tip[0], tip_pointwise_p90=pw_tip[1],
        interaction_error=err if nj else math.nan,
        pushback_median=pb[0], pushback_max=pb[2],
        mean_flow_others_median=float(np.median(mean_others)) if nj else math.nan,
        spacing=d_nn, spacing_exponent=exponent, spacing_10=spacing_10,
        wall_height=h, filament_radius=a, wall_drag_along=along, wall_drag_across=across,
        wall_drag_formula=wall_drag_formula(h, a), wall_regime=regime,
        mu=float(carpet.mu), mu_source=carpet.mu_source, mu_sbt=mu_sbt, flow_speed_error=mu_sbt / float(carpet.mu) - 1.0,
        coupled=carpet.coupling != "none",
        **({} if not standing else dict(
            geometry="standing", wall_height_min=None if heights is None else float(heights.min()),
            wall_height_max=None if heights is None else float(heights.max()), wall_drag_along_max=low[0],
            wall_drag_across_max=low[1])))
