"""The report of what a carpet's model leaves out: :class:`Omissions`, the sizes of the neglected
effects in numbers (with units), as a strict-JSON summary and in one plain sentence each
(definitions: :mod:`ciliary_carpet.carpet.omissions` and its modules)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ciliary_carpet.carpet.omissions.interaction import TARGET_RATIO
from ciliary_carpet.carpet.omissions.oscillation import N_OSCILLATION

__all__ = ["Omissions"]


@dataclass(frozen=True, eq=False)
class Omissions:
    """The neglected effects of a carpet, sized (definitions: :mod:`ciliary_carpet.carpet.omissions`).

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
    :data:`~ciliary_carpet.carpet.omissions.interaction.TARGET_RATIO` (NaN when not measured).

    Wall: ``wall_height`` [L] (None without a wall), ``filament_radius`` a [L],
    ``wall_drag_along``, ``wall_drag_across`` (dimensionless, 1 without a wall): the filaments'
    resistance near the wall over the free-space one the model uses, for motion along and across
    them (:func:`~ciliary_carpet.carpet.omissions.wall_drag.wall_drag_ratios`), ``wall_drag_formula``:
    the closed form (:func:`~ciliary_carpet.carpet.omissions.wall_drag.wall_drag_formula`),
    ``wall_regime`` (text).

    A standing carpet (``geometry = "standing"``): ``wall_height`` is the median of the cilia's
    mean heights above the wall (force centre's z plus the wall's distance below the clamps),
    ``wall_height_min``, ``wall_height_max`` their range, the drag ratios are at the median
    height and ``wall_drag_along_max``, ``wall_drag_across_max`` at the lowest.

    Viscosity: ``mu`` (the carpet's, B tau / L^4), ``mu_source`` (``"filaments"``: the default,
    from eta and the radius; ``"given"``: set by the user), ``mu_sbt`` (slender-body theory's from eta and
    a, same units), ``flow_speed_error`` = mu_sbt / mu - 1 (dimensionless: the carpet's flow
    speeds relative to consistent ones, minus 1).

    Oscillating part of the others' flow
    (:mod:`~ciliary_carpet.carpet.omissions.oscillation`; per sampled cilium, NaN where it has no
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


def _pct(x: float) -> str:
    """A fraction as a percentage: whole percent from 10 % on, two significant digits below."""
    return f"{100 * x:.0f}" if 100 * x >= 9.5 else f"{100 * x:.2g}"
