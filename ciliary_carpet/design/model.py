"""The design model: the carpet's cycle-mean flow at the control points as a smooth function of
the curvatures chi_N, with its exact gradient (what :func:`~ciliary_carpet.design.inverse.design_layout`
minimises between full-model checks).

Design model
------------
The design works on the steady (cycle-averaged) flow at control points x_k. Each cilium j is
represented by the carpet's dipole carriers (:func:`~ciliary_carpet.carpet.carriers.dipole_forces`):
three point forces at c_j + delta_j e_m (e_m at 0, 120, 240 degrees,
:data:`~ciliary_carpet.carpet.carriers.DESIGN_DIPOLE`; delta_j = a_j / 2) that carry the
cycle-mean force Fbar(chi_j) and its first moment Dbar(chi_j) about the force centre c_j,

    f_jm(chi) = Fbar(chi) / 3 + 2 / (3 delta_j) Dbar(chi)^T e_m,
    u_k(chi) = 1/(8 pi mu) sum_{j, m} G(x_k - c_j - delta_j e_m) f_jm(chi_j),

with Blake's tensor for G when the carpet has a wall. Fbar, Dbar, the centre offset and the
swept radius are functions of chi_N alone (in the field frame);
:class:`~ciliary_carpet.design.moments.CycleMoments` samples them once from the table's cycle
data (the carpet's own moment code) and interpolates
them with cubic splines, whose chi_N derivatives give the exact gradient. The geometry (c_j,
delta_j) is frozen during one inner solve and refreshed between passes.

Near field. The carriers stand for a cilium only a few swept radii away; for every pair of a
control point and a cilium whose base lies within :data:`NEAR_RADIUS` (2 L) of it the model
uses the pair's exact resolved mean flow instead, tabulated in chi_N (:class:`NearField`):

    u_k(chi) = carriers(chi) + sum_{j near k} [v_kj(chi_j) - carriers_kj(chi_j)].

The carriers alone are 44 % rms off the full model at 300 scattered points over 144 cilia
above a wall 0.5 L below (5 % in free space), almost all of it within a swept radius of a
cilium, and the defect correction below, a constant shift, cannot follow that as chi moves;
with the near field 0.15 % (0.05 % free). The near field is what makes points inside swept
regions usable (``inside_swept``) and designs above a wall reach their threshold.


Gradient. dJ/dchi_j = sum_m g(c_jm) . f_jm'(chi_j) with g(y) = sum_k G(x_k - y)^T dJ/du_k
(:meth:`DesignModel.gradient`): one more Stokeslet sum with sources and targets swapped.

Coupled carpets (``coupling = "mean"``). The cilia then beat in the flows U_j the others make,
and a change of curvature moves every cilium's force through the flow. The model linearises that
at each pass's coupled state (:class:`~ciliary_carpet.carpet.coupling.CouplingResponse`): each
cilium's mean force changes as the table says at its own flow, dF_U = Fbar(chi, U) - Fbar(chi_geom, U),
and the others answer, dF^c = (I - P A)^{-1} dF_U (P = d Fbar / d U, A the monopole flow between
the force centres); the difference dF^c - dF_0 from the still-fluid change the carriers hold is
spread over the three carriers, and its gradient is the adjoint solve (I - P A)^{-T}. Measured on
6 x 6 cilia: a curvature change moves the coupled carpet's flow at control points among the cilia
as this model says to 7 %, against 27 % for the still-fluid model (5 % is the still model's own
error against the uncoupled carpet). Dense: for at most
:data:`~ciliary_carpet.carpet.coupling.DENSE_CILIA` cilia; above, the design's full-model checks
alone carry the coupling (the defect correction).

Also here: the objective's angle term (:func:`angle_objective`, :func:`angle_terms`), the speed
floor's reference (:func:`floor_reference`), the sweep out of local minima (:func:`sweep`) and the
threads of a solve (:func:`solver_threads`).

One concept over 500 lines: the design model's flow, its carriers and their exact gradient.
"""
from __future__ import annotations

import contextlib
import logging
import math
import time as _time
import warnings

import numpy as np
from scipy.interpolate import CubicSpline

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.carpet.carriers import DESIGN_DIPOLE, dipole_forces
from ciliary_carpet.design.moments import CycleMoments, cycle_moments
from ciliary_carpet.stokes import Treecode, Wall, make_kernel, stokeslet_velocity, stokeslet_velocity_ranges

logger = logging.getLogger(__name__)

__all__ = ["NearField", "DesignModel", "GOOD_ENOUGH", "NEAR_RADIUS", "NEAR_CHI_SAMPLES", "TREE_PAIRS", "SERIAL_PAIRS",
           "FLOOR_RADIUS_SPACINGS", "SWEEP_RADIUS", "carrier_forces", "floor_reference", "angle_objective",
           "angle_terms", "sweep", "solver_threads"]

FLOOR_RADIUS_SPACINGS = 5.0
"""The speed floor's reference is the flow of the straight cilia within this many spacings of
the control point (``floor_radius`` of :func:`~ciliary_carpet.design.inverse.design_layout`; see :mod:`ciliary_carpet.design.inverse`)."""
SERIAL_PAIRS = 200_000
"""Kernel sums with fewer (target, source) pairs than this run on one numba thread in the design."""
GOOD_ENOUGH = 0.2
"""Given a threshold, :func:`design_layout` starts no further pass once the full-model rms
residual is at most this fraction of it: the design's job is the threshold, and what a further
pass gains is then below the error bar the design may state (half the threshold)."""
TREE_PAIRS = 3e7
"""The design model sums through a :class:`~ciliary_carpet.stokes.treecode.Treecode` (opening angle
0.3: velocity error below 2e-4 relative, 1.5e-4 rad in angle; tests/test_treecode.py) from this
many control-point x carrier pairs on (about 3,000 cilia); below it directly (the direct sums
cost less there)."""



@contextlib.contextmanager
def solver_threads(pairs: int):
    """One BLAS thread for L-BFGS-B (its vectors are tiny: threads cost more than they save,
    the more so on a loaded machine), and one numba thread for the kernel sums when a sum has
    fewer than :data:`SERIAL_PAIRS` pairs (benchmarks/bench_design.py)."""
    import numba
    from threadpoolctl import threadpool_limits

    n0 = numba.get_num_threads()
    with threadpool_limits(limits=1, user_api="blas"):
        if pairs < SERIAL_PAIRS:
            numba.set_num_threads(1)
        try:
            yield
        finally:
            numba.set_num_threads(n0)



def carrier_forces(moments: CycleMoments, rot: np.ndarray, delta, chi, nu: int = 0) -> np.ndarray:
    """(N, 3, 2) carrier forces f_jm (lab frame; module docstring) of cilia at ``chi`` (N,) with
    carrier radii ``delta`` (N,), or their chi derivatives (nu = 1)."""
    m = moments(np.asarray(chi, dtype=float), nu)
    F = m["F"] @ rot.T
    D = rot @ m["D"] @ rot.T
    return dipole_forces(F, D, np.asarray(delta, dtype=float), DESIGN_DIPOLE)



NEAR_RADIUS = 2.0
"""The design model's near field (:class:`NearField`): the exact mean flow of every cilium whose
base lies within this distance [L] of a control point (the swept region of any curvature lies
within 1 L of the base; beyond 2 L the dipole carriers are accurate: see :class:`NearField`)."""
NEAR_CHI_SAMPLES = 65
"""Curvatures at which :class:`NearField` samples each near pair's mean flow (uniform on
[-chi_c, chi_c], interpolated by a cubic spline; see :class:`NearField` for its error)."""


class NearField:
    """The exact cycle-mean flow of the cilia near each control point, as smooth functions of chi_N.

    The dipole carriers of :class:`DesignModel` stand for a cilium only where their Taylor
    expansion holds, a few swept radii away; at a control point close to a cilium, and above all
    inside its swept region, they are wrong by as much as the flow itself (144 cilia, spacing
    2.5, a wall 0.5 L below, 300 scattered points: the carriers' flow is 44 % rms off the full
    model's, 5 % in free space, almost all of it from the points within one swept radius of a
    cilium). Above a wall, whose image system screens each cilium's far field (a force parallel
    to the wall makes a flow that decays like h^2 / R^3 in the plane), that near field is most
    of the flow, and the defect correction -- a constant shift -- cannot follow it as chi
    changes: this is what held designs above a wall at 0.15-0.2 rms.

    The mean flow of one cilium at a point depends only on its curvature and on the point's
    position relative to its base (the cycle average does not see the cilium's phase, and the
    wall is invariant under translations in the plane):

        v_kj(chi) = 1/(8 pi mu) 1/n_p sum_p sum_s w_s G(x_k - b_j, r(s, p; chi)) f(s, p; chi),

    the resolved mean flow of :meth:`Carpet.evaluate` (:class:`CycleMean`; the table's phase samples, Simpson
    weights w_s, the carpet's own kernel: regularised, with the wall when there is one). For
    every near pair (k, j), |x_k - b_j| <= ``radius`` (:data:`NEAR_RADIUS`), it is sampled at
    ``n_chi`` (:data:`NEAR_CHI_SAMPLES`) uniform curvatures on [-chi_c, chi_c] -- one
    Stokeslet sum per sample, from the sources of one cilium at that curvature to the relative
    positions of every pair -- and interpolated by a cubic spline (its derivative gives the
    exact gradient of the interpolant). The design model then adds, per near pair,
    v_kj(chi_j) minus the pair's carrier flow (:meth:`DesignModel.velocity`): the carriers stay
    in the sums for the far pairs only.

    Cost: n_distinct x n_chi x n_phase x n_s kernel evaluations once per design (4.9e8 for 900
    cilia at 900 scattered points, spacing 2.5).
    Interpolation error of the spline against the resolved flow computed directly between the
    samples (tests/test_design.py): 1.6e-3 of the pairs' largest flow for |chi_N| <= 120, up to
    1.1e-2 within 20 of the cutoff, where the cycle changes fastest and the thrust vanishes; what
    is left is in the defect correction (the full-model checks).

    Pairs with the same relative position (to 1e-9 L) share one sampled flow: on a lattice with
    control points at the cell centres there are only a few distinct ones, whatever the carpet's
    size (4 on a square lattice), so the near field costs next to nothing there.

    Attributes: ``k`` (n_pairs,) control point and ``j`` (n_pairs,) cilium of each pair, ``inv``
    (n_pairs,) its distinct relative position, ``grid`` (n_chi,) the sampled curvatures, ``vals``
    (n_chi, n_distinct, 2) the sampled flows, ``coef`` (4, n_chi - 1, n_distinct, 2) the spline's
    piecewise cubic coefficients, ``key`` (n_pairs,) k N + j (sorted), ``seconds`` the time to
    build it."""

    def __init__(self, carpet: Carpet, control, radius: float = NEAR_RADIUS, n_chi: int = NEAR_CHI_SAMPLES,
                 moments: CycleMoments | None = None):
        from scipy.spatial import cKDTree

        clock = _time.perf_counter()
        X = np.asarray(control, dtype=float)
        self.P, self.N = X.shape[0], carpet.n
        mom = moments if moments is not None else cycle_moments(carpet.table)
        lists = cKDTree(carpet.bases).query_ball_point(X, float(radius))
        cnt = np.array([len(x) for x in lists], np.int64)
        self.k = np.repeat(np.arange(self.P), cnt)
        self.j = np.concatenate([np.asarray(x, np.int64) for x in lists]) if cnt.sum() else np.zeros(0, np.int64)
        o = np.lexsort((self.j, self.k))  # by point, then cilium: ``key`` sorted
        self.k, self.j = self.k[o], self.j[o]
        cut = mom.cutoff
        self.grid = np.linspace(-cut, cut, int(n_chi))
        # the pairs' relative positions, each distinct one sampled once (on a lattice with cell-centre
        # control points there are a handful: 4 on a square lattice, however large the carpet)
        rel2 = X[self.k] - carpet.bases[self.j]
        _, first, self.inv = np.unique(np.round(rel2 * 1e9).astype(np.int64), axis=0, return_index=True,
                                       return_inverse=True)
        self.inv = self.inv.ravel()
        npair = first.size
        vals = np.zeros((self.grid.size, npair, 2))
        if npair:
            rel = np.column_stack([rel2[first], np.zeros(npair)])
            # one cilium per sampled curvature, far apart (no overlap), the carpet's field, kernel and table
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                ref = Carpet(np.column_stack([10.0 * np.arange(self.grid.size), np.zeros(self.grid.size)]),
                             self.grid, carpet.table.in_still_fluid(), None, carpet.direction, viscosity=carpet.mu,
                             wall=carpet.wall, backend=carpet.backend, blob=carpet.blob)
            c = ref.cycles
            wgt = c.weights / c.n_phase
            on = np.nonzero(c.flutter)[0]  # a still filament makes no flow
            if on.size:
                # one ranged sum: every pair's point against the sources of every sampled curvature
                pos, frc = ref.cycle_samples(on)
                blk = pos.shape[1] * pos.shape[2]
                src = np.zeros((on.size * blk, 3))
                src[:, :2] = (pos - ref.bases[on][:, None, None, :]).reshape(-1, 2)
                f = np.zeros_like(src)
                f[:, :2] = (frc * wgt[None, None, :, None]).reshape(-1, 2)
                tg = np.tile(rel, (on.size, 1))
                m = np.repeat(np.arange(on.size), npair)
                rng = np.ascontiguousarray(np.column_stack([m * blk, (m + 1) * blk]), dtype=np.int64)
                u = stokeslet_velocity_ranges(tg, src, f, np.arange(tg.shape[0] + 1, dtype=np.int64), rng,
                                              carpet.mu, kernel=ref.kernel, backend=carpet.backend)
                vals[on] = u[:, :2].reshape(on.size, npair, 2)
        self.vals = vals
        self.key = self.k * self.N + self.j  # sorted (the pairs come point by point, cilia in order)
        self.coef = CubicSpline(self.grid, vals, axis=0).c if npair else np.zeros((4, self.grid.size - 1, 0, 2))
        self.seconds = _time.perf_counter() - clock
        logger.info("near field: %d pairs (%d distinct relative positions) within %.3g L of %d control points, %d "
                    "curvatures, %.2f s", self.k.size, npair, radius, self.P, self.grid.size, self.seconds)

    def _pieces(self, chi):
        c = np.clip(np.asarray(chi, dtype=float)[self.j], self.grid[0], self.grid[-1])
        i = np.clip(np.searchsorted(self.grid, c, side="right") - 1, 0, self.grid.size - 2)
        t = (c - self.grid[i])[:, None]
        a = self.coef[:, i, self.inv, :]  # (4, n_pairs, 2)
        return a, t

    def pair_velocity(self, chi) -> np.ndarray:
        """(n_pairs, 2) the near pairs' mean flows v_kj(chi_j)."""
        a, t = self._pieces(chi)
        return ((a[0] * t + a[1]) * t + a[2]) * t + a[3]

    def pair_derivative(self, chi) -> np.ndarray:
        """(n_pairs, 2) d v_kj / d chi_j at chi_j."""
        a, t = self._pieces(chi)
        return (3.0 * a[0] * t + 2.0 * a[1]) * t + a[2]


class DesignModel:
    """The design model of ``carpet``'s mean flow at ``control`` (P, 2) points, with the carrier
    geometry (force centres c_j and carrier radii delta_j) frozen at the curvatures ``chi_geom``
    (see the module docstring): :meth:`velocity` (P, 2) for any chi (N,), :meth:`gradient` the
    exact vector-Jacobian product, both one Stokeslet sum of P x 3N pairs."""

    def __init__(self, carpet: Carpet, control, chi_geom, moments: CycleMoments | None = None,
                 near: NearField | None = None, response=None):
        self.carpet = carpet
        self.moments = moments if moments is not None else cycle_moments(carpet.table)
        X = np.asarray(control, dtype=float)
        self.X3 = np.column_stack([X, np.zeros(X.shape[0])])
        self.rot = carpet.rotation
        self.wall = None if carpet.wall is None else Wall(z=-float(carpet.wall))
        m = self.moments(np.asarray(chi_geom, dtype=float))
        cen = carpet.bases + m["offset"] @ self.rot.T
        self.delta = 0.5 * np.maximum(m["radius"], 1e-6)
        pos = cen[:, None, :] + self.delta[:, None, None] * DESIGN_DIPOLE[None]
        self.pos3 = np.column_stack([pos.reshape(-1, 2), np.zeros(3 * carpet.n)])
        # large carpets: the sums through a treecode over the frozen geometry (its A^T is the
        # exact transpose, so the gradient stays exact for the model it minimises)
        self.tree = Treecode(self.X3, self.pos3, make_kernel(self.wall), carpet.mu, carpet.backend) \
            if self.X3.shape[0] * self.pos3.shape[0] >= TREE_PAIRS else None
        # the near pairs: their exact flows (NearField) replace their carriers' flows, whose
        # kernel blocks Gc (n_pairs, 2, 3, 2) (velocity component, carrier, force component) are
        # subtracted from the carrier sum
        self.near = near if near is not None and near.j.size else None
        if self.near is not None:
            k, j = self.near.k, self.near.j
            npair = k.size
            self.Gc = self.pair_blocks(k, j)
        # a coupled carpet (CouplingResponse at chi_geom's coupled state): each cilium's mean force
        # changes as the table says at its own flow U_j, dF_U = F(chi, U) - F(chi_geom, U), and the
        # others answer through the flow: F^c - F^c_geom = (I + Q) dF_U; the carriers hold the
        # still-fluid change dF_0, so dF^c - dF_0 is spread over the three carriers (the near
        # pairs' exact flows stay those of still fluid)
        self.response = response
        if response is not None:
            g = np.asarray(chi_geom, dtype=float)
            self.F_ref = self.carriers(g).sum(axis=1)
            self.FU_ref = response.forces(g)

    def pair_blocks(self, k: np.ndarray, j: np.ndarray) -> np.ndarray:
        """(n, 2, 3, 2) the kernel blocks of the pairs (control point k, cilium j): the in-plane
        velocity at x_k of a unit in-plane force on each of cilium j's three carriers."""
        n = k.size
        out = np.empty((n, 2, 3, 2))
        ptr = np.arange(n + 1, dtype=np.int64)
        for m in range(3):
            rng = np.ascontiguousarray(np.column_stack([3 * j + m, 3 * j + m + 1]), dtype=np.int64)
            for b in range(2):
                f = np.zeros((self.pos3.shape[0], 3))
                f[:, b] = 1.0
                out[:, :, m, b] = stokeslet_velocity_ranges(self.X3[k], self.pos3, f, ptr, rng, self.carpet.mu,
                                                            wall=self.wall, backend=self.carpet.backend)[:, :2]
        return out

    def carriers(self, chi, nu: int = 0) -> np.ndarray:
        """(N, 3, 2) carrier forces (lab frame) at ``chi``, or their chi derivatives (nu = 1)."""
        return carrier_forces(self.moments, self.rot, self.delta, chi, nu)

    def velocity(self, chi) -> np.ndarray:
        """(P, 2) mean flow at the control points for curvatures ``chi`` (N,)."""
        f3 = self.carriers(chi)
        f = f3.reshape(-1, 2)
        if self.response is not None:
            dFU = self.response.forces(chi) - self.FU_ref
            dq = (dFU + self.response.apply(dFU) - (f3.sum(axis=1) - self.F_ref)) / 3.0
            f = (f3 + dq[:, None, :]).reshape(-1, 2)
        c = self.carpet
        if self.tree is not None:
            u = self.tree.apply(np.column_stack([f, np.zeros(f.shape[0])]))[:, :2]
        else:
            u = stokeslet_velocity(self.X3, self.pos3, np.column_stack([f, np.zeros(f.shape[0])]), c.mu,
                                   wall=self.wall, backend=c.backend)[:, :2]
        if self.near is not None:
            nf = self.near
            d = nf.pair_velocity(chi) - np.einsum("pamb,pmb->pa", self.Gc, f3[nf.j])
            u = u + np.column_stack([np.bincount(nf.k, d[:, 0], u.shape[0]), np.bincount(nf.k, d[:, 1], u.shape[0])])
        return u

    def gradient(self, chi, g_u) -> np.ndarray:
        """(N,) d/dchi_j of sum_k g_u[k] . u_k(chi): the adjoint Stokeslet sum from the control
        points to the carriers, contracted with the carriers' chi derivatives."""
        c = self.carpet
        g_u = np.asarray(g_u, dtype=float)
        if self.tree is not None:
            gp = self.tree.adjoint(np.column_stack([g_u, np.zeros(g_u.shape[0])]))[:, :2].reshape(c.n, 3, 2)
        else:
            gp = stokeslet_velocity(self.pos3, self.X3, np.column_stack([g_u, np.zeros(g_u.shape[0])]), c.mu,
                                    wall=self.wall, backend=c.backend)[:, :2].reshape(c.n, 3, 2)
        d1 = self.carriers(chi, 1)
        coupled = 0.0
        if self.response is not None:  # d/dchi_j of the carriers' ((I + Q) dF_U - dF_0) / 3
            h = gp.sum(axis=1) / 3.0
            z = h + self.response.adjoint(h)
            coupled = np.einsum("jb,jb->j", z, self.response.forces(chi, 1)) - np.einsum("jb,jb->j", h, d1.sum(axis=1))
        if self.near is None:
            return np.einsum("jkb,jkb->j", gp, d1) + coupled
        nf = self.near
        gk = g_u[nf.k]
        gp = gp.copy()
        np.subtract.at(gp, nf.j, np.einsum("pa,pamb->pmb", gk, self.Gc))
        out = np.einsum("jkb,jkb->j", gp, d1) + coupled
        return out + np.bincount(nf.j, np.sum(gk * nf.pair_derivative(chi), axis=1), c.n)


def floor_reference(carpet: Carpet, control, radius: float | None = None, spacing: float | None = None,
                    moments: CycleMoments | None = None) -> np.ndarray:
    """(P,) the speed floor's reference at the control points (P, 2): the speed of the flow that
    the straight cilia (chi_N = 0) whose force centre lies within ``radius`` of the point make
    there (design model; ``radius`` default :data:`FLOOR_RADIUS_SPACINGS` x ``spacing``, spacing
    default the median nearest-neighbour distance of the bases; ``inf``: every cilium), raised
    to at least a tenth of its median (points at the edge of the carpet).

    Why local: the straight carpet's own speed at a point sums the Stokeslets of every cilium
    (1/r), so it grows with the carpet's size, while the cross-stream flow a pattern of width w
    can make grows only with w; a floor on a fixed fraction of the whole carpet's speed then
    forbids large carpets the patterns small ones make (1000 cilia, focusing at 20 degrees:
    the design model's optimum under the whole-carpet floor is 0.054 rad, with this one 0.026)."""
    X = np.asarray(control, dtype=float)
    zero = np.zeros(carpet.n)
    dm = DesignModel(carpet, X, zero, moments=moments)
    if radius is None:
        if spacing is None:
            from scipy.spatial import cKDTree

            spacing = float(np.median(cKDTree(carpet.bases).query(carpet.bases, k=2)[0][:, 1])) \
                if carpet.n > 1 else 1.0
        radius = FLOOR_RADIUS_SPACINGS * float(spacing)
    radius = float(radius)
    if not radius > 0:
        raise ValueError(f"floor_radius must be > 0 (L), got {radius!r}")
    s = _local_speed(dm, zero, radius)
    return np.maximum(s, 0.1 * float(np.median(s)) + 1e-300)


def _local_speed(dm: "DesignModel", chi: np.ndarray, radius: float) -> np.ndarray:
    return np.linalg.norm(_local_velocity(dm, chi, radius), axis=1)


def _local_velocity(dm: "DesignModel", chi: np.ndarray, radius: float) -> np.ndarray:
    """(P, 2) the flow at each control point of the cilia whose force centre lies within
    ``radius`` of it (design model at ``chi``; every cilium when radius is infinite)."""
    f = dm.carriers(chi).reshape(-1, 2)
    F3 = np.column_stack([f, np.zeros(f.shape[0])])
    if not math.isfinite(radius):
        return stokeslet_velocity(dm.X3, dm.pos3, F3, dm.carpet.mu, wall=dm.wall, backend=dm.carpet.backend)[:, :2]
    from scipy.spatial import cKDTree

    cen = dm.pos3[:, :2].reshape(-1, 3, 2).mean(axis=1)
    lists = cKDTree(cen).query_ball_point(dm.X3[:, :2], radius)
    cnt = np.array([len(x) for x in lists], np.int64)
    ptr = np.concatenate([[0], np.cumsum(cnt)]).astype(np.int64)
    j = np.concatenate([np.asarray(x, np.int64) for x in lists]) if cnt.sum() else np.zeros(0, np.int64)
    ranges = np.column_stack([3 * j, 3 * j + 3]).astype(np.int64)
    return stokeslet_velocity_ranges(dm.X3, dm.pos3, F3, ptr, ranges, dm.carpet.mu, wall=dm.wall,
                                     backend=dm.carpet.backend)[:, :2]


def angle_objective(u, target, floor, weight: float = 1.0, point_weights=None) -> tuple[float, np.ndarray]:
    """J = sum_k c_k [(1 - uhat_k . t_k) + (w/2) max(0, 1 - u_k . t_k / floor_k)^2] and dJ/du
    (P, 2) for velocities ``u`` (P, 2), unit target directions ``target`` (P, 2) and speed
    floors ``floor`` (P,) (no floor term where floor is 0 or w = 0), with c_k = 1/P, or with
    ``point_weights`` omega_k (P,) c_k = omega_k / sum omega; see :mod:`ciliary_carpet.design.inverse`."""
    P = u.shape[0]
    c = np.full(P, 1.0 / P) if point_weights is None else \
        np.asarray(point_weights, dtype=float) / max(float(np.sum(point_weights)), 1e-300)
    nrm = np.maximum(np.linalg.norm(u, axis=1), 1e-300)
    uh = u / nrm[:, None]
    cos = np.sum(uh * target, axis=1)
    J = float(np.sum(c * (1.0 - cos)))
    g_u = -(target - uh * cos[:, None]) * (c / nrm)[:, None]
    floor = np.broadcast_to(np.asarray(floor, dtype=float), (P,))
    if weight > 0 and np.any(floor > 0):
        on = floor > 0
        h = np.zeros(P)
        h[on] = np.maximum(0.0, 1.0 - np.sum(u[on] * target[on], axis=1) / floor[on])
        J += 0.5 * weight * float(np.sum(c * h ** 2))
        g_u[on] -= weight * (c[on] * h[on] / floor[on])[:, None] * target[on]
    return J, g_u


def angle_terms(u, target, floor, weight: float, c) -> np.ndarray:
    """The per-point terms of :func:`angle_objective` (their sum is J) for flows ``u`` (..., n, 2)
    at n points with targets, floors and point factors c_k (n,)."""
    nrm = np.maximum(np.linalg.norm(u, axis=-1), 1e-300)
    dot = np.sum(u * target, axis=-1)
    out = 1.0 - dot / nrm
    if weight > 0:
        on = floor > 0
        h = np.where(on, np.maximum(0.0, 1.0 - dot / np.where(on, floor, 1.0)), 0.0)
        out = out + 0.5 * weight * h ** 2
    return c * out


SWEEP_RADIUS = 6.0
"""The sweep (:func:`sweep`) counts the change of the objective at the control points within
this distance [L] of the cilium it moves (the others change by its far field only)."""


def sweep(dm: DesignModel, near: NearField, chi: np.ndarray, u: np.ndarray, terms, penalty,
           radius: float = SWEEP_RADIUS) -> tuple[np.ndarray, int]:
    """One Gauss-Seidel sweep over the cilia on the design model: in turn, each cilium's chi_N is
    set to the best of the curvatures ``near.grid`` (all of [-chi_c, chi_c], both signs) with
    the others fixed, when that lowers the objective.

    Why: the objective is not convex in chi. Each cilium's flow traces a curve as chi_N runs
    over its branch (the thrust turns and shrinks toward the cutoff, the swept region moves), so
    a cilium whose neighbours' flows pull the wrong way at the start settles on the wrong side
    of that curve (typically the wrong sign of chi_N) and a gradient method cannot leave it: on
    144 cilia above a wall, a reachable target stopped at 0.081 rms with 8 cilia off by more
    than 30 (their signs flipped); one sweep and a second L-BFGS-B solve reach 1e-3.

    ``u`` (P, 2): the model's flow at ``chi`` (the defect included); ``terms(u_sub, ks)``: the
    per-point objective terms of flows u_sub (..., n, 2) at control points ks (n,), whose sum
    over all points is the data term; ``penalty(j, values, chi)``: the change of the regularisers
    when chi_j takes ``values`` (the others at ``chi``). The change of a cilium's flow is taken exactly (near pairs from
    the table, the others from its carriers) at the control points within ``radius``; beyond, it
    is left out of the decision (the caller keeps the sweep only if the full design model's
    objective fell). Returns the new chi and the number of cilia moved."""
    from scipy.spatial import cKDTree

    c = dm.carpet
    N, grid = c.n, near.grid
    lists = cKDTree(dm.X3[:, :2]).query_ball_point(c.bases, float(radius))
    cnt = np.array([len(x) for x in lists], np.int64)
    ptr = np.concatenate([[0], np.cumsum(cnt)])
    jj = np.repeat(np.arange(N), cnt)
    kk = np.concatenate([np.asarray(x, np.int64) for x in lists]) if cnt.sum() else np.zeros(0, np.int64)
    G = dm.pair_blocks(kk, jj)
    key = kk * N + jj
    pos = np.clip(np.searchsorted(near.key, key), 0, max(near.key.size - 1, 0))
    is_near = near.key[pos] == key if near.key.size else np.zeros(key.size, bool)
    ng = grid.size
    Fg = carrier_forces(dm.moments, dm.rot, np.repeat(dm.delta, ng), np.tile(grid, N)).reshape(N, ng, 3, 2)
    chi = np.array(chi, dtype=float)
    f_cur = dm.carriers(chi)
    v_cur = near.pair_velocity(chi)
    u = np.array(u, dtype=float)
    moved = 0
    for j in range(N):
        sl = slice(ptr[j], ptr[j + 1])
        ks = kk[sl]
        if ks.size == 0:
            continue
        du = np.einsum("pamb,gmb->gpa", G[sl], Fg[j] - f_cur[j])
        nm = is_near[sl]
        if nm.any():
            pi = pos[sl][nm]
            du[:, nm] = near.vals[:, near.inv[pi]] - v_cur[pi][None]
        base = terms(u[ks], ks)
        dJ = np.sum(terms(u[ks][None] + du, ks) - base[None], axis=1) + penalty(j, grid, chi)
        m = int(np.argmin(dJ))
        if dJ[m] < -1e-12 * max(float(np.sum(base)), 1e-300):
            chi[j] = grid[m]
            u[ks] += du[m]
            f_cur[j] = Fg[j, m]
            if nm.any():
                v_cur[pos[sl][nm]] = near.vals[m, near.inv[pos[sl][nm]]]
            moved += 1
    return chi, moved

