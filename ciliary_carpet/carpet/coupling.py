"""Cilia that feel the flow: the self-consistent (coupled) carpet.

The uncoupled carpet superposes filaments that each beat as if the fluid around them were at
rest. In a coupled carpet each cilium j beats in the uniform background flow U_j that all the
*other* cilia make, on average over their cycles, at its force centre c_j:

    U_j = M_j(U) = u_others,j(c_j; U),   j = 1 .. N,                                   (1)

where u_others,j is the cycle-mean flow of the carpet whose cilia beat in the flows U minus
cilium j's own (:meth:`Carpet.others_mean_flow <ciliary_carpet.carpet.carpet.Carpet.others_mean_flow>`),
and each cilium's cycle, period and thrust come from a thrust table over the background flow
(:mod:`single_cilium.flowtable`; its ``U_par`` along the field, ``U_perp`` across it) at U_j.
U_j is the flow at one point: how much the others' flow varies along a filament is what the
omissions' interaction ratio measures.

Frames. Every U_j, M_j, thrust and force here is a 2-vector in cilium j's 2D frame
(:class:`~ciliary_carpet.carpet.geometry.Embedding`: a vector v of the frame is ``axes_j @ v``
in space, ``axes_j`` (3, 2) with orthonormal columns), and only the flow's part in that frame
enters, M_j = axes_j^T u_others,j(c_j):

* planar carpet: the frame is the lab plane z = 0 (axes e_x, e_y; the table reads
  ``rotation^T U_j``), the centres c_j lie in it; above a wall the mean flow there has a small
  component along e_z, which the planar filaments cannot feel;
* standing carpet: the frame is cilium j's beat plane (axes e_psi_j, e_z; the field frame
  itself, ``rotation`` the identity), c_j its force centre in space, above the substrate:
  U_j = (u . e_psi_j, u . e_z) = (``U_perp``, ``U_par``); the horizontal component along
  e_z x e_psi_j, normal to the beat plane, is what it cannot feel.

The part normal to each frame, w_j = u_others,j . (axes_j[:, 0] x axes_j[:, 1]), is reported as
:attr:`Coupling.normal_flow`.

Solver: Newton's method on R(U) = U - M(U) with an approximate Jacobian, each step solved
exactly for that approximation,

    (I - A B(U)) dU = -R(U),      U <- U + lambda dU,

where B(U) = blockdiag(d Fbar_j / d U_j) is each cilium's mean-thrust derivative (the table's
splines, central differences of step :data:`DU`, in each cilium's 2D frame) and A the cycle-mean
flow at the other cilia's centres of point forces at the centres (the carpet's kernel, blob and
wall; no self term): block (i, j) is axes_i^T G(c_i, c_j) axes_j / (8 pi mu) for i != j and zero
for i = j, a force f_j of cilium j's frame acting along axes_j f_j at c_j in space and the
velocity at c_i read in cilium i's frame (each cilium's own point force is left out of the sum
at its centre: the self term G(c_j, c_j) of the regularised kernel and its wall image differs
from cilium to cilium when their heights differ): the far field of each cilium, with its dipole
and higher moments, and the near field of its resolved line frozen at the current step. The error
of that Jacobian only slows the convergence (it stays linear, with the rate the neglected
moments' share of dM/dU); every residual is of the full model (1). A carpet much larger than
its cilia's reach needs Newton: the plain iteration U <- M(U) diverges once |A B| > 1 (the
2-norm, which grows with the number of cilia a cilium's flow reaches), because every cilium then
answers the flow it is pushed with by a push back larger than the cause. The
step is damped (lambda = 1, 1/2, 1/4, ..., at most :data:`MAX_HALVINGS` times) until the
residual falls and every U_j lies in the table's flow grid. The linear solve is GMRES
(matrix-free: one Stokeslet sum over the centres per product, each centre's own term left out;
relative tolerance :data:`GMRES_RTOL`). A has zero diagonal blocks (no self term), so
trace(A B) = 0 and A B has eigenvalues of both signs of real part; where I - A B stays far from
singular, GMRES takes tens of products.

Stops when the residual ``max_j |R_j| / max_j |M_j|`` is at most ``rtol`` (default
:data:`RTOL`, ten times the evaluation's tolerance ``tol``: a smaller residual would be below
the error of M itself), or, unconverged, after ``max_iter`` steps (``status = "max_iter"``) or
when no damped step lowers it (``"stalled"``); the result says which and what to change. A flow
outside the table's grid raises :class:`CouplingError` naming the cilium, its flow and the grid.

The linear estimate without a flow table (:func:`coupling_estimate`). A carpet whose table is for
still fluid cannot be solved, but the size of the coupling can be estimated: with the slender-body
drag of a straight filament along the field, d Fbar_j / d U_j = -eta L (t t^T + 2 (I - t t^T))
(t the field direction in each cilium's 2D frame: ``rotation[:, 1]``, e_z's (0, 1) for a standing
cilium), the linear coupled flow solves (I - A B) U = M(0): how far the uncoupled flow M(0) is from
it is the coupling's size in the summary of an uncoupled carpet.

One concept over 500 lines: the coupled solve, its operator and its estimates.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse.linalg import LinearOperator, gmres

from single_cilium.tablefile import TableError

from ciliary_carpet.stokes import Wall, make_kernel, stokeslet_velocity_ranges

logger = logging.getLogger(__name__)

__all__ = ["Coupling", "CouplingError", "CouplingResponse", "couple", "coupling_estimate", "COUPLINGS", "DENSE_CILIA", "RTOL", "DU", "GMRES_RTOL", "LOOSE_TOL",
           "MAX_HALVINGS", "MAX_ITER"]

COUPLINGS = ("none", "mean")
"""The carpet models of the scene key ``[carpet] coupling``: ``"none"`` (each cilium beats as in
still fluid), ``"mean"`` (each beats in the others' mean flow at it, solved self-consistently)."""
RTOL = 1e-3
"""Default relative residual of the coupled solve."""
DU = 1e-3
"""Step (L / tau) of the central differences of the mean thrust in the flow."""
RESPONSE_CHI_SAMPLES = 97
"""Curvatures at which :meth:`CouplingResponse.forces` samples each cilium's thrust in its frozen
flow (uniform over the table's chi_N range, both signs)."""
DENSE_CILIA = 2000
"""Most cilia of a :class:`CouplingResponse` (dense: 4 N^2 numbers, 128 MB at 2000)."""
GMRES_RTOL = 1e-6
"""Relative tolerance of the Newton step's linear solve."""
MAX_HALVINGS = 6
"""Most halvings of a Newton step."""
MAX_ITER = 20
"""Default most Newton steps."""
LOOSE_TOL = 1e-2
"""Tolerance of the evaluations of M before the certifying one (:func:`couple`): the levels of
detail's bound is loose (their error lies well under it), and a looser evaluation costs less."""


class CouplingError(ValueError):
    """The coupled carpet cannot be solved: the flow it needs lies outside the thrust table's flow
    grid, or the table is for still fluid."""


@dataclass(frozen=True, eq=False)
class Coupling:
    """The coupled carpet and how it was found.

    Attributes
    ----------
    carpet : Carpet
        The coupled carpet (``background`` = U).
    background : (N, 2) ndarray
        U_j, the others' mean flow at each cilium's force centre (L / tau), its part in the
        cilium's 2D frame (module docstring: the lab plane's (x, y) for a planar carpet,
        (u . e_psi_j, u . e_z) in the beat plane for a standing one).
    uncoupled : (N, 2) ndarray
        M(0), the others' mean flow at each cilium of the uncoupled carpet, in the same frames
        (at :data:`LOOSE_TOL`; evaluated on first use when the solve started from a first guess).
    residual, rtol : float
        max_j |U_j - M_j(U)| / max_j |M_j(U)| at the end, and the one asked.
    history : tuple
        The residual after each Newton step (the first entry at the first guess: still fluid,
        or ``couple``'s ``start``; the last at the certifying tolerance).
    iterations, evaluations : int
        Newton steps taken; evaluations of M (the uncoupled M(0) and the certifying one included).
    status, message : str
        ``"converged"``, ``"max_iter"`` or ``"stalled"``; what happened and what to change.
    contraction : float
        abs(A B) estimated by the power method at the solution (above 1 the plain iteration
        U <- M(U) would diverge).
    normal_flow : float
        max_j abs(w_j) / max_j abs(U_j) (the denominator the largest component of U), w_j the
        others' mean flow's component normal to cilium j's 2D frame at its centre, which it
        cannot feel: along e_z for a planar carpet (zero in free space), horizontal and normal
        to the beat plane (along e_z x e_psi_j) for a standing one.
    wall_s : float
        Seconds spent."""

    carpet: Carpet
    background: np.ndarray
    _uncoupled: np.ndarray | None
    residual: float
    rtol: float
    history: tuple
    iterations: int
    evaluations: int
    status: str
    message: str
    contraction: float
    normal_flow: float
    wall_s: float

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    @property
    def uncoupled(self) -> np.ndarray:
        if self._uncoupled is None:  # the carpet in still fluid, made once, on demand
            still = replace(self.carpet, background=None)
            object.__setattr__(self, "_uncoupled", _in_frames(still, still.others_mean_flow(tol=LOOSE_TOL))[0])
        return self._uncoupled

    def change(self) -> dict:
        """How far the uncoupled flow at the cilia is from the coupled one: the median and largest
        |M(0)_j - U_j| / |U_j| over the fluttering cilia, and the median speeds |U_j|, |M(0)_j|."""
        fl = self.carpet.flutter
        u, u0 = self.background[fl], self.uncoupled[fl]
        s, s0 = np.linalg.norm(u, axis=1), np.linalg.norm(u0, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.linalg.norm(u0 - u, axis=1) / s
        rel = rel[np.isfinite(rel)]
        return {"median_speed_coupled": float(np.median(s)) if s.size else math.nan,
                "median_speed_uncoupled": float(np.median(s0)) if s0.size else math.nan,
                "relative_change_median": float(np.median(rel)) if rel.size else math.nan,
                "relative_change_max": float(np.max(rel)) if rel.size else math.nan}

    def summary(self) -> dict:
        return {"model": "mean", "status": self.status, "message": self.message, "residual": self.residual,
                "rtol": self.rtol, "iterations": self.iterations, "evaluations": self.evaluations,
                "history": list(self.history), "contraction": self.contraction, "normal_flow": self.normal_flow,
                "wall_s": self.wall_s, **self.change()}


def _kernel(carpet: Carpet):
    """The kernel of A: the carpet's wall (``Wall(z=-wall)``, the substrate of a standing carpet
    at ``wall = 0``), regularised at the filament radius (also for a carpet of singular Stokeslets:
    the point forces of A stand at the centres, not on the filaments)."""
    return make_kernel(None if carpet.wall is None else Wall(z=-float(carpet.wall)), carpet.filament_radius)


def _in_frames(carpet: Carpet, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flows ``u`` (N, 3) in space at the cilia, split: (N, 2) the part in each cilium's 2D frame,
    ``axes_j^T u_j``, and (N,) the component normal to it, ``u_j . (axes_j[:, 0] x axes_j[:, 1])``
    (along e_z for a planar carpet; along e_psi_j x e_z = -(e_z x e_psi_j), horizontal, for a
    standing one)."""
    ax = carpet.embedding.axes
    normal = np.cross(ax[:, :, 0], ax[:, :, 1])
    return np.einsum("jqa,jq->ja", ax, u), np.einsum("jq,jq->j", normal, u)


def _others_ranges(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The CSR lists of a ranged Stokeslet sum over ``n`` sources at ``n`` targets that leave each
    target's own source out: target i sums sources [0, i) and [i + 1, n)."""
    i = np.arange(n, dtype=np.int64)
    rng = np.empty((2 * n, 2), dtype=np.int64)
    rng[0::2, 0], rng[0::2, 1] = 0, i
    rng[1::2, 0], rng[1::2, 1] = i + 1, n
    return np.arange(0, 2 * n + 1, 2, dtype=np.int64), rng


def _operator(carpet: Carpet):
    """The product f -> A f, (2N,) -> (2N,) (2 components per cilium, each in its 2D frame): the
    cycle-mean flow at each centre c_i (:attr:`CycleData.centre3
    <ciliary_carpet.carpet.cycles.CycleData.centre3>`, in space) of point forces ``axes_j @ f_j``
    at the other centres j != i, read in cilium i's frame, ``axes_i^T u(c_i)`` (module docstring):
    the carpet's wall and viscosity, regularised at its filament radius (:func:`_kernel`). The
    self term (which differs from cilium to cilium with the centre's height above a wall) is left
    out of the sum itself, for each cilium (:func:`_others_ranges`), not subtracted: A's diagonal
    blocks are exactly zero."""
    c3 = np.ascontiguousarray(carpet.cycles.centre3)
    ax = carpet.embedding.axes
    n = c3.shape[0]
    kern = _kernel(carpet)
    ptr, rng = _others_ranges(n)

    def apply(f2: np.ndarray) -> np.ndarray:
        f = np.ascontiguousarray(np.einsum("jqa,ja->jq", ax, f2.reshape(n, 2)))
        u = stokeslet_velocity_ranges(c3, c3, f, ptr, rng, carpet.mu, kernel=kern, backend=carpet.backend)
        return np.einsum("jqa,jq->ja", ax, u).ravel()
    return apply


def _field_frame(carpet: Carpet, U: np.ndarray) -> dict:
    """The table's keywords for flows U (N, 2) in each cilium's 2D frame: ``U_perp`` along the
    field frame's e1, ``U_par`` along e2 (the field), ``rotation^T U_j`` (a standing carpet's
    rotation is the identity: its 2D frames are the field frames)."""
    u = U @ carpet.rotation
    return {"U_perp": u[:, 0], "U_par": u[:, 1]}


def _outside(carpet: Carpet, U: np.ndarray) -> np.ndarray:
    """(N,) whether U_j (N, 2, each cilium's 2D frame) lies outside the table's flow grid (after
    the mirror for chi_N < 0)."""
    (p0, p1), (q0, q1) = carpet.table.U_range
    k = _field_frame(carpet, U)
    q = np.where(carpet.chi_N < 0, -k["U_perp"], k["U_perp"])
    return (k["U_par"] < p0) | (k["U_par"] > p1) | (q < q0) | (q > q1)


def _thrust(table, chi, U_par, U_perp, nu: int = 0) -> np.ndarray:
    """(N, 2) the table's mean thrust (field frame) at (chi_N, U_par, U_perp), or its ``nu``-th
    chi_N derivative."""
    return np.stack([table.scalar(k, chi, nu, U_par=U_par, U_perp=U_perp) for k in ("thrust_x", "thrust_y")],
                    axis=-1)


def _thrust_derivative(carpet: Carpet, U: np.ndarray) -> np.ndarray:
    """(N, 2, 2) d Fbar_j / d U_j in each cilium's 2D frame (the lab plane of a planar carpet,
    the beat plane of a standing one), at flows U (N, 2) in those frames: central differences of
    step DU of the table's mean thrust (one-sided at the grid's edge), rotated from the field
    frame by ``rotation`` (the identity for a standing carpet)."""
    t, c, R = carpet.table, carpet.chi_N, carpet.rotation
    (p0, p1), (q0, q1) = t.U_range
    k = _field_frame(carpet, U)
    q, p = k["U_perp"], k["U_par"]
    sg = np.where(c < 0, -1.0, 1.0)  # the table's U_perp grid serves sg * U_perp

    J = np.empty((c.size, 2, 2))
    for col, (lo, hi, base) in enumerate(((q0, q1, q), (p0, p1, p))):
        mq = sg * q if col == 0 else base  # the grid coordinate of this component
        up = np.minimum(mq + DU, hi)
        dn = np.maximum(mq - DU, lo)
        h = up - dn
        a = (sg * up, p) if col == 0 else (q, up)
        b = (sg * dn, p) if col == 0 else (q, dn)
        J[:, :, col] = (_thrust(t, c, a[1], a[0]) - _thrust(t, c, b[1], b[0])) / (h * (sg if col == 0 else 1.0))[:, None]
    return R @ J @ R.T


def _gmres(matvec, rhs: np.ndarray) -> np.ndarray:
    n = rhs.size
    op = LinearOperator((n, n), matvec=matvec, dtype=float)
    x, info = gmres(op, rhs, rtol=GMRES_RTOL, atol=0.0, restart=60, maxiter=20)
    if info != 0:
        logger.warning("the coupled Newton step's linear solve stopped at info = %d (GMRES)", info)
    return x


def _others(carpet: Carpet, U: np.ndarray | None, tol: float) -> tuple[Carpet, np.ndarray]:
    """The carpet in the flows U (N, 2, each cilium's 2D frame) and the others' mean flow at its
    centres in space (N, 3)."""
    try:
        c = replace(carpet, background=U)
    except ValueError as exc:  # a TableError, or cilia that touch or (standing) dip below the substrate in U
        raise CouplingError(f"the coupled carpet cannot be built: {exc}") from None
    return c, c.others_mean_flow(tol=tol)


def _check_table(carpet: Carpet) -> None:
    (p0, p1), (q0, q1) = carpet.table.U_range
    if p0 == p1 and q0 == q1:
        raise CouplingError("coupling = \"mean\" needs a thrust table over the background flow (this one is for still "
                            "fluid): build one with build_table(chi_E, eta, chi_N, U_par=..., U_perp=...) or, in a "
                            "scene, [table.build] flow = U_max")


def couple(carpet: Carpet, tol: float = 1e-4, rtol: float = RTOL, max_iter: int = MAX_ITER) -> Coupling:
    """Solve the coupled carpet (1) of the module docstring by damped Newton steps.

    Parameters
    ----------
    carpet : the :class:`~ciliary_carpet.carpet.carpet.Carpet`, planar or standing
        (``coupling = "none"``); its ``background`` is the first guess of U (None: still fluid;
        e.g. the solution for nearby curvatures, which saves Newton steps); its table must be
        over the background flow. (A carpet made with ``coupling = "mean"`` calls this itself.)
    tol : the tolerance of the evaluation of the mean flow (:meth:`Carpet.others_mean_flow`)
        that certifies the solution. Inexact Newton: the evaluations before it are made at
        ``min(LOOSE_TOL, max(tol, res / 10))`` at the current residual ``res`` (and the uncoupled
        flow M(0) at :data:`LOOSE_TOL`); a residual at or below ``rtol`` is evaluated again at
        ``tol`` before it is accepted.
    rtol : the relative residual to reach (default :data:`RTOL`); at least ``tol``.
    max_iter : most Newton steps.

    Returns
    -------
    Coupling : the coupled carpet, the flows U (N, 2, each cilium's 2D frame), the residual
        history and the status.

    Raises
    ------
    CouplingError : a table for still fluid, a flow that leaves the table's grid (the message
        names the cilium, its flow and the grid), or a carpet that cannot be made in the flows
        (cilia that touch; a standing cilium that dips below its substrate).
    """
    if not hasattr(carpet, "others_mean_flow"):
        raise TypeError(f"carpet must be a Carpet, got {type(carpet).__name__}")
    rtol, tol = float(rtol), float(tol)
    if not (math.isfinite(rtol) and rtol > 0) or rtol < tol:
        raise ValueError(f"rtol must be a positive number, at least tol = {tol:g}, got {rtol!r}")
    if int(max_iter) < 0:
        raise ValueError(f"max_iter must be >= 0, got {max_iter!r}")
    _check_table(carpet)
    t0 = time.perf_counter()
    n = carpet.n
    loose = max(tol, LOOSE_TOL)
    # the first guess: the carpet itself (still fluid when it has no background)
    U = np.zeros((n, 2)) if carpet.background is None else np.array(carpet.background, dtype=float)
    if np.any(_outside(carpet, U)):
        carpet, U = replace(carpet, background=None), np.zeros((n, 2))
    cur, m = carpet, carpet.others_mean_flow(tol=loose)
    uncoupled = _in_frames(carpet, m)[0] if carpet.background is None else None
    evals, at = 1, loose  # evaluations of M; the tolerance of the current one

    def residual(U, m):
        M = _in_frames(carpet, m)[0]
        return (U - M), float(np.abs(U - M).max() / max(np.abs(M).max(), 1e-300))
    R, res = residual(U, m)
    history, status, it = [res], "max_iter", 0
    while True:
        if res <= rtol and at > tol:  # certify at the tolerance asked
            m = cur.others_mean_flow(tol=tol)
            evals += 1
            at = tol
            R, res = residual(U, m)
            history[-1] = res
        if res <= rtol:
            status = "converged"
            break
        if it >= int(max_iter):
            break
        tk = min(loose, max(tol, res / 10))  # inexact Newton: the evaluation a step's residual needs
        if at > 2 * tk:  # the current residual (about) that accurate before a step is taken from it
            # (by halves at least: at most log2(LOOSE_TOL / tol) such evaluations in a solve)
            m = cur.others_mean_flow(tol=tk)
            evals += 1
            at = tk
            R, res = residual(U, m)
            history[-1] = res
            continue
        B = _thrust_derivative(cur, U)
        A = _operator(cur)
        dU = _gmres(lambda x: x - A(np.einsum("jab,jb->ja", B, x.reshape(n, 2)).ravel()), -R.ravel()).reshape(n, 2)
        lam, accepted = 1.0, False
        for _ in range(MAX_HALVINGS + 1):
            Un = U + lam * dU
            if not np.any(_outside(carpet, Un)):
                cn, mn = _others(carpet, Un, tk)
                evals += 1
                Rn, rn = residual(Un, mn)
                if rn < res:
                    U, cur, m, R, res, at, accepted = Un, cn, mn, Rn, rn, tk, True
                    carpet = cur  # the next trial carpets are made from it; the one before can go
                    break
            lam *= 0.5
        it += 1
        if not accepted and at > tol:  # perhaps the evaluation's error: measure the residual at tol, then step again
            m = cur.others_mean_flow(tol=tol)
            evals += 1
            at = tol
            R, res = residual(U, m)
            history.append(res)
            continue
        if not accepted:
            out = _outside(carpet, U + dU)
            if np.any(out):
                j = int(np.flatnonzero(out)[0])
                k = _field_frame(carpet, (U + dU)[j:j + 1])
                (p0, p1), (q0, q1) = carpet.table.U_range
                raise CouplingError(
                    f"the coupled flow leaves the thrust table's flow grid: cilium {j} needs U_par = "
                    f"{float(k['U_par'][0]):.3g}, U_perp = {float(k['U_perp'][0]):.3g} L/tau (the grid spans U_par in "
                    f"[{p0:g}, {p1:g}], U_perp in [{q0:g}, {q1:g}]); build the table over a wider flow grid")
            status = "stalled"
            break
        history.append(res)
        logger.info("coupled carpet: Newton step %d, step length %g, residual %.3g", it, lam, res)
    # |A B| at the solution, by the power method (10 products)
    B = _thrust_derivative(cur, U)
    A = _operator(cur)
    x = np.random.default_rng(0).standard_normal(2 * n)
    rho = 0.0
    for _ in range(10):
        y = A(np.einsum("jab,jb->ja", B, x.reshape(n, 2)).ravel())
        ny = float(np.linalg.norm(y))
        rho = ny / float(np.linalg.norm(x))
        if ny == 0.0:  # one cilium, or none beating: no coupling
            break
        x = y / ny
    normal = float(np.abs(_in_frames(carpet, m)[1]).max() / max(np.abs(U).max(), 1e-300))
    msg = {"converged": f"coupled: residual {res:.2g} <= rtol {rtol:g} after {it} Newton steps ({evals} evaluations)",
           "max_iter": f"NOT converged: residual {res:.2g} > rtol {rtol:g} after {it} Newton steps; raise max_iter",
           "stalled": f"NOT converged: no damped Newton step lowered the residual {res:.2g} (rtol {rtol:g}); "
                      "loosen rtol or tighten tol (the evaluation's error may exceed the residual asked)"}[status]
    return Coupling(carpet=cur, background=U, _uncoupled=uncoupled, residual=res, rtol=rtol, history=tuple(history),
                    iterations=it, evaluations=evals, status=status, message=msg, contraction=rho, normal_flow=normal,
                    wall_s=time.perf_counter() - t0)


def coupling_estimate(carpet: Carpet, tol: float = 1e-4) -> dict:
    """The coupling's size without a flow table (module docstring): the linear coupled flow with
    the straight filament's slender-body drag against the uncoupled flow M(0) at the centres.
    Returns the medians of |M(0)_j| and |U_j| over the fluttering cilia and the median and largest
    |M(0)_j - U_j| / |U_j| (the uncoupled flow's error, in this estimate)."""
    n = carpet.n
    m0 = _in_frames(carpet, carpet.others_mean_flow(tol=tol))[0]
    t = carpet.rotation[:, 1]  # the field in each cilium's 2D frame
    P = np.outer(t, t)
    B = -float(carpet.table.eta) * (P + 2.0 * (np.eye(2) - P))
    A = _operator(carpet)
    U = _gmres(lambda x: x - A((x.reshape(n, 2) @ B.T).ravel()), m0.ravel()).reshape(n, 2)
    fl = carpet.flutter
    s, s0 = np.linalg.norm(U[fl], axis=1), np.linalg.norm(m0[fl], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.linalg.norm(m0[fl] - U[fl], axis=1) / s
    rel = rel[np.isfinite(rel)]
    nan = math.nan
    return {"model": "linear drag estimate", "median_speed_coupled": float(np.median(s)) if s.size else nan,
            "median_speed_uncoupled": float(np.median(s0)) if s0.size else nan,
            "relative_change_median": float(np.median(rel)) if rel.size else nan,
            "relative_change_max": float(np.max(rel)) if rel.size else nan}


class CouplingResponse:
    """How a coupled carpet's mean forces answer a change of its cilia's own (the design model's
    coupling, :class:`~ciliary_carpet.design.model.DesignModel`).

    Every vector here is in each cilium's 2D frame (module docstring), A the Newton step's
    (:func:`_operator`) as a dense matrix. At a coupled state (U, the carpet ``carpet`` with
    ``coupling = "mean"``), a change dF of the
    cilia's mean forces at fixed flows (a change of curvature: :meth:`forces`, the table's thrust
    at each cilium's own flow U_j) changes the flows by dU = A dF^c and the forces by P dU,
    P = blockdiag(d Fbar_j / d U_j), so that to first order (the monopole level of the solver's
    Jacobian, module docstring)

        dF^c = (I - P A)^{-1} dF,     Q = (I - P A)^{-1} - I:  dF^c = dF + Q dF.

    :meth:`apply` gives Q dF (N, 2) and :meth:`adjoint` Q^T h, each by the LU factors of the
    dense (2N, 2N) matrix I - P A, made once (for at most :data:`DENSE_CILIA` cilia: 4N^2 numbers;
    A assembled by one sparse Stokeslet sum of N^2 single-source blocks per force component).
    """

    def __init__(self, carpet):
        from scipy.linalg import lu_factor

        if carpet.coupled is None:
            raise ValueError("CouplingResponse needs a coupled carpet (coupling = \"mean\")")
        n = carpet.n
        if n > DENSE_CILIA:
            raise ValueError(f"CouplingResponse is dense: at most {DENSE_CILIA} cilia, got {n}")
        self.n = n
        U = carpet.coupled.background  # (N, 2): the carpet's own is None where the solve stayed at U = 0
        P = _thrust_derivative(carpet, U)  # (N, 2, 2)
        c3 = np.ascontiguousarray(carpet.cycles.centre3)
        ax = carpet.embedding.axes
        kern = _kernel(carpet)
        t = np.tile(c3, (n, 1))  # target t for source k at row k n + t
        ptr = np.arange(n * n + 1, dtype=np.int64)
        k = np.repeat(np.arange(n, dtype=np.int64), n)
        rng = np.column_stack([k, k + 1])
        # A[t, a, k, b]: component a (cilium t's frame) of the velocity at centre t of a unit force
        # along cilium k's frame axis b at centre k
        A = np.empty((n, 2, n, 2))
        for b in range(2):
            f = np.ascontiguousarray(ax[:, :, b])
            u = stokeslet_velocity_ranges(t, c3, f, ptr, rng, carpet.mu, kernel=kern, backend=carpet.backend)
            A[:, :, :, b] = np.einsum("tqa,ktq->tak", ax, u.reshape(n, n, 3))
        A[np.arange(n), :, np.arange(n), :] = 0.0  # the others only
        PA = np.einsum("jab,jbkc->jakc", P, A).reshape(2 * n, 2 * n)
        self._lu = lu_factor(np.eye(2 * n) - PA)
        self._table, self._rot = carpet.table, carpet.rotation
        self._flow = _field_frame(carpet, U)
        self._coef = self._grid = None

    def forces(self, chi, nu: int = 0) -> np.ndarray:
        """(N, 2) the cilia's mean forces (each cilium's 2D frame: the lab plane of a planar carpet,
        the beat plane of a standing one) at curvatures ``chi`` in the coupled state's flows U
        (frozen), or their chi derivatives (``nu = 1``): the table's thrust at (chi_j, U_j),
        sampled once per cilium at :data:`RESPONSE_CHI_SAMPLES` curvatures over the table's range
        and interpolated by a cubic spline in chi (its derivative for ``nu = 1``; the table
        itself interpolates its chi_N rows by splines, and the design corrects the model by the
        full model's defect, so this only saves the table's per-call cost)."""
        if self._coef is None:
            from scipy.interpolate import CubicSpline

            top = float(self._table.chi_N_range[1])
            self._grid = g = np.linspace(-top, top, RESPONSE_CHI_SAMPLES)
            n = self.n
            flow = {k: np.tile(v, g.size) for k, v in self._flow.items()}
            try:
                T = _thrust(self._table, np.tile(g[:, None], (1, n)).ravel(), **flow).reshape(g.size, n, 2)
            except TableError:  # a curvature of the grid the table does not serve: the table at each call
                self._coef = False
            else:
                self._coef = CubicSpline(g, np.nan_to_num(T), axis=0).c  # (4, G - 1, N, 2)
        if self._coef is False:
            return _thrust(self._table, np.asarray(chi, dtype=float), nu=nu, **self._flow) @ self._rot.T
        g = self._grid
        c = np.clip(np.asarray(chi, dtype=float), g[0], g[-1])
        i = np.clip(np.searchsorted(g, c, side="right") - 1, 0, g.size - 2)
        t = (c - g[i])[:, None]
        a = self._coef[:, i, np.arange(self.n), :]  # (4, N, 2)
        v = ((a[0] * t + a[1]) * t + a[2]) * t + a[3] if nu == 0 else (3.0 * a[0] * t + 2.0 * a[1]) * t + a[2]
        return v @ self._rot.T

    def apply(self, dF: np.ndarray) -> np.ndarray:
        """(N, 2) Q dF."""
        from scipy.linalg import lu_solve

        x = np.asarray(dF, dtype=float).reshape(-1)
        return (lu_solve(self._lu, x) - x).reshape(self.n, 2)

    def adjoint(self, h: np.ndarray) -> np.ndarray:
        """(N, 2) Q^T h."""
        from scipy.linalg import lu_solve

        x = np.asarray(h, dtype=float).reshape(-1)
        return (lu_solve(self._lu, x, trans=1) - x).reshape(self.n, 2)
