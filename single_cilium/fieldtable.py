"""A thrust table over chi_E: the table of a field between the grid's fields.

:class:`~single_cilium.lookup.ThrustTable` serves any field strength in the span of a table over
chi_E by :func:`field_between`: at a fixed fraction ``r = chi_N / chi_c(chi_E)`` of the flutter
cutoff. The cutoff ``chi_c(chi_E)`` is interpolated (polynomial spline of degree
``min(3, n - 1)`` through the fields' cutoffs), every field's table is evaluated at
``r chi_c(chi_E_j)`` (so that the Hopf onsets line up), and each scalar, shape and force is
interpolated across the fields by the same spline in chi_E; the nodes in ``r`` are those of the
nearest field. Rows above ``chi_c(chi_E)`` have no flutter; ``alpha`` and ``beta`` there are linear
in chi_E between the neighbouring fields (NaN where coiled).

Interpolation error in chi_E, measured against fresh cycles (:func:`limit_cycle`, same
discretisation: degree 8, 64 steps; chi_N grid 0:200:21; eta = 1; at chi_E = 195 and 205,
chi_N = 0 to 0.97 chi_c; benchmarks/bench_table_chi_E.py, results in
benchmarks/results/bench_cycles.md; a coarser case is asserted in tests/test_table.py):

* fields 180, 200, 220 (spacing 20, a parabola in chi_E): cutoff 1.6e-4, period 1.4e-4,
  abs thrust 4e-4 up to 0.75 chi_c (1.2e-3 at 0.9, 4.8e-3 at 0.97), angle 1.5e-4 rad,
  shape x 3.1e-4;
* fields 180:220:5 (spacing 10, a cubic spline): cutoff 2.1e-6, period 1.4e-6, abs thrust
  1.8e-5 up to 0.9 chi_c (9.7e-5 at 0.97), angle 1.7e-6 rad, shape x 7.5e-5

(relative, maximum over the points; the thrust, which vanishes at the cutoff, is worst
there). Halving the spacing, with the spline degree rising from 2 to 3, gains a factor of
about 100; the chi_N spacing of the grid contributes the one-field table's own error.
"""
from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.interpolate import make_interp_spline

from .equilibrium import NoLimitAngleError, limit_angle
from .params import CiliumParams
from .tablefile import FIELDS, REST_FIELDS, REST_SCALARS, SCALARS, coiled, grid_text, regime_of

__all__ = ["field_between"]


def field_between(ds: xr.Dataset, knots: dict, E: float) -> xr.Dataset:
    """The one-field Dataset at ``E`` (between the fields ``knots``: ``chi_E -> ThrustTable``, each
    with a flutter branch and a cutoff) of the table over chi_E ``ds``, interpolated at fixed
    fractions of the cutoff (module docstring)."""
    Es = np.array(sorted(knots))
    tabs = [knots[e] for e in Es]
    k = min(3, Es.size - 1)

    def across(values):  # (n_fields, ...) -> value at E
        return make_interp_spline(Es, np.asarray(values), k=k, axis=0, check_finite=False)(E)

    cj = np.array([float(t.ds.attrs["chi_N_cutoff"]) for t in tabs])
    c = float(across(cj))
    # the fractions of the cutoff that every field's branch covers
    ranges = [t.flutter_range for t in tabs]
    r_lo = max(b[0] / cc for b, cc in zip(ranges, cj))
    r_hi = min(b[1] / cc for b, cc in zip(ranges, cj))
    to_cutoff = all(b[1] == cc for b, cc in zip(ranges, cj))  # every branch ends at its cutoff row
    near = int(np.argmin(np.abs(Es - E)))
    t = tabs[near]
    r = t.ds.chi_N.values[t.ds.flutter.values.astype(bool)] / cj[near]
    r = np.unique(np.concatenate([[r_lo, r_hi], r[(r > r_lo * (1 + 1e-12)) & (r < r_hi * (1 - 1e-12))]]))
    if to_cutoff:
        r[-1] = 1.0
    n = r.size
    scal = {}
    for name in SCALARS:
        vals = []
        for t, cc, b in zip(tabs, cj, ranges):
            vals.append(t.scalar(name, np.clip(r * cc, *b)))  # NaN where the column was not computed
        scal[name] = across(vals)
    cyc = [t.cycles(np.clip(r * cc, *b)) for t, cc, b in zip(tabs, cj, ranges)]
    fields = {name: across([cy[name] for cy in cyc]) for name in FIELDS}
    if to_cutoff:  # the last row is the zero-amplitude cycle at the cutoff, as in a one-field build
        for name in ("thrust_norm", "thrust_x", "thrust_y", "tip_area"):
            scal[name][-1] = 0.0
        scal["thrust_angle"][-1] = np.nan
        fields["fx"][-1] = fields["fy"][-1] = 0.0
    chi = r * c
    # rows of the grid above the cutoff: no flutter (none when a branch ends before its cutoff:
    # the table then ends with the branch)
    grid = ds.chi_N.values
    above = grid[grid > c * (1 + 1e-12)] if to_cutoff else grid[:0]
    m = above.size
    for name in SCALARS:
        scal[name] = np.concatenate([scal[name], np.full(m, np.nan)])
    for name in ("thrust_norm", "thrust_x", "thrust_y", "tip_area"):
        scal[name][n:] = 0.0
    for name in ("alpha", "beta"):  # linear in chi_E between the neighbouring fields
        col = ds[name].sel(chi_N=above).transpose("chi_N", "chi_E").values
        allE = ds.chi_E.values
        scal[name][n:] = [np.interp(E, allE, v) for v in col]
    for i, a in enumerate(above):
        p = CiliumParams(E, float(ds.attrs["eta"]), float(a))
        try:
            scal["theta_lim"][n + i] = limit_angle(p) if not coiled(E, a) else np.nan
        except NoLimitAngleError:
            scal["theta_lim"][n + i] = np.nan
    n_p, n_s = ds.sizes["phase"], ds.sizes["s"]
    for name in FIELDS:
        fields[name] = np.concatenate([fields[name], np.full((m, n_p, n_s), np.nan)])
    chi_all = np.concatenate([chi, above])
    out = xr.Dataset({name: ("chi_N", v) for name, v in scal.items()},
                     coords={"chi_N": chi_all, "phase": ds.phase.values, "s": ds.s.values})
    out["flutter"] = ("chi_N", np.r_[np.ones(n, np.int8), np.zeros(m, np.int8)])
    out["coiled"] = ("chi_N", np.array([coiled(E, x) for x in chi_all], np.int8))
    for name, v in fields.items():
        out[name] = (("chi_N", "phase", "s"), v)
    if "regime" in ds:  # version 2: still fluid, so the rest state exerts no force
        out["regime"] = ("chi_N", regime_of(out).astype(np.int8))
        for name in REST_SCALARS:
            out[name] = ("chi_N", np.zeros(chi_all.size))
        for name in REST_FIELDS:
            out[name] = (("chi_N", "s"), np.zeros((chi_all.size, n_s)))
    err = float(across(ds.chi_N_cutoff_error.sel(chi_E=Es).values))
    out.attrs = {**ds.attrs, "chi_E": E, "chi_N_cutoff": c, "chi_N_cutoff_error": err,
                 "interpolated": f"in chi_E between the fields {grid_text(Es)} at fixed chi_N / chi_N_cutoff"}
    return out
