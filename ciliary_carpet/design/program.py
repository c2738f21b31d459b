"""A program: one curvature layout that makes a target flow in each of several field states.

A carpet's curvatures chi_N are fixed at fabrication, but the field strength chi_E that drives
it can be switched. Each state s (its own thrust table, so its own flutter range, thrust angles,
thrust sizes and coupled flow) has a target at its control points, and the program asks one
chi_N (N,) for all of them:

    J(chi) = sum_s w_s J_s(chi) + (sum_s w_s) [ lambda/N sum_j ((chi_j - chi0_j)/B)^2
                                               + mu/E sum_(i,j) ((chi_i - chi_j)/B)^2 ],

J_s the data term of a single-state design (:mod:`ciliary_carpet.design.inverse`: 1 - cos of
the angle error plus the speed floor for angle targets, the relative squared error for velocity
targets) on state s's carpet, w_s the state's weight. The curvature bound B is common: the
largest flutter cutoff of the states, but no more than the smallest top of their tables' chi_N
grids (every state must know a cilium's shape and force there). A cilium beyond a state's
cutoff rests in that state (no force), so a layout can switch a region off: the moments and near
flows of each state are zero beyond its cutoff (:class:`~ciliary_carpet.design.moments.CycleMoments`).

The solve is that of :func:`~ciliary_carpet.design.inverse.design_layout` with the states
summed: each state's design model (carriers, near field, coupled response) corrected by its full
model's defect, minimised by L-BFGS-B in x = chi / B; a Gauss-Seidel sweep over the cilia on a
common grid of curvatures (:func:`joint_sweep`, both signs, every state's change of objective
summed) takes the layout out of local minima (switching a cilium on or off is such a move); each
pass is measured with every state's full model, and the best layout by the full models' J is
returned (never worse than the joint local layout). The joint local layout is the mixture layout
(:func:`mixture_layout`): per neighbourhood, the fractions of curvatures whose summed thrust
points along every state's target (a linear program), realised by ordered dithering; on a coupled
carpet made once more with each state's thrusts read in the flow its cilia beat in.

Each state's residual then carries its error bar, made at most half its threshold by a final
check at a tolerance chosen for it (:func:`~ciliary_carpet.design.inverse.final_check`), and its
verdict; :attr:`Program.limiting` names the state farthest from its threshold and by how much.
"""
from __future__ import annotations

import logging
import math
import time as _time
import warnings
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from scipy.interpolate import PPoly
from scipy.optimize import minimize

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.carpet.coupling import DENSE_CILIA, CouplingResponse
from ciliary_carpet.design.control import control_points
from ciliary_carpet.design.frame import Frame
from ciliary_carpet.design.moments import cycle_moments
from ciliary_carpet.design.inverse import (DesignProblem, checked_settings, design_result, final_check,
                                           weigh_control_points)
from ciliary_carpet.design.model import (GOOD_ENOUGH, NEAR_CHI_SAMPLES, NEAR_RADIUS, SWEEP_RADIUS, DesignModel,
                                         carrier_forces, solver_threads)
from ciliary_carpet.design.result import Design
from ciliary_carpet.design.target import DEFAULT_SPEED_FLOOR, Target

logger = logging.getLogger(__name__)

__all__ = ["StateProblem", "Program", "design_program", "program_bound", "joint_sweep", "state_problem", "mixture_layout",
           "program_dataset"]


@dataclass(frozen=True)
class StateProblem:
    """One field state of a program: its name, its carpet (the state's table, coupling and
    phases; the bases shared by every state; its chi_N the starting guess of velocity targets),
    its target at ``control`` (P, 2) points -- deflections ``angles`` (P,) [rad, anticlockwise from
    the straight filaments' flow direction] or ``velocities`` (P, 2) [L/tau, lab frame] --, the
    angle each cilium is asked at its force centre ``cilium_angles`` (N,) (angle targets; default
    the angle of the nearest control point), the state's ``weight`` in the joint objective, its
    acceptance ``threshold`` on the rms residual, and the single-state design settings
    (:func:`~ciliary_carpet.design.inverse.design_layout`). ``carpet_of(chi)``: the full model's
    carpet of curvatures chi (N,) in this state, where ``carpet`` is a cheaper stand-in for the
    design model (e.g. an uncoupled carpet of the same table in still fluid, and ``carpet_of`` the
    coupled one); None: ``carpet`` with the curvatures chi."""

    name: str
    carpet: Carpet
    control: np.ndarray
    angles: np.ndarray | None = None
    velocities: np.ndarray | None = None
    cilium_angles: np.ndarray | None = None
    weight: float = 1.0
    threshold: float | None = None
    speed_floor: float = DEFAULT_SPEED_FLOOR
    spacing: float | None = None
    inside_swept: str = "use"
    sample_weights: np.ndarray | None = None
    carpet_of: Callable[[np.ndarray], Carpet] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (isinstance(self.name, str) and self.name):
            raise ValueError(f"a state needs a name, got {self.name!r}")
        w = float(self.weight)
        if not (math.isfinite(w) and w > 0):
            raise ValueError(f"state {self.name!r}: weight must be a finite number > 0, got {self.weight!r}")

    @property
    def chi_E(self) -> float:
        """The state's field strength (its table's)."""
        return float(self.carpet.table.chi_E)


@dataclass(frozen=True)
class Program:
    """A program's layout and how well it makes each state's flow.

    ``chi_N`` (N,): the signed curvatures, one per cilium, shared by every state; ``states``: the
    states' names; ``designs``: per state a :class:`~ciliary_carpet.design.result.Design` of
    ``chi_N`` on that state's carpet (its residual with its error bar, its threshold, its carpet);
    ``weights``: the states' weights; ``bound``: the common curvature bound B; ``objective``,
    ``local_objective``: the joint objective J on the full models' flows of the returned layout
    and of the joint local layout (objective <= local_objective); ``returned``: which iterate
    ("local" or "pass k"); ``resting`` per state: the indices of cilia that rest there (beyond the
    state's flutter cutoff); ``status`` "success" (L-BFGS-B converged) or "inaccurate";
    ``message``; ``work``: iterations, evaluations, full-model checks, sweeps, seconds."""

    chi_N: np.ndarray
    states: tuple[str, ...]
    designs: tuple[Design, ...]
    weights: tuple[float, ...]
    bound: float
    objective: float
    local_objective: float
    returned: str
    resting: tuple[tuple[int, ...], ...]
    status: str = "success"
    message: str = ""
    work: dict = field(default_factory=dict)

    @property
    def met(self) -> tuple[bool, ...]:
        """Per state: its rms residual is within its threshold (True where it has none)."""
        return tuple(d.threshold is None or d.residual_rms <= d.threshold for d in self.designs)

    @property
    def limiting(self) -> tuple[str, float] | None:
        """The state farthest from its threshold and its rms residual over the threshold (None
        when no state has a threshold); > 1 means that state is not met."""
        r = [(d.residual_rms / d.threshold, n) for n, d in zip(self.states, self.designs) if d.threshold]
        if not r:
            return None
        q, n = max(r)
        return n, float(q)

    def summary(self) -> dict:
        """The program's record for summaries (strict JSON)."""
        lim = self.limiting
        return {
            "states": [{"name": n, "chi_E": float(d.carpet.table.chi_E) if d.carpet is not None else None,
                        "weight": w, "residual_rms": float(d.residual_rms), "residual_error": float(d.residual_error),
                        "threshold": d.threshold, "met": m, "resting": len(r), "kind": d.kind,
                        "model": "uncoupled" if d.carpet is None or d.carpet.coupled is None else "coupled"}
                       for n, d, w, m, r in zip(self.states, self.designs, self.weights, self.met, self.resting)],
            "bound": self.bound, "objective": self.objective, "local_objective": self.local_objective,
            "returned": self.returned, "status": self.status, "message": self.message,
            "limiting": None if lim is None else {"state": lim[0], "residual_over_threshold": lim[1]},
            "work": {k: (round(v, 3) if isinstance(v, float) else v) for k, v in self.work.items()},
        }


def state_problem(name: str, target: Target, carpet: Carpet, bases: np.ndarray, frame: Frame, *, spacing: float,
                  weight: float = 1.0, carpet_of: Callable[[np.ndarray], Carpet] | None = None) -> StateProblem:
    """The :class:`StateProblem` of a resolved single-state ``target`` (any planar kind) on
    ``carpet`` (the state's field; ``bases`` (N, 2) and ``frame`` the target's frame of them),
    set up as :func:`~ciliary_carpet.design.target_design.design_target` sets up a single-state
    design: an angle target asked at its control points and, per cilium, at the straight
    filament's force centre; a velocity target at its sample points with their weights."""
    common = dict(name=name, carpet=carpet, weight=weight, threshold=target.threshold(), carpet_of=carpet_of,
                  speed_floor=target.speed_floor, spacing=spacing, inside_swept=target.inside_swept)
    if target.is_angle:
        mom = cycle_moments(carpet.table)
        a = carpet.direction
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        centres0 = bases + mom(np.zeros(1))["offset"] @ rot.T
        X = control_points(bases, frame, target.control)
        return StateProblem(control=X, angles=target.deflection(X, frame),
                            cilium_angles=target.deflection(centres0, frame), **common)
    X, U = target.velocities()
    return StateProblem(control=X, velocities=U, sample_weights=target.sample_weights(), **common)


def program_bound(carpets) -> float:
    """The common curvature bound B of a program's states: the largest flutter cutoff among the
    states' tables, capped by the smallest top of their chi_N grids (so that every state has a
    cilium's shape and force over [-B, B])."""
    cut = max(float(c.table.in_still_fluid().flutter_range[1]) for c in carpets)
    top = min(float(c.table.chi_N_range[1]) for c in carpets)
    return min(cut, top)


def _check_states(states) -> list[StateProblem]:
    states = list(states)
    if len(states) < 2:
        raise ValueError(f"a program needs at least two states, got {len(states)}")
    names = [s.name for s in states]
    if len(set(names)) != len(names):
        raise ValueError(f"state names must be unique, got {names}")
    E = [s.chi_E for s in states]
    for i in range(len(E)):
        for k in range(i):
            if abs(E[i] - E[k]) <= 1e-9 * max(abs(E[i]), abs(E[k])):
                raise ValueError(f"states {names[k]!r} and {names[i]!r} have the same field chi_E = {E[i]:g} "
                                 "(duplicate states)")
    b0 = states[0].carpet.bases
    for s in states:
        if s.carpet.geometry != "planar":
            raise ValueError(f"state {s.name!r}: design_program takes planar carpets (programs of standing "
                             "carpets are not available)")
        if s.carpet.bases.shape != b0.shape or not np.array_equal(s.carpet.bases, b0):
            raise ValueError(f"state {s.name!r}: every state must be the same carpet (bases) in another field")
        if not s.carpet.table.in_still_fluid().flutter_range[1] > 0:
            raise ValueError(f"state {s.name!r}: no cilium flutters at chi_E = {s.chi_E:g}")
    return states


MIXTURE_WEIGHT = 20.0
"""The weight M of the directions against the speed in the joint local layout's linear program
(:func:`mixture_layout`): a unit of relative speed is traded for 1/M of cross-stream flow, so the
layout starts within about 1/M rad of every state's direction where it can."""

DITHER = (0.7548776662466927, 0.5698402909980532)
"""The constants of the R2 low-discrepancy sequence (the plastic number's inverse powers): the
rank u_j = frac(a1 x_j / h + a2 y_j / h) of a cilium at (x_j, y_j) on a lattice of spacing h
spreads any fraction of the cilia evenly over the carpet (ordered dithering)."""


def mixture_layout(parts: list, grid: np.ndarray, bases: np.ndarray, spacing: float | None,
                   flows: list | None = None) -> np.ndarray | None:
    """The joint local layout: per cilium a curvature drawn from the best local *mixture* of
    curvatures (module docstring), or None when no state has an angle target.

    A cilium cannot turn its own thrust one way in one field and the other way in another (its
    thrust angle has the sign of chi_N in every field), but a neighbourhood can: some of its
    cilia beat in one field only. So the layout is chosen for neighbourhoods. For the angles
    alpha_s each state s asks near a cilium (t_s the unit target direction, n_s its normal, Fhat_s
    = F_s / |F_s(0)| the thrust relative to the state's straight filament), the linear program

        maximise  z - M sum_s w_s e_s   over p >= 0 on ``grid``, sum p = 1, z, e >= 0,
        subject to  sum_k p_k Fhat_s(g_k) . t_s >= z,  |sum_k p_k Fhat_s(g_k) . n_s| <= e_s

    (M = :data:`MIXTURE_WEIGHT`, w_s the states' weights) gives the fractions p of the
    curvatures g_k whose summed thrust points along every state's target with the largest
    common speed; each cilium then takes the curvature at which the cumulative fractions pass
    its rank u_j (:data:`DITHER`), so that neighbouring cilia realise the mixture. Where one
    curvature serves every state the mixture is that curvature. Cilia asking the same angles (to
    1e-3 rad) share one program.

    ``flows``: per state (of ``parts``) None, or (the background flow (2,) [L/tau, lab frame] the
    cilia beat in -- a coupled carpet's median of the others' flow at the cilia --, the state's
    table over the flow), at which the thrusts F_s are then read off that table (a cilium that rests in still
    fluid may beat in a flow, and the flow turns and slows the thrust)."""
    from scipy.optimize import linprog

    angle_parts = [(st, ob, want) for st, ob, want in parts if want is not None]
    if not angle_parts:
        return None
    S, G = len(angle_parts), grid.size
    Ft = []  # per state (G, 2) relative thrust in the lab frame
    flows = [None] * len(parts) if flows is None else list(flows)
    for (st, ob, want), U in zip(angle_parts, [f for f, (_, _, w) in zip(flows, parts) if w is not None]):
        F0 = ob.mom(np.zeros(1))["F"][0]
        if U is None:
            m = ob.mom(grid)["F"]
        else:
            U, table = U
            u = st.carpet.rotation.T @ np.asarray(U, dtype=float)  # field frame: (U_perp, U_par)
            (p0, p1), (q0, q1) = table.U_range
            up, uq = float(np.clip(u[1], p0, p1)), float(np.clip(u[0], -q1, q1))
            a = np.abs(grid)
            sg = np.where(grid < 0, -1.0, 1.0)
            # the mirror image: chi_N -> -chi_N is x -> -x, so a negative chi_N in U_perp is |chi_N| in -U_perp
            q = np.clip(sg * uq, q0, q1)
            tx = np.array([table.scalar("thrust_x", ai, U_par=up, U_perp=qi) for ai, qi in zip(a, q)])
            ty = np.array([table.scalar("thrust_y", ai, U_par=up, U_perp=qi) for ai, qi in zip(a, q)])
            m = np.column_stack([sg * np.nan_to_num(tx), np.nan_to_num(ty)])
        Ft.append((m @ st.carpet.rotation.T) / float(np.hypot(*F0)))
    d0 = [st.carpet.rotation @ np.array([0.0, -1.0]) for st, _, _ in angle_parts]  # straight flow, lab frame
    base = [math.atan2(d[1], d[0]) for d in d0]
    W = np.array([float(st.weight) for st, _, _ in angle_parts])
    wants = np.column_stack([np.asarray(want, dtype=float) for _, _, want in angle_parts])  # (N, S)
    keys, inv = np.unique(np.round(wants, 3), axis=0, return_inverse=True)
    inv = inv.ravel()
    # variables: p (G), z, e (S); minimise -z + M sum w e
    c = np.concatenate([np.zeros(G), [-1.0], MIXTURE_WEIGHT * W])
    A_eq = np.concatenate([np.ones(G), [0.0], np.zeros(S)])[None]
    cdf = np.empty((keys.shape[0], G))
    for q, a in enumerate(keys):
        rows = []
        for s in range(S):
            th = base[s] + a[s]
            t, n = np.array([math.cos(th), math.sin(th)]), np.array([-math.sin(th), math.cos(th)])
            par, perp = Ft[s] @ t, Ft[s] @ n
            e = np.zeros(S)
            e[s] = -1.0
            rows.append(np.concatenate([-par, [1.0], np.zeros(S)]))  # z - par . p <= 0
            rows.append(np.concatenate([perp, [0.0], e]))            # perp . p - e <= 0
            rows.append(np.concatenate([-perp, [0.0], e]))           # -perp . p - e <= 0
        r = linprog(c, A_ub=np.array(rows), b_ub=np.zeros(len(rows)), A_eq=A_eq, b_eq=[1.0],
                    bounds=[(0, None)] * G + [(None, None)] + [(0, None)] * S, method="highs")
        p = np.clip(r.x[:G], 0.0, None) if r.status == 0 else np.eye(G)[G // 2]
        cdf[q] = np.cumsum(p) / max(float(p.sum()), 1e-300)
    h = float(spacing) if spacing else 1.0
    u = np.mod(DITHER[0] * bases[:, 0] / h + DITHER[1] * bases[:, 1] / h, 1.0)
    k = np.array([int(np.searchsorted(cdf[inv[j]], u[j] * (1 - 1e-12), side="right")) for j in range(bases.shape[0])])
    return grid[np.clip(k, 0, G - 1)]


def joint_sweep(parts: list, chi: np.ndarray, grid: np.ndarray, penalty, radius: float = SWEEP_RADIUS
                ) -> tuple[np.ndarray, int]:
    """One Gauss-Seidel sweep over the cilia on the states' design models together: each
    cilium's chi_N in turn set to the curvature of ``grid`` (common to the states, both signs,
    beyond a state's cutoff a resting cilium there) that lowers the summed objective
    sum_s w_s J_s + penalty most, the others fixed (as :func:`~ciliary_carpet.design.model.sweep`
    does for one state, whose docstring says why).

    ``parts``: per state (weight, DesignModel, NearField or None, model flow (P_s, 2) at ``chi``
    with the defect, terms(u_sub, ks)); ``penalty(j, values, chi)``: the regularisers' change.
    Returns the new chi and the number of cilia moved."""
    from scipy.spatial import cKDTree

    chi = np.array(chi, dtype=float)
    N, ng = chi.size, grid.size
    prep = []
    for w, dm, near, u, terms in parts:
        c = dm.carpet
        lists = cKDTree(dm.X3[:, :2]).query_ball_point(c.bases, float(radius))
        cnt = np.array([len(x) for x in lists], np.int64)
        ptr = np.concatenate([[0], np.cumsum(cnt)])
        jj = np.repeat(np.arange(N), cnt)
        kk = np.concatenate([np.asarray(x, np.int64) for x in lists]) if cnt.sum() else np.zeros(0, np.int64)
        G = dm.pair_blocks(kk, jj)
        Fg = carrier_forces(dm.moments, dm.rot, np.repeat(dm.delta, ng), np.tile(grid, N)).reshape(N, ng, 3, 2)
        rec = {"w": float(w), "ptr": ptr, "kk": kk, "G": G, "Fg": Fg, "f": dm.carriers(chi), "u": np.array(u, float),
               "terms": terms, "near": near}
        if near is not None and near.key.size:
            key = kk * N + jj
            pos = np.clip(np.searchsorted(near.key, key), 0, near.key.size - 1)
            rec["is_near"], rec["pos"] = near.key[pos] == key, pos
            rec["v"] = near.pair_velocity(chi)
            # the near pairs' flows on the common grid (a resting cilium: the cutoff's, zero flow)
            rec["Vg"] = PPoly(near.coef, near.grid)(np.clip(grid, near.grid[0], near.grid[-1]))
        else:
            rec["near"] = None
        prep.append(rec)
    moved = 0
    for j in range(N):
        dJ = np.asarray(penalty(j, grid, chi), dtype=float).copy()
        base_total = 0.0
        dus = []
        for r in prep:
            sl = slice(r["ptr"][j], r["ptr"][j + 1])
            ks = r["kk"][sl]
            if ks.size == 0:
                dus.append(None)
                continue
            du = np.einsum("pamb,gmb->gpa", r["G"][sl], r["Fg"][j] - r["f"][j])
            nm = None
            if r["near"] is not None:
                nm = r["is_near"][sl]
                if nm.any():
                    pi = r["pos"][sl][nm]
                    du[:, nm] = r["Vg"][:, r["near"].inv[pi]] - r["v"][pi][None]
                else:
                    nm = None
            base = r["terms"](r["u"][ks], ks)
            base_total += r["w"] * float(np.sum(base))
            dJ += r["w"] * np.sum(r["terms"](r["u"][ks][None] + du, ks) - base[None], axis=1)
            dus.append((ks, du, nm, sl))
        m = int(np.argmin(dJ))
        if dJ[m] < -1e-12 * max(base_total, 1e-300):
            chi[j] = grid[m]
            moved += 1
            for r, d in zip(prep, dus):
                r["f"][j] = r["Fg"][j, m]
                if d is None:
                    continue
                ks, du, nm, sl = d
                r["u"][ks] += du[m]
                if nm is not None:
                    pi = r["pos"][sl][nm]
                    r["v"][pi] = r["Vg"][m, r["near"].inv[pi]]
    return chi, moved


def design_program(states, *, tol: float = 1e-3, check_tol: float | None = None, floor_weight: float = 1.0,
                   regularization: float = 1e-3, smoothness: float = 0.0, outer: int = 3, ftol: float = 1e-6,
                   maxiter: int = 500, near_radius: float = NEAR_RADIUS, sweeps: int = 3,
                   n_grid: int = 2 * NEAR_CHI_SAMPLES - 1) -> Program:
    """One chi_N per cilium for every state of a program (module docstring).

    ``states``: two or more :class:`StateProblem` s on one planar carpet (same bases) in
    different fields. ``tol``, ``check_tol``, ``floor_weight``, ``regularization``,
    ``smoothness``, ``outer``, ``ftol``, ``maxiter``, ``near_radius``, ``sweeps``: as in
    :func:`~ciliary_carpet.design.inverse.design_layout`; ``n_grid``: curvatures of the sweeps'
    and the joint local layout's common grid on [-B, B].

    Raises ValueError for fewer than two states, duplicate names or fields, states on different
    carpets, and a state in whose field nothing flutters; a TargetError for a target's bad
    control points (as a single-state design)."""
    clock = _time.perf_counter()
    states = _check_states(states)
    carpets = [s.carpet for s in states]
    B = program_bound(carpets)
    N = carpets[0].n
    check_tol = max(tol, 3e-2) if check_tol is None else float(check_tol)
    grid = np.linspace(-B, B, int(n_grid))
    obs, infos, parts = [], [], []
    for s in states:
        X = checked_settings(s.control, s.angles, s.velocities, s.speed_floor, floor_weight, regularization,
                             smoothness, 0.0, 16, s.inside_swept, s.threshold)
        X, ang, vel, w_pts, inside_info, done = weigh_control_points(s.carpet, X, s.spacing, s.inside_swept,
                                                                     s.sample_weights, s.angles, s.velocities)
        with warnings.catch_warnings():  # the state's own local requests are not used (the joint layout is)
            warnings.simplefilter("ignore", UserWarning)
            ob = DesignProblem(s.carpet, X, w_pts, ang, vel, None if ang is None else np.zeros(N), True,
                               check_tol=check_tol, speed_floor=s.speed_floor, floor_weight=floor_weight,
                               regularization=regularization, smoothness=smoothness, spacing=s.spacing,
                               floor_radius=None, robust_sigma=0.0, robust_samples=16, robust_seed=12345,
                               near_radius=near_radius, scale=B)
        want = None
        if ang is not None:
            from scipy.spatial import cKDTree

            A = np.broadcast_to(np.asarray(ang, dtype=float), (X.shape[0],))
            want = A[cKDTree(X).query(s.carpet.centres)[1]] if s.cilium_angles is None else \
                np.broadcast_to(np.asarray(s.cilium_angles, dtype=float), (N,))
        ob.carpet_of = s.carpet_of
        obs.append(ob)
        infos.append((inside_info, done))
        parts.append((s, ob, want))
    chi0 = mixture_layout(parts, grid, carpets[0].bases, states[0].spacing)
    if chi0 is None:
        chi0 = np.clip(carpets[0].chi_N, -B, B)
    W = np.array([float(s.weight) for s in states])
    counters = {"iterations": 0, "evaluations": 0, "checks": 0, "sweeps": 0, "swept_cilia": 0, "passes": 0}

    def check_all(chi, cs=None):
        out = []
        for i, ob in enumerate(obs):
            c, u, e = ob.check(chi, c=None if cs is None else cs[i])
            out.append((c, u, e))
        counters["checks"] += 1
        return out

    def score(chi, checked) -> float:
        return float(sum(w * ob.score(u, chi, c) for w, ob, (c, u, _) in zip(W, obs, checked)))

    for ob in obs:
        ob.chi0 = chi0.copy()
    checked = check_all(chi0)
    J_loc = score(chi0, checked)
    # coupled carpets: the mixture again, with each state's thrusts in the flow its cilia beat in
    for _ in range(1 if any(c.coupled is not None for c, _, _ in checked) else 0):
        flows = [None if c.coupled is None else (np.median(c.coupled.background, axis=0), c.table)
                 for c, _, _ in checked]
        chi1 = mixture_layout(parts, grid, carpets[0].bases, states[0].spacing, flows)
        if chi1 is None:
            break
        for ob in obs:
            ob.chi0 = chi1.copy()
        checked1 = check_all(chi1)
        J1 = score(chi1, checked1)
        logger.info("program: mixture layout in the coupled flows %s: objective %.4g (before %.4g)",
                    ", ".join(f"({f[0][0]:.3g}, {f[0][1]:.3g})" for f in flows if f is not None), J1, J_loc)
        if not J1 < J_loc:
            for ob in obs:
                ob.chi0 = chi0.copy()
            break
        chi0, checked, J_loc = chi1, checked1, J1
    local = [(ob.wrms(ob.residual(u)), ob.score(u, chi0, c)) for ob, (c, u, _) in zip(obs, checked)]
    best = {"chi": chi0.copy(), "J": J_loc, "checked": checked, "label": "local", "res": None}
    logger.info("program: joint local layout, objective %.4g; rms %s", J_loc,
                ", ".join(f"{s.name} {r:.3g}" for s, (r, _) in zip(states, local)))
    chi, prev = chi0.copy(), checked
    res = None
    for p in range(1, max(1, int(outer)) + 1):
        counters["passes"] += 1
        res, J_model = _joint_pass(obs, W, states, chi, prev, grid, B, ftol=ftol, maxiter=maxiter, sweeps=sweeps,
                                   counters=counters)
        chi = np.clip(res.x * B, -B, B)
        checked = check_all(chi)
        J_full = score(chi, checked)
        gain = (best["J"] - J_full) / max(best["J"], 1e-300)
        rms = [ob.wrms(ob.residual(u)) for ob, (_, u, _) in zip(obs, checked)]
        logger.info("program pass %d: objective %.4g on the full models, %.4g on the design models; rms %s", p,
                    J_full, J_model, ", ".join(f"{s.name} {r:.3g}" for s, r in zip(states, rms)))
        if gain > 1e-12:
            best = {"chi": chi.copy(), "J": J_full, "checked": checked, "label": f"pass {p}", "res": res}
        prev = checked
        if abs(J_full - J_model) <= 0.05 * J_full or (p > 1 and gain < 0.02):
            break
        thr = [s.threshold for s in states]
        if all(t is not None for t in thr) and all(
                ob.wrms(ob.residual(u)) <= GOOD_ENOUGH * t for ob, (_, u, _), t in zip(obs, best["checked"], thr)):
            break
    return _program_result(states, obs, infos, best, res, local, J_loc, B, W, check_tol, counters, clock)


def _joint_pass(obs, W, states, chi, prev, grid, B, *, ftol, maxiter, sweeps, counters):
    """One pass: every state's design model at ``chi`` corrected by its full model's defect
    (``prev``: per state (carpet, flow, bound)), the weighted sum minimised by L-BFGS-B in x =
    chi / B, then swept (:func:`joint_sweep`) while that lowers it. Returns (the solver's
    result, the design models' J at it)."""
    N = chi.size
    ob0 = obs[0]
    edges, reg, smooth, chi0 = ob0.edges, ob0.regularization, ob0.smoothness, ob0.chi0
    Wsum = float(np.sum(W))
    models = []
    for ob, (c_prev, u_prev, _) in zip(obs, prev):
        response = CouplingResponse(c_prev) if c_prev.coupled is not None and c_prev.n <= DENSE_CILIA else None
        dm = DesignModel(ob.carpet, ob.X, chi, moments=ob.mom, near=ob.near, response=response)
        models.append((dm, u_prev - dm.velocity(chi)))
    J_scale = 1.0

    def fun(x):
        counters["evaluations"] += 1
        c = x * B
        J, g = 0.0, np.zeros(N)
        for w, ob, (dm, shift) in zip(W, obs, models):
            Js, gs = ob.expected(dm, shift, c, True)
            J += w * Js
            g += w * gs
        dc = (c - chi0) / B
        J += Wsum * reg * float(np.sum(dc ** 2)) / N
        g = g + Wsum * 2.0 * reg * dc / (B * N)
        if edges.size:
            de = (c[edges[:, 0]] - c[edges[:, 1]]) / B
            J += Wsum * smooth * float(np.sum(de ** 2)) / len(edges)
            ge = Wsum * 2.0 * smooth * de / (B * len(edges))
            g = g + np.bincount(edges[:, 0], ge, N) - np.bincount(edges[:, 1], ge, N)
        return J / J_scale, g * (B / J_scale)

    def penalty(j, vals, chi_now):
        return Wsum * ob0.penalty(j, vals, chi_now)

    P = sum(ob.P for ob in obs)
    with solver_threads(3 * N * P):
        J_scale = max(fun(chi / B)[0], 1e-300)
        opts = {"gtol": 1e-10, "ftol": ftol, "maxiter": maxiter}
        res = minimize(fun, chi / B, jac=True, method="L-BFGS-B", bounds=[(-1.0, 1.0)] * N, options=opts)
        counters["iterations"] += int(res.nit)
        for _ in range(int(sweeps)):
            chi_k = np.clip(res.x * B, -B, B)
            sparts = [(w, dm, ob.near, dm.velocity(chi_k) + shift, ob.terms)
                      for w, ob, (dm, shift) in zip(W, obs, models)]
            chi_s, moved = joint_sweep(sparts, chi_k, grid, penalty)
            counters["sweeps"] += 1
            if moved == 0 or not fun(chi_s / B)[0] < float(res.fun) * (1.0 - 1e-6):
                break
            counters["swept_cilia"] += moved
            res2 = minimize(fun, chi_s / B, jac=True, method="L-BFGS-B", bounds=[(-1.0, 1.0)] * N, options=opts)
            counters["iterations"] += int(res2.nit)
            logger.info("program: sweep moved %d cilia; model objective %.4g -> %.4g of its start", moved,
                        float(res.fun), float(res2.fun))
            if not res2.fun < res.fun:
                break
            res = res2
    return res, float(res.fun) * J_scale


def _program_result(states, obs, infos, best, res, local, J_loc, B, W, check_tol, counters, clock) -> Program:
    """Each state's final check (error bar at most half its threshold) and Design, and the
    program's message."""
    chi = best["chi"]
    designs, resting = [], []
    for s, ob, (inside_info, done), (c, u, e), (rms_loc, Jl) in zip(states, obs, infos, best["checked"], local):
        resid = ob.residual(u)
        b = {"chi": chi, "u": u, "resid": resid, "rms": ob.wrms(resid), "bound": e, "carpet": c,
             "J": ob.score(u, chi, c), "label": best["label"], "res": best["res"]}
        chi_f, u_f, resid_f, rms_f, r_err = final_check(ob, b, s.threshold, check_tol)
        d = design_result(ob, b, res, chi_f, u_f, resid_f, rms_f, r_err, rms_loc, Jl, inside_info, done, s.threshold,
                          clock)
        rest = tuple(np.nonzero(np.abs(chi) > ob.mom.cutoff)[0].tolist())
        verdict = "met" if s.threshold is None or rms_f <= s.threshold else "NOT met"
        thr = "" if s.threshold is None else f" of {s.threshold:g}"
        d = replace(d, message=f"state {s.name} (chi_E = {s.chi_E:g}): {d.message}; {len(rest)} of {ob.N} cilia rest "
                    f"in this field; target {verdict} (rms {rms_f:.3g} +- {r_err:.2g}{thr})")
        designs.append(d)
        resting.append(rest)
    last = best["res"] if best["res"] is not None else res
    status = "success" if (last is not None and last.success) else "inaccurate"
    counters["seconds"] = _time.perf_counter() - clock
    prog = Program(chi_N=chi.copy(), states=tuple(s.name for s in states), designs=tuple(designs),
                   weights=tuple(float(w) for w in W), bound=float(B), objective=float(best["J"]),
                   local_objective=float(J_loc), returned=best["label"], resting=tuple(resting), status=status,
                   work=dict(counters))
    lim = prog.limiting
    parts = "; ".join(f"{n}: rms {d.residual_rms:.3g} +- {d.residual_error:.2g}"
                      + ("" if d.threshold is None else f" / {d.threshold:g}") for n, d in zip(prog.states, designs))
    if lim is None:
        verdict = "no thresholds"
    elif lim[1] <= 1:
        verdict = f"every state met (closest to its threshold: {lim[0]}, at {lim[1]:.2f} of it)"
    else:
        bad = [n for n, m in zip(prog.states, prog.met) if not m]
        verdict = (f"NOT every state met: {', '.join(bad)} (limiting: {lim[0]}, its rms {lim[1]:.2f}x its "
                   "threshold)")
    msg = (f"program of {len(states)} states on {chi.size} cilia: {parts}; {verdict}; returned the {best['label']} "
           f"layout (joint objective {best['J']:.4g}, local layout {J_loc:.4g}); {counters['seconds']:.1f} s")
    logger.info("%s", msg)
    return replace(prog, message=msg)


def program_dataset(program: Program):
    """The program's layout as an xarray Dataset: per cilium its base point, chi_N and phase;
    per state ``<name>_`` variables (the thrust angle in that field, ``<name>_resting``, and over
    the state's own ``<name>_control`` dimension its control points, target, achieved flow and
    residual) and attributes (``<name>_chi_E``, ``<name>_residual_rms``, ...), as
    :meth:`~ciliary_carpet.design.result.Design.to_dataset` writes one state."""
    import xarray as xr

    c0 = program.designs[0].carpet
    ds = xr.Dataset(
        {"x": ("cilium", c0.bases[:, 0], {"long_name": "base point x", "units": "L"}),
         "y": ("cilium", c0.bases[:, 1], {"long_name": "base point y", "units": "L"}),
         "chi_N": ("cilium", program.chi_N, {"long_name": "natural curvature chi_N = L kappa_N", "units": "1"}),
         "phase": ("cilium", c0.phases, {"long_name": "beat phase at t = 0", "units": "1"})},
        attrs={"states": list(program.states), "bound": program.bound, "objective": program.objective,
               "local_objective": program.local_objective, "returned": program.returned, "status": program.status,
               "message": program.message, "eta": c0.table.eta, "direction": c0.direction})
    for n, d, rest in zip(program.states, program.designs, program.resting):
        sub = d.to_dataset(d.carpet)
        for v in ("thrust_angle", "near_cutoff"):
            ds[f"{n}_{v}"] = sub[v]
        r = np.zeros(c0.n, np.int8)
        r[list(rest)] = 1
        ds[f"{n}_resting"] = ("cilium", r, {"long_name": f"rests in state {n} (beyond its flutter cutoff)",
                                             "units": "1"})
        for v in ("control_x", "control_y", "target_u", "target_v", "u", "v", "residual", "speed_ratio"):
            if v in sub:
                ds[f"{n}_{v}"] = sub[v].rename({"control": f"{n}_control"})
        for a in ("chi_E", "target_kind", "residual_rms", "residual_error", "local_rms", "message"):
            ds.attrs[f"{n}_{a}"] = sub.attrs[a]
        ds.attrs[f"{n}_weight"] = program.weights[program.states.index(n)]
        if d.threshold is not None:
            ds.attrs[f"{n}_threshold"] = d.threshold
    return ds
