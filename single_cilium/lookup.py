"""The thrust lookup table: :class:`ThrustTable`, a validated table Dataset (schema in
:mod:`single_cilium.tablefile`) with interpolation and inversion.

It interpolates smoothly in chi_N (cubic splines on the flutter branch; for the shapes and forces
in ``sqrt(chi_c - chi_N)``, in which their Hopf onset is smooth), inverts the thrust angle, and
mirrors negative chi_N; a table over chi_E is interpolated in chi_E too, at fixed fractions of
each field's cutoff, and a table over the background flow in ``(U_par, U_perp)``
(:mod:`single_cilium.flowtable`). Built by :func:`single_cilium.table.build_table`; the front door
for both is :mod:`single_cilium.table`.

One concept: one class, whose every lookup serves the three kinds of table through one signature.
"""
from __future__ import annotations

import math
from importlib import resources
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.interpolate import CubicSpline, make_interp_spline
from scipy.optimize import brentq

from cilia_runtime.files import write_netcdf
from .equilibrium import NoLimitAngleError, limit_angle
from .fieldtable import field_between
from .flowtable import FlowGrid, thrust_angle_of
from .params import CiliumParams
from .tablefile import (FIELDS, ODD, REGIMES, REST_FIELDS, REST_SCALARS, SAFETY, SCALARS, U_DIMS, TableError,
                        coiled, read, regime_of, validate)

__all__ = ["ThrustTable", "DEFAULT_FILE", "DEFAULT_FLOW_FILE", "FLOW_FILE_150", "SHIPPED_FIELDS", "SHIPPED_TABLES",
           "shipped_field"]

DEFAULT_FILE = "table_chiE200_eta1.nc"
"""The shipped table over chi_N in still fluid (chi_E = 200, eta = 1)."""
DEFAULT_FLOW_FILE = "flow_chiE200_eta1.nc"
"""The shipped table over the background flow (chi_E = 200, eta = 1): what a coupled carpet of
that field reads (:meth:`ThrustTable.default` with ``flow=True``)."""
FLOW_FILE_150 = "flow_chiE150_eta1.nc"
"""The shipped table over the background flow for chi_E = 150, eta = 1 (the grid of
:data:`DEFAULT_FLOW_FILE`); its flow U = 0 is that field's still-fluid table."""
SHIPPED_FIELDS = (150.0, 200.0)
"""The field strengths chi_E (eta = 1) whose tables ship with single_cilium
(:meth:`ThrustTable.default`)."""
SHIPPED_TABLES = {150.0: (FLOW_FILE_150, FLOW_FILE_150), 200.0: (DEFAULT_FILE, DEFAULT_FLOW_FILE)}
"""Each shipped field's files in ``single_cilium/data``: (the still-fluid table's, the table over
the background flow's); a field shipped only over the flow names that file twice (its still-fluid
table is the flow U = 0 of it, :meth:`ThrustTable.in_still_fluid`)."""


def shipped_field(chi_E: float) -> float | None:
    """The shipped field (:data:`SHIPPED_FIELDS`) equal to ``chi_E`` within 1e-9 relative, or
    None when no table ships for it."""
    x = float(chi_E)
    return next((c for c in SHIPPED_FIELDS if abs(c - x) <= 1e-9 * max(abs(c), abs(x))), None)

_THRUST = ("thrust_x", "thrust_y", "thrust_norm", "thrust_angle")
_STEADY = ("stable", "flutter", "divergence")  # rows with a steady state (its force and spectrum)
#: what :meth:`ThrustTable.rest` serves: the steady state's force, force per length and leading eigenvalue
REST = REST_SCALARS + REST_FIELDS + ("alpha", "beta")


class ThrustTable:
    """The thrust table of one field, over a grid of fields, or over a grid of background flows:
    a validated Dataset with interpolation and inversion.

    A table over chi_E (dims ``chi_E, chi_N``, from ``build_table([chi_E, ...], eta, chi_N)``)
    serves any field strength in :attr:`chi_E_range` through the keyword ``chi_E=`` of
    :meth:`at`, :meth:`scalar`, :meth:`cycles`, :meth:`thrust_angle_range` and
    :meth:`chi_N_for_angle` (required there; a one-field table accepts only its own chi_E).
    At a field value of the grid this is that field's table exactly; between grid values the
    field's table is interpolated at fixed fractions of its flutter cutoff (how, and its
    error, in :mod:`single_cilium.fieldtable`).

    A table over the background flow (dims ``U_par, U_perp, chi_N``, from
    ``build_table(chi_E, eta, chi_N, U_par=..., U_perp=...)``) serves any flow in its grid's
    rectangle through the keywords ``U_par=``, ``U_perp=`` (default 0, still fluid) of the same
    methods, vectorised for :meth:`scalar` and :meth:`cycles`; how, and its error, in
    :mod:`single_cilium.flowtable` (:meth:`interpolation_error`). A table without that grid
    serves still fluid only. In a flow the thrust of a filament that does not flutter is the
    force of its steady state in the flow (:meth:`rest`), not zero.
    """

    def __init__(self, ds: xr.Dataset, source: str = "<memory>"):
        self.ds = validate(ds, source)
        self._source = source
        self._fields: dict[float, ThrustTable] = {}
        self._flow: FlowGrid | None = None
        if "chi_E" in self.ds.dims:
            self._init_grid()
            return
        if U_DIMS[0] in self.ds.dims:
            self._init_flow()
            return
        self._init_one()

    def _init_one(self) -> None:
        """Splines of one field in one flow: the flutter branch, and the steady state over all rows."""
        ds = self.ds
        fl = ds.flutter.values.astype(bool)
        c = ds.chi_N.values
        self._regime = regime_of(ds)
        self._U = (float(ds.attrs.get("U_par", 0.0)), float(ds.attrs.get("U_perp", 0.0)))
        self._branch = c[fl]
        self._splines = {}
        self._quadratic = {}
        # near the Hopf cutoff the amplitude grows like sqrt(chi_c - chi_N): in the variable
        # u = sqrt(chi_c - chi_N) shapes and forces are smooth, so their splines use it when the
        # branch ends at the cutoff row; the scalars (thrust ~ amplitude^2) are smooth in chi_N
        chi_c = float(ds.attrs.get("chi_N_cutoff", np.nan))
        self._cut = chi_c if self._branch.size and np.isfinite(chi_c) and self._branch[-1] == chi_c else None
        if self._branch.size >= 2:
            for k in SCALARS:
                v = ds[k].values[fl]
                ok = np.isfinite(v)
                if ok.sum() >= 2:
                    self._splines[k] = CubicSpline(self._branch[ok], v[ok])
                    if ok.sum() >= 3:  # for the interpolation error estimate
                        self._quadratic[k] = make_interp_spline(self._branch[ok], v[ok], k=2)
            u = self._u(self._branch)
            order = np.argsort(u)
            for k in FIELDS:
                self._splines[k] = CubicSpline(u[order], ds[k].values[fl][order], axis=0)
        # the steady state (its force and leading eigenvalue): smooth across the cutoff, over
        # every row that has one
        have = np.isin(self._regime, [REGIMES.index(r) for r in _STEADY]) & np.isfinite(ds.alpha.values)
        self._rest: dict[str, CubicSpline] = {}
        self._rest_quadratic: dict = {}  # for the interpolation error estimate
        self._rest_rows = c[have]
        if have.sum() >= 2:
            for k in REST:
                if k in ds:
                    self._rest[k] = CubicSpline(c[have], ds[k].values[have], axis=0)
                    if have.sum() >= 3 and k in REST_SCALARS:
                        self._rest_quadratic[k] = make_interp_spline(c[have], ds[k].values[have], k=2)

    # ------------------------------------------------------------------ tables over chi_E
    def _init_grid(self) -> None:
        """The fields' own tables, and the ones with a flutter branch and a cutoff (interpolated
        between)."""
        ds = self.ds
        self._grid = {}
        for i, E in enumerate(ds.chi_E.values.tolist()):
            one = ds.isel(chi_E=i).drop_vars(["chi_E", "chi_N_cutoff", "chi_N_cutoff_error"])
            one.attrs = {**ds.attrs, "chi_E": E, "chi_N_cutoff": float(ds.chi_N_cutoff[i]),
                         "chi_N_cutoff_error": float(ds.chi_N_cutoff_error[i])}
            self._grid[E] = ThrustTable(one, f"{self._source} (chi_E = {E:g})")
        self._knots = [E for E, t in self._grid.items()
                       if t._branch.size >= 2 and np.isfinite(float(t.ds.attrs["chi_N_cutoff"]))]

    # ------------------------------------------------------------------ tables over the flow
    def _init_flow(self) -> None:
        """The tables of the grid's flows (their own rows only), interpolated between by
        :class:`~single_cilium.flowtable.FlowGrid`."""
        ds = self.ds
        knots = {}
        for a, up in enumerate(ds.U_par.values.tolist()):
            for b, uq in enumerate(ds.U_perp.values.tolist()):
                one = ds.isel(U_par=a, U_perp=b).drop_vars(["U_par", "U_perp", "chi_N_cutoff", "chi_N_cutoff_error"])
                own = one.regime.values != REGIMES.index("not_computed")
                one = one.isel(chi_N=np.flatnonzero(own))
                one.attrs = {**ds.attrs, "U_par": up, "U_perp": uq,
                             "chi_N_cutoff": float(ds.chi_N_cutoff[a, b]),
                             "chi_N_cutoff_error": float(ds.chi_N_cutoff_error[a, b])}
                knots[(a, b)] = ThrustTable(one, f"{self._source} (U_par = {up:g}, U_perp = {uq:g})")
        self._flow = FlowGrid(ds, knots, self._source)

    @property
    def chi_E_range(self) -> tuple[float, float]:
        """The field strengths the table serves: its own chi_E (one field), or the span of the
        grid's fields with a flutter branch and a cutoff (a table over chi_E)."""
        if "chi_E" not in self.ds.dims:
            return self.chi_E, self.chi_E
        if len(self._knots) < 2:
            raise TableError(f"{self._source}: fewer than two fields of the chi_E grid have a flutter branch "
                             "and a cutoff: nothing to interpolate in chi_E")
        return self._knots[0], self._knots[-1]

    @property
    def U_range(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """``((U_par_min, U_par_max), (U_perp_min, U_perp_max))``: the background flows the table
        serves (field frame, ``L / tau``; all zero for a table in still fluid)."""
        if self._flow is None:
            return (0.0, 0.0), (0.0, 0.0)
        return self._flow.U_range

    def _table(self, chi_E, U_par=None, U_perp=None) -> "ThrustTable":
        """The one-field table that serves ``chi_E`` (see the class docstring); a table over the
        flow serves itself."""
        if self._flow is None and ((U_par is not None and np.any(np.asarray(U_par) != 0))
                                   or (U_perp is not None and np.any(np.asarray(U_perp) != 0))):
            raise TableError(f"{self._source}: this table is for still fluid only (asked a background flow "
                             "U_par, U_perp): build one over the flow (build_table(chi_E, eta, chi_N, U_par=..., "
                             "U_perp=...))")
        if "chi_E" not in self.ds.dims:
            if chi_E is not None and float(chi_E) != self.chi_E:
                raise TableError(f"this table is for chi_E = {self.chi_E:g} only (asked {chi_E!r}): build one "
                                 "over a chi_E grid (build_table([chi_E, ...], eta, chi_N)) to vary the field")
            return self
        if chi_E is None:
            lo, hi = self.ds.chi_E.values[[0, -1]]
            raise TableError(f"this table spans chi_E in [{lo:g}, {hi:g}]: say which field (chi_E=...)")
        E = float(chi_E)
        if not math.isfinite(E):
            raise TableError(f"chi_E must be finite, got {chi_E}")
        if E in self._grid:
            return self._grid[E]
        if E not in self._fields:
            lo, hi = self.chi_E_range
            if not lo <= E <= hi:
                raise TableError(f"chi_E = {E:g} is outside the table's range [{lo:g}, {hi:g}] (fields with a "
                                 "flutter branch)")
            if len(self._fields) >= 32:
                self._fields.pop(next(iter(self._fields)))
            one = field_between(self.ds, {e: self._grid[e] for e in self._knots}, E)
            self._fields[E] = ThrustTable(one, f"{self._source} interpolated at chi_E = {E:g}")
        return self._fields[E]

    def _u(self, chi_N):
        chi_N = np.asarray(chi_N, dtype=float)
        return np.sqrt(np.maximum(self._cut - chi_N, 0.0)) if self._cut is not None else chi_N

    @property
    def chi_E(self) -> float:
        """The field of a one-field table (a table over chi_E has none: see :attr:`chi_E_range`)."""
        if "chi_E" in self.ds.dims:
            raise TableError(f"{self._source}: a table over chi_E in {self.ds.chi_E.values.tolist()} has no single "
                             "chi_E: pass chi_E=... to at, scalar, cycles, thrust_angle_range, chi_N_for_angle")
        return float(self.ds.attrs["chi_E"])

    @property
    def eta(self) -> float:
        return float(self.ds.attrs["eta"])

    @property
    def chi_N_range(self) -> tuple[float, float]:
        c = self.ds.chi_N.values
        return float(c[0]), float(c[-1])

    def __reduce__(self):
        """Pickled (sent to a worker process) as its dataset and name: the splines and the stacked
        coefficients of a table over the flow (hundreds of MB) are made again where they are used."""
        return (type(self), (self.ds, self._source))

    def save(self, path) -> Path:
        """Write as NetCDF4/HDF5 (h5netcdf), atomically."""
        return write_netcdf(self.ds, path)

    @classmethod
    def load(cls, path) -> "ThrustTable":
        """Read and validate a table file; a missing, corrupt or foreign file raises TableError."""
        return cls(read(path), str(path))

    @classmethod
    def default(cls, flow: bool = False, chi_E: float = 200.0) -> "ThrustTable":
        """A shipped table for the field ``chi_E`` (one of :data:`SHIPPED_FIELDS`, within 1e-9
        relative) and eta = 1: over chi_N in still fluid, or with ``flow`` over the background
        flow too (U_par, U_perp in [-1.5, 1.5] L/tau, spacing 0.5: for chi_E = 200 every flow a
        carpet of that field sustains, below 0.87 L/tau, with margin; its interpolation error
        against fresh cycles is in benchmarks/results/bench_table_flow.md).

        chi_E = 200 ships both tables; chi_E = 150 ships the table over the flow only, and its
        still-fluid table is that table's flow U = 0 (:meth:`in_still_fluid`: its own rows, 20
        over chi_N). Regenerate the chi_E = 200 tables with ``python -m single_cilium.table``
        (``--flow``).

        Raises
        ------
        TableError
            For a field that does not ship (naming the shipped ones): a scene computes its table
            with ``table.file`` and ``[table.build]``, code with
            :func:`single_cilium.table.build_table`.
        """
        c = shipped_field(chi_E)
        if c is None:
            raise TableError(f"no table ships for chi_E = {chi_E:g}: the shipped tables are for chi_E = "
                             f"{' or '.join(f'{x:g}' for x in SHIPPED_FIELDS)} (eta = 1); compute one for this field "
                             f"(a scene: table.file with a [table.build] section; code: "
                             f"single_cilium.table.build_table)")
        still, over_flow = SHIPPED_TABLES[c]
        table = cls.load(resources.files("single_cilium") / "data" / (over_flow if flow else still))
        return table if flow or still != over_flow else table.in_still_fluid()

    def cutoff(self, chi_E: float | None = None, *, U_par: float | None = None,
               U_perp: float | None = None) -> float:
        """The flutter cutoff chi_N of the field ``chi_E`` (a table over chi_E) in the flow
        ``(U_par, U_perp)`` (a table over the flow; interpolated between its grid's flows)."""
        if self._flow is not None:
            self._table(chi_E)
            return float(self._flow.cutoff(0.0 if U_par is None else U_par, 0.0 if U_perp is None else U_perp))
        return float(self._table(chi_E, U_par, U_perp).ds.attrs["chi_N_cutoff"])

    def at(self, chi_N: float, chi_E: float | None = None, *, U_par: float | None = None,
           U_perp: float | None = None) -> xr.Dataset:
        """One row at any chi_N in the table's range (or its mirror image): cubic-spline
        interpolation of every scalar and of the cycle data on the flutter branch; rows outside
        the branch (no flutter) are interpolated as no-flutter rows. Negative chi_N by mirror
        symmetry (x, fx, thrust_x, thrust_angle, theta_lim and tip_area change sign; in a flow,
        ``U_perp`` too). ``chi_E``: the field (required for a table over chi_E; see the class
        docstring); ``U_par``, ``U_perp``: the background flow (a table over the flow; default 0)."""
        t = self._table(chi_E, U_par, U_perp)
        if self._flow is not None:
            return self._flow.row(chi_N, 0.0 if U_par is None else U_par, 0.0 if U_perp is None else U_perp)
        if t is not self:
            return t.at(chi_N).assign_coords(chi_E=float(chi_E))
        c = float(chi_N)
        if not math.isfinite(c):
            raise TableError(f"chi_N must be finite, got {chi_N}")
        self._check(c)
        a = abs(c)
        on_branch = self._branch.size >= 2 and self._branch[0] <= a <= self._branch[-1]
        template = self.ds.isel(chi_N=0).drop_vars("chi_N")
        if on_branch:
            ua = float(self._u(a))
            row = template.copy(data={k: (self._splines[k](ua if k in FIELDS else a) if k in self._splines
                                          else template[k].values) for k in template.data_vars})
            row["flutter"] = template.flutter.copy(data=np.int8(1))
            if "regime" in row:
                row["regime"] = row.regime.copy(data=np.int8(REGIMES.index("flutter")))
        else:
            still = self.ds.flutter.values == 0
            if (self._branch.size and self._branch[0] <= a <= self._branch[-1]) or not np.any(still):
                raise TableError(f"chi_N = {a:g} lies between flutter rows that are too few to interpolate")
            nearest = self.ds.isel(chi_N=np.flatnonzero(still)).sel(chi_N=a, method="nearest")
            row = nearest.drop_vars("chi_N")
            p = CiliumParams(self.chi_E, self.eta, a)
            try:
                row["theta_lim"] = row.theta_lim.copy(data=limit_angle(p))
            except NoLimitAngleError:
                row["theta_lim"] = row.theta_lim.copy(data=np.nan)
            if "coiled" in row:
                row["coiled"] = row.coiled.copy(data=np.int8(coiled(self.chi_E, a)))
            if self._in_flow:
                for k in ("thrust_x", "thrust_y", "thrust_norm", "thrust_angle"):
                    row[k] = row[k].copy(data=self.scalar(k, a))
        if "regime" in row and self._rest:  # the steady state where the row has one
            ok = self._rest_served(np.array([a]), strict=False)[0]
            for k in REST_SCALARS + REST_FIELDS:
                row[k] = row[k].copy(data=self._rest[k](a) if ok else np.full_like(row[k].values, np.nan))
        if c < 0:
            for k in ODD:
                if k in row:
                    row[k] = -row[k]
        return row.assign_coords(chi_N=c)

    @property
    def _in_flow(self) -> bool:
        """A one-flow table in a background flow (a grid point of a table over the flow)."""
        return self._flow is None and "chi_E" not in self.ds.dims and self._U != (0.0, 0.0)

    def in_still_fluid(self) -> "ThrustTable":
        """The one-flow table of still fluid: this table, or, for a table over the background
        flow, its grid flow U = 0 (its own rows, no interpolation). A TableError when U = 0 is not
        a flow of the grid (an even number of values per component)."""
        if self._flow is None:
            return self
        for (a, b), t in self._flow.knots.items():
            if self._flow.grids[0][a] == 0 and self._flow.grids[1][b] == 0:
                return t
        raise TableError(f"{self._source}: U = 0 is not a flow of the table's grid: build it with an odd number of "
                         "values per flow component, symmetric about 0")

    @property
    def flutter_range(self) -> tuple[float, float]:
        """The |chi_N| interval of the flutter branch (where the table has cycles); a table over
        chi_E has one per field: ``at(chi_N, chi_E=...).flutter``, a table over the flow one per
        flow (:meth:`cutoff`)."""
        if "chi_E" in self.ds.dims or self._flow is not None:
            raise TableError(f"a table over {'chi_E' if self._flow is None else 'the background flow'} has a flutter "
                             "branch per field or flow: ask at(chi_N, ...).flutter, cutoff(...) or "
                             "thrust_angle_range(...)")
        if self._branch.size < 2:
            raise TableError("the table has no flutter branch")
        return float(self._branch[0]), float(self._branch[-1])

    def _check(self, chi_N) -> np.ndarray:
        c = np.asarray(chi_N, dtype=float)
        if not np.all(np.isfinite(c)):
            raise TableError("chi_N must be finite")
        lo, hi = self.chi_N_range
        a = np.abs(c)
        bad = (a < lo) | (a > hi)
        if np.any(bad):
            raise TableError(f"|chi_N| = {float(a[bad].flat[0]):g} is outside the table's range [{lo:g}, {hi:g}]")
        if self._flow is None and "chi_E" not in self.ds.dims and self._U[1] != 0 and np.any(c < 0):
            raise TableError(f"{self._source}: a negative chi_N is the mirror image in the flow U_perp = "
                             f"{-self._U[1]:g}, not in this table's flow")
        return c

    def _rest_served(self, a: np.ndarray, strict: bool = True) -> np.ndarray:
        """Where (|chi_N| = ``a``) the steady state is known: between rows that have one. With
        ``strict``, a TableError elsewhere."""
        rows = self._rest_rows
        ok = (rows.size >= 2) & (a >= (rows[0] if rows.size else 0)) & (a <= (rows[-1] if rows.size else 0))
        if rows.size >= 2:
            c = self.ds.chi_N.values
            none = c[self._regime == REGIMES.index("no_steady_state")]
            for x in none:  # an interval that ends in a row without a steady state is not served
                k = np.searchsorted(rows, x)
                lo = rows[k - 1] if k > 0 else -np.inf
                hi = rows[k] if k < rows.size else np.inf
                ok &= ~((a > lo) & (a < hi))
        if strict and not np.all(ok):
            x = float(a[~ok].flat[0])
            span = f"[{rows[0]:g}, {rows[-1]:g}]" if rows.size >= 2 else "none"
            raise TableError(f"{self._source}: no steady state known at chi_N = {x:g} (rows with one span {span}; "
                             "beyond them, or next to a row where the flow tips the filament over, it is not "
                             "computed)")
        return ok

    def rest(self, name: str, chi_N, chi_E: float | None = None, *, nu: int = 0) -> np.ndarray:
        """A quantity of the steady state (the filament held at rest in its background flow):
        ``rest_thrust_x``, ``rest_thrust_y`` (its force on the fluid, ``-int d ds``; 0 in still
        fluid), ``rest_fx``, ``rest_fy`` (per length, shape ``chi_N.shape + (s,)``), ``alpha``,
        ``beta`` (its leading eigenvalue), at any chi_N of the rows that have a steady state,
        flutter rows included (cubic splines in chi_N; ``nu``: their ``nu``-th derivative);
        mirrored for negative chi_N. Where the filament does not flutter its thrust is
        ``rest_thrust``. A table over chi_E: ``chi_E`` of a grid field only."""
        if name not in REST:
            raise KeyError(f"{name!r} is not a quantity of the steady state ({', '.join(REST)})")
        t = self._table(chi_E)
        if self._flow is not None:
            raise TableError("a table over the background flow: ask at(chi_N, U_par=..., U_perp=...)")
        if t is not self:
            if t not in self._grid.values():
                raise TableError("the steady state is kept for the fields of the chi_E grid only")
            return t.rest(name, chi_N, nu=nu)
        c = self._check(chi_N)
        if name not in self._rest:
            if name in REST_SCALARS + REST_FIELDS and "rest_thrust_x" not in self.ds:  # version 1: still fluid
                return np.zeros(c.shape + ((self.ds.sizes["s"],) if name in REST_FIELDS else ()))
            raise TableError(f"{self._source}: fewer than two rows with a steady state")
        a = np.abs(c)
        self._rest_served(a)
        v = self._rest[name](a, nu)
        if (int(name in ODD) + nu) % 2:
            v = np.where((c < 0).reshape(c.shape + (1,) * (v.ndim - c.ndim)), -v, v)
        return v

    def scalar(self, name: str, chi_N, nu: int = 0, chi_E: float | None = None, *, U_par=None,
               U_perp=None) -> np.ndarray:
        """A scalar column (e.g. ``"thrust_x"``, ``"period"``) or its ``nu``-th derivative in
        chi_N, vectorised over ``chi_N`` (any shape) and mirrored for negative chi_N
        (thrust_x, thrust_angle, theta_lim and tip_area are odd in chi_N, the rest even).
        Off the flutter branch the thrust columns are the steady state's force in the flow (0 in
        still fluid) and the others NaN. ``chi_E``: the field (required for a table over chi_E);
        ``U_par``, ``U_perp``: the background flow (a table over the flow: broadcast with chi_N;
        default 0)."""
        if name not in SCALARS:
            raise KeyError(f"{name!r} is not a scalar column of the table ({', '.join(SCALARS)})")
        t = self._table(chi_E, U_par, U_perp)
        if self._flow is not None:
            return self._flow.scalar(name, chi_N, nu, 0.0 if U_par is None else U_par,
                                     0.0 if U_perp is None else U_perp)
        if t is not self:
            return t.scalar(name, chi_N, nu)
        return self._branch_values(name, chi_N, nu, self._splines)

    def _branch_values(self, name: str, chi_N, nu: int, splines: dict, rest: dict | None = None) -> np.ndarray:
        """A scalar column on the flutter branch (NaN where the column was not computed, e.g.
        error estimates skipped) and off it (thrust: the steady state's, 0 in still fluid)."""
        if self._branch.size < 2 and not (self._in_flow and name in _THRUST):
            raise TableError(f"the table has no flutter branch to interpolate {name!r}")
        c = self._check(chi_N)
        a = np.abs(c)
        on = np.zeros(a.shape, bool)
        if self._branch.size >= 2:
            b0, b1 = self.flutter_range
            on = (a >= b0) & (a <= b1)
        off = np.full(a.shape, 0.0 if name.startswith("thrust") else np.nan)
        if self._in_flow and name in _THRUST and not np.all(on):
            off[~on] = self._rest_thrust(name, a[~on], nu, rest)
        v = off
        if np.any(on):
            sp = splines.get(name)
            v = np.where(on, (sp if nu == 0 else sp.derivative(nu))(np.clip(a, b0, b1)) if sp is not None
                         else np.nan, off)
        odd = name in ODD
        # f(c) = sgn(c)^odd g(|c|)  =>  f^(nu)(c) = sgn(c)^(odd + nu) g^(nu)(|c|)
        if (odd + nu) % 2:  # an odd function of chi_N: vanishes at 0 (the mirror image meets itself,
            # unless a flow across the field tells the two apart)
            v = np.where(c < 0, -v, np.where((c == 0) & (self._U[1] == 0), 0.0, v))
        return v

    def _rest_thrust(self, name: str, a: np.ndarray, nu: int, rest: dict | None = None) -> np.ndarray:
        """The thrust columns where the filament does not flutter in its flow: the steady state's
        force (a TableError where that state is unstable without flutter or unknown)."""
        self._rest_served(a)
        c = self.ds.chi_N.values
        bad = c[self._regime == REGIMES.index("divergence")]
        for x in bad:
            k = np.searchsorted(c, x)
            near = (a > c[max(k - 1, 0)]) & (a < c[min(k + 1, c.size - 1)])
            if np.any(near):
                raise TableError(f"{self._source}: at chi_N = {float(a[near][0]):g} the steady state in the flow is "
                                 f"unstable without flutter (divergence at the row chi_N = {x:g}): no steady or "
                                 "periodic thrust")
        rest = self._rest if rest is None else rest
        fx, fy = rest["rest_thrust_x"], rest["rest_thrust_y"]
        if name in ("thrust_x", "thrust_y"):
            return (fx if name == "thrust_x" else fy).derivative(nu)(a) if nu else (fx if name == "thrust_x" else fy)(a)
        if nu:
            raise TableError(f"derivatives of {name} off the flutter branch: take them of thrust_x and thrust_y")
        x, y = fx(a), fy(a)
        return np.hypot(x, y) if name == "thrust_norm" else thrust_angle_of(x, y)

    def interpolation_error(self, name: str, chi_N, chi_E: float | None = None, *, U_par=None,
                            U_perp=None) -> np.ndarray:
        """An estimate of the interpolation error of ``scalar(name, chi_N, ...)`` (absolute,
        same shape): ``SAFETY = 2`` times the largest change from the quadratic to the cubic
        interpolant in chi_N over the point's interval between rows (and, for a table over the
        flow, in U over its cell; :mod:`single_cilium.flowtable` says why). Zero at the rows of the grid; it does not include the rows' own
        discretisation error (``*_error`` columns). Not for a table over chi_E."""
        if name not in SCALARS:
            raise KeyError(f"{name!r} is not a scalar column of the table ({', '.join(SCALARS)})")
        t = self._table(chi_E, U_par, U_perp)
        if self._flow is not None:
            return self._flow.interpolation_error(name, chi_N, 0.0 if U_par is None else U_par,
                                                  0.0 if U_perp is None else U_perp)
        if t is not self:
            raise TableError("no interpolation error estimate for a table over chi_E")
        return self._chi_N_error(name, chi_N)

    def _chi_N_error(self, name: str, chi_N) -> np.ndarray:
        """The chi_N part of :meth:`interpolation_error` of a one-flow table: ``SAFETY`` times the
        largest ``|cubic - quadratic|`` over the point and the points 1/3 and 2/3 across its
        interval between rows (the change crosses zero inside an interval where the error does
        not), on the flutter branch and, in a flow, of the steady state's force off it; 0 at a row."""
        c = self._check(chi_N)
        if name not in self._quadratic and not (self._in_flow and name in _THRUST):
            return np.zeros(c.shape)
        a = np.abs(c).ravel()
        rows = self.ds.chi_N.values
        s = np.repeat(a[:, None], 3, axis=1)
        if rows.size >= 2:
            k = np.clip(np.searchsorted(rows, a, side="right") - 1, 0, rows.size - 2)
            lo, hi = rows[k], rows[k + 1]
            inside = (a != lo) & (a != hi)
            s[inside, 1] = (lo + (hi - lo) / 3)[inside]
            s[inside, 2] = (lo + 2 * (hi - lo) / 3)[inside]
        cubic = self._branch_values(name, s, 0, self._splines)
        quad = self._branch_values(name, s, 0, {**self._splines, **self._quadratic},
                                   self._rest_quadratic if self._rest_quadratic else None)
        d = np.abs(np.where(np.isfinite(cubic - quad), cubic - quad, 0.0))
        return SAFETY * d.max(axis=1).reshape(c.shape)

    def cycles(self, chi_N, chi_E: float | None = None, *, U_par=None, U_perp=None) -> dict[str, np.ndarray]:
        """The cycle data of many cilia at once: ``x, y, fx, fy`` of shape (n, phase, s) for the
        1-d array ``chi_N`` (n,), with ``flutter`` (n,) bool; non-fluttering rows have no cycle:
        their shape is left NaN and their force per length is the steady state's in the flow
        (zero in still fluid: a still filament exerts no force). Negative chi_N by mirror
        symmetry (x and fx change sign). ``chi_E``: the field (required for a table over
        chi_E); ``U_par``, ``U_perp``: the background flow (a table over the flow; broadcast)."""
        t = self._table(chi_E, U_par, U_perp)
        if self._flow is not None:
            return self._flow.cycles(chi_N, 0.0 if U_par is None else U_par, 0.0 if U_perp is None else U_perp)
        if t is not self:
            return t.cycles(chi_N)
        c = np.atleast_1d(self._check(chi_N)).astype(float)
        if c.ndim != 1:
            raise ValueError(f"chi_N must be 1-d, got shape {c.shape}")
        a = np.abs(c)
        n_p, n_s = self.ds.sizes["phase"], self.ds.sizes["s"]
        out = {k: np.zeros((c.size, n_p, n_s)) for k in FIELDS}
        flutter = np.zeros(c.size, bool)
        if self._branch.size >= 2:
            b0, b1 = self.flutter_range
            flutter = (a >= b0) & (a <= b1)
            if np.all(flutter):  # the usual case: no gather and scatter
                u = self._u(a)
                for k in FIELDS:
                    out[k] = self._splines[k](u)
            elif np.any(flutter):
                u = self._u(a[flutter])
                for k in FIELDS:
                    out[k][flutter] = self._splines[k](u)
        for k in ("x", "y"):
            out[k][~flutter] = np.nan
        if self._in_flow and not np.all(flutter):
            self._rest_thrust("thrust_x", a[~flutter], 0)  # refuses where there is no steady thrust
            for k in ("fx", "fy"):
                out[k][~flutter] = self._rest["rest_" + k](a[~flutter])[:, None, :]
        neg = c < 0
        for k in ("x", "fx"):
            out[k][neg] = -out[k][neg]
        out["flutter"] = flutter
        return out

    def _angle_branch(self) -> tuple[float, float]:
        """chi_N range of the rows that define the thrust angle."""
        if "thrust_angle" not in self._splines:
            raise TableError("the table has no flutter branch")
        x = self._splines["thrust_angle"].x
        return float(x[0]), float(x[-1])

    def _angle(self, chi_N):
        return self._splines["thrust_angle"](chi_N)

    def _angle_samples(self) -> tuple[np.ndarray, np.ndarray]:
        """The thrust angle at 2001 chi_N over the branch (:meth:`_angle_branch`), made once: where
        :meth:`chi_N_for_angle` looks for its bracket (a design asks it for every cilium)."""
        got = self.__dict__.get("_angle_curve")
        if got is None:
            b0, b1 = self._angle_branch()
            xs = np.linspace(b0, b1, 2001)
            got = self.__dict__["_angle_curve"] = (xs, self._angle(xs))
        return got

    def thrust_angle_range(self, chi_E: float | None = None, *, U_par: float | None = None,
                           U_perp: float | None = None) -> tuple[float, float]:
        """The thrust angles the computed flutter rows reach (chi_N >= 0) under the field ``chi_E``
        (required for a table over chi_E) in the flow ``(U_par, U_perp)`` (a table over the flow)."""
        t = self._table(chi_E, U_par, U_perp)
        if self._flow is not None:
            vals = self._flow.angle_curve(0.0 if U_par is None else U_par, 0.0 if U_perp is None else U_perp)[1]
            return float(vals.min()), float(vals.max())
        if t is not self:
            return t.thrust_angle_range()
        vals = self._angle_samples()[1]
        return float(vals.min()), float(vals.max())

    def chi_N_for_angle(self, angle, chi_E: float | None = None, *, U_par: float | None = None,
                        U_perp: float | None = None):
        """The chi_N whose mean thrust points at ``thrust_angle = angle`` (inverse on the monotone
        branch; a negative angle gives a negative chi_N by mirror symmetry, in a flow that of the
        mirrored flow ``-U_perp``) under the field ``chi_E`` (required for a table over chi_E)
        in the flow ``(U_par, U_perp)`` (a table over the flow; the first crossing along the
        branch where the angle is not monotone).

        ``angle`` a float gives a float; an array of angles (a design's, one per cilium) gives
        an array of that shape, each distinct angle solved once (a uniform target on 10^4 cilia
        asks for one angle 10^4 times)."""
        if np.ndim(angle) > 0:
            a = np.asarray(angle, dtype=float)
            uniq, inv = np.unique(a, return_inverse=True)
            vals = np.array([self.chi_N_for_angle(float(x), chi_E, U_par=U_par, U_perp=U_perp) for x in uniq])
            return vals[inv].reshape(a.shape)
        t = self._table(chi_E, U_par, U_perp)
        if self._flow is None and t is not self:
            return t.chi_N_for_angle(angle)
        if not math.isfinite(angle):
            raise TableError(f"angle must be finite, got {angle}")
        if self._flow is not None:
            up, uq = 0.0 if U_par is None else float(U_par), 0.0 if U_perp is None else float(U_perp)
            uq = -uq if angle < 0 else uq  # a negative angle: the mirror image, in the mirrored flow
            xs, vals = self._flow.angle_curve(up, uq)

            def f(x):
                return float(self._flow.scalar("thrust_angle", x, 0, up, uq))
        else:
            xs, vals = self._angle_samples()
            f = self._angle
        lo, hi = float(vals.min()), float(vals.max())
        a = abs(angle)
        if a < lo <= 1e-6:  # the straight filament's angle is 0 up to round-off (a table over the flow: its interpolation)
            a = lo
        if not lo <= a <= hi:
            raise TableError(f"thrust angle {angle:.6g} is not achievable with this field: |angle| must lie in "
                             f"[{lo:.6g}, {hi:.6g}] rad (chi_N in [{xs[0]:g}, {xs[-1]:g}])")
        d = vals - a
        change = np.nonzero(np.sign(d[:-1]) != np.sign(d[1:]))[0]
        if change.size == 0:
            c = float(xs[int(np.argmin(np.abs(d)))])
        else:
            k = int(change[0])
            c = brentq(lambda x: float(f(x)) - a, xs[k], xs[k + 1], xtol=1e-13)
        return math.copysign(c, angle) if angle != 0 else c
