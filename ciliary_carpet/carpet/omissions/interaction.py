"""The hydrodynamic interaction between cilia, the neighbours' mean push, and how the interaction
falls with the spacing (sections (b) and (c) of :mod:`ciliary_carpet.carpet.omissions`).

The interaction. For a sampled cilium j, a point s on it (mid-length s = 1/2 and the tip s = 1)
and an instant t,

    induced_j(s, t) = |u_others(x_j(s, t), t)|,   u_others = u_carpet - u_j,

the flow that all the *other* cilia make at the filament point: the carpet's flow
(:meth:`Carpet.evaluate <ciliary_carpet.carpet.carpet.Carpet.evaluate>` at tolerance ``tol``) minus
cilium j's own resolved line of Stokeslets (:mod:`~ciliary_carpet.carpet.omissions.own_flow`: the
same kernel, blob, wall and Simpson weights as the carpet's sum, at the same phase; the carpet
resolves a cilium at its own points, so the subtraction removes exactly that term, to rounding).
Its error is the evaluation's ``FlowSample.error_bound`` (the rigorous bound of the levels of
detail, ``tol``-relative to the sum of the cilia's far fields), reported as ``interaction_error``
in the units of the ratios below.

The cilium's own speed there is |dx_j/dt (s, t)|, the exact time derivative of the phase
interpolant the carpet evaluates (:meth:`Carpet.beat_velocity
<ciliary_carpet.carpet.carpet.Carpet.beat_velocity>`). It passes through (nearly) zero twice a beat, at
the stroke's turning points, where a pointwise ratio is meaningless; the reported ratio is
therefore normalised by the cilium's **r.m.s. beat speed at that s over its cycle**,

    ratio_j(s, t) = induced_j(s, t) / v_rms,j(s),   v_rms,j(s)^2 = <|dx_j/dt (s)|^2>_cycle,

(the cycle average by the uniform rule on 2 n_phase phases: exact for the interpolant's
trigonometric polynomial), and its median, 90th percentile and maximum over the sampled
cilia and instants are given for s = 1/2 and s = 1. The pointwise ratio induced / |dx/dt| is
given too (median and 90th percentile only: its maximum is unbounded at the turning points); the
two differ little in the median, by design. A standing carpet's filament points, forces and force
centres are taken in space (each cilium's beat plane, :meth:`Carpet.state_in_space
<ciliary_carpet.carpet.carpet.Carpet.state_in_space>`); the beat speeds are the same in either
frame.

Sampling: at most ``n_cilia`` (:data:`N_CILIA`) fluttering cilia, drawn without replacement by
``numpy.random.default_rng(seed)`` (all of them when there are fewer; still cilia neither beat
nor push and are not sampled), and ``n_instants`` (:data:`N_INSTANTS`) instants
t_k = k T / n_instants, k = 0 .. n_instants - 1, T the median period of the fluttering cilia. Each
instant is one carpet evaluation at 2 x n_cilia points (and the force centres of the oscillation,
:mod:`~ciliary_carpet.carpet.omissions.oscillation`); the sampled force centres add one mean-flow
evaluation, and the spread carpet (below) its direct sums.

The mean push of the neighbours. A filament held in a uniform stream U feels about eta U per
unit length (eta the model's tangential resistive coefficient, MODEL.md section 2; 2 eta across
the stream), so the stream that would cancel cilium j's mean thrust |Fbar_j| has the speed
U_cancel,j = |Fbar_j| / (eta L). The others' cycle-mean flow at j's force centre c_j,
|u_mean_others(c_j)| (:meth:`Carpet.velocity` of the :class:`CycleMean` minus j's own
cycle-averaged resolved line), over U_cancel,j is the ``pushback`` ratio: 1 means the neighbours'
mean flow would stall the cilium (the tangential coefficient makes it a lower bound, by up to 2,
of that push; the flow's magnitude is used, not its component along Fbar_j: in a carpet whose
cilia push the same way the two agree). The mean flow does not depend on the phases: carpets of
the same lattice and curvatures give the same pushback.

Spacing. The induced flow falls with the carpet's spacing d. The same carpet with its base
points spread by a factor :data:`SPREAD` (same layout shape, curvatures, phases, wall) is summed
directly (every pair resolved) at the same points, giving a local power law median ~ d^-p; the
spacing at which the median tip ratio would fall to 10 % is d (median / 0.1)^(1 / p) (an
extrapolation of that power law; for a carpet whose median is already under 10 % it is not
extrapolated downwards: the carpet's own spacing is given). In free space p = 1 (the coupling is
the far fields' 1 / R sum, which the spread scales by 1 / 2 exactly); a wall screens the far
field, and p is larger (2.2 to 3.1 for a wall 1 to 0.05 L below). This is the
same cilia spread apart; on a fixed footprint (fewer cilia) the far-field sum falls faster, like
the density n ~ d^-2.
"""
from __future__ import annotations

import math

import numpy as np

from ciliary_carpet.carpet.carpet import Carpet, Instant
from ciliary_carpet.carpet.omissions.own_flow import others_mean_flow_in_space, own_flow, pad
from ciliary_carpet.stokes import stokeslet_velocity

__all__ = ["beat_speeds", "interaction", "mean_push", "N_CILIA", "N_INSTANTS", "TARGET_RATIO", "SPREAD",
           "SPREAD_SOURCES"]

N_CILIA = 64
"""Default largest number of sampled cilia."""
N_INSTANTS = 6
"""Default number of instants over one (median) beat period."""
TARGET_RATIO = 0.1
"""The interaction level at which :attr:`Omissions.spacing_10
<ciliary_carpet.carpet.omissions.report.Omissions>` is given (median tip ratio)."""
SPREAD = 2.0
"""Factor by which the base points are spread to measure the spacing power law."""
SPREAD_SOURCES = 1_500_000
"""The spread carpet (:data:`SPREAD`) is summed directly at m of the instants, evenly spaced, with
m x N x n_s (its sources over those instants) at most this: all six instants up to about 3,800
cilia, two at 100 x 100."""


def beat_speeds(carpet: Carpet, js: np.ndarray, pts: np.ndarray, n_phase: int) -> np.ndarray:
    """(len(js), len(pts)) the r.m.s. beat speed of cilia ``js`` at their points ``pts`` (indices
    into the carpet's s) over each one's own cycle: the uniform rule on 2 ``n_phase`` phases (the
    table's phase samples), exact for the phase interpolant (module docstring)."""
    nj = js.size
    M = 2 * n_phase
    ph0, Tj = carpet.phases[js], carpet.periods[js]
    v2 = np.zeros((nj, 2))
    for m in range(M):
        v = carpet.beat_velocity((m / M - ph0) * Tj, js)[:, pts]
        v2 += (v ** 2).sum(-1)
    return np.sqrt(v2 / M)


def interaction(carpet: Carpet, js: np.ndarray, instants: np.ndarray, pts: np.ndarray, w: np.ndarray,
                vrms: np.ndarray, tol: float, spacing: bool, d_nn: float, shared: dict,
                first: tuple | None) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """The interaction ratios of cilia ``js`` at their points ``pts`` (mid-length and tip) at the
    ``instants`` (module docstring): (ratio, pointwise, error, exponent, spacing_10), ``ratio``
    and ``pointwise`` (2, len(instants), len(js)) over the r.m.s. beat speeds ``vrms``
    (:func:`beat_speeds`) and over the instantaneous ones, ``error`` the largest error bound of a
    ratio, and, with ``spacing`` (and more than one cilium), the spacing power law's exponent p
    and the spacing at which the median tip ratio falls to :data:`TARGET_RATIO` (``d_nn`` the
    carpet's spacing; NaN when not measured). The carpet's flow is evaluated at tolerance ``tol``,
    its Simpson weights ``w``. ``shared`` maps an instant's index k to the index m of the
    oscillation's instant it is; ``first`` = (indices into ``js``, their force centres in space,
    the oscillation's arrays of that group: ``at_centres[0]`` of
    :func:`~ciliary_carpet.carpet.omissions.oscillation.oscillation`): at the shared instants the
    centres join the evaluation, and the flow there and the cilia's own lines are written into
    those arrays."""
    geometry = carpet.placement
    nj, n_s = js.size, carpet.s.size
    bases = carpet.bases
    ratio = np.full((2, instants.size, nj), np.nan)
    pointwise = np.full((2, instants.size, nj), np.nan)
    err = 0.0
    exponent = spacing_10 = math.nan
    spread = SPREAD if spacing and carpet.n > 1 else None
    # the spread carpet needs every cilium's state: at most SPREAD_SOURCES sources x instants
    n_spread = max(1, min(instants.size, SPREAD_SOURCES // (carpet.n * n_s))) if spread else 0
    spread_k = set(np.unique(np.linspace(0, instants.size, n_spread, endpoint=False).astype(int)).tolist())
    near, far = [], []
    for k, t in enumerate(instants):
        pos3, frc3, _ = geometry.shapes(carpet, t, js)  # in space: each cilium in its frame
        targets = np.ascontiguousarray(pos3[:, pts].reshape(-1, 3))  # (nj * 2, 3)
        src = np.ascontiguousarray(pos3.reshape(-1, 3))
        force = np.ascontiguousarray((frc3 * w[None, :, None]).reshape(-1, 3))
        m = shared.get(k)
        if m is None:
            sample = carpet.evaluate(targets, Instant(t), tol)
            vel, bound = sample.velocity, sample.error_bound
        else:  # the first group's force centres in the same evaluation
            g, centres, at = first
            sample = carpet.evaluate(np.concatenate([targets, centres]), Instant(t), tol)
            vel, bound = sample.velocity[:2 * nj], sample.error_bound[:2 * nj]
            at[0][m] = sample.velocity[2 * nj:]
            at[1][m] = src.reshape(nj, n_s, 3)[g].reshape(-1, 3)
            at[2][m] = force.reshape(nj, n_s, 3)[g].reshape(-1, 3)
        u = vel - own_flow(carpet, targets, src, force, 2, n_s)
        ind = np.linalg.norm(u, axis=1).reshape(nj, 2)
        ratio[:, k] = (ind / vrms).T
        own = np.linalg.norm(carpet.beat_velocity(t, js)[:, pts], axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            pointwise[:, k] = (ind / own).T
        err = max(err, float(np.max(bound.reshape(nj, 2) / vrms)))
        if k in spread_k:  # the same carpet, bases spread by SPREAD: every pair resolved
            shift = pad((spread - 1.0) * bases)
            p_all, f_all, _ = geometry.shapes(carpet, t)
            all_src = (p_all + shift[:, None, :]).reshape(-1, 3)
            all_frc = (f_all * w[None, :, None]).reshape(-1, 3)
            tg = (pos3[:, pts] + shift[js][:, None, :]).reshape(-1, 3)
            own_src = (pos3 + shift[js][:, None, :]).reshape(-1, 3)
            u2 = stokeslet_velocity(tg, all_src, all_frc, carpet.mu, kernel=carpet.kernel, backend=carpet.backend) \
                - own_flow(carpet, tg, own_src, force, 2, n_s)
            far.append(np.linalg.norm(u2, axis=1).reshape(nj, 2)[:, 1] / vrms[:, 1])
            near.append(ratio[1, k])
    if far:
        r1, r2 = float(np.median(np.concatenate(near))), float(np.median(np.concatenate(far)))
        if r1 > 0 and r2 > 0 and r1 > r2:
            exponent = math.log(r1 / r2) / math.log(spread)
            spacing_10 = d_nn * max(1.0, (float(np.median(ratio[1])) / TARGET_RATIO) ** (1.0 / exponent))
    return ratio, pointwise, err, exponent, spacing_10


def mean_push(carpet: Carpet, js: np.ndarray, tol: float, eta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                             np.ndarray]:
    """The neighbours' mean push on cilia ``js`` (module docstring): (um, its norms, the norms of
    the cilia's mean thrusts Fbar, pushback), ``um`` (len(js), 3) the others' cycle-mean flow at
    their force centres in space (at tolerance ``tol``), ``pushback`` = norm(um) eta / norm(Fbar)
    (NaN where the cilium has no mean thrust)."""
    # the others' mean flow at the force centres against the stream that cancels the thrust
    if carpet.geometry == "standing":
        um = others_mean_flow_in_space(carpet, js, tol)
    else:
        um = carpet.others_mean_flow(js, tol)
    mean_others = np.linalg.norm(um, axis=1)
    fbar = np.linalg.norm(carpet.mean_thrust[js], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        pushback = np.where(fbar > 0, mean_others * eta / fbar, np.nan)
    return um, mean_others, fbar, pushback
