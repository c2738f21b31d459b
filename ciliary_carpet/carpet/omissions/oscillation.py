"""The oscillating part of the others' flow at a cilium and the thrust it shifts (section (d) of
:mod:`ciliary_carpet.carpet.omissions`), which even a coupled carpet leaves out.

A coupled carpet (``coupling = "mean"``, :mod:`~ciliary_carpet.carpet.coupling`) lets cilium j beat
in the cycle-mean flow U_j that the other cilia make at its force centre c_j
(:meth:`Carpet.others_mean_flow <ciliary_carpet.carpet.carpet.Carpet.others_mean_flow>`); an
uncoupled one lets it beat in still fluid. Both leave out the oscillating part

    u'_j(t) = u_others(c_j, t) - U_j,

u_others(c_j, t) the carpet's flow at c_j at t (:meth:`Carpet.velocity
<ciliary_carpet.carpet.carpet.Carpet.velocity>` at ``tol``) minus cilium j's own resolved line at t
(:mod:`~ciliary_carpet.carpet.omissions.own_flow`). Only its part in the cilium's 2D frame counts,
axes_j^T u (the x, y components for a planar carpet; for a standing one, at the force centre in
space, the components along e_psi_j and e_z of its beat plane). Its size is the
``oscillation_ratio``

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
in which the cilia's phases emerge from the flow they feel would include it.

In step, the neighbours' oscillations add up at a cilium's centre; out of step they partly cancel
while the mean stays: a uniform carpet with synchronous phases has a larger ratio than the same
carpet with random phases.

Sampling. The cilia of the interaction (:mod:`~ciliary_carpet.carpet.omissions.interaction`);
``n_oscillation`` (:data:`N_OSCILLATION` = 12) instants evenly spaced over each cilium's own
period T_j, t_jk = t_c + (k - (n - 1) / 2) T_j / n. The uniform rule on n points averages a
trigonometric polynomial of degree below n exactly; the harmonics of u' at a force centre fall as
1, 0.1, 1.5e-2, 4e-3, 7e-4, 2e-4, 3e-5 (uniform_deflection) and K's as 1, 0.4, 4e-2, 4e-3,
1.7e-3, 3e-4, 4e-5, so the products' harmonics from the 12th on are some 1e-6 of the first.
Against 24 instants (uniform 4 x 4 carpets, random and synchronous phases, every sum resolved),
12 give the ratio to 6e-8 and the shift to 2e-6 of itself, 8 instants to 2e-5 and 6e-4, 6 to
7e-4 and 1.3e-2 (tests/test_neglected.py compares 8, 12 and 24). 12 is twice
:data:`~ciliary_carpet.carpet.omissions.interaction.N_INSTANTS`, so every interaction instant is
one of them: the force centres join those evaluations, and a carpet whose cilia share the median
period T costs 6 evaluations more.

Periods. Cilia of different periods (curvatures; a coupled carpet's flows) would each need
instants of their own. Instead the sampled cilia are grouped by period (:data:`PERIOD_GROUP` =
2 %: those within 2 % of T, then from the shortest period up, each group within a factor 1.04):
each group's flow is evaluated at n instants evenly spaced over its period T_g, and each cilium's
own window, centred on the group's, is read from their trigonometric interpolant (the others' flow
is smooth in t). The interpolation's error (coupled uniform_deflection, 17 cilia, each against 12
evaluations at its own instants): windows up to 0.5 % off T_g give the shift to 0.05 % (median;
max 0.4 %) and the ratio to 5e-5, where the group's window itself, uninterpolated, errs by 2 %
(max 6 %) of the shift (a small mean of a large oscillating product, sensitive to its window);
windows 1, 2, 3, 5 % off give the shift to 0.06, 0.2, 0.5, 1.1 % (median; max 0.3, 0.9, 1.7,
3.8 %). ``oscillation_window`` is the largest offset interpolated. Each group costs n evaluations
of the carpet's flow at its centres, eight instants prepared at a time (:meth:`Carpet.prepare
<ciliary_carpet.carpet.carpet.Carpet.prepare>`), and each cilium's own line at each (one state and
one short sum an instant).
"""
from __future__ import annotations

import math

import numpy as np

from ciliary_carpet.carpet.carpet import Carpet, Instant
from ciliary_carpet.carpet.cycles import simpson
from ciliary_carpet.carpet.omissions.own_flow import own_flow, own_line

__all__ = ["drag_tensor", "thrust_shift", "period_groups", "oscillation", "coupling_change", "N_OSCILLATION",
           "PERIOD_GROUP"]

N_OSCILLATION = 12
"""Default number of instants over a cilium's own period at which the oscillating part of the
others' flow and the cilium's drag are sampled (module docstring): the uniform rule on 12 points
averages a trigonometric polynomial of degree up to 11 exactly, and the products averaged have
fallen to some 1e-6 of their largest harmonic there (against 24 instants the shift is right to
2e-6 of itself; 8 instants leave 6e-4, 6 leave 1.3e-2). Twice
:data:`~ciliary_carpet.carpet.omissions.interaction.N_INSTANTS`, so that every interaction instant
is one of them."""
PERIOD_GROUP = 0.02
"""Sampled cilia whose periods lie within this relative distance of a common period share that
period's instants (their own windows interpolated from them: module docstring)."""


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
    the fluid per unit uniform flow of the filament held in its shape (module docstring),
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
    per unit uniform flow, by MODEL.md section 2's resistive force theory (module docstring): a
    flow u gives the force K u on the fluid. The trigonometric interpolant in phase of its values
    at the table's phase samples (K's harmonics fall to some 1e-9 of the largest by the 16th of the
    32 the samples hold). Its quadrature in s (second-order differences, Simpson)
    and a chord-and-midpoint one agree to 0.2 % (chi_N = 92)."""
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


def period_groups(periods: np.ndarray, T: float, spread: float) -> list[tuple[float, np.ndarray]]:
    """The sampled cilia (``periods`` (n,)) in groups that share one period's instants (module
    docstring): first those within ``spread`` of ``T`` (the interaction's period: their
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


def oscillation(carpet: Carpet, js: np.ndarray, groups: list, at_centres: list, um: np.ndarray, n_o: int,
                tol: float, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The oscillating part of the others' flow at the force centres of cilia ``js`` and the
    thrust it shifts (module docstring): the r.m.s. ratio (len(js),), dF (len(js), 2) and the
    largest relative window interpolated over. ``groups``: :func:`period_groups`; ``at_centres``:
    per group the carpet's flow (n_o, group size, 3) in space at the centres at its instants and the
    group's own resolved lines then (n_o, group size x n_s, 3, twice: sources, weighted forces),
    NaN where not yet evaluated (evaluated here); ``um`` (len(js), 3): the others' cycle-mean flow
    at the centres; ``xs``: the cilia's shapes at the table's phase samples."""
    nj = js.size
    if int(np.count_nonzero(carpet.flutter)) <= 1:  # no other cilium beats: nothing to size
        return np.full(nj, np.nan), np.full((nj, 2), np.nan), math.nan
    n_s = carpet.s.size
    w = simpson(n_s)
    axes = carpet.embedding.axes[js]  # (len(js), 3, 2): the part of a flow each cilium can feel
    U = np.einsum("jab,ja->jb", axes, um)
    centres3 = carpet.placement.centres(carpet, js)
    Ks = np.moveaxis(_drag_samples(carpet, xs), 1, 0)  # (n_phase, len(js), 2, 2)
    periods = carpet.periods[js]
    osc, shift, window = np.full(nj, np.nan), np.zeros((nj, 2)), 0.0
    for (Tg, g), (flow, src, force) in zip(groups, at_centres):
        todo = [m for m in range(n_o) if np.isnan(flow[m, 0, 0])]  # the others: with the interaction
        for i, m in enumerate(todo):
            if i % 8 == 0:  # their carriers made together (Carpet.prepare keeps 8 instants)
                carpet.prepare([Tg * q / n_o for q in todo[i:i + 8]], tol)
            t = Tg * m / n_o
            src[m], force[m] = own_line(carpet, t, js[g], w)
            flow[m] = carpet.velocity(centres3[g], Instant(t), tol)
        # minus each cilium's own resolved line at each instant: one sum over all of them
        own = own_flow(carpet, np.ascontiguousarray(np.tile(centres3[g], (n_o, 1))), src.reshape(-1, 3),
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


def coupling_change(carpet: Carpet, js: np.ndarray) -> np.ndarray:
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
