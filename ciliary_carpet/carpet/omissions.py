"""What the carpet model leaves out, sized for a given carpet (MODEL.md section 6, last bullet).

The carpet's flow superposes filaments that each beat on their own limit cycle, computed for a
single filament in fluid at rest, far from any wall, with resistive coefficients that fix a
viscosity of their own. :func:`omissions` measures, for any :class:`~ciliary_carpet.carpet.carpet.Carpet`,
how large the neglected effects are, and :class:`Omissions` says it in numbers (with units)
and in one plain sentence each (:meth:`Omissions.lines`, :meth:`Omissions.summary`): (b) the
cilia's hydrodynamic interaction and the neighbours' mean push, (a) the wall's effect on each
cilium's own drag, the viscosity's consistency, and (d) the oscillating part of the others' flow,
which even a coupled carpet leaves out, and the thrust it shifts.

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
evaluation at 2 x n_cilia points (and the force centres of section (d)), plus one mean-flow
evaluation at the sampled force centres and the spread carpet's direct sums (below): measured on
2 shared cores, about 1.5 s for 10 x 10 and 6 s for 100 x 100 (``spacing=False``: about 1 s and
4.5 s), after the carpet is built, before section (d) added its instants (its cost: there).

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

(d) The oscillating part of the others' flow
--------------------------------------------
A coupled carpet (``coupling = "mean"``, :mod:`~ciliary_carpet.carpet.coupling`) lets cilium j beat
in the cycle-mean flow U_j that the other cilia make at its force centre c_j
(:meth:`Carpet.others_mean_flow <ciliary_carpet.carpet.carpet.Carpet.others_mean_flow>`); an
uncoupled one lets it beat in still fluid. Both leave out the oscillating part

    u'_j(t) = u_others(c_j, t) - U_j,

u_others(c_j, t) the carpet's flow at c_j at t (:meth:`Carpet.velocity
<ciliary_carpet.carpet.carpet.Carpet.velocity>` at ``tol``) minus cilium j's own resolved line at t
(as in (b)). Only its part in the cilium's 2D frame counts, axes_j^T u (the x, y components for a
planar carpet; for a standing one, at the force centre in space, the components along e_psi_j and
e_z of its beat plane). Its size is the ``oscillation_ratio``

    r_j = sqrt(< |u'_j(t)|^2 >_cycle) / |U_j|,

median and max over the sampled cilia (NaN without another fluttering cilium: there is no flow of
others). The cilia beat at (nearly) one period, so u'_j correlates with cilium j's own phase and
shifts its mean thrust at first order. With MODEL.md section 2's resistive force theory, the
filament held in its shape at phase phi in a uniform flow u exerts on the fluid the force K_j(phi) u,

    K_j(phi) = -eta int_0^1 (2 I - t t^T) ds,     dF_j = < K_j(phi_j(t)) u'_j(t) >_cycle,

t(s, phi) the unit tangent of the table's shape x(s, phi), y(s, phi) in the cilium's 2D frame
(second-order differences in s, normalised; Simpson's rule; at the table's phase samples,
interpolated trigonometrically in phase: :func:`drag_tensor`, :func:`thrust_shift`), and dF_j,
like the thrust, the force on the fluid (single_cilium's ``thrust_convention``). Reported:
``thrust_shift_ratio`` |dF_j| / |Fbar_j| (Fbar_j the cilium's mean thrust,
:attr:`CycleData.F_mean <ciliary_carpet.carpet.cycles.CycleData>`) and, for a coupled carpet,
``thrust_shift_of_coupling`` |dF_j| / |Fbar_j(U_j) - Fbar_j(0)|, against the change of the thrust
that the coupling models (both ends the table's mean thrust in the flow); medians and maxima. It
is a **first-order estimate of a quasi-static drag response**: the shape's own response to u'
(the beat changes in the flow, and with it the force) is neglected, and the mean flows it would
change are not re-solved. For a steady flow the same estimate, <K_j>, can be held against the flow
table's d Fbar / d U, which includes the beat's response: on the coupled uniform_deflection they
agree across the field (-1.74 eta) and differ by 25 % along it (-1.26 against -1.00 eta). A model
in which the cilia's phases emerge from the flow they feel (an issue to come) would include it.

Sampling. The cilia of (b); ``n_oscillation`` (:data:`N_OSCILLATION` = 12) instants evenly spaced
over each cilium's own period T_j, t_jk = t_c + (k - (n - 1) / 2) T_j / n. The uniform rule on n
points averages a trigonometric polynomial of degree below n exactly; the harmonics of u' at a
force centre fall as 1, 0.1, 1.5e-2, 4e-3, 7e-4, 2e-4, 3e-5 (uniform_deflection) and K's as 1, 0.4,
4e-2, 4e-3, 1.7e-3, 3e-4, 4e-5, so the products' harmonics from the 12th on are some 1e-6 of the
first. Measured against 24 instants (uniform 4 x 4 carpets, random and synchronous phases, every
sum resolved): 12 give the ratio to 6e-8 and the shift to 2e-6 of itself, 8 instants to 2e-5 and
6e-4, 6 to 7e-4 and 1.3e-2 (tests/test_neglected.py compares 8, 12 and 24). 12 is twice
:data:`N_INSTANTS`, so every interaction instant is one of them: the force centres join those
evaluations, and a carpet whose cilia share the median period T costs 6 evaluations more.

Periods. Cilia of different periods (curvatures; a coupled carpet's flows: 0.7 % apart on the
coupled uniform_deflection) would each need instants of their own. Instead the sampled cilia are
grouped by period (:data:`PERIOD_GROUP` = 2 %: those within 2 % of T, then from the shortest period
up, each group within a factor 1.04): each group's flow is evaluated at n instants evenly spaced
over its period T_g, and each cilium's own window, centred on the group's, is read from their
trigonometric interpolant (the others' flow is smooth in t). Measured (coupled
uniform_deflection, 17 cilia, each against 12 evaluations at its own instants): windows up to
0.5 % off T_g give the shift to 0.05 % (median; max 0.4 %) and the ratio to 5e-5, where the group's
window itself, uninterpolated, errs by 2 % (max 6 %) of the shift (a small mean of a large
oscillating product, sensitive to its window); windows 1, 2, 3, 5 % off give the shift to 0.06,
0.2, 0.5, 1.1 % (median; max 0.3, 0.9, 1.7, 3.8 %). ``oscillation_window`` is the largest offset
interpolated. Each group costs n evaluations of the carpet's flow at its centres, eight instants
prepared at a time (:meth:`Carpet.prepare <ciliary_carpet.carpet.carpet.Carpet.prepare>`), and
each cilium's own line at each (one state and one short sum an instant). Measured on 2 busy shared
cores, uniform_deflection (one group, 6 instants more): some 0.2 s of CPU, a quarter more than
the omissions took before (coupled: 0.65 to 0.83 s CPU, 0.98 to 1.24 s wall; medians of 10).

Measured on uniform_deflection (10 x 10, spacing 2 L, 64 cilia, seed 0): in still fluid, ratio
0.52 (median; max 1.34), shift 3.2 % of |Fbar| (max 11 %); coupled (the shipped flow table), ratio
1.2 (max 3.1), shift 8.4 % (max 24 %), 6.8 % (max 24 %) of the coupling's change of the thrust.
A uniform 4 x 4 carpet (chi_N = 92, spacing 2 L) with synchronous phases has a ratio of 6.0
(median), with random phases 2.7: in step, the neighbours' oscillations add up at a centre; out of
step they partly cancel while the mean stays.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ciliary_carpet.carpet.carpet import Carpet, CycleMean, Instant, sbt_viscosity
from ciliary_carpet.carpet.cycles import simpson
from ciliary_carpet.stokes import Wall, make_kernel, stokeslet_velocity, stokeslet_velocity_ranges

__all__ = ["Omissions", "omissions", "wall_drag_ratios", "wall_drag_formula", "drag_tensor", "thrust_shift",
           "N_CILIA", "N_INSTANTS", "N_OSCILLATION", "PERIOD_GROUP", "TARGET_RATIO", "SPREAD", "SPREAD_SOURCES"]

N_CILIA = 64
"""Default largest number of sampled cilia."""
N_INSTANTS = 6
"""Default number of instants over one (median) beat period."""
N_OSCILLATION = 12
"""Default number of instants over a cilium's own period at which the oscillating part of the
others' flow and the cilium's drag are sampled (module docstring, section (d)): the uniform rule on
12 points averages a trigonometric polynomial of degree up to 11 exactly, and the products
averaged have fallen to some 1e-6 of their largest harmonic there (measured: the shift to 2e-6 of
itself; 8 instants leave 6e-4, 6 leave 1.3e-2). Twice :data:`N_INSTANTS`, so that every
interaction instant is one of them."""
PERIOD_GROUP = 0.02
"""Sampled cilia whose periods lie within this relative distance of a common period share that
period's instants (their own windows interpolated from them: module docstring, section (d))."""
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

    Oscillating part of the others' flow (section (d); per sampled cilium, NaN where it has no
    fluttering neighbour): ``oscillation_ratio`` (n_sampled,), r.m.s. over its cycle of |u'| at its
    force centre over |U| (the others' cycle-mean flow there, both in its beat plane),
    ``oscillation_ratio_median``, ``oscillation_ratio_max``; ``thrust_shift`` (n_sampled, 2) [B / L^2],
    dF = <K u'>, the first-order shift of its mean force on the fluid (its 2D frame, as
    :attr:`Carpet.mean_thrust <ciliary_carpet.carpet.carpet.Carpet.mean_thrust>`), and
    ``thrust_shift_ratio`` (n_sampled,) = |dF| / |Fbar|, ``thrust_shift_median``,
    ``thrust_shift_max``; ``thrust_shift_of_coupling`` (n_sampled,) = |dF| / |Fbar(U) - Fbar(0)|,
    ``thrust_shift_of_coupling_median``, ``thrust_shift_of_coupling_max`` (coupled carpets; NaN
    otherwise); ``oscillation_instants`` (instants per cycle), ``oscillation_groups`` (period groups
    evaluated), ``oscillation_window`` (the largest |T_j / T_g - 1| over which a cilium's window
    was interpolated; 0 when every sampled cilium beats at its group's period).

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
    oscillation_ratio: np.ndarray = None
    oscillation_ratio_median: float = math.nan
    oscillation_ratio_max: float = math.nan
    thrust_shift: np.ndarray = None
    thrust_shift_ratio: np.ndarray = None
    thrust_shift_median: float = math.nan
    thrust_shift_max: float = math.nan
    thrust_shift_of_coupling: np.ndarray = None
    thrust_shift_of_coupling_median: float = math.nan
    thrust_shift_of_coupling_max: float = math.nan
    oscillation_instants: int = N_OSCILLATION
    oscillation_groups: int = 0
    oscillation_window: float = math.nan

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
            "oscillation": {
                "definition": "r.m.s. over the cilium's cycle of |u'| / |U|: u' = flow of the other cilia at its force "
                              "centre minus its cycle mean U there, both in the cilium's beat plane",
                "ratio": {"median": f(self.oscillation_ratio_median), "max": f(self.oscillation_ratio_max)},
                "thrust_shift": {
                    "definition": "|dF| / |Fbar|, dF = <K(t) u'(t)> over the cilium's cycle, K(t) the resistive-force "
                                  "drag of its shape at t against a uniform flow (force on the fluid per unit flow): "
                                  "a first-order estimate of a quasi-static drag response (the shape's own response "
                                  "neglected)",
                    "median": f(self.thrust_shift_median), "max": f(self.thrust_shift_max),
                    "of_coupling_definition": "|dF| / |Fbar(U) - Fbar(0)| (coupled carpets only)",
                    "of_coupling_median": f(self.thrust_shift_of_coupling_median),
                    "of_coupling_max": f(self.thrust_shift_of_coupling_max)},
                "instants": int(self.oscillation_instants), "period_groups": int(self.oscillation_groups),
                "window_interpolated_max": f(self.oscillation_window),
            },
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
        if len(self.cilia):
            out.append(self._oscillation_line())
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


    def _oscillation_line(self) -> str:
        """The sentence of the oscillating part of the others' flow and the thrust it shifts."""
        if not math.isfinite(self.oscillation_ratio_median):
            return ("No other cilium beats: there is no oscillating flow of the others at a cilium, and no thrust "
                    "for it to shift.")
        size = f"{self.oscillation_ratio_median:.2g} times the mean (median; max {self.oscillation_ratio_max:.2g})"
        shift = (f"shifts its mean thrust by {_pct(self.thrust_shift_median)} % of |Fbar| (median; max "
                 f"{_pct(self.thrust_shift_max)} %)")
        estimate = ("a first-order estimate of the quasi-static resistive drag of the beating shape in that flow (the "
                    "shape's own response neglected)")
        emerge = ("a model in which the cilia's phases emerge from the flow they feel (an issue to come) would "
                  "include it.")
        if self.coupled:
            of = ""
            if math.isfinite(self.thrust_shift_of_coupling_median):
                of = (f", {_pct(self.thrust_shift_of_coupling_median)} % (median; max "
                      f"{_pct(self.thrust_shift_of_coupling_max)} %) of the coupling's own change of the thrust")
            return ("The coupling lets each cilium beat in the others' cycle-mean flow at its force centre but leaves "
                    f"out the oscillation about that mean, whose r.m.s. over the cilium's beat is {size} and which, "
                    f"correlated with the cilium's own beat, {shift}{of}: {estimate}; {emerge}")
        return ("The others' flow at a cilium's force centre oscillates about its cycle mean with an r.m.s. over the "
                f"cilium's beat of {size} and, correlated with the cilium's own beat, {shift}: {estimate}; the model "
                f"leaves this out, as it leaves out the mean flow, and {emerge}")

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


def _trig_at(samples: np.ndarray, t: np.ndarray, period: float) -> np.ndarray:
    """The trigonometric interpolant of ``samples`` (n, m, ...), taken at t_k = k period / n
    (k = 0 .. n-1) for each of m columns, at the times ``t`` (e, m) of each column: (e, m, ...).
    For even n the Nyquist harmonic is taken as its cosine (the real interpolant)."""
    n = samples.shape[0]
    c = np.fft.rfft(samples, axis=0)
    f = np.arange(c.shape[0])
    wt = np.full(f.size, 2.0)
    wt[0] = 1.0
    if n % 2 == 0:
        wt[-1] = 1.0
    e = np.exp((2j * np.pi / period) * f[:, None, None] * np.asarray(t, dtype=float)[None]) * (wt / n)[:, None, None]
    return np.einsum("fem,fm...->em...", e, c).real


def _drag_samples(carpet: Carpet, xs: np.ndarray) -> np.ndarray:
    """(len(js), n_phase, 2, 2) K at the table's phase samples of cilia whose shapes are ``xs``
    (len(js), n_phase, n_s, 2) (:meth:`Carpet.cycle_samples`, each cilium's 2D frame): the force on
    the fluid per unit uniform flow of the filament held in its shape (module docstring, (d)),
    -eta int_0^1 (2 I - t t^T) ds, the tangent t the shape's derivative in s (second order,
    normalised), the integral the carpet's Simpson rule."""
    s = carpet.s
    tg = np.gradient(xs, s, axis=2, edge_order=2)
    tg /= np.linalg.norm(tg, axis=-1, keepdims=True)
    tt = np.einsum("jpsa,jpsb,s->jpab", tg, tg, simpson(s.size), optimize=True)
    return -float(carpet.table.eta) * (2.0 * np.eye(2) - tt)


def drag_tensor(carpet: Carpet, js, phases) -> np.ndarray:
    """K_j(phi) (len(js), m, 2, 2) of cilia ``js`` at their phases ``phases`` (len(js), m) (or (m,),
    the same for all), in each cilium's 2D frame (the lab plane of a planar carpet, the beat plane
    of a standing one): the force the filament held in its shape at that phase exerts on the fluid
    per unit uniform flow, by MODEL.md section 2's resistive force theory (module docstring,
    section (d)): a flow u gives the force K u on the fluid. The trigonometric interpolant in phase
    of its values at the table's phase samples (K's harmonics fall to some 1e-9 of the largest by
    the 16th of the 32 the samples hold). Its quadrature in s (second-order differences, Simpson)
    and a chord-and-midpoint one agree to 0.2 % (measured, chi_N = 92)."""
    js = np.asarray(js, dtype=np.int64).reshape(-1)
    ph = np.broadcast_to(np.asarray(phases, dtype=float), (js.size,) + np.shape(phases)[-1:])
    ks = _drag_samples(carpet, carpet.cycle_samples(js)[0])  # (len(js), n_phase, 2, 2)
    return _trig_at(np.moveaxis(ks, 1, 0), np.mod(ph, 1.0).T, 1.0).transpose(1, 0, 2, 3)


def thrust_shift(carpet: Carpet, js, times, flow) -> np.ndarray:
    """dF_j = < K_j(phi_j(t)) u_j(t) > (len(js), 2): the first-order shift of the mean force on the
    fluid of cilia ``js`` (each one's 2D frame) by the uniform flows ``flow`` (m, len(js), 2) [L / tau,
    in the same frames] at the times ``times`` (m, len(js)) or (m,) [tau], averaged with equal
    weights (instants evenly spaced over each cilium's period: the cycle average). K:
    :func:`drag_tensor` at each cilium's phase phi_j(t) = phases_j + t / T_j."""
    js = np.asarray(js, dtype=np.int64).reshape(-1)
    t = np.asarray(times, dtype=float)
    t = np.broadcast_to(t[:, None] if t.ndim == 1 else t, (t.shape[0], js.size))
    u = np.asarray(flow, dtype=float).reshape(t.shape + (2,))
    ph = carpet.phases[js][None] + t / carpet.periods[js][None]
    K = drag_tensor(carpet, js, ph.T)  # (len(js), m, 2, 2)
    return np.einsum("jmab,mjb->ja", K, u) / t.shape[0]


def _period_groups(periods: np.ndarray, T: float, spread: float) -> list[tuple[float, np.ndarray]]:
    """The sampled cilia (``periods`` (n,)) in groups that share one period's instants (module
    docstring, (d)): first those within ``spread`` of ``T`` (the interaction's period: their
    instants include the interaction's), then, from the shortest period up, each group the
    periods within a factor 1 + 2 ``spread`` of its shortest, at the geometric mean of its
    shortest and longest. [(T_g, indices into periods)]."""
    idx = np.arange(periods.size)
    near = np.abs(periods / T - 1.0) <= spread
    out = [(float(T), idx[near])] if near.any() else []
    rest = idx[~near][np.argsort(periods[~near], kind="stable")]
    while rest.size:
        lo = periods[rest[0]]
        take = periods[rest] <= lo * (1.0 + 2.0 * spread)
        g = rest[take]
        out.append((math.sqrt(lo * float(periods[g].max())), np.sort(g)))
        rest = rest[~take]
    return out


def _oscillation(carpet: Carpet, js: np.ndarray, groups: list, at_centres: list, um: np.ndarray, n_o: int,
                 tol: float, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The oscillating part of the others' flow at the force centres of cilia ``js`` and the
    thrust it shifts (module docstring, (d)): the r.m.s. ratio (len(js),), dF (len(js), 2) and the
    largest relative window interpolated over. ``groups``: :func:`_period_groups`; ``at_centres``:
    per group the carpet's flow (n_o, group size, 3) in space at the centres at its instants and the
    group's own resolved lines then (n_o, group size x n_s, 3, twice: sources, weighted forces),
    NaN where not yet evaluated (evaluated here); ``um`` (len(js), 3): the others' cycle-mean flow
    at the centres; ``xs``: the cilia's shapes at the table's phase samples."""
    nj = js.size
    if int(np.count_nonzero(carpet.flutter)) <= 1:  # no other cilium beats: nothing to size
        return np.full(nj, np.nan), np.full((nj, 2), np.nan), math.nan
    standing = carpet.geometry == "standing"
    n_s = carpet.s.size
    w = simpson(n_s)
    axes = carpet.embedding.axes[js]  # (len(js), 3, 2): the part of a flow each cilium can feel
    U = np.einsum("jab,ja->jb", axes, um)
    centres3 = carpet.in_space("centres", js) if standing else _pad(carpet.centres[js])
    Ks = np.moveaxis(_drag_samples(carpet, xs), 1, 0)  # (n_phase, len(js), 2, 2)
    periods = carpet.periods[js]
    osc, shift, window = np.full(nj, np.nan), np.zeros((nj, 2)), 0.0
    for (Tg, g), (flow, src, force) in zip(groups, at_centres):
        todo = [m for m in range(n_o) if np.isnan(flow[m, 0, 0])]  # the others: with the interaction
        for i, m in enumerate(todo):
            if i % 8 == 0:  # their carriers made together (Carpet.prepare keeps 8 instants)
                carpet.prepare([Tg * q / n_o for q in todo[i:i + 8]], tol)
            t = Tg * m / n_o
            src[m], force[m] = _own_line(carpet, t, js[g], w)
            flow[m] = carpet.velocity(centres3[g], Instant(t), tol)
        # minus each cilium's own resolved line at each instant: one sum over all of them
        own = _own(carpet, np.ascontiguousarray(np.tile(centres3[g], (n_o, 1))), src.reshape(-1, 3),
                   force.reshape(-1, 3), 1, n_s)
        up = np.einsum("jab,mja->mjb", axes[g], flow - own.reshape(flow.shape)) - U[g][None]  # (n_o, group, 2)
        Tj = periods[g]
        # each cilium's own window, centred on the group's: t_jk = t_c + (k - (n_o - 1) / 2) T_j / n_o
        t = Tg * (n_o - 1) / (2 * n_o) + (np.arange(n_o) - (n_o - 1) / 2)[:, None] * Tj[None] / n_o
        if np.any(Tj != Tg):
            up = _trig_at(up, t, Tg)
            window = max(window, float(np.max(np.abs(Tj / Tg - 1.0))))
        K = _trig_at(Ks[:, g], np.mod(carpet.phases[js[g]][None] + t / Tj[None], 1.0), 1.0)  # (n_o, group, 2, 2)
        shift[g] = np.einsum("mjab,mjb->ja", K, up) / n_o
        rms, un = np.sqrt((up ** 2).sum(-1).mean(axis=0)), np.linalg.norm(U[g], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            osc[g] = np.where(un > 0, rms / un, np.nan)
    return osc, shift, window


def _own_line(carpet: Carpet, t: float, js: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The resolved lines of cilia ``js`` at time ``t`` in space: sources and forces times the
    Simpson weights ``w``, (len(js) x n_s, 3) each (what the carpet sums for them at ``t``)."""
    if carpet.geometry == "standing":
        pos, frc, _ = carpet.state_in_space(t, js)
        return pos.reshape(-1, 3), (frc * w[None, :, None]).reshape(-1, 3)
    pos, frc, _ = carpet.state(t, js)
    return _pad(pos.reshape(-1, 2)), _pad((frc * w[None, :, None]).reshape(-1, 2))


def _coupling_change(carpet: Carpet, js: np.ndarray) -> np.ndarray:
    """(len(js), 2) Fbar_j(U_j) - Fbar_j(0) of a coupled carpet's cilia ``js`` (lab frame): the
    change of each one's mean thrust that the coupling models, both ends from the table's mean
    thrust in the flow (the same interpolation), U_j the carpet's background."""
    if carpet.background is None:
        return np.full((js.size, 2), np.nan)
    R = carpet.rotation
    u = np.asarray(carpet.background, dtype=float)[js] @ R  # field frame: U_perp along e1, U_par along e2
    chi = carpet.chi_N[js]

    def thrust(par, perp):
        return np.stack([carpet.table.scalar(k, chi, U_par=par, U_perp=perp) for k in ("thrust_x", "thrust_y")],
                        axis=-1) @ R.T

    return thrust(u[:, 1], u[:, 0]) - thrust(np.zeros(js.size), np.zeros(js.size))


def omissions(carpet: Carpet, tol: float = 1e-4, n_cilia: int = N_CILIA, n_instants: int = N_INSTANTS,
              seed: int = 0, spacing: bool = True, n_oscillation: int = N_OSCILLATION) -> Omissions:
    """Size what ``carpet``'s model leaves out (module docstring): the cilia's hydrodynamic
    interaction at ``n_instants`` instants of a beat on at most ``n_cilia`` fluttering cilia
    drawn with ``seed``, the carpet's flow evaluated at tolerance ``tol``; the neighbours' mean
    push; with ``spacing`` the spacing power law (a direct sum of the carpet spread by
    :data:`SPREAD`); the oscillating part of the others' flow at the sampled cilia's force
    centres and the thrust it shifts, at ``n_oscillation`` instants over each one's period; the
    wall's effect on the filaments' drag; the viscosity's consistency."""
    if not isinstance(carpet, Carpet):
        raise TypeError(f"carpet must be a Carpet, got {type(carpet).__name__}")
    if int(n_cilia) < 1 or int(n_instants) < 1 or int(n_oscillation) < 1:
        raise ValueError(f"n_cilia, n_instants and n_oscillation must be >= 1, got {n_cilia!r}, {n_instants!r}, "
                         f"{n_oscillation!r}")
    n_o = int(n_oscillation)
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
    osc = np.full(nj, np.nan)
    shift = np.zeros((nj, 2))
    shift_ratio = np.full(nj, np.nan)
    shift_coupling = np.full(nj, np.nan)
    window = math.nan
    # the oscillating part (section (d)): the others' flow at the force centres, in space, at the
    # instants of each period group; the group at the median period T shares the interaction's
    groups = _period_groups(periods[js], T, PERIOD_GROUP) if nj else []
    centres3 = carpet.in_space("centres", js) if standing else _pad(carpet.centres[js])
    at_centres = [(np.full((n_o, g.size, 3), np.nan), np.empty((n_o, g.size * n_s, 3)),
                   np.empty((n_o, g.size * n_s, 3))) for _, g in groups]
    shared = {}
    if groups and groups[0][0] == T and np.all(np.abs(periods[js][groups[0][1]] / T - 1.0) <= PERIOD_GROUP):
        shared = {k: k * n_o // int(n_instants) for k in range(int(n_instants)) if (k * n_o) % int(n_instants) == 0}
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
            m = shared.get(k)
            if m is None:
                sample = carpet.evaluate(targets, Instant(t), tol)
                vel, bound = sample.velocity, sample.error_bound
            else:  # the first group's force centres in the same evaluation
                g = groups[0][1]
                sample = carpet.evaluate(np.concatenate([targets, centres3[g]]), Instant(t), tol)
                vel, bound = sample.velocity[:2 * nj], sample.error_bound[:2 * nj]
                at_centres[0][0][m] = sample.velocity[2 * nj:]
                at_centres[0][1][m] = src.reshape(nj, n_s, 3)[g].reshape(-1, 3)
                at_centres[0][2][m] = force.reshape(nj, n_s, 3)[g].reshape(-1, 3)
            u = vel - _own(carpet, targets, src, force, 2, n_s)
            ind = np.linalg.norm(u, axis=1).reshape(nj, 2)
            ratio[:, k] = (ind / vrms).T
            own = np.linalg.norm(carpet.beat_velocity(t, js)[:, pts], axis=-1)
            with np.errstate(divide="ignore", invalid="ignore"):
                pointwise[:, k] = (ind / own).T
            err = max(err, float(np.max(bound.reshape(nj, 2) / vrms)))
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

        # (d) the oscillating part of the others' flow and the thrust it shifts
        osc, shift, window = _oscillation(carpet, js, groups, at_centres, um, n_o, tol, xs)
        with np.errstate(divide="ignore", invalid="ignore"):
            shift_ratio = np.where(fbar > 0, np.linalg.norm(shift, axis=1) / fbar, np.nan)
        if carpet.coupling != "none":
            dF = _coupling_change(carpet, js)
            with np.errstate(divide="ignore", invalid="ignore"):
                shift_coupling = np.linalg.norm(shift, axis=1) / np.linalg.norm(dF, axis=1)

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
        oscillation_ratio=osc, oscillation_ratio_median=_stats(osc)[0], oscillation_ratio_max=_stats(osc)[2],
        thrust_shift=shift, thrust_shift_ratio=shift_ratio, thrust_shift_median=_stats(shift_ratio)[0],
        thrust_shift_max=_stats(shift_ratio)[2], thrust_shift_of_coupling=shift_coupling,
        thrust_shift_of_coupling_median=_stats(shift_coupling)[0],
        thrust_shift_of_coupling_max=_stats(shift_coupling)[2], oscillation_instants=n_o,
        oscillation_groups=len(groups), oscillation_window=window,
        **({} if not standing else dict(
            geometry="standing", wall_height_min=None if heights is None else float(heights.min()),
            wall_height_max=None if heights is None else float(heights.max()), wall_drag_along_max=low[0],
            wall_drag_across_max=low[1])))
