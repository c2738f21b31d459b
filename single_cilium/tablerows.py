"""The rows of a thrust table build (:func:`single_cilium.table.build_table`): what one row holds
(:func:`row`; the schema in :mod:`single_cilium.tablefile`), the grid of rows a build computes
and the fingerprint its row files carry (:class:`TableGrid`), and the rows an interrupted build
left behind (:func:`resume`).

A row is one chi_N of one column: a field in a background flow, ``(chi_E, U_par, U_perp)``. It
holds the limit cycle where the filament flutters, and always the steady state in the flow where
there is one (its force on the fluid: the thrust where it does not flutter).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import xarray as xr

from .version import __version__
from .cycle import LimitCycle
from .equilibrium import NoLimitAngleError, equilibrium_shape, limit_angle
from .filament import Filament
from .flowtable import thrust_angle_of
from .mesh import Mesh
from .params import CiliumParams
from .tablefile import FIELDS, REGIMES, SCALARS, SCHEMA_VERSION, TableError, coiled, grid_text

__all__ = ["row", "rest_state", "hole", "TableGrid", "resume"]


def rest_state(params: CiliumParams, degree: int, s_grid: np.ndarray):
    """The steady state in the flow: its force on the fluid ``F = -int d ds`` (2,), its force per
    length on the fluid ``-d`` on ``s_grid`` (n_s, 2) and its shape (x, y) on ``s_grid``; zero
    force in still fluid (the closed-form shape)."""
    if not params.has_background:
        x, y = equilibrium_shape(params, s_grid)
        return np.zeros(2), np.zeros((s_grid.size, 2)), (x, y)
    mesh = Mesh.for_params(params, degree)
    fil = Filament(params, mesh)
    theta = fil.split(fil.equilibrium_state())[0]
    d = fil.drag(theta, np.zeros_like(theta))
    r = fil.shape(theta)
    f = -mesh.interpolate(d, s_grid)
    return fil.clamp_force(d), f, (mesh.interpolate(r[:, 0], s_grid), mesh.interpolate(r[:, 1], s_grid))


def row(params: CiliumParams, cyc: LimitCycle | None, s_grid: np.ndarray, n_phase: int, alpha: float,
         beta: float, regime: str, rest=None, cutoff: bool = False) -> xr.Dataset:
    """One row (dims ``chi_N: 1, phase, s``): ``regime`` one of REGIMES; ``rest`` the steady
    state (:func:`rest_state`; None where there is none)."""
    is_coiled = coiled(params.chi_E, params.chi_N)
    try:
        tl = math.nan if is_coiled else limit_angle(params.with_background((0.0, 0.0)))
    except NoLimitAngleError:
        tl = math.nan
    sc = {k: math.nan for k in SCALARS}
    F, f = (rest[0], rest[1]) if rest is not None else (np.full(2, math.nan), np.full((s_grid.size, 2), math.nan))
    sc.update(theta_lim=tl, alpha=alpha, beta=beta, tip_area=0.0)
    if not params.has_background:  # still fluid: no cycle, no force (as in version 1)
        sc.update(thrust_norm=0.0, thrust_x=0.0, thrust_y=0.0)
    elif regime == "stable" or cutoff:  # no cycle: the steady state's force in the flow (else NaN)
        sc.update(thrust_x=F[0], thrust_y=F[1], thrust_norm=float(np.hypot(*F)),
                  thrust_angle=float(thrust_angle_of(*F)))
    fields = {k: np.full((n_phase, s_grid.size), np.nan) for k in FIELDS}
    if cutoff:  # zero amplitude: the cycle shrinks onto the equilibrium with period 2 pi / beta
        # the direction of a vanishing mean force is not defined by the table: NaN (the angle
        # spline uses the other rows)
        sc.update(period=2 * math.pi / beta, floquet=1.0, period_error=0.0, thrust_norm_error=0.0,
                  floquet_trivial_error=0.0)
        x, y = rest[2]
        fields.update(x=np.broadcast_to(x, (n_phase, s_grid.size)).copy(),
                      y=np.broadcast_to(y, (n_phase, s_grid.size)).copy(),
                      fx=np.broadcast_to(f[:, 0], (n_phase, s_grid.size)).copy(),
                      fy=np.broadcast_to(f[:, 1], (n_phase, s_grid.size)).copy())
    elif cyc is not None and cyc.flutter:
        e = cyc.errors
        sc.update(period=cyc.period, thrust_norm=cyc.thrust_norm, thrust_angle=cyc.thrust_angle,
                  thrust_x=cyc.thrust_x, thrust_y=cyc.thrust_y, floquet=cyc.floquet, tip_area=cyc.tip_area,
                  period_error=e.get("period", math.nan), thrust_norm_error=e.get("thrust_norm", math.nan),
                  thrust_angle_error=e.get("thrust_angle", math.nan),
                  floquet_trivial_error=cyc.floquet_trivial_error)
        for k in FIELDS:
            fields[k] = cyc.mesh.interpolate(cyc.data[k].values.T, s_grid).T
    ds = xr.Dataset({k: ((), v) for k, v in sc.items()})
    ds["flutter"] = ((), np.int8(cutoff or regime == "flutter"))
    ds["coiled"] = ((), np.int8(is_coiled))
    ds["regime"] = ((), np.int8(REGIMES.index("flutter" if cutoff else regime)))
    for k, v in fields.items():
        ds[k] = (("phase", "s"), v)
    ds["rest_thrust_x"], ds["rest_thrust_y"] = ((), float(F[0])), ((), float(F[1]))
    ds["rest_fx"], ds["rest_fy"] = (("s",), f[:, 0]), (("s",), f[:, 1])
    return ds.expand_dims(chi_N=[params.chi_N])


def hole(chi_E: float, chi_N: float, s_grid: np.ndarray, n_phase: int) -> xr.Dataset:
    """A row of the shared chi_N grid that another flow's cutoff put there: not computed."""
    r = row(CiliumParams(chi_E, 1.0, chi_N), None, s_grid, n_phase, math.nan, math.nan, "not_computed")
    for k in ("thrust_norm", "thrust_x", "thrust_y", "theta_lim", "tip_area"):
        r[k][:] = math.nan
    return r


# ---------------------------------------------------------------------------------- the grid
class TableGrid:
    """What a build computes: its columns (a field in a flow: ``(chi_E, U_par, U_perp)``), their
    kind (``"field"``, ``"chi_E"``: a grid of fields, ``"flow"``: a grid of flows), row keys
    ``(chi_E, U_par, U_perp, chi_N)`` and row files."""

    def __init__(self, kind: str, columns: list, fields, flows):
        self.kind, self.columns, self.fields, self.flows = kind, columns, fields, flows

    def key(self, r: xr.Dataset, chi_E: float) -> tuple:
        """(chi_E, U_par, U_perp, chi_N) of a one-row Dataset."""
        e = float(r.chi_E.values[0]) if "chi_E" in r.dims else float(chi_E)
        up = float(r.U_par.values[0]) if "U_par" in r.dims else 0.0
        uq = float(r.U_perp.values[0]) if "U_perp" in r.dims else 0.0
        return e, up, uq, float(r.chi_N.values[0])

    def file(self, parts, key: tuple) -> Path:
        E, up, uq, c = key
        name = {"field": f"row_{c:.17g}", "chi_E": f"row_{E:.17g}_{c:.17g}",
                "flow": f"row_{up:.17g}_{uq:.17g}_{c:.17g}"}[self.kind]
        return Path(parts) / f"{name}.nc"

    def key_of_file(self, f: Path, chi_E: float) -> tuple:
        v = [float(x) for x in f.name[4:-3].split("_")]
        return {"field": lambda: (chi_E, 0.0, 0.0, v[0]), "chi_E": lambda: (v[0], 0.0, 0.0, v[1]),
                "flow": lambda: (chi_E, v[0], v[1], v[2])}[self.kind]()

    def expand(self, row: xr.Dataset, col: tuple) -> xr.Dataset:
        if self.kind == "chi_E":
            return row.expand_dims(chi_E=[col[0]])
        if self.kind == "flow":
            return row.expand_dims(U_perp=[col[2]]).expand_dims(U_par=[col[1]])
        return row

    def fingerprint(self, eta: float, settings: dict) -> dict:
        """What a stored row was computed for (attrs ``build_*`` of each row file): a resumed build
        reuses a row only if all of these match. A table over chi_E or over the flow records its
        whole grid (its rows are continued from one another)."""
        field = ({"build_chi_E_grid": grid_text(self.fields)} if self.kind == "chi_E"
                 else {"build_chi_E": float(self.fields[0])})
        if self.kind == "flow":
            field.update(build_U_par_grid=grid_text(self.flows[0]), build_U_perp_grid=grid_text(self.flows[1]))
        return {"build_kind": self.kind, **field, "build_eta": float(eta), "build_degree": int(settings["degree"]),
                "build_n_phase": int(settings["n_phase"]), "build_n_s": len(settings["s"]),
                "build_error_estimate": int(bool(settings.get("error_estimate", True))),
                "build_tol": float(settings.get("tol", 1e-8)),
                "build_method": str(settings.get("method", "shooting")), "build_package_version": __version__,
                "build_schema_version": SCHEMA_VERSION}


def resume(parts: Path, grid: TableGrid, wanted: set, want: dict, chi_E: float,
           ours: set | None = None) -> dict[tuple, xr.Dataset]:
    """Rows of an interrupted build in ``parts`` that match the request (keys in ``wanted``);
    refuse any other. ``ours``, if given, gains the path of every row file it returns (the
    files the build may remove once the table is written).

    Nothing in ``parts`` is removed or changed: a build writes each row file whole (a temporary,
    renamed), so a ``row_*.nc`` that cannot be read is not one of its rows; it is refused
    (:class:`TableError` naming it), as is a row of a build with other settings.
    """
    done: dict[tuple, xr.Dataset] = {}
    for f in sorted(parts.glob("row_*.nc")):
        try:
            with xr.open_dataset(f, engine="h5netcdf") as r:
                r = r.load()
        except (OSError, ValueError) as exc:
            why = " ".join(str(exc).split())[:160] or type(exc).__name__
            raise TableError(f"{f}: not a readable row of a table build ({why}); a build writes its rows whole, "
                             f"so this file is not one of them and is left as it is: move it out of {parts} (or "
                             "build into another path), then repeat the request") from None
        got = {k: r.attrs.get(k) for k in want}
        bad = [k for k in want if not _same(got[k], want[k])]
        if bad:
            def show(v):
                return repr(v.item() if isinstance(v, np.generic) else v)

            diff = ", ".join(f"{k[6:]} = {show(got[k])} (asked {show(want[k])})" for k in bad)
            raise TableError(f"{f}: a row of an interrupted build with other settings ({diff}); it is not "
                             f"merged into this table: remove {parts} (or build into another path) to "
                             "start afresh, or repeat the original request to resume it")
        key = grid.key(r, chi_E)
        if key in wanted:  # rows outside the requested grid are never merged in (nor removed)
            done[key] = r
            if ours is not None:
                ours.add(Path(f))
    return done


def _same(got, want) -> bool:
    """A stored attribute equals the requested value (of the same kind)."""
    if got is None:
        return False
    try:
        if isinstance(want, str):
            return str(got) == want
        return type(want)(got) == want
    except (TypeError, ValueError):
        return False
