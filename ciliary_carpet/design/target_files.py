"""Control-point files of a "points" target: control points, target velocities and, when given,
their uncertainties, read from CSV or NetCDF (:func:`read_target_samples`). Every fault of a file
is a :class:`~ciliary_carpet.design.errors.TargetError` naming the file and the line or variable."""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from ciliary_carpet.design.errors import TargetError

__all__ = ["read_target_points", "read_target_samples", "CSV_SUFFIXES", "NETCDF_SUFFIXES"]

CSV_SUFFIXES = (".csv", ".txt")
NETCDF_SUFFIXES = (".nc", ".nc4", ".cdf", ".netcdf", ".h5", ".hdf5")


def read_target_points(path) -> tuple[np.ndarray, np.ndarray]:
    """Control points (P, 2) and target velocities (P, 2) from a file (:func:`read_target_samples`
    without the uncertainties)."""
    xy, uv, _ = read_target_samples(path)
    return xy, uv


def read_target_samples(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Control points (P, 2), target velocities (P, 2) and, when the file gives them (columns or
    variables ``du`` and ``dv``, both), the velocities' standard uncertainties (P, 2) (else None)
    from a file: CSV (``.csv``/``.txt``:
    a header naming the columns x, y, u, v in any order, extra columns ignored, comma- or
    whitespace-separated, ``#`` starts a comment) or NetCDF (``.nc``, ``.nc4``, ``.cdf``, ``.h5``:
    variables x, y, u, v along one common dimension). Positions in L, velocities in model units
    (L / tau), lab frame; uncertainties in L / tau, >= 0. Missing columns, one of du, dv without
    the other, non-numbers, NaN/inf, negative uncertainties and empty files are a
    :class:`TargetError` naming the file and the line or variable."""
    p = Path(path)
    if not p.is_file():
        raise TargetError(f"{p}: no such control-point file")
    suf = p.suffix.lower()
    if suf in CSV_SUFFIXES or suf in NETCDF_SUFFIXES:
        cols = (_read_csv if suf in CSV_SUFFIXES else _read_netcdf)(p)
        big = np.abs(cols) > 1e150  # squares and sums of these stay finite
        if np.any(big):
            i, j = (int(k[0]) for k in np.nonzero(big))
            raise TargetError(f"{p}: control point {i} (data row {i + 1}): {_ALL_COLS[j]} = {cols[i, j]:g}"
                              f" is beyond +-1e150; positions are in L, velocities in L / tau")
        if cols.shape[1] > 4:
            neg = np.nonzero(cols[:, 4:] < 0)
            if neg[0].size:
                i, j = int(neg[0][0]), int(neg[1][0])
                raise TargetError(f"{p}: control point {i} (data row {i + 1}): {_UNC_COLS[j]} = {cols[i, 4 + j]:g} "
                                  f"is negative; an uncertainty is >= 0 (L / tau)")
        return cols[:, :2].copy(), cols[:, 2:4].copy(), (cols[:, 4:6].copy() if cols.shape[1] > 4 else None)
    raise TargetError(f"{p}: unknown control-point file type {suf!r} (CSV: {', '.join(CSV_SUFFIXES)}; "
                      f"NetCDF: {', '.join(NETCDF_SUFFIXES)})")


_COLS = ("x", "y", "u", "v")
_UNC_COLS = ("du", "dv")
_ALL_COLS = _COLS + _UNC_COLS


def _optional_pair(p: Path, present: list) -> tuple:
    """The columns to read: x, y, u, v, and du, dv when both are ``present`` (one alone is an
    error naming the other)."""
    has = [c in present for c in _UNC_COLS]
    if any(has) and not all(has):
        there, missing = (_UNC_COLS if has[0] else _UNC_COLS[::-1])
        raise TargetError(f"{p}: column {there!r} without {missing!r}: the uncertainties of u and v come as a pair")
    return _ALL_COLS if all(has) else _COLS


def _read_csv(p: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise TargetError(f"{p}: cannot read ({exc})") from None
    lines = [(n, ln.split("#", 1)[0].strip()) for n, ln in enumerate(text.splitlines(), start=1)]
    lines = [(n, ln) for n, ln in lines if ln]
    if not lines:
        raise TargetError(f"{p}: empty file (expected a header with columns x, y, u, v and data rows)")

    def split(s: str) -> list[str]:
        if "," in s:
            return [c.strip() for c in next(csv.reader(io.StringIO(s)))]
        return s.split()

    n0, head = lines[0]
    names = [c.lower() for c in split(head)]
    missing = [c for c in _COLS if c not in names]
    if missing:
        raise TargetError(f"{p}: line {n0}: header {head!r} lacks column(s) {', '.join(missing)} "
                          f"(needs x, y, u, v)")
    want = _optional_pair(p, names)
    dup = [c for c in want if names.count(c) > 1]
    if dup:
        raise TargetError(f"{p}: line {n0}: column(s) {', '.join(dup)} appear twice in the header")
    col = {c: names.index(c) for c in want}
    rows = []
    for k, (n, ln) in enumerate(lines[1:], start=1):
        cells = split(ln)
        if len(cells) != len(names):
            raise TargetError(f"{p}: line {n} (data row {k}): {len(cells)} fields, the header has {len(names)}")
        vals = []
        for c in want:
            s = cells[col[c]]
            try:
                x = float(s)
            except ValueError:
                raise TargetError(f"{p}: line {n} (data row {k}): column {c!r} is not a number: {s!r}") from None
            if not math.isfinite(x):
                raise TargetError(f"{p}: line {n} (data row {k}): column {c!r} is {s!r}; every value must be finite")
            vals.append(x)
        rows.append(vals)
    if not rows:
        raise TargetError(f"{p}: no data rows after the header")
    return np.array(rows)


def _read_netcdf(p: Path) -> tuple[np.ndarray, np.ndarray]:
    import xarray as xr

    try:
        with xr.open_dataset(p) as ds:
            ds = ds.load()
    except Exception as exc:  # h5netcdf/scipy raise OSError, ValueError, KeyError, ...
        raise TargetError(f"{p}: not a readable NetCDF file ({type(exc).__name__}: {exc})") from None
    missing = [c for c in _COLS if c not in ds.variables]
    if missing:
        raise TargetError(f"{p}: missing variable(s) {', '.join(missing)} (needs x, y, u, v along one dimension)")
    arrs = {}
    want = _optional_pair(p, list(ds.variables))
    dims = {c: ds[c].dims for c in want}
    for c in want:
        if len(dims[c]) != 1:
            raise TargetError(f"{p}: variable {c!r} must be 1-d, has dims {dims[c]}")
    if len({dims[c] for c in want}) != 1:
        raise TargetError(f"{p}: variables {', '.join(want)} must share one dimension, have "
                          f"{', '.join(f'{c}{dims[c]}' for c in want)}")
    for c in want:
        try:
            v = np.asarray(ds[c].values, dtype=float)
        except (TypeError, ValueError):
            raise TargetError(f"{p}: variable {c!r} is not numeric (dtype {ds[c].dtype})") from None
        bad = np.nonzero(~np.isfinite(v))[0]
        if bad.size:
            raise TargetError(f"{p}: variable {c!r} is not finite at index {int(bad[0])} (along "
                              f"'{dims[c][0]}'; {bad.size} such values); x, y, u, v must be finite")
        arrs[c] = v
    if arrs["x"].size == 0:
        raise TargetError(f"{p}: no control points (dimension '{dims['x'][0]}' is empty)")
    return np.column_stack([arrs[c] for c in want])
