"""The cycle-mean moments of one cilium as smooth functions of its natural curvature.

The design model (:mod:`~ciliary_carpet.design.model`) asks, for any chi_N, what a carpet's
:class:`~ciliary_carpet.carpet.cycles.CycleData` computes for one cilium of that curvature: its
mean force on the fluid, the first moment of the force about the force centre, the centre's offset
from the base and the swept radius (field frame). :class:`CycleMoments` samples them from the
thrust table along the flutter branch with the carpet's own moment code
(:func:`~ciliary_carpet.carpet.cycles.sample_moments`) and interpolates them by cubic splines in
chi_N, with the chi_N derivatives the design's gradients need.
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

from single_cilium.table import ThrustTable

from ciliary_carpet.carpet.cycles import sample_moments, simpson

__all__ = ["CycleMoments", "cycle_moments"]


class CycleMoments:
    """Cycle-mean moments of one cilium as smooth functions of its signed chi_N (field frame).

    ``F`` (2,): the mean force on the fluid, ``D`` (2, 2): its first moment about the force
    centre (D_ab = <int (r - c)_a f_b ds>), ``offset`` (2,): the force centre relative to the
    base, ``radius``: the largest distance of a swept sample from the centre -- exactly the
    quantities :class:`~ciliary_carpet.carpet.cycles.CycleData` computes per cilium (the same code, :func:`sample_moments`:
    centroid of the samples, composite Simpson over s, mean over the phase samples). They are
    sampled at ``n`` values of |chi_N| on the flutter branch [0, chi_c] and extended to negative
    chi_N by the mirror symmetry (x -> -x: F_x, D_xy, D_yx, offset_x odd, the rest even), then
    interpolated by cubic splines (``nu`` = 1 gives the chi_N derivative). Outside the branch a
    cilium is still: zero force.

    Interpolation error: the spline through 2n - 1 samples, checked against the table at the
    midpoints in the tests (below 1e-6 relative to |Fbar(0)| for n = 257)."""

    def __init__(self, table: ThrustTable, n: int = 257):
        b0, b1 = table.flutter_range
        self.cutoff = float(b1)
        a = np.linspace(0.0, b1, int(n))
        F = np.empty((a.size, 2))
        D = np.empty((a.size, 2, 2))
        off = np.empty((a.size, 2))
        rad = np.empty(a.size)
        w = simpson(table.ds.sizes["s"])
        n_p = table.ds.sizes["phase"]
        for lo in range(0, a.size, 64):
            sl = slice(lo, lo + 64)
            cyc = table.cycles(a[sl])
            k = cyc["x"].shape[0]
            x, y = (np.where(np.isfinite(cyc[q]), cyc[q], 0.0) for q in ("x", "y"))
            Fp, Dp, Tp = np.empty((k, n_p, 2)), np.empty((k, n_p, 2, 2)), np.empty((k, n_p, 2, 2, 2))
            Qp, Q2p = np.empty((k, n_p)), np.empty((k, n_p))
            sample_moments(x, y, cyc["fx"], cyc["fy"], np.eye(2), np.zeros((k, 2)), w, off[sl], rad[sl], Fp, Dp, Tp,
                            Qp, Q2p)
            F[sl] = Fp.mean(axis=1)
            D[sl] = Dp.mean(axis=1)
        # mirror: sign of each component under chi -> -chi
        vals = np.column_stack([F, D.reshape(-1, 4), off, rad])
        odd = np.array([1, 0, 0, 1, 1, 0, 1, 0, 0], bool)  # Fx Fy Dxx Dxy Dyx Dyy ox oy r
        neg = np.where(odd, -1.0, 1.0) * vals[:0:-1]
        self._spline = CubicSpline(np.concatenate([-a[:0:-1], a]), np.vstack([neg, vals]), axis=0)
        self.thrust0 = float(np.hypot(*F[0]))

    def __call__(self, chi, nu: int = 0) -> dict:
        """``F`` (N, 2), ``D`` (N, 2, 2), ``offset`` (N, 2), ``radius`` (N,) at ``chi`` (N,)
        in the field frame (their ``nu``-th chi_N derivatives for nu > 0; zero off the branch)."""
        c = np.asarray(chi, dtype=float)
        on = np.abs(c) <= self.cutoff
        v = self._spline(np.clip(c, -self.cutoff, self.cutoff), nu) if nu else self._spline(
            np.clip(c, -self.cutoff, self.cutoff))
        v = np.where(on[:, None], v, 0.0)
        if nu == 0:  # a still filament: its base, no force
            v[~on, 8] = 0.0
        return {"F": v[:, :2], "D": v[:, 2:6].reshape(-1, 2, 2), "offset": v[:, 6:8], "radius": v[:, 8]}

    def thrust_norm(self, chi) -> np.ndarray:
        """|Fbar| at ``chi`` (N,)."""
        return np.hypot(*self(np.atleast_1d(chi))["F"].T)


_MOMENTS: dict = {}


def cycle_moments(table: ThrustTable) -> CycleMoments:
    """The :class:`CycleMoments` of ``table`` in still fluid (cached per table object; a table over
    the background flow gives its flow U = 0: the design model's cilia beat in still fluid)."""
    table = table.in_still_fluid()
    key = id(table)
    m = _MOMENTS.get(key)
    if m is None or m[0] is not table:
        _MOMENTS[key] = m = (table, CycleMoments(table))
    return m[1]
