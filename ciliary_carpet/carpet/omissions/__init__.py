"""What the carpet model leaves out, sized for a given carpet (MODEL.md section 6, last bullet).

The carpet's flow superposes filaments that each beat on their own limit cycle, computed for a
single filament in fluid at rest, far from any wall, with resistive coefficients that fix a
viscosity of their own. :func:`omissions` measures, for any :class:`~ciliary_carpet.carpet.carpet.Carpet`,
how large the neglected effects are, and :class:`~ciliary_carpet.carpet.omissions.report.Omissions`
says it in numbers (with units) and in one plain sentence each (its ``lines`` and ``summary``):

* (a) the wall's effect on each cilium's own drag, and the viscosity's consistency with that
  drag (:mod:`~ciliary_carpet.carpet.omissions.wall_drag`: slender-body theory near a no-slip
  plane);
* (b) the cilia's hydrodynamic interaction and the neighbours' mean push, and (c) how the
  interaction falls with the spacing (:mod:`~ciliary_carpet.carpet.omissions.interaction`);
* (d) the oscillating part of the others' flow, which even a coupled carpet leaves out, and the
  thrust it shifts (:mod:`~ciliary_carpet.carpet.omissions.oscillation`).

The flow of the *other* cilia at a cilium is the carpet's flow minus that cilium's own resolved
line (:mod:`~ciliary_carpet.carpet.omissions.own_flow`). The names of those modules are importable
from here.
"""
from __future__ import annotations

import math

import numpy as np

from ciliary_carpet.carpet.carpet import Carpet, sbt_viscosity
from ciliary_carpet.carpet.cycles import simpson
from ciliary_carpet.carpet.omissions.interaction import (N_CILIA, N_INSTANTS, SPREAD, SPREAD_SOURCES, TARGET_RATIO,
                                                         beat_speeds, interaction, mean_push)
from ciliary_carpet.carpet.omissions.oscillation import (N_OSCILLATION, PERIOD_GROUP, coupling_change, drag_tensor,
                                                         oscillation, period_groups, thrust_shift)
from ciliary_carpet.carpet.omissions.report import Omissions
from ciliary_carpet.carpet.omissions.wall_drag import wall_drag_formula, wall_drag_ratios, wall_effect

__all__ = ["Omissions", "omissions", "wall_drag_ratios", "wall_drag_formula", "drag_tensor", "thrust_shift",
           "N_CILIA", "N_INSTANTS", "N_OSCILLATION", "PERIOD_GROUP", "TARGET_RATIO", "SPREAD", "SPREAD_SOURCES"]


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
    # the oscillating part: the others' flow at the force centres, in space, at the instants of each
    # period group; the group at the median period T shares the interaction's
    groups = period_groups(periods[js], T, PERIOD_GROUP) if nj else []
    centres3 = carpet.placement.centres(carpet, js)
    at_centres = [(np.full((n_o, g.size, 3), np.nan), np.empty((n_o, g.size * n_s, 3)),
                   np.empty((n_o, g.size * n_s, 3))) for _, g in groups]
    shared = {}
    if groups and groups[0][0] == T and np.all(np.abs(periods[js][groups[0][1]] / T - 1.0) <= PERIOD_GROUP):
        shared = {k: k * n_o // int(n_instants) for k in range(int(n_instants)) if (k * n_o) % int(n_instants) == 0}
    exponent = spacing_10 = math.nan
    if nj:
        xs, fs = carpet.cycle_samples(js)  # (nj, n_phase, n_s, 2): the table's phase samples
        vrms = beat_speeds(carpet, js, pts, xs.shape[1])  # (nj, 2)
        first = (groups[0][1], centres3[groups[0][1]], at_centres[0]) if shared else None
        ratio, pointwise, err, exponent, spacing_10 = interaction(carpet, js, instants, pts, w, vrms, tol, spacing,
                                                                  d_nn, shared, first)
        um, mean_others, fbar, pushback = mean_push(carpet, js, tol, eta)
        osc, shift, window = oscillation(carpet, js, groups, at_centres, um, n_o, tol, xs)
        with np.errstate(divide="ignore", invalid="ignore"):
            shift_ratio = np.where(fbar > 0, np.linalg.norm(shift, axis=1) / fbar, np.nan)
        if carpet.coupling != "none":
            dF = coupling_change(carpet, js)
            with np.errstate(divide="ignore", invalid="ignore"):
                shift_coupling = np.linalg.norm(shift, axis=1) / np.linalg.norm(dF, axis=1)

    mid, tip = _stats(ratio[0].ravel()), _stats(ratio[1].ravel())
    pw_mid, pw_tip = _stats(pointwise[0].ravel()), _stats(pointwise[1].ravel())
    pb = _stats(pushback)
    h, heights, along, across, low, regime = wall_effect(carpet, a)
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
        geometry=carpet.geometry, wall_height_min=None if heights is None else float(heights.min()),
        wall_height_max=None if heights is None else float(heights.max()), wall_drag_along_max=low[0],
        wall_drag_across_max=low[1])


def _stats(r: np.ndarray) -> tuple[float, float, float]:
    """(median, 90th percentile, max) of the finite values of ``r``; NaN for none."""
    r = r[np.isfinite(r)]
    if r.size == 0:
        return math.nan, math.nan, math.nan
    return float(np.median(r)), float(np.percentile(r, 90)), float(r.max())
