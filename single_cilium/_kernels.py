"""Compiled kernels of the filament's hot loop (numba, cached on disk).

The Radau stage residual ``G_j = f(Y_j) - M(Y_j) K_j`` of the Galerkin filament is evaluated
for all stages in one call: per stage four triangular-ish matvecs with the cumulative
integration matrix and two with the stiffness and load matrices, O(n^2) work that numpy would
spread over some twenty calls. No fastmath: the exact mirror symmetry chi_N -> -chi_N is tested
bit for bit.

Background flow: in a uniform stream ``U = (U1, U2)`` (field frame, units ``L / tau``) the drag
acts on the relative velocity, ``d = -eta ((v - U).t t + 2 (v - U).n n)``. With
``v = -(a, b)``, ``a = int_0^s cos(theta) theta_t``, ``b = int_0^s sin(theta) theta_t``, this is
``a -> a + U1``, ``b -> b + U2`` at every quadrature node: the kernels take ``U1, U2`` and do
exactly that, so every derivative with respect to ``theta`` (which acts on the tangent and
normal at the node, not on ``U``) picks the stream up, and the derivative with respect to
``theta_t`` (the drag matrix) is unchanged. ``U = (0, 0)`` adds nothing (bit for bit).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# the Radau IIA(5) tableau (its one home; compile-time constants of the kernels here)
from .radau import C as C_NODES
from .radau import MU_COMPLEX, MU_REAL, TI_COMPLEX, TI_REAL
from .radau import T as T_MAT

__all__ = ["stage_residual", "radau_steps"]



@njit(cache=True)
def stage_residual(Y, Kd, I, w, Kmat, Bmat, eta, chi_E, chi_N, relax, U1, U2):
    """``f(Y_j) - M(Y_j) K_j`` for each row ``j``.

    Parameters
    ----------
    Y, Kd : (k, 2n-1) float arrays
        Stage states and stage derivatives, layout ``[theta_1..theta_{n-1}, kappa_0..kappa_{n-1}]``.
    I : (n, n) cumulative integration matrix; w : (n,) quadrature weights.
    Kmat, Bmat : (n, n) stiffness and load matrices.
    eta, chi_E, chi_N : float
    relax : float
        1.0 for the activity law ``kappa_t = -kappa - chi_E sin theta``; 0.0 for frozen kappa
        (``chi_E`` must then be passed as 0.0).
    U1, U2 : float
        Background flow (module docstring); 0.0, 0.0 for the fluid at rest.
    """
    k = Y.shape[0]
    n = w.shape[0]
    G = np.empty_like(Y)
    th = np.empty(n)
    tht = np.empty(n)
    c = np.empty(n)
    s = np.empty(n)
    ct = np.empty(n)
    st = np.empty(n)
    wdx = np.empty(n)
    wdy = np.empty(n)
    load = np.empty(n)
    for j in range(k):
        th[0] = 0.0
        tht[0] = 0.0
        for i in range(1, n):
            th[i] = Y[j, i - 1]
            tht[i] = Kd[j, i - 1]
        for i in range(n):
            c[i] = np.cos(th[i])
            s[i] = np.sin(th[i])
            ct[i] = c[i] * tht[i]
            st[i] = s[i] * tht[i]
        # velocity v = -(a, b) by cumulative integration, then the drag density, weighted
        for q in range(n):
            a = U1
            b = U2
            for i in range(n):
                a += I[q, i] * ct[i]
                b += I[q, i] * st[i]
            vpar = a * s[q] - b * c[q]
            vperp = a * c[q] + b * s[q]
            wdx[q] = w[q] * eta * (vpar * s[q] + 2.0 * vperp * c[q])
            wdy[q] = w[q] * eta * (-vpar * c[q] + 2.0 * vperp * s[q])
        for i in range(n):
            load[i] = Y[j, n - 1 + i] + chi_N
        for i in range(1, n):
            px = 0.0
            py = 0.0
            f = 0.0
            for q in range(n):
                px += I[q, i] * wdx[q]
                py += I[q, i] * wdy[q]
                f += Bmat[i, q] * load[q] - Kmat[i, q] * th[q]
            G[j, i - 1] = f - (c[i] * px + s[i] * py)
        for i in range(n):
            G[j, n - 1 + i] = -relax * Y[j, n - 1 + i] - chi_E * s[i] - Kd[j, n - 1 + i]
    return G


# ---------------------------------------------------------------------------------------------
# Radau IIA(5) steps with exact sensitivities (the period map of the shooting method)
#
# One step from y0 = (theta0, kappa0) with step h solves for the theta stage increments
# Ztheta (3, n-1); the kappa increments are linear in kappa and are eliminated exactly:
#     Zkappa_i = sum_j Q_ij (-kappa0 - chi_E sin Theta_j),   Q = (I + A^-1 / h)^-1,
# with Theta_i = theta0 + Ztheta_i (full nodal, 0 at the clamp). The reduced residual is
#     R_i = B (kappa0 + Zkappa_i + chi_N) - K Theta_i - D(Theta_i) V_i,   V = A^-1 Ztheta / h,
# whose Jacobian J (3(n-1) square, every stage coupled) drives a full Newton iteration; the same
# J at the converged stages gives dZ/d(y0, h) = -J^-1 dR/d(y0, h) (implicit function theorem),
# hence the exact derivative of the discrete step map.
# ---------------------------------------------------------------------------------------------
@njit(cache=True)
def _drag_projections(th, v, I, w, eta, U1, U2):
    """The pieces of ``D(th) v`` for full nodal ``th`` and ``v`` (theta_t): cos th, sin th, the
    tangential and normal velocities at the nodes, ``I[:, 1:]``, and the quadrature-weighted drag
    projected on the free nodes, ``Px``, ``Py`` (so that ``D(th) v = cos th Px + sin th Py``).
    With a background flow ``(U1, U2)`` the velocities are relative to it and ``Px``, ``Py``
    include the stream's drag (``D(th) v + g_U(th)``)."""
    c = np.cos(th)
    s = np.sin(th)
    a = I @ (c * v)
    b = I @ (s * v)
    if U1 != 0.0 or U2 != 0.0:
        a = a + U1
        b = b + U2
    vpar = a * s - b * c
    vperp = a * c + b * s
    wdx = w * eta * (vpar * s + 2.0 * vperp * c)
    wdy = w * eta * (-vpar * c + 2.0 * vperp * s)
    If = np.ascontiguousarray(I[:, 1:])
    return c, s, vpar, vperp, If, If.T @ wdx, If.T @ wdy


@njit(cache=True)
def stage_terms(th, v, I, w, eta, U1, U2):
    """For full nodal ``th`` and ``v`` (theta_t): ``D(th) v`` on the free nodes (n-1,), the drag
    matrix ``D(th)`` (n-1, n-1) and ``d(D(th) v)/dth`` at fixed ``v`` (n-1, n-1). With a
    background flow the first and the last include the stream's drag ``g_U(th)`` (the first is
    then ``D(th) v + g_U(th)``; at ``v = 0``, ``g_U`` and its Jacobian)."""
    n = th.shape[0]
    c, s, vpar, vperp, If, Px, Py = _drag_projections(th, v, I, w, eta, U1, U2)
    Dv = c[1:] * Px + s[1:] * Py
    # drag matrix: D = eta (Wt^T W Wt + 2 Wn^T W Wn), Wt[q, a] = I[q, a] sin(th_q - th_a)
    Wt = np.empty((n, n - 1))
    Wn = np.empty((n, n - 1))
    Gx = np.empty((n, n - 1))
    Gy = np.empty((n, n - 1))
    for q in range(n):
        for m in range(1, n):
            sq = s[q] * c[m] - c[q] * s[m]  # sin(th_q - th_m)
            cq = c[q] * c[m] + s[q] * s[m]  # cos(th_q - th_m)
            Wt[q, m - 1] = If[q, m - 1] * sq
            Wn[q, m - 1] = If[q, m - 1] * cq
            g = eta * If[q, m - 1] * v[m]
            Gx[q, m - 1] = w[q] * g * (-cq * s[q] + 2.0 * sq * c[q])
            Gy[q, m - 1] = w[q] * g * (cq * c[q] + 2.0 * sq * s[q])
        if q >= 1:
            Gx[q, q - 1] += w[q] * eta * (-vperp[q] * s[q] - vpar[q] * c[q])
            Gy[q, q - 1] += w[q] * eta * (vperp[q] * c[q] - vpar[q] * s[q])
    Ww = Wt * w.reshape((n, 1))
    Wnw = Wn * w.reshape((n, 1))
    D = eta * (Wt.T @ Ww + 2.0 * (Wn.T @ Wnw))
    dPx = If.T @ Gx
    dPy = If.T @ Gy
    Jd = c[1:].reshape((n - 1, 1)) * dPx + s[1:].reshape((n - 1, 1)) * dPy
    for a_ in range(n - 1):
        Jd[a_, a_] += -s[a_ + 1] * Px[a_] + c[a_ + 1] * Py[a_]
    return Dv, D, Jd


@njit(cache=True)
def _reduced_system(Zt, th0, ka0, h, Q, Ainv, I, w, Kr, Bmat, eta, chi_E, chi_N, jac, U1, U2):
    """Residual (3(n-1),) of the reduced stage equations and, if ``jac``, the Jacobian and the
    per-stage pieces needed for the sensitivities (see the block comment above)."""
    n = th0.shape[0]
    m = n - 1
    Th = np.empty((3, n))
    for i in range(3):
        Th[i, 0] = 0.0
        for a_ in range(m):
            Th[i, a_ + 1] = th0[a_ + 1] + Zt[i, a_]
    sinT = np.sin(Th)
    R = np.empty(3 * m)
    J = np.zeros((3 * m, 3 * m)) if jac else np.zeros((1, 1))
    Ds = np.empty((3, m, m)) if jac else np.empty((1, 1, 1))
    Jds = np.empty((3, m, m)) if jac else np.empty((1, 1, 1))
    Vs = np.empty((3, m))
    Br = np.ascontiguousarray(Bmat[1:, :])
    Bf = np.ascontiguousarray(Bmat[1:, 1:])
    cosT = np.cos(Th)
    for i in range(3):
        ka = np.empty(n)
        qs = Q[i, 0] + Q[i, 1] + Q[i, 2]
        for q in range(n):
            ka[q] = ka0[q] * (1.0 - qs) - chi_E * (Q[i, 0] * sinT[0, q] + Q[i, 1] * sinT[1, q]
                                                   + Q[i, 2] * sinT[2, q]) + chi_N
        v = np.zeros(n)
        for a_ in range(m):
            v[a_ + 1] = (Ainv[i, 0] * Zt[0, a_] + Ainv[i, 1] * Zt[1, a_] + Ainv[i, 2] * Zt[2, a_]) / h
            Vs[i, a_] = v[a_ + 1]
        th = Th[i].copy()
        if jac:
            Dv, D, Jd = stage_terms(th, v, I, w, eta, U1, U2)
            Ds[i] = D
            Jds[i] = Jd
        else:
            Dv = _dv_only(th, v, I, w, eta, U1, U2)
        Ri = Br @ ka - Kr @ th[1:] - Dv
        R[i * m:(i + 1) * m] = Ri
        if jac:
            for j in range(3):
                blk = J[i * m:(i + 1) * m, j * m:(j + 1) * m]
                for a_ in range(m):
                    for b_ in range(m):
                        blk[a_, b_] = (-chi_E * Q[i, j] * Bf[a_, b_] * cosT[j, b_ + 1]
                                       - (Ainv[i, j] / h) * D[a_, b_])
                if i == j:
                    for a_ in range(m):
                        for b_ in range(m):
                            blk[a_, b_] -= Kr[a_, b_] + Jd[a_, b_]
    return R, J, Ds, Jds, Vs, Th, sinT, cosT


@njit(cache=True)
def _dv_only(th, v, I, w, eta, U1, U2):
    """``D(th) v`` (+ ``g_U(th)``) on the free nodes alone (no matrices: the cheap path of the stage Newton)."""
    c, s, _, _, _, Px, Py = _drag_projections(th, v, I, w, eta, U1, U2)
    return c[1:] * Px + s[1:] * Py


@njit(cache=True)
def radau_steps(y0, h, n_steps, sens, Ainv, P, I, w, Kmat, Bmat, eta, chi_E, chi_N, tol, max_newton,
                U1, U2):
    """``n_steps`` Radau IIA(5) steps of size ``h`` from ``y0`` (full Newton on the stages), in
    the background flow ``(U1, U2)`` (module docstring; the reduced residual then reads
    ``R_i = B (...) - K Theta_i - D(Theta_i) V_i - g_U(Theta_i)``, and the sensitivities carry
    ``dg_U/dtheta``).

    Returns ``Y`` (n_steps+1, N) the step ends, ``Yd`` (n_steps+1, N) the derivative of the
    collocation polynomial there (at the start: of the first step's polynomial), ``S``
    (N, N) the derivative of the last state with respect to ``y0`` (the monodromy for a whole
    period; identity unless ``sens``), ``Sh`` (N,) its derivative with respect to ``h``, and
    ``counts`` = [Newton iterations, Jacobian factorisations, failed step index or -1].
    """
    n = w.shape[0]
    m = n - 1
    N = 2 * n - 1
    Kr = np.ascontiguousarray(Kmat[1:, 1:])
    Br = np.ascontiguousarray(Bmat[1:, :])
    Bf = np.ascontiguousarray(Bmat[1:, 1:])
    E3 = np.eye(3)
    Q = np.linalg.inv(E3 + Ainv / h)
    dQ = Q @ Ainv @ Q / (h * h)
    Y = np.empty((n_steps + 1, N))
    Yd = np.empty((n_steps + 1, N))
    Y[0] = y0
    S = np.eye(N)
    Sh = np.zeros(N)
    counts = np.zeros(3, dtype=np.int64)
    counts[2] = -1
    Zprev = np.zeros((3, N))
    y = y0.copy()
    for k in range(n_steps):
        th0 = np.zeros(n)
        th0[1:] = y[:m]
        ka0 = y[m:].copy()
        # predictor: the previous step's collocation polynomial, extrapolated
        Zt = np.zeros((3, m))
        if k > 0:
            for i in range(3):
                x = 1.0 + C_NODES[i]
                for r in range(3):
                    coef = (x ** (r + 1) - 1.0)
                    for a_ in range(m):
                        Zt[i, a_] += coef * (Zprev[0, a_] * P[0, r] + Zprev[1, a_] * P[1, r]
                                             + Zprev[2, a_] * P[2, r])
        Z_pred = Zt.copy()
        ok = False
        # simplified Newton: the stage Jacobian frozen at the step start (theta0, with the rate
        # of the previous step end), block-diagonalised by the eigenvectors of A^-1 (one real and
        # one complex (n-1)-square system, as in RADAU5)
        D0 = np.empty((m, m))
        v0 = np.zeros(n)
        if k > 0:
            v0[1:] = Yd[k, :m]
        _, D0, Jd0 = stage_terms(th0, v0, I, w, eta, U1, U2)
        c0 = np.cos(th0[1:])
        sr = MU_REAL / h
        sc = MU_COMPLEX / h
        Ar = np.empty((m, m))
        Ac = np.empty((m, m), dtype=np.complex128)
        for a_ in range(m):
            for b_ in range(m):
                base = Kr[a_, b_] + Jd0[a_, b_]
                bc = chi_E * Bf[a_, b_] * c0[b_]
                Ar[a_, b_] = bc / (1.0 + sr) + base + sr * D0[a_, b_]
                Ac[a_, b_] = bc / (1.0 + sc) + base + sc * D0[a_, b_]
        counts[1] += 2
        last = 1e300
        for it in range(max_newton):
            R = _reduced_system(Zt, th0, ka0, h, Q, Ainv, I, w, Kr, Bmat, eta, chi_E, chi_N, False, U1, U2)[0]
            counts[0] += 1
            if not np.all(np.isfinite(R)):
                break
            Gr = np.zeros(m)
            Gc = np.zeros(m, dtype=np.complex128)
            for i in range(3):
                Gr += TI_REAL[i] * R[i * m:(i + 1) * m]
                Gc += TI_COMPLEX[i] * R[i * m:(i + 1) * m]
            wr = np.linalg.solve(Ar, Gr)
            wc = np.linalg.solve(Ac, Gc)
            size = 0.0
            for i in range(3):
                for a_ in range(m):
                    dz = T_MAT[i, 0] * wr[a_] + T_MAT[i, 1] * wc[a_].real + T_MAT[i, 2] * wc[a_].imag
                    Zt[i, a_] += dz
                    size = max(size, abs(dz))
            if not np.isfinite(size):
                break
            rate = size / last
            if size <= tol or (it >= 1 and rate < 1.0 and rate / (1.0 - rate) * size < tol) or (
                    size < 1e3 * tol and rate > 0.5):
                ok = True
                break
            if it >= 1 and rate >= 0.9:
                break
            last = size
        if not ok:
            # full Newton (the exact stage Jacobian at every iterate), from the predictor
            Zt[:] = Z_pred
            last = 1e300
            for it in range(max_newton):
                R, J, Ds, Jds, Vs, Th, sinT, cosT = _reduced_system(Zt, th0, ka0, h, Q, Ainv, I, w, Kr, Bmat,
                                                                     eta, chi_E, chi_N, True, U1, U2)
                counts[0] += 1
                counts[1] += 1
                if not np.all(np.isfinite(R)):
                    break
                dz = np.linalg.solve(J, -R)
                size = np.max(np.abs(dz))
                for i in range(3):
                    for a_ in range(m):
                        Zt[i, a_] += dz[i * m + a_]
                if size <= tol or (size < 1e3 * tol and size > 0.5 * last) or (
                        it >= 1 and size < 0.1 * last and size * size * size < tol * last * last):
                    ok = True
                    break
                if not np.isfinite(size) or (it >= 2 and size > last):
                    break
                last = size
        if not ok:
            counts[2] = k
            return Y, Yd, S, Sh, counts
        # stages at the converged point
        R, J, Ds, Jds, Vs, Th, sinT, cosT = _reduced_system(Zt, th0, ka0, h, Q, Ainv, I, w, Kr, Bmat,
                                                             eta, chi_E, chi_N, sens, U1, U2)
        Zk = np.empty((3, n))
        for i in range(3):
            qs = Q[i, 0] + Q[i, 1] + Q[i, 2]
            for q in range(n):
                Zk[i, q] = -ka0[q] * qs - chi_E * (Q[i, 0] * sinT[0, q] + Q[i, 1] * sinT[1, q]
                                                   + Q[i, 2] * sinT[2, q])
        for i in range(3):
            Zprev[i, :m] = Zt[i]
            Zprev[i, m:] = Zk[i]
        ynew = y + Zprev[2]
        if k == 0:
            for q in range(N):
                Yd[0, q] = (Zprev[0, q] * P[0, 0] + Zprev[1, q] * P[1, 0] + Zprev[2, q] * P[2, 0]) / h
        for q in range(N):
            Yd[k + 1, q] = (Ainv[2, 0] * Zprev[0, q] + Ainv[2, 1] * Zprev[1, q] + Ainv[2, 2] * Zprev[2, q]) / h
        if sens:
            counts[1] += 1
            # dR/dp for p = (theta0 free, kappa0, h): columns 0..m-1, m..m+n-1, m+n
            npar = N + 1
            RHS = np.zeros((3 * m, npar))
            for i in range(3):
                qs = Q[i, 0] + Q[i, 1] + Q[i, 2]
                dqs = dQ[i, 0] + dQ[i, 1] + dQ[i, 2]
                blk = RHS[i * m:(i + 1) * m]
                for b_ in range(m):
                    cw = Q[i, 0] * cosT[0, b_ + 1] + Q[i, 1] * cosT[1, b_ + 1] + Q[i, 2] * cosT[2, b_ + 1]
                    for a_ in range(m):
                        blk[a_, b_] = -chi_E * cw * Bf[a_, b_] - Kr[a_, b_] - Jds[i, a_, b_]
                for q in range(n):
                    for a_ in range(m):
                        blk[a_, m + q] = (1.0 - qs) * Br[a_, q]
                dka = np.empty(n)
                for q in range(n):
                    dka[q] = -ka0[q] * dqs - chi_E * (dQ[i, 0] * sinT[0, q] + dQ[i, 1] * sinT[1, q]
                                                      + dQ[i, 2] * sinT[2, q])
                col = Br @ dka + (Ds[i] @ Vs[i]) / h
                for a_ in range(m):
                    blk[a_, N] = col[a_]
            X = -np.linalg.solve(J, RHS)
            Sk = np.zeros((N, npar))
            # theta rows
            for a_ in range(m):
                for p in range(npar):
                    Sk[a_, p] = X[2 * m + a_, p]
                Sk[a_, a_] += 1.0
            # kappa rows
            qs3 = Q[2, 0] + Q[2, 1] + Q[2, 2]
            dqs3 = dQ[2, 0] + dQ[2, 1] + dQ[2, 2]
            for q in range(n):
                Sk[m + q, m + q] += 1.0 - qs3
                Sk[m + q, N] += -ka0[q] * dqs3 - chi_E * (dQ[2, 0] * sinT[0, q] + dQ[2, 1] * sinT[1, q]
                                                          + dQ[2, 2] * sinT[2, q])
                if q >= 1:
                    for j in range(3):
                        f = -chi_E * Q[2, j] * cosT[j, q]
                        for p in range(npar):
                            Sk[m + q, p] += f * X[j * m + q - 1, p]
                        Sk[m + q, q - 1] += f
            S = np.ascontiguousarray(Sk[:, :N]) @ S
            Sh = np.ascontiguousarray(Sk[:, :N]) @ Sh + Sk[:, N]
        y = ynew
        Y[k + 1] = y
    return Y, Yd, S, Sh, counts
