"""Compiled kernels of the filament's hot loop (numba, cached on disk).

The Radau stage residual ``G_j = f(Y_j) - M(Y_j) K_j`` of the Galerkin filament is evaluated
for all stages in one call: per stage four triangular-ish matvecs with the cumulative
integration matrix and two with the stiffness and load matrices, O(n^2) work that numpy would
spread over some twenty calls. No fastmath: the exact mirror symmetry chi_N -> -chi_N is tested
bit for bit.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["stage_residual"]


@njit(cache=True)
def stage_residual(Y, Kd, I, w, Kmat, Bmat, eta, chi_E, chi_N, relax):
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
            a = 0.0
            b = 0.0
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
