"""The thrust table over the background flow: interpolation in ``(chi_N, U_par, U_perp)``.

Frame (DESIGN.md's field frame): ``e2`` along the field, ``e1`` across it; the uniform flow the
filament sits in is ``U = U_par e2 + U_perp e1`` in units of ``L / tau``, i.e.
``CiliumParams(chi_E, eta, chi_N, background=(U_perp, U_par))``. ``U_par > 0`` runs along the
field, from the clamp towards the tip of the straight filament; ``U_perp > 0`` runs along ``+e1``,
away from the side to which a positive chi_N bends the filament (its tip lies at ``x < 0``).
Mirror symmetry: ``(chi_N, U_par, U_perp) -> (-chi_N, U_par, -U_perp)`` mirrors the cilium
(``e1 -> -e1``: ``thrust_x``, ``thrust_angle``, ``x``, ``fx`` change sign); a table holds
``chi_N >= 0`` only and serves negative chi_N by it, so its ``U_perp`` grid should be symmetric
about 0 to serve both signs of chi_N over the same flows.

How a point is interpolated (:class:`FlowGrid`; per axis of ``n`` grid values, the Lagrange
polynomial of degree ``k = min(3, n - 1)`` through the ``k + 1`` grid values around the point's
cell, tensor products of the two axes: a point reads its 4 x 4 grid flows, never the whole grid,
so the cost of a lookup does not grow with the grid; continuous, with jumps of O(h^3) in the
slope between cells):

* the flutter cutoff ``chi_c(U)`` from the grid flows' cutoffs (each one a row of its flow);
* on the flutter branch (``|chi_N| <= chi_c(U)``), at the fixed fraction ``r = chi_N / chi_c(U)``
  of the cutoff: each grid flow's table (cubic in chi_N, shapes and forces in
  ``sqrt(chi_c - chi_N)``) at ``r chi_c(U_ab)``, so that the Hopf onsets line up, then the spline
  across the flows -- as :class:`~single_cilium.lookup.ThrustTable` does across chi_E;
* off it, no flutter: the steady state's force, each grid flow's at the same chi_N (its steady
  state is smooth across its own cutoff), then the spline across the flows;
* ``thrust_norm`` and ``thrust_angle`` from the interpolated ``thrust_x``, ``thrust_y`` (the
  angle wraps at ``+-pi`` where a strong flow against the field turns the thrust along ``+e2``).

No extrapolation: a flow outside the grid's rectangle (after the mirror) is a TableError, and so
is a flow whose spline needs a grid flow without a flutter cutoff (no flutter at chi_N = 0, or
flutter at every chi_N up to the coiled filament): the Hopf onsets cannot be lined up there (its
rows are still served at that grid flow itself).

Error estimate (:meth:`FlowGrid.interpolation_error`): ``SAFETY = 2`` times the largest change
from the quadratic to the cubic interpolant in U over the point's cell (at the point and 1/3 and
2/3 across the cell in each axis), plus the grid flows' own estimate in chi_N (the same, over the
interval between rows). The change estimates the quadratic interpolant's error, an upper bound
of the cubic's with room. Accuracy of the shipped table (U spacing 0.5, chi_N spacing 10),
against fresh cycles of its discretisation at 120 points off its grid (|U| up to 2, chi_N from 0
to above the cutoff, both signs): the thrust's error is at most 4.9e-4 (2.6e-4 of |F|; 1.1e-4
at |U| < 0.9), at most 0.36 of the estimate (0.72 with a factor 1, 0.41 from the change at the
point alone) and a median 1/21 of it; the period within 1.9e-4 (relative), the angle 1.8e-4 rad
(benchmarks/bench_table_flow.py, results in benchmarks/results/bench_table_flow.md section 4;
asserted in tests/test_table_flow.py).

One concept over 500 lines: the table over the background flow and its interpolation.
"""
from __future__ import annotations

import math

import numpy as np
import xarray as xr
from numba import njit, prange

from .cycle import thrust_angle
from .equilibrium import NoLimitAngleError, limit_angle
from .params import CiliumParams
from .tablefile import FIELDS, ODD, REGIMES, REST_FIELDS, REST_SCALARS, SAFETY, SCALARS, TableError, coiled

__all__ = ["FlowGrid", "thrust_angle_of"]

_DERIVED = ("thrust_norm", "thrust_angle")


@njit(cache=True, parallel=True)
def _blend(ptr, knot, weight, u, bx, nbx, coef, out):  # pragma: no cover - compiled
    """``out[i] = sum_p weight[p] S_knot[p](u[p])`` over ``p in ptr[i]:ptr[i + 1]``: each grid
    flow's cycle data at its own point of its branch, weighted across the flows, in one pass per
    point. ``S_k`` is grid flow k's cubic piecewise polynomial in u (scipy's PPoly layout:
    breakpoints ``bx[k, :nbx[k]]``, coefficients ``coef[k, m, j, q]`` of ``(u - bx_j)^(3 - m)``,
    the end pieces continued outside)."""
    n = ptr.size - 1
    mq = out.shape[1]
    for i in prange(n):
        for q in range(mq):
            out[i, q] = 0.0
        for p in range(ptr[i], ptr[i + 1]):
            k = knot[p]
            x = u[p]
            lo, hi = 0, nbx[k] - 2
            while lo < hi:
                mid = (lo + hi + 1) // 2
                if bx[k, mid] <= x:
                    lo = mid
                else:
                    hi = mid - 1
            dx = x - bx[k, lo]
            w = weight[p]
            for q in range(mq):
                out[i, q] += w * (((coef[k, 0, lo, q] * dx + coef[k, 1, lo, q]) * dx + coef[k, 2, lo, q]) * dx
                                  + coef[k, 3, lo, q])
_THRUST_ANGLE = np.vectorize(thrust_angle, otypes=[float])


def thrust_angle_of(x, y) -> np.ndarray:
    """:func:`single_cilium.cycle.thrust_angle` of the mean forces ``(x, y)`` (arrays of one
    shape), NaN where the force is zero (no direction)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    a = _THRUST_ANGLE(x, y)
    return np.where((x == 0) & (y == 0), np.nan, a)


class FlowGrid:
    """Interpolation across the grid flows of a table over the background flow (module docstring).

    Parameters
    ----------
    ds : xarray.Dataset
        The validated table (dims ``U_par, U_perp, chi_N, phase, s``).
    knots : dict
        ``(i, j) -> ThrustTable`` of the grid flow ``(U_par[i], U_perp[j])`` (its own rows).
    source : str
        Named in errors.
    """

    def __init__(self, ds: xr.Dataset, knots: dict, source: str):
        self.ds, self.knots, self.source = ds, knots, source
        self.grids = (ds.U_par.values.astype(float), ds.U_perp.values.astype(float))
        self.cut = ds.chi_N_cutoff.values.astype(float)
        self.chi_E, self.eta = float(ds.attrs["chi_E"]), float(ds.attrs["eta"])
        c = ds.chi_N.values
        self.chi_N_range = (float(c[0]), float(c[-1]))
        self.n_phase, self.n_s = ds.sizes["phase"], ds.sizes["s"]
        # grid flows whose flutter branch does not end at a cutoff row: no onsets to line up
        self.unaligned: dict = {}
        self.branch: dict = {}
        for ij, t in knots.items():
            cc = float(self.cut[ij])
            try:
                b0, b1 = t.flutter_range
            except TableError:
                self.unaligned[ij] = "no flutter at chi_N = 0 in this flow" if not np.isfinite(cc) else "no branch"
                continue
            if not np.isfinite(cc):
                self.unaligned[ij] = "flutter up to the coiled filament"
                continue
            self.branch[ij] = (b0, b1)
        # the fractions of the cutoff that every grid flow's branch covers
        self.r_lo = max((b0 / self.cut[ij] for ij, (b0, _) in self.branch.items()), default=0.0)
        self.r_hi = min((b1 / self.cut[ij] for ij, (_, b1) in self.branch.items()), default=1.0)

    @property
    def U_range(self) -> tuple[tuple[float, float], tuple[float, float]]:
        return tuple((float(g[0]), float(g[-1])) for g in self.grids)

    # ------------------------------------------------------------------ weights
    def _weights(self, axis: int, x: np.ndarray, lower: bool) -> np.ndarray:
        """(n, m) interpolation weights of the grid values of ``axis`` at ``x`` (already in
        range): the Lagrange polynomial of degree ``k = min(3, m - 1)`` (one lower with ``lower``)
        through the ``k + 1`` grid values nearest the point's cell (module docstring); exactly
        one-hot at a grid value. At most ``k + 1`` weights of a row are non-zero, whatever the
        grid's size: a point reads only the grid flows next to it."""
        g = self.grids[axis]
        m = g.size
        n = x.size
        if m == 1:
            return np.ones((n, 1))
        k = max(0, min(3, m - 1) - int(lower))
        i = np.clip(np.searchsorted(g, x, side="right") - 1, 0, m - 2)  # the cell [g_i, g_i+1]
        if k % 2:  # an even number of values: as many on each side of the cell
            start = i - (k - 1) // 2
        else:  # an odd number: the extra one on the side nearer the point
            near_hi = (x - g[i]) > (g[i + 1] - x)
            start = i - k // 2 + near_hi.astype(int)
        idx = np.clip(start, 0, m - k - 1)[:, None] + np.arange(k + 1)[None, :]
        xs = g[idx]
        L = np.ones((n, k + 1))
        for a in range(k + 1):
            for b in range(k + 1):
                if a != b:
                    L[:, a] *= (x - xs[:, b]) / (xs[:, a] - xs[:, b])
        W = np.zeros((n, m))
        np.put_along_axis(W, idx, L, axis=1)
        hit = np.minimum(np.searchsorted(g, x), m - 1)
        exact = g[hit] == x
        W[exact] = np.eye(m)[hit[exact]]
        return W

    def _points(self, chi_N, U_par, U_perp):
        """Flattened, mirrored and range-checked points: ``(a, up, uq, neg, shape)``, ``a = |chi_N|``
        and ``uq`` the mirrored ``U_perp`` where ``chi_N < 0``."""
        c, up, uq = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (chi_N, U_par, U_perp)))
        shape = c.shape
        c, up, uq = c.ravel(), up.ravel(), uq.ravel()
        for name, v in (("chi_N", c), ("U_par", up), ("U_perp", uq)):
            if not np.all(np.isfinite(v)):
                raise TableError(f"{name} must be finite")
        neg = c < 0
        a = np.abs(c)
        uq = np.where(neg, -uq, uq)  # the mirror image: (-chi_N, U_perp) -> (chi_N, -U_perp)
        lo, hi = self.chi_N_range
        bad = (a < lo) | (a > hi)
        if np.any(bad):
            raise TableError(f"|chi_N| = {float(a[bad][0]):g} is outside the table's range [{lo:g}, {hi:g}]")
        for name, v, g in (("U_par", up, self.grids[0]), ("U_perp", uq, self.grids[1])):
            bad = (v < g[0]) | (v > g[-1])
            if np.any(bad):
                i = int(np.flatnonzero(bad)[0])
                mirror = (f" (chi_N = {-a[i]:g} < 0 is served by its mirror image, chi_N = {a[i]:g} at "
                          f"U_perp = {v[i]:g})" if name == "U_perp" and neg[i] else "")
                rng = (f"the table's range [{g[0]:g}, {g[-1]:g}]" if g.size > 1
                       else f"the table's {name} = {g[0]:g} only")
                raise TableError(f"{name} = {v[i]:g} is outside {rng}{mirror}: no extrapolation in the background "
                                 "flow; build the table over a wider grid")
        return a, up, uq, neg, shape

    def _stencil(self, up, uq, lower: bool = False):
        """Weights (n, m_par, m_perp) and the interpolated cutoff (n,); a TableError where a grid
        flow without a cutoff takes part."""
        W = np.einsum("na,nb->nab", self._weights(0, up, lower), self._weights(1, uq, lower))
        for (i, j), why in self.unaligned.items():
            use = W[:, i, j] != 0
            if np.any(use):
                k = int(np.flatnonzero(use)[0])
                raise TableError(f"{self.source}: the flow (U_par, U_perp) = ({up[k]:g}, {uq[k]:g}) is interpolated "
                                 f"from the grid flow ({self.grids[0][i]:g}, {self.grids[1][j]:g}), which has no "
                                 f"flutter cutoff ({why}): the Hopf onsets cannot be lined up across it; ask at a "
                                 "grid flow, or build the table over a grid whose flows all have a cutoff")
        C = np.einsum("nab,ab->n", W, np.where(np.isfinite(self.cut), self.cut, 0.0))
        return W, C

    def cutoff(self, U_par, U_perp) -> np.ndarray:
        """The interpolated flutter cutoff chi_N in the flow ``(U_par, U_perp)``."""
        _, up, uq, _, shape = self._points(np.zeros(np.shape(U_par)), U_par, U_perp)
        t = self._lone(up, uq)
        if t is not None:
            return np.full(shape, float(t.ds.attrs["chi_N_cutoff"]))
        return self._stencil(up, uq)[1].reshape(shape)

    def _lone(self, up: np.ndarray, uq: np.ndarray):
        """The table of a grid flow without a cutoff when every point lies exactly on it (served
        by its own rows; the spline across the flows cannot use it), else None."""
        for (i, j) in self.unaligned:
            if np.all(up == self.grids[0][i]) and np.all(uq == self.grids[1][j]):
                return self.knots[(i, j)]
        return None

    # ------------------------------------------------------------------ evaluation
    def _knot_values(self, t, name: str, x: np.ndarray, nu: int, on: bool) -> np.ndarray:
        """One grid flow's value of a scalar or field at chi_N = ``x`` (>= 0): on its flutter
        branch (``on``; fields of shape (n, phase, s)) or of its steady state."""
        if name in REST_SCALARS + REST_FIELDS:
            return t.rest(name, x, nu=nu)
        if on:
            return t.cycles(x)[name] if name in FIELDS else t.scalar(name, x, nu)
        if name in ("fx", "fy"):
            return t.rest("rest_" + name, x)[:, None, :]
        if name in ("thrust_x", "thrust_y"):
            return t.rest("rest_" + name, x, nu=nu)
        if name in ("alpha", "beta"):
            return t.rest(name, x, nu=nu)
        return np.full((x.size,) + ((self.n_phase, self.n_s) if name in FIELDS else ()), np.nan)

    def _check_steady(self, W: np.ndarray, a: np.ndarray) -> None:
        """No thrust off the branch where a grid flow taking part has a row of divergence (an
        unstable steady state without flutter) next to ``a``."""
        for (i, j), t in self.knots.items():
            use = W[:, i, j] != 0
            if not np.any(use):
                continue
            c = t.ds.chi_N.values
            for x in c[t.ds.regime.values == REGIMES.index("divergence")]:
                k = int(np.searchsorted(c, x))
                near = use & (a > c[max(k - 1, 0)]) & (a < c[min(k + 1, c.size - 1)])
                if np.any(near):
                    raise TableError(f"{self.source}: at chi_N = {float(a[near][0]):g} the grid flow "
                                     f"({self.grids[0][i]:g}, {self.grids[1][j]:g}) has a steady state that is "
                                     "unstable "
                                     f"without flutter (divergence at its row chi_N = {x:g}): no thrust there")

    def _evaluate(self, names, a, up, uq, nu: int = 0, lower: bool = False,
                  steady: bool = True) -> tuple[dict, np.ndarray, list]:
        """The interpolated ``names`` at the (mirrored, checked) points, the flutter mask, and per
        grid flow taking part ``(weights, on-branch chi_N)`` (for the error estimate). The steady
        state's own quantities (``rest_*``) at fixed chi_N; ``steady``: refuse the thrust off the
        branch next to a divergence."""
        W, C = self._stencil(up, uq, lower)
        on = a <= C
        out_of = on & ((a < self.r_lo * C * (1 - 1e-12)) | (a > self.r_hi * C * (1 + 1e-12)))
        if np.any(out_of):
            raise TableError(f"chi_N = {float(a[out_of][0]):g} lies outside the flutter rows of some grid flow "
                             f"(fractions {self.r_lo:.6g} to {self.r_hi:.6g} of its cutoff): not interpolated; "
                             "extend the chi_N grid")
        if steady and np.any(~on):
            self._check_steady(W[~on], a[~on])
        r = np.where(on, a / np.where(C > 0, C, 1.0), 0.0)
        trail = {n: (self.n_phase, self.n_s) if n in FIELDS else (self.n_s,) if n in REST_FIELDS else ()
                 for n in names}
        out = {n: np.zeros((a.size,) + trail[n]) for n in names}
        blend = [n for n in names if n in FIELDS]  # on the branch: one compiled pass (_blend_fields)
        used = []
        for (i, j), t in self.knots.items():
            w = W[:, i, j]
            if not np.any(w != 0):
                continue
            x = np.clip(r * self.cut[i, j], *self.branch[(i, j)])  # its point on its branch
            used.append((w, x, t))
            for mask, is_on in ((on, True), (~on, False)):
                sel = mask & (w != 0)
                if not np.any(sel):
                    continue
                sel = slice(None) if sel.all() else np.flatnonzero(sel)  # all: no gather and scatter (25 % faster)
                ws = w[sel]
                for name in names:
                    if is_on and name in blend:
                        continue
                    if is_on and name not in REST_SCALARS + REST_FIELDS:
                        v = self._knot_values(t, name, x[sel], nu, True)
                        if nu:  # d/dchi_N of g(chi_N c_ij / C)
                            v = v * (self.cut[i, j] / C[sel]) ** nu
                    else:
                        v = self._knot_values(t, name, a[sel], nu, is_on)
                    out[name][sel] += ws.reshape((-1,) + (1,) * len(trail[name])) * v
        if blend and np.any(on):
            self._blend_fields(blend, W, r, on, out)
        return out, on, used

    def _stacked(self):
        """The grid flows' cubic pieces of the cycle data in u, stacked for :func:`_blend` (made
        on first use): knot index per (i, j), breakpoints (K, P) and coefficients
        (K, 4, P - 1, 4 n_phase n_s), x, y, fx, fy side by side; each grid flow's own splines
        then read their coefficients from it (views, not copies)."""
        got = self.__dict__.get("_stack")
        if got is None:
            ids = {ij: k for k, ij in enumerate(self.branch)}
            sp = [[self.knots[ij]._splines[f] for f in FIELDS] for ij in self.branch]
            P = max(s[0].x.size for s in sp)
            m = self.n_phase * self.n_s
            bx = np.full((len(sp), P), np.inf)
            nbx = np.empty(len(sp), np.int64)
            coef = np.zeros((len(sp), 4, P - 1, len(FIELDS) * m))
            for k, s in enumerate(sp):
                nb = s[0].x.size
                bx[k, :nb], nbx[k] = s[0].x, nb
                for f, one in enumerate(s):
                    coef[k, :, :nb - 1, f * m:(f + 1) * m] = one.c.reshape(4, nb - 1, m)
                    # the grid flow's own spline reads the same numbers (one copy in memory)
                    one.c = coef[k, :, :nb - 1, f * m:(f + 1) * m].reshape(one.c.shape)
            # each grid flow's variable u: sqrt(its cutoff - chi_N), or chi_N itself (no cutoff row)
            own = np.array([np.nan if self.knots[ij]._cut is None else self.knots[ij]._cut for ij in self.branch])
            got = self.__dict__["_stack"] = (ids, bx, nbx, coef, own)
        return got

    def _blend_fields(self, names, W, r, on, out) -> None:
        """The cycle data ``names`` (of FIELDS) at the points on the branch, into ``out``: each
        point's grid flows of non-zero weight, each at its point ``r chi_c`` of its branch (as
        :meth:`_evaluate`), in one compiled pass over the points (:func:`_blend`)."""
        ids, bx, nbx, coef, own = self._stacked()
        pts = np.flatnonzero(on)
        Wf = W[pts].reshape(pts.size, -1)
        rows, cols = np.nonzero(Wf)  # row-major: grouped by point
        flows = list(self.branch)
        ij = [(c // W.shape[2], c % W.shape[2]) for c in range(Wf.shape[1])]
        kid = np.array([ids.get(t, -1) for t in ij], dtype=np.int64)[cols]
        if np.any(kid < 0):  # (the stencil refuses grid flows without a branch before this)
            raise TableError(f"{self.source}: a grid flow without a flutter branch takes part")
        lo = np.array([self.branch[f][0] for f in flows])[kid]
        hi = np.array([self.branch[f][1] for f in flows])[kid]
        cut = self.cut.reshape(-1)[cols]
        x = np.clip(r[pts][rows] * cut, lo, hi)
        u = np.where(np.isnan(own[kid]), x, np.sqrt(np.maximum(own[kid] - x, 0.0)))
        ptr = np.searchsorted(rows, np.arange(pts.size + 1)).astype(np.int64)
        res = np.empty((pts.size, coef.shape[3]))
        _blend(ptr, kid, Wf[rows, cols].astype(float), u, bx, nbx, coef, res)
        m = self.n_phase * self.n_s
        for name in names:
            f = FIELDS.index(name)
            out[name][pts] = res[:, f * m:(f + 1) * m].reshape(pts.size, self.n_phase, self.n_s)

    def _scalars(self, names, a, up, uq, nu: int = 0, lower: bool = False) -> tuple[dict, np.ndarray]:
        """Scalars, the thrust's norm and angle from its interpolated components (interpolating
        the angle itself across the flows would err by up to 1 rad at U spacing 1, where a stream
        cancels part of the thrust); off the branch only the thrust (the steady state's force)
        is defined, the rest NaN."""
        need = [n for n in names if n not in _DERIVED]
        if set(names) & set(_DERIVED):
            need = sorted(set(need) | {"thrust_x", "thrust_y"})
        vals, on, _ = self._evaluate(need, a, up, uq, nu, lower)
        if set(names) & set(_DERIVED):
            x, y = vals["thrust_x"], vals["thrust_y"]
            if nu == 0:
                vals["thrust_norm"], vals["thrust_angle"] = np.hypot(x, y), thrust_angle_of(x, y)
            elif nu == 1:
                v0 = self._evaluate(["thrust_x", "thrust_y"], a, up, uq, 0, lower)[0]
                x0, y0 = v0["thrust_x"], v0["thrust_y"]
                n2 = x0 * x0 + y0 * y0
                vals["thrust_norm"] = (x0 * x + y0 * y) / np.sqrt(n2)
                vals["thrust_angle"] = (x0 * y - y0 * x) / n2
            else:
                raise TableError("derivatives of thrust_norm and thrust_angle beyond the first: take them of "
                                 "thrust_x and thrust_y")
        for n in names:
            if n not in ("thrust_x", "thrust_y") + _DERIVED:
                vals[n] = np.where(on, vals[n], np.nan)
        return vals, on

    @staticmethod
    def _mirror(name: str, v: np.ndarray, neg: np.ndarray, nu: int = 0) -> np.ndarray:
        """``f(-chi_N, U_perp) = +-f(chi_N, -U_perp)``: odd columns change sign (their
        ``nu``-th chi_N derivative with ``(-1)^(odd + nu)``)."""
        if (int(name in ODD) + nu) % 2 and np.any(neg):
            v = np.where(neg.reshape((-1,) + (1,) * (v.ndim - 1)), -v, v)
        return v

    def scalar(self, name: str, chi_N, nu: int, U_par, U_perp) -> np.ndarray:
        a, up, uq, neg, shape = self._points(chi_N, U_par, U_perp)
        t = self._lone(up, uq)
        v = t.scalar(name, a, nu) if t is not None else self._scalars([name], a, up, uq, nu)[0][name]
        return self._mirror(name, v, neg, nu).reshape(shape)

    def _cell(self, axis: int, x: np.ndarray) -> np.ndarray:
        """(n, 3): ``x`` and the points 1/3 and 2/3 across its cell of the grid of ``axis``
        (``x`` three times where it is a grid value: no interpolation in that axis)."""
        g = self.grids[axis]
        s = np.repeat(x[:, None], 3, axis=1)
        if g.size > 1:
            k = np.clip(np.searchsorted(g, x, side="right") - 1, 0, g.size - 2)
            lo, hi = g[k], g[k + 1]
            inside = (x != lo) & (x != hi)
            s[inside, 1] = (lo + (hi - lo) / 3)[inside]
            s[inside, 2] = (lo + 2 * (hi - lo) / 3)[inside]
        return s

    def _U_change(self, names, a, up, uq, on) -> dict:
        """The largest ``|cubic - quadratic|`` in U over the point and the points 1/3 and 2/3
        across its cell in each axis, at the same fraction of the cutoff (on the branch) or the
        same chi_N (off it): the change crosses zero inside a cell where the error does not."""
        su, sq = self._cell(0, up), self._cell(1, uq)
        n = a.size
        up_s = np.repeat(su, 3, axis=1).ravel()  # (n, 9): every pair of the two axes' samples
        uq_s = np.tile(sq, (1, 3)).ravel()
        C = self._stencil(up, uq)[1]
        C_s = self._stencil(up_s, uq_s)[1]
        r = np.repeat(np.where(on, a / np.where(C > 0, C, 1.0), np.nan), 9)
        a_s = np.where(np.repeat(on, 9), r * C_s, np.repeat(a, 9))
        a_s = np.clip(a_s, *self.chi_N_range)
        full = self._evaluate(names, a_s, up_s, uq_s, steady=False)[0]
        coarse = self._evaluate(names, a_s, up_s, uq_s, lower=True, steady=False)[0]
        return {k: np.nanmax(np.abs(full[k] - coarse[k]).reshape(n, 9), axis=1) for k in names}

    def interpolation_error(self, name: str, chi_N, U_par, U_perp) -> np.ndarray:
        """Estimate of ``|scalar(name, ...) - exact|``: ``SAFETY`` times the largest change from
        the quadratic to the cubic interpolant in U over the point's cell (:meth:`_U_change`),
        plus the grid flows' own estimates in chi_N, weighted by ``|weight|`` (for the thrust's
        norm and angle, from those of its components: ``e_norm = |(e_x, e_y)|``,
        ``e_angle = e_norm / |thrust|``)."""
        a, up, uq, neg, shape = self._points(chi_N, U_par, U_perp)
        t = self._lone(up, uq)
        if t is not None:
            return t.interpolation_error(name, a).reshape(shape)
        names = ["thrust_x", "thrust_y"] if name in _DERIVED else [name]
        full, on, used = self._evaluate(names, a, up, uq)
        change = self._U_change(names, a, up, uq, on)
        err = {}
        for n in names:
            e = SAFETY * change[n]
            for w, x, t in used:  # the grid flows' own chi_N interpolation, on the branch and off it
                for sel, at in ((on & (w != 0), x), (~on & (w != 0), a)):
                    if np.any(sel):
                        e[sel] += np.abs(w[sel]) * t.interpolation_error(n, at[sel])
            err[n] = e
        if name in _DERIVED:
            e = np.hypot(err["thrust_x"], err["thrust_y"])
            if name == "thrust_angle":
                e = e / np.hypot(full["thrust_x"], full["thrust_y"])
        else:
            e = err[name]
        return np.where(np.isfinite(e), e, 0.0).reshape(shape)

    def cycles(self, chi_N, U_par, U_perp) -> dict[str, np.ndarray]:
        a, up, uq, neg, shape = self._points(chi_N, U_par, U_perp)
        if len(shape) != 1:
            raise ValueError(f"chi_N must be 1-d, got shape {shape}")
        t = self._lone(up, uq)
        if t is not None:
            out = t.cycles(a)
            return {k: self._mirror(k, v, neg) if k in FIELDS else v for k, v in out.items()}
        vals, on, _ = self._evaluate(list(FIELDS), a, up, uq)
        out = {k: self._mirror(k, np.array(vals[k], dtype=float), neg) for k in FIELDS}
        for k in ("x", "y"):
            out[k][~on] = np.nan
        out["flutter"] = on
        return out

    def angle_curve(self, U_par: float, U_perp: float, n: int = 2001) -> tuple[np.ndarray, np.ndarray]:
        """``(chi_N, thrust_angle)`` along the flutter branch in the flow ``(U_par, U_perp)``."""
        t = self._lone(*self._points(0.0, U_par, U_perp)[1:3])
        if t is not None:
            xs = np.linspace(*t.flutter_range, n)
            return xs, t.scalar("thrust_angle", xs)
        C = float(self.cutoff(U_par, U_perp))
        xs = np.linspace(self.r_lo * C, self.r_hi * C, n)
        return xs, self.scalar("thrust_angle", xs, 0, U_par, U_perp)

    def row(self, chi_N: float, U_par: float, U_perp: float) -> xr.Dataset:
        """One row at ``(chi_N, U_par, U_perp)`` (``ThrustTable.at``), with
        ``thrust_interpolation_error``: the estimate of ``|thrust - exact|`` (absolute)."""
        c = float(chi_N)
        a, up, uq, neg, _ = self._points(c, U_par, U_perp)
        t = self._lone(up, uq)
        if t is not None:
            ds = t.at(float(a[0]))
            for k in ODD:
                if neg[0] and k in ds:
                    ds[k] = -ds[k]
            ds["thrust_interpolation_error"] = ((), float(self.interpolation_error("thrust_norm", c, U_par, U_perp)))
            return ds.assign_coords(chi_N=c, U_par=float(U_par), U_perp=float(U_perp))
        vals, on = self._scalars(list(SCALARS), a, up, uq)
        flutter = bool(on[0])
        fields = self._evaluate(list(FIELDS), a, up, uq, steady=False)[0]
        try:  # the steady state (unknown next to a row where the flow tips the filament over)
            rest = self._evaluate(list(REST_SCALARS + REST_FIELDS) + ["alpha", "beta"], a, up, uq, steady=False)[0]
        except TableError:
            rest = None
        ds = xr.Dataset(coords={"phase": self.ds.phase.values, "s": self.ds.s.values})
        for k in SCALARS:
            ds[k] = ((), float(self._mirror(k, vals[k], neg)[0]))
        if not flutter:  # no cycle: the steady state's eigenvalue
            for k in ("alpha", "beta"):
                ds[k] = ((), float(rest[k][0]) if rest is not None else math.nan)
        for k in FIELDS:
            v = self._mirror(k, np.array(fields[k], dtype=float), neg)[0]
            ds[k] = (("phase", "s"), v if flutter or k in ("fx", "fy") else np.full(v.shape, np.nan))
        for k in REST_SCALARS + REST_FIELDS:
            v = self._mirror(k, rest[k], neg)[0] if rest is not None else np.full(
                (self.n_s,) if k in REST_FIELDS else (), np.nan)
            ds[k] = (("s",) if k in REST_FIELDS else (), v)
        try:
            tl = limit_angle(CiliumParams(self.chi_E, self.eta, c))
        except NoLimitAngleError:
            tl = math.nan
        ds["theta_lim"] = ((), tl)
        ds["flutter"] = ((), np.int8(flutter))
        ds["coiled"] = ((), np.int8(coiled(self.chi_E, c)))
        ds["regime"] = ((), np.int8(REGIMES.index("flutter" if flutter else "stable")))
        e = self.interpolation_error("thrust_norm", c, U_par, U_perp)
        ds["thrust_interpolation_error"] = ((), float(e))
        ds.thrust_interpolation_error.attrs.update(long_name="estimate of |thrust - exact| from the interpolation",
                                                   units="1")
        return ds.assign_coords(chi_N=c, U_par=float(U_par), U_perp=float(U_perp))
