"""The thrust table file: its schema, its validation on load, and the error a table raises.

Shared by the builder (:mod:`single_cilium.table`) and the reader (:mod:`single_cilium.lookup`);
the front door for both is :mod:`single_cilium.table`.

Schema, version 2 (``SCHEMA_VERSION``; what :func:`~single_cilium.table.build_table` writes)
---------------------------------------------------------------------------------------------
Dims ``chi_N`` (>= 0, strictly increasing), ``phase`` (uniform in [0, 1)), ``s`` (uniform in
[0, 1]); per chi_N ``flutter`` (int8 0/1), ``period``, ``thrust_norm``, ``thrust_angle``,
``thrust_x``, ``thrust_y``, ``theta_lim``, ``alpha``, ``beta``, ``floquet``, ``tip_area`` and
the error estimates ``period_error``, ``thrust_norm_error``, ``thrust_angle_error``,
``floquet_trivial_error``; per (chi_N, phase, s) ``x``, ``y``, ``fx``, ``fy`` (force per length
on the fluid, ``-d``); ``coiled`` (int8; 1 where ``|chi_N| > |chi_E|``: no equilibrium, the row is
not computed). Rows without flutter: period NaN, cycle data NaN, thrust the rest state's (below).
Attributes ``chi_E``, ``eta``, ``chi_N_cutoff``, ``chi_N_cutoff_error``, ``schema_version`` and
``build_*`` (what the rows were computed for).

Version 2 adds, per chi_N:

* ``regime`` (int8, CF ``flag_values`` / ``flag_meanings``): ``REGIMES[regime]``, one of
  ``stable`` (the steady state is stable: no cycle), ``flutter``, ``divergence`` (the steady
  state is unstable without oscillating: no steady or periodic thrust, NaN), ``no_steady_state``
  (the background flow tips the filament over: a fold, NaN), ``coiled`` and ``not_computed``
  (a row of the shared chi_N grid that belongs to another background flow's cutoff, NaN);
* ``rest_thrust_x``, ``rest_thrust_y``: the force ``-int d ds`` of the filament held at its
  steady state in the background flow, on the fluid (0 in still fluid; for every row with a
  steady state, flutter rows included: it is smooth across the cutoff) and per (chi_N, s)
  ``rest_fx``, ``rest_fy``, its force per length on the fluid. A row without flutter has
  ``thrust = rest thrust`` (and NaN in divergence).

A table over chi_E has a leading dimension ``chi_E`` (> 0, strictly increasing): per
(chi_E, chi_N) the scalars, per (chi_E, chi_N, phase, s) the fields, and per chi_E
``chi_N_cutoff`` and ``chi_N_cutoff_error`` as variables (no ``chi_E`` attribute; the ``chi_N``
grid holds every field's cutoff, each a plain row for the other fields).

A table over the background flow (version 2 only) has the leading dimensions ``U_par`` and
``U_perp`` (each finite and strictly increasing; one value or more): the uniform flow
``U = U_par e2 + U_perp e1`` the filament sits in, in the field frame (``e2`` along the field;
``U_perp > 0`` along ``+e1``, the side away from which a positive chi_N bends the filament), in
units of ``L / tau``; ``CiliumParams(..., background=(U_perp, U_par))``. Per (U_par, U_perp)
``chi_N_cutoff`` and ``chi_N_cutoff_error`` (NaN where there is no cutoff); the ``chi_N`` grid
holds every flow's cutoff, a row computed only for its own flow (``regime = not_computed``
elsewhere). Attributes ``chi_E``, ``eta`` and ``background_frame``.

Version 1 tables (no ``regime``, no ``rest_*``, no background flow) load unchanged: their
regime follows from ``flutter`` and ``coiled``, their rest thrust is 0 (still fluid).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import xarray as xr

__all__ = ["TableError", "SCHEMA_VERSION", "SCALARS", "FIELDS", "REST_SCALARS", "REST_FIELDS", "REGIMES",
           "ODD", "SAFETY", "coiled", "grid_text", "with_attrs", "validate", "read", "regime_of", "compact"]

SCHEMA_VERSION = 2
READABLE = (1, 2)
SCALARS = ("period", "thrust_norm", "thrust_angle", "thrust_x", "thrust_y", "theta_lim", "alpha", "beta",
           "floquet", "tip_area", "period_error", "thrust_norm_error", "thrust_angle_error",
           "floquet_trivial_error")
FIELDS = ("x", "y", "fx", "fy")
REST_SCALARS = ("rest_thrust_x", "rest_thrust_y")
REST_FIELDS = ("rest_fx", "rest_fy")
REGIMES = ("stable", "flutter", "divergence", "no_steady_state", "coiled", "not_computed")
#: columns that change sign under the mirror image chi_N -> -chi_N (e1 -> -e1)
ODD = ("thrust_x", "thrust_angle", "theta_lim", "tip_area", "rest_thrust_x", "x", "fx", "rest_fx")
U_DIMS = ("U_par", "U_perp")
#: interpolation error estimates are this factor times the largest change from the quadratic to
#: the cubic interpolant over the point's cell (over the shipped flow table's 120 check points the
#: error is at most 0.36 of the estimate: single_cilium.flowtable, bench_table_flow.md section 4)
SAFETY = 2.0
FRAME = ("field frame: U = U_par e2 + U_perp e1, e2 along the field, U_perp > 0 along +e1; units L / tau; "
         "CiliumParams(..., background=(U_perp, U_par))")


class TableError(ValueError):
    """A table file or request that cannot be served; the message names the problem."""


def coiled(chi_E: float, chi_N: float) -> bool:
    """``|chi_E| < |chi_N|``: no fixed point, the filament coils (no limit angle, no row computed)."""
    return abs(chi_E) < abs(chi_N)


def grid_text(values) -> str:
    return ",".join(f"{float(v):.17g}" for v in values)


_LONG = {
    "flutter": "1 if the equilibrium flutters (a limit cycle exists)", "period": "period of the limit cycle",
    "thrust_norm": "|mean force on the fluid over one period|",
    "thrust_angle": "angle of the mean force from e2, minus pi, in (-pi, pi]",
    "thrust_x": "mean force on the fluid, e1", "thrust_y": "mean force on the fluid, e2",
    "theta_lim": "limit angle of the equilibrium", "alpha": "growth rate of the leading eigenvalue",
    "beta": "angular frequency of the leading eigenvalue", "floquet": "largest non-trivial Floquet multiplier modulus",
    "tip_area": "signed area enclosed by the tip orbit", "period_error": "relative error estimate of period",
    "thrust_norm_error": "relative error estimate of thrust_norm",
    "thrust_angle_error": "absolute error estimate of thrust_angle (rad)",
    "floquet_trivial_error": "distance of the trivial Floquet multiplier from 1",
    "coiled": "1 if |chi_E| < |chi_N| (no equilibrium: the filament coils; not computed)",
    "x": "position along e1", "y": "position along e2", "fx": "force per length on the fluid, e1",
    "fy": "force per length on the fluid, e2",
    "rest_thrust_x": "force on the fluid of the steady state in the background flow, e1",
    "rest_thrust_y": "force on the fluid of the steady state in the background flow, e2",
    "rest_fx": "force per length on the fluid of the steady state, e1",
    "rest_fy": "force per length on the fluid of the steady state, e2",
}


def with_attrs(ds: xr.Dataset) -> xr.Dataset:
    """CF-style ``long_name`` and ``units`` on every variable of a built table."""
    for k, v in _LONG.items():
        if k in ds:
            ds[k].attrs.update(long_name=v, units="1")
    if "regime" in ds:
        ds.regime.attrs.update(long_name="what the row holds", flag_values=np.arange(len(REGIMES), dtype=np.int8),
                               flag_meanings=" ".join(REGIMES), units="1")
    ds.chi_N.attrs.update(long_name="natural curvature L kappa_N", units="1")
    ds.phase.attrs.update(long_name="phase t/T from the upward crossing of the tip angle through its mean",
                          units="1")
    ds.s.attrs.update(long_name="arc length / filament length", units="1")
    for k, what in (("U_par", "background flow along the field (e2)"),
                    ("U_perp", "background flow across the field (e1)")):
        if k in ds.dims:
            ds[k].attrs.update(long_name=what, units="L / tau")
    return ds


def compact(ds: xr.Dataset, phase_step: int = 2, bits: int = 13) -> xr.Dataset:
    """A table stored with what accuracy needs: the fields ``x, y, fx, fy`` (and ``rest_fx``,
    ``rest_fy``) at every ``phase_step``-th phase sample, in float32 rounded to ``bits`` bits of
    mantissa (relative rounding ``2**-(bits + 1)``: 6e-5 for 13) so that zlib (with byte shuffle,
    level 9, on every variable) packs them; the scalars stay float64 and every row as computed.

    The cycles themselves are unchanged (each was computed with its own number of steps); the
    phase samples set how finely a carpet resolves the beat in time, the rounding a relative
    change far below the interpolation error. Returns a new Dataset; the attribute ``storage``
    says what was kept."""
    if int(phase_step) < 1 or ds.sizes["phase"] % int(phase_step):
        raise ValueError(f"phase_step must divide the {ds.sizes['phase']} phase samples, got {phase_step!r}")
    if not 8 <= int(bits) <= 23:
        raise ValueError(f"bits must be in [8, 23] (float32 keeps 23), got {bits!r}")
    out = ds.isel(phase=slice(None, None, int(phase_step))).copy()
    drop = 23 - int(bits)
    half, mask = np.uint32(1 << (drop - 1)) if drop else np.uint32(0), np.uint32((0xFFFFFFFF >> drop) << drop)
    for k in out.data_vars:
        enc = {"zlib": True, "complevel": 9, "shuffle": True}
        if k in FIELDS + REST_FIELDS:
            v = np.ascontiguousarray(out[k].values, dtype=np.float32)
            b = v.view(np.uint32)
            r = np.where(np.isfinite(v), (b + half) & mask, b).astype(np.uint32).view(np.float32)
            out[k] = (out[k].dims, r, out[k].attrs)
            enc["dtype"] = "float32"
        out[k].encoding = enc
    out.attrs["field_bits"] = int(bits)  # what a reader may trust of the fields (a carpet's harmonics)
    out.attrs["storage"] = (f"fields x, y, fx, fy, rest_fx, rest_fy: every {int(phase_step)} phase samples of the "
                            f"{ds.sizes['phase']} computed, float32 rounded to {int(bits)} mantissa bits (relative "
                            f"{2.0 ** -(int(bits) + 1):.1e}); scalars float64 as computed")
    return out


def regime_of(ds: xr.Dataset) -> np.ndarray:
    """The ``regime`` codes of a table's rows (derived from ``flutter`` and ``coiled`` for a
    version 1 table)."""
    if "regime" in ds:
        return ds.regime.values.astype(int)
    fl = ds.flutter.values.astype(int)
    co = ds.coiled.values.astype(int) if "coiled" in ds else np.zeros_like(fl)
    return np.where(co == 1, REGIMES.index("coiled"), np.where(fl == 1, REGIMES.index("flutter"), 0))


def _grid_ok(v: np.ndarray, positive: bool = False) -> bool:
    return (v.size > 0 and bool(np.all(np.isfinite(v))) and bool(np.all(np.diff(v) > 0))
            and (not positive or v[0] > 0))


def validate(ds: xr.Dataset, source: str) -> xr.Dataset:
    """``ds`` if it is a thrust table of a version this package reads (schema above); else a
    :class:`TableError` naming ``source`` and what is wrong."""
    missing = [k for k in SCALARS + FIELDS + ("flutter",) if k not in ds]
    if missing or "chi_N" not in ds.dims:
        raise TableError(f"{source}: not a thrust table (missing {missing or 'dim chi_N'})")
    v = ds.attrs.get("schema_version")
    if v not in READABLE:
        raise TableError(f"{source}: table schema version {v!r}, this package reads versions "
                         f"{', '.join(map(str, READABLE))}: rebuild it with build_table")
    if v >= 2:
        lack = [k for k in ("regime",) + REST_SCALARS + REST_FIELDS if k not in ds]
        if lack:
            raise TableError(f"{source}: a version {v} table without {lack}")
        r = ds.regime.values
        if np.any((r < 0) | (r >= len(REGIMES))):
            raise TableError(f"{source}: regime codes must lie in 0..{len(REGIMES) - 1}")
    two_d = "chi_E" in ds.dims
    stream = [d for d in U_DIMS if d in ds.dims]
    if stream:
        if len(stream) != 2:
            raise TableError(f"{source}: a table over the background flow needs both dims {U_DIMS}, has {stream}")
        if v < 2:
            raise TableError(f"{source}: a version {v} table cannot hold a background flow grid")
        if two_d:
            raise TableError(f"{source}: a table over both chi_E and the background flow is not supported")
        for d in U_DIMS:
            if not _grid_ok(ds[d].values):
                raise TableError(f"{source}: {d} coordinate must be finite and strictly increasing")
    if two_d or stream:
        lack = [k for k in ("chi_N_cutoff", "chi_N_cutoff_error") if k not in ds]
        if lack:
            raise TableError(f"{source}: a table over {'chi_E' if two_d else 'the background flow'} without {lack}")
    if two_d and not _grid_ok(ds.chi_E.values, positive=True):
        raise TableError(f"{source}: chi_E coordinate must be finite, > 0 and strictly increasing")
    for k in ("eta",) if two_d else ("chi_E", "eta"):
        if k not in ds.attrs:
            raise TableError(f"{source}: attribute {k!r} missing")
        val = ds.attrs[k]
        try:
            ok = np.ndim(val) == 0 and not isinstance(val, (str, bytes)) and math.isfinite(float(val))
        except (TypeError, ValueError):
            ok = False
        if not ok or (k == "eta" and float(val) <= 0):
            need = "a finite number > 0" if k == "eta" else "a finite number"
            raise TableError(f"{source}: attribute {k!r} = {val!r} is not {need}")
    if not _grid_ok(ds.chi_N.values):
        raise TableError(f"{source}: chi_N coordinate must be finite and strictly increasing")
    return ds


def read(path) -> xr.Dataset:
    """The Dataset of a table file, validated; a missing, corrupt or foreign file raises
    :class:`TableError`."""
    path = Path(path)
    if not path.exists():
        raise TableError(f"{path}: no such table file")
    if not path.is_file():  # a named pipe would hang the reader
        raise TableError(f"{path}: not a regular file (a folder, named pipe or device); a table is a NetCDF file")
    try:
        with xr.open_dataset(path, engine="h5netcdf") as ds:
            ds = ds.load()
    except Exception as exc:  # h5py/h5netcdf raise OSError, ValueError, KeyError, ...
        raise TableError(f"{path}: not a readable NetCDF4/HDF5 table ({type(exc).__name__}: {exc})") from None
    return validate(ds, str(path))
