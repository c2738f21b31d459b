"""The thrust lookup table over the natural curvature chi_N, for one field (chi_E, eta).

:func:`build_table` computes limit cycles (:func:`~single_cilium.cycle.limit_cycle`) on a grid
of chi_N by continuation: each worker walks a contiguous chunk of the grid (chunks of equal
work, one per core), predicting every cycle from the last three by a parabola in chi_N, so that
a row costs two Newton steps with the exact monodromy plus its error estimates. It runs on any
``concurrent.futures.Executor`` (default: a local process pool; with ``scheduler=ADDRESS``, a
Dask distributed cluster through its executor). It finds the flutter cutoff
(:func:`~single_cilium.stability.flutter_cutoff`) and puts a row exactly there. With ``path``
every finished row is kept on disk at once (with ``build_*`` attributes recording the field,
settings and package version it was computed for), so an interrupted build resumes where it
stopped; rows of a build with any other field or settings are refused, never merged, and rows
outside the requested grid are ignored.

:class:`ThrustTable` wraps the Dataset of DESIGN.md (schema below), validates it on load,
interpolates it smoothly in chi_N (cubic splines on the flutter branch; for the shapes and
forces in ``sqrt(chi_c - chi_N)``, in which their Hopf onset is smooth), inverts the thrust
angle, and mirrors negative chi_N.

Schema (version 1): dims ``chi_N``, ``phase`` (uniform in [0, 1)), ``s`` (uniform in [0, 1]);
per chi_N ``flutter`` (int8 0/1), ``period``, ``thrust_norm``, ``thrust_angle``, ``thrust_x``,
``thrust_y``, ``theta_lim``, ``alpha``, ``beta``, ``floquet``, ``tip_area`` and the error
estimates ``period_error``, ``thrust_norm_error``, ``thrust_angle_error``,
``floquet_trivial_error``; per (chi_N, phase, s) ``x``, ``y``, ``fx``, ``fy`` (force per
length on the fluid, ``-d``). Rows without flutter: period NaN, thrust 0, cycle data NaN.
"""
from __future__ import annotations

import logging
import math
import os
import shutil
from concurrent.futures import Executor
from importlib import resources
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.interpolate import CubicSpline
from scipy.optimize import brentq

from . import __version__
from ._io import write_netcdf
from .cycle import CycleError, LimitCycle, limit_cycle
from .equilibrium import NoLimitAngleError, limit_angle
from .params import CiliumParams
from .progress import Progress
from .stability import flutter_cutoff, stability

logger = logging.getLogger(__name__)

__all__ = ["build_table", "ThrustTable", "TableError", "SCHEMA_VERSION"]

SCHEMA_VERSION = 1
SCALARS = ("period", "thrust_norm", "thrust_angle", "thrust_x", "thrust_y", "theta_lim", "alpha", "beta",
           "floquet", "tip_area", "period_error", "thrust_norm_error", "thrust_angle_error",
           "floquet_trivial_error")
FIELDS = ("x", "y", "fx", "fy")
DEFAULT_FILE = "table_chiE200_eta1.nc"
_ODD = ("thrust_x", "thrust_angle", "theta_lim", "tip_area")


class TableError(ValueError):
    """A table file or request that cannot be served; the message names the problem."""


# ---------------------------------------------------------------------------------- rows
def _row(params: CiliumParams, cyc: LimitCycle | None, s_grid: np.ndarray, n_phase: int,
         alpha: float, beta: float, cutoff: bool = False) -> xr.Dataset:
    try:
        tl = limit_angle(params)
    except NoLimitAngleError:
        tl = math.nan
    sc = {k: math.nan for k in SCALARS}
    sc.update(theta_lim=tl, alpha=alpha, beta=beta, thrust_norm=0.0, thrust_x=0.0, thrust_y=0.0,
              tip_area=0.0)
    fields = {k: np.full((n_phase, s_grid.size), np.nan) for k in FIELDS}
    flutter = 0
    if cutoff:  # zero amplitude: the cycle shrinks onto the equilibrium with period 2 pi / beta
        flutter = 1
        # the direction of the vanishing mean force is not defined by the table: NaN (the
        # angle spline uses the other rows)
        sc.update(period=2 * math.pi / beta, floquet=1.0, period_error=0.0, thrust_norm_error=0.0,
                  floquet_trivial_error=0.0)
        from .equilibrium import equilibrium_shape
        x, y = equilibrium_shape(params, s_grid)
        fields.update(x=np.broadcast_to(x, (n_phase, s_grid.size)).copy(),
                      y=np.broadcast_to(y, (n_phase, s_grid.size)).copy(),
                      fx=np.zeros((n_phase, s_grid.size)), fy=np.zeros((n_phase, s_grid.size)))
    elif cyc is not None and cyc.flutter:
        flutter = 1
        e = cyc.errors
        sc.update(period=cyc.period, thrust_norm=cyc.thrust_norm, thrust_angle=cyc.thrust_angle,
                  thrust_x=cyc.thrust_x, thrust_y=cyc.thrust_y, floquet=cyc.floquet, tip_area=cyc.tip_area,
                  period_error=e.get("period", math.nan), thrust_norm_error=e.get("thrust_norm", math.nan),
                  thrust_angle_error=e.get("thrust_angle", math.nan),
                  floquet_trivial_error=cyc.floquet_trivial_error)
        for k in FIELDS:
            fields[k] = cyc.mesh.interpolate(cyc.data[k].values.T, s_grid).T
    ds = xr.Dataset({k: ((), v) for k, v in sc.items()})
    ds["flutter"] = ((), np.int8(flutter))
    for k, v in fields.items():
        ds[k] = (("phase", "s"), v)
    return ds.expand_dims(chi_N=[params.chi_N])


def _fingerprint(chi_E: float, eta: float, settings: dict) -> dict:
    """What a stored row was computed for (attrs ``build_*`` of each row file): a resumed build
    reuses a row only if all of these match."""
    return {"build_chi_E": float(chi_E), "build_eta": float(eta), "build_degree": int(settings["degree"]),
            "build_n_phase": int(settings["n_phase"]), "build_n_s": len(settings["s"]),
            "build_error_estimate": int(bool(settings.get("error_estimate", True))),
            "build_tol": float(settings.get("tol", 1e-8)),
            "build_method": str(settings.get("method", "shooting")), "build_package_version": __version__}


def _resume(parts: Path, grid: np.ndarray, want: dict) -> dict[float, xr.Dataset]:
    """Rows of an interrupted build in ``parts`` that match the request; refuse any other."""
    done: dict[float, xr.Dataset] = {}
    wanted = set(grid.tolist())
    for f in sorted(parts.glob("row_*.nc")):
        try:
            with xr.open_dataset(f, engine="h5netcdf") as r:
                r = r.load()
        except (OSError, ValueError):
            f.unlink()  # a row file cut short by the interruption
            continue
        got = {k: r.attrs.get(k) for k in want}
        bad = [k for k in want if not _same(got[k], want[k])]
        if bad:
            def show(v):
                return repr(v.item() if isinstance(v, np.generic) else v)

            diff = ", ".join(f"{k[6:]} = {show(got[k])} (asked {show(want[k])})" for k in bad)
            raise TableError(f"{f}: a row of an interrupted build with other settings ({diff}); it is not "
                             f"merged into this table: remove {parts} (or build into another path) to "
                             "start afresh, or repeat the original request to resume it")
        c = float(r.chi_N.values[0])
        if c in wanted:  # rows outside the requested grid are never merged in
            done[c] = r
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


def _chunk(args):
    """Compute a contiguous run of rows by continuation; write each row to ``parts`` if given."""
    chi_E, eta, chi_Ns, settings, parts = args
    degree, n_phase, s_grid = settings["degree"], settings["n_phase"], np.asarray(settings["s"])
    rows, seeds = [], []
    for cN in chi_Ns:
        p = CiliumParams(chi_E, eta, cN)
        st = stability(p, degree=degree, check=False, n_modes=1)
        cyc = None
        if st.regime == "flutter":
            # continuation: the parabola through the last three cycles predicts this one
            try:
                cyc = limit_cycle(p, degree=degree, n_phase=n_phase, seed=seeds[-3:], tol=settings.get("tol", 1e-8),
                                  error_estimate=settings.get("error_estimate", True))
            except CycleError as exc:
                err = CycleError(f"thrust table (chi_E = {chi_E:g}, eta = {eta:g}): the cycle at chi_N = {cN:.10g} "
                                 f"did not converge ({exc})", exc.t)
                err.chi_N = float(cN)
                raise err from None
            seeds.append(cyc)
        else:
            seeds = []
        row = _row(p, cyc, s_grid, n_phase, st.alpha, st.beta)
        row.attrs.update(_fingerprint(chi_E, eta, settings))
        if parts is not None:
            write_netcdf(row, Path(parts) / f"row_{cN:.17g}.nc")
        rows.append(row)
    return rows


def _balanced_chunks(todo: np.ndarray, chi_c: float, n_chunks: int) -> list[list[float]]:
    """Contiguous runs of the grid (each continued from its own start), one per worker, of equal
    work: a flutter row (below the cutoff) costs a cycle, a stable row about 5 % of one."""
    if todo.size == 0:
        return []
    weight = np.where(todo < chi_c, 1.0, 0.05) if np.isfinite(chi_c) else np.ones(todo.size)
    n_chunks = max(1, min(todo.size, n_chunks))
    cum = np.cumsum(weight)
    edges = np.searchsorted(cum, cum[-1] * np.arange(1, n_chunks) / n_chunks, side="right")
    return [c.tolist() for c in np.split(todo, edges) if c.size]


def build_table(chi_E: float, eta: float, chi_N, *, degree: int = 8, n_phase: int = 64, n_s: int = 65,
                executor: Executor | None = None, scheduler: str | None = None,
                progress: Progress | None = None, path=None, error_estimate: bool = True,
                tol: float = 1e-8) -> "ThrustTable":
    """Compute the thrust table of DESIGN.md over ``chi_N`` (>= 0, strictly increasing).

    Parameters
    ----------
    chi_E, eta : float
        The field.
    chi_N : array_like
        The grid; the flutter cutoff is added to it when it lies inside.
    degree, n_phase : discretisation of each cycle (see :func:`limit_cycle`).
    n_s : int
        Points of the uniform arc-length grid of the stored shapes and forces.
    executor : concurrent.futures.Executor, optional
        Where chunks run (default: a process pool over the machine's cores).
    scheduler : str, optional
        Address of a Dask distributed scheduler; its executor is used (the same code path).
    path : path-like, optional
        Where the table is written; finished rows are kept in ``<path>.parts/`` while building,
        so a rerun after an interruption computes only the missing rows.
    error_estimate : bool
        Refinement error estimates per row (about doubles the cost); NaN without.
    tol : float
        Newton tolerance of each cycle on the scaled shooting residual (the row's quantities
        then carry errors of about that size, far below the discretisation error estimates).
    """
    base = CiliumParams(chi_E, eta, 0.0)
    grid = np.atleast_1d(np.asarray(chi_N, dtype=float))
    if grid.ndim != 1 or grid.size == 0:
        raise ValueError("chi_N must be a non-empty 1-d grid")
    if not np.all(np.isfinite(grid)):
        raise ValueError("chi_N grid contains NaN or inf")
    if np.any(np.diff(grid) <= 0):
        raise ValueError("chi_N grid must be strictly increasing")
    if grid[0] < 0:
        raise ValueError("chi_N grid must be >= 0 (negative chi_N follow by mirror symmetry)")
    cut = flutter_cutoff(base.chi_E, base.eta, degree=degree)
    chi_c = cut.chi_N_cutoff
    if np.isfinite(chi_c) and grid[0] < chi_c < grid[-1]:
        grid = np.unique(np.concatenate([grid[np.abs(grid - chi_c) > 1e-9 * chi_c], [chi_c]]))
    s_grid = np.linspace(0.0, 1.0, int(n_s))
    if not (0 < tol < 1e-3):
        raise ValueError(f"tol must lie in (0, 1e-3), got {tol}")
    settings = {"degree": int(degree), "n_phase": int(n_phase), "s": s_grid.tolist(),
                "error_estimate": bool(error_estimate), "tol": float(tol)}
    parts = None
    done: dict[float, xr.Dataset] = {}
    if path is not None:
        parts = Path(str(path) + ".parts")
        parts.mkdir(parents=True, exist_ok=True)
        done = _resume(parts, grid, _fingerprint(base.chi_E, base.eta, settings))
        if done:
            logger.info("build_table: resuming %s, %d of %d rows done", parts, len(done), grid.size)
    todo = [c for c in grid if not (np.isfinite(chi_c) and c == chi_c) and c not in done]
    rows = dict(done)
    if np.isfinite(chi_c) and chi_c in grid:
        p = CiliumParams(base.chi_E, base.eta, chi_c)
        rows[chi_c] = _row(p, None, s_grid, int(n_phase), 0.0, cut.beta, cutoff=True)
    progress = progress if progress is not None else Progress()
    progress.start(len(grid), "thrust table")
    progress.update(len(grid) - len(todo))
    own = None
    if executor is None:
        if scheduler is not None:
            from dask.distributed import Client

            own = Client(scheduler)
            executor = own.get_executor()
        else:
            from concurrent.futures import ProcessPoolExecutor

            own = executor = ProcessPoolExecutor(max_workers=os.cpu_count() or 1)
    try:
        chunks = _balanced_chunks(np.array(todo), chi_c, os.cpu_count() or 1)
        tasks = [(base.chi_E, base.eta, c, settings, str(parts) if parts else None) for c in chunks]
        finished = len(grid) - len(todo)
        try:
            for res in executor.map(_chunk, tasks):
                for r in res:
                    rows[float(r.chi_N.values[0])] = r
                finished += len(res)
                progress.update(finished)
        except CycleError as exc:
            failed = getattr(exc, "chi_N", math.inf)
            good = set(rows) | ({float(f.name[4:-3]) for f in parts.glob("row_*.nc")} if parts else set())
            before = [c for c in good if c < failed]
            last = f"chi_N = {max(before):.10g}" if before else "none"
            kept = (f"; the finished rows are kept in {parts}, and the same request resumes from them"
                    if parts is not None else "")
            raise CycleError(f"{exc}; last good row before it: {last}{kept}", exc.t) from None
    finally:
        progress.close()
        if own is not None:
            (own.close() if hasattr(own, "close") else own.shutdown())
    ds = xr.concat([rows[c] for c in sorted(rows)], dim="chi_N")
    ds = ds.assign_coords(phase=np.arange(n_phase) / n_phase, s=s_grid)
    ds.attrs.update({
        "chi_E": base.chi_E, "eta": base.eta, "chi_N_cutoff": chi_c, "chi_N_cutoff_error": cut.error,
        "schema_version": SCHEMA_VERSION, "package_version": __version__,
        "field_direction": "e2 (angles anticlockwise from e2)",
        "discretisation": f"Mesh.for_params(params, degree={degree}); {n_phase} Radau IIA(5) steps per period; "
                          f"shooting (exact monodromy) to a scaled residual of {tol:g}",
        "thrust_convention": "thrust = mean force on the fluid -<int d ds>; thrust_angle = phi_Fbar - pi",
    })
    table = ThrustTable(_with_attrs(ds))
    if path is not None:
        table.save(path)
        shutil.rmtree(parts, ignore_errors=True)
    return table


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
    "x": "position along e1", "y": "position along e2", "fx": "force per length on the fluid, e1",
    "fy": "force per length on the fluid, e2",
}


def _with_attrs(ds: xr.Dataset) -> xr.Dataset:
    for k, v in _LONG.items():
        ds[k].attrs.update(long_name=v, units="1")
    ds.chi_N.attrs.update(long_name="natural curvature L kappa_N", units="1")
    ds.phase.attrs.update(long_name="phase t/T from the upward crossing of the tip angle through its mean",
                          units="1")
    ds.s.attrs.update(long_name="arc length / filament length", units="1")
    return ds


# ---------------------------------------------------------------------------------- table
class ThrustTable:
    """The thrust table of one field: a validated Dataset with interpolation and inversion."""

    def __init__(self, ds: xr.Dataset, source: str = "<memory>"):
        self.ds = self._validate(ds, source)
        fl = self.ds.flutter.values.astype(bool)
        c = self.ds.chi_N.values
        self._branch = c[fl]
        self._splines = {}
        # near the Hopf cutoff the amplitude grows like sqrt(chi_c - chi_N): in the variable
        # u = sqrt(chi_c - chi_N) shapes and forces are smooth, so their splines use it when the
        # branch ends at the cutoff row; the scalars (thrust ~ amplitude^2) are smooth in chi_N
        chi_c = float(self.ds.attrs.get("chi_N_cutoff", np.nan))
        self._cut = chi_c if self._branch.size and np.isfinite(chi_c) and self._branch[-1] == chi_c else None
        if self._branch.size >= 2:
            for k in SCALARS:
                v = self.ds[k].values[fl]
                ok = np.isfinite(v)
                if ok.sum() >= 2:
                    self._splines[k] = CubicSpline(self._branch[ok], v[ok])
            u = self._u(self._branch)
            order = np.argsort(u)
            for k in FIELDS:
                self._splines[k] = CubicSpline(u[order], self.ds[k].values[fl][order], axis=0)

    def _u(self, chi_N):
        chi_N = np.asarray(chi_N, dtype=float)
        return np.sqrt(np.maximum(self._cut - chi_N, 0.0)) if self._cut is not None else chi_N

    @staticmethod
    def _validate(ds: xr.Dataset, source: str) -> xr.Dataset:
        missing = [k for k in SCALARS + FIELDS + ("flutter",) if k not in ds]
        if missing or "chi_N" not in ds.dims:
            raise TableError(f"{source}: not a thrust table (missing {missing or 'dim chi_N'})")
        v = ds.attrs.get("schema_version")
        if v != SCHEMA_VERSION:
            raise TableError(f"{source}: table schema version {v!r}, this package reads version {SCHEMA_VERSION}: "
                             "rebuild it with build_table")
        for k in ("chi_E", "eta"):
            if k not in ds.attrs:
                raise TableError(f"{source}: attribute {k!r} missing")
            v = ds.attrs[k]
            try:
                ok = np.ndim(v) == 0 and not isinstance(v, (str, bytes)) and math.isfinite(float(v))
            except (TypeError, ValueError):
                ok = False
            if not ok or (k == "eta" and float(v) <= 0):
                need = "a finite number > 0" if k == "eta" else "a finite number"
                raise TableError(f"{source}: attribute {k!r} = {v!r} is not {need}")
        c = ds.chi_N.values
        if c.size == 0 or np.any(~np.isfinite(c)) or np.any(np.diff(c) <= 0):
            raise TableError(f"{source}: chi_N coordinate must be finite and strictly increasing")
        return ds

    @property
    def chi_E(self) -> float:
        return float(self.ds.attrs["chi_E"])

    @property
    def eta(self) -> float:
        return float(self.ds.attrs["eta"])

    @property
    def chi_N_range(self) -> tuple[float, float]:
        c = self.ds.chi_N.values
        return float(c[0]), float(c[-1])

    def save(self, path) -> Path:
        """Write as NetCDF4/HDF5 (h5netcdf), atomically."""
        return write_netcdf(self.ds, path)

    @classmethod
    def load(cls, path) -> "ThrustTable":
        """Read and validate a table file; a missing, corrupt or foreign file raises TableError."""
        path = Path(path)
        if not path.exists():
            raise TableError(f"{path}: no such table file")
        try:
            with xr.open_dataset(path, engine="h5netcdf") as ds:
                ds = ds.load()
        except Exception as exc:  # h5py/h5netcdf raise OSError, ValueError, KeyError, ...
            raise TableError(f"{path}: not a readable NetCDF4/HDF5 table ({type(exc).__name__}: {exc})") from None
        return cls(ds, str(path))

    @classmethod
    def default(cls) -> "ThrustTable":
        """The shipped table for (chi_E, eta) = (200, 1) (regenerate: ``python -m single_cilium.table``)."""
        return cls.load(resources.files("single_cilium") / "data" / DEFAULT_FILE)

    def at(self, chi_N: float) -> xr.Dataset:
        """One row at any chi_N in the table's range (or its mirror image): cubic-spline
        interpolation of every scalar and of the cycle data on the flutter branch; rows outside
        the branch (no flutter) are interpolated as no-flutter rows. Negative chi_N by mirror
        symmetry (x, fx, thrust_x, thrust_angle, theta_lim and tip_area change sign)."""
        c = float(chi_N)
        if not math.isfinite(c):
            raise TableError(f"chi_N must be finite, got {chi_N}")
        a = abs(c)
        lo, hi = self.chi_N_range
        if not lo <= a <= hi:
            raise TableError(f"|chi_N| = {a:g} is outside the table's range [{lo:g}, {hi:g}]")
        on_branch = self._branch.size >= 2 and self._branch[0] <= a <= self._branch[-1]
        template = self.ds.isel(chi_N=0).drop_vars("chi_N")
        if on_branch:
            ua = float(self._u(a))
            row = template.copy(data={k: (self._splines[k](ua if k in FIELDS else a) if k in self._splines
                                          else template[k].values) for k in template.data_vars})
            row["flutter"] = template.flutter.copy(data=np.int8(1))
        else:
            nearest = self.ds.sel(chi_N=a, method="nearest")
            if int(nearest.flutter) == 1:
                raise TableError(f"chi_N = {a:g} lies between flutter rows that are too few to interpolate")
            row = nearest.drop_vars("chi_N")
            p = CiliumParams(self.chi_E, self.eta, a)
            try:
                row["theta_lim"] = row.theta_lim.copy(data=limit_angle(p))
            except NoLimitAngleError:
                pass
        if c < 0:
            for k in ("x", "fx", "thrust_x", "thrust_angle", "theta_lim", "tip_area"):
                row[k] = -row[k]
        return row.assign_coords(chi_N=c)

    @property
    def flutter_range(self) -> tuple[float, float]:
        """The |chi_N| interval of the flutter branch (where the table has cycles)."""
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
        return c

    def scalar(self, name: str, chi_N, nu: int = 0) -> np.ndarray:
        """A scalar column (e.g. ``"thrust_x"``, ``"period"``) or its ``nu``-th derivative in
        chi_N, vectorised over ``chi_N`` (any shape) and mirrored for negative chi_N
        (thrust_x, thrust_angle, theta_lim and tip_area are odd in chi_N, the rest even).
        Off the flutter branch the thrust columns are 0 and the others NaN."""
        if name not in SCALARS:
            raise KeyError(f"{name!r} is not a scalar column of the table ({', '.join(SCALARS)})")
        if name not in self._splines:
            raise TableError(f"the table has no flutter branch to interpolate {name!r}")
        c = self._check(chi_N)
        a = np.abs(c)
        b0, b1 = self.flutter_range
        on = (a >= b0) & (a <= b1)
        sp = self._splines[name] if nu == 0 else self._splines[name].derivative(nu)
        v = np.where(on, sp(np.clip(a, b0, b1)), 0.0 if name.startswith("thrust") else np.nan)
        odd = name in _ODD
        # f(c) = sgn(c)^odd g(|c|)  =>  f^(nu)(c) = sgn(c)^(odd + nu) g^(nu)(|c|)
        if (odd + nu) % 2:  # an odd function of chi_N: vanishes at 0 (the mirror image meets itself)
            v = np.where(c < 0, -v, np.where(c == 0, 0.0, v))
        return v

    def cycles(self, chi_N) -> dict[str, np.ndarray]:
        """The cycle data of many cilia at once: ``x, y, fx, fy`` of shape (n, phase, s) for the
        1-d array ``chi_N`` (n,), with ``flutter`` (n,) bool; non-fluttering rows are zero
        (a still filament exerts no force) with their equilibrium shape left NaN.
        Negative chi_N by mirror symmetry (x and fx change sign)."""
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
            if np.any(flutter):
                u = self._u(a[flutter])
                for k in FIELDS:
                    out[k][flutter] = self._splines[k](u)
        for k in ("x", "y"):
            out[k][~flutter] = np.nan
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

    def thrust_angle_range(self) -> tuple[float, float]:
        """The thrust angles the computed flutter rows reach (chi_N >= 0)."""
        a, b = self._angle_branch()
        vals = self._angle(np.linspace(a, b, 2001))
        return float(vals.min()), float(vals.max())

    def chi_N_for_angle(self, angle: float) -> float:
        """The chi_N whose mean thrust points at ``thrust_angle = angle`` (inverse on the monotone
        branch; a negative angle gives a negative chi_N by mirror symmetry)."""
        if not math.isfinite(angle):
            raise TableError(f"angle must be finite, got {angle}")
        lo, hi = self.thrust_angle_range()
        a = abs(angle)
        if lo - 1e-12 <= a < lo:  # the straight filament's angle is 0 up to round-off
            a = lo
        if not lo <= a <= hi:
            b0, b1 = self._angle_branch()
            raise TableError(f"thrust angle {angle:.6g} is not achievable with this field: |angle| must lie in "
                             f"[{lo:.6g}, {hi:.6g}] rad (chi_N in [{b0:g}, {b1:g}])")
        b0, b1 = self._angle_branch()
        xs = np.linspace(b0, b1, 2001)
        vals = self._angle(xs) - a
        change = np.nonzero(np.sign(vals[:-1]) != np.sign(vals[1:]))[0]
        if change.size == 0:
            c = float(xs[int(np.argmin(np.abs(vals)))])
        else:
            k = int(change[0])
            c = brentq(lambda x: float(self._angle(x)) - a, xs[k], xs[k + 1], xtol=1e-13)
        return math.copysign(c, angle) if angle != 0 else c


if __name__ == "__main__":  # regenerate the shipped default table
    import argparse

    ap = argparse.ArgumentParser(description="regenerate the shipped default thrust table (chi_E=200, eta=1)")
    ap.add_argument("--n", type=int, default=41, help="chi_N grid points in [0, cutoff] (default 41)")
    args = ap.parse_args()
    cut = flutter_cutoff(200.0, 1.0, degree=8).chi_N_cutoff
    grid = np.linspace(0.0, cut, args.n)[:-1]
    grid = np.concatenate([grid, [cut + 0.05 * cut]])
    out = Path(__file__).parent / "data" / DEFAULT_FILE
    t = build_table(200.0, 1.0, grid)
    for k in FIELDS:  # shapes and force densities in float32: 1e-7, far below the interpolation error
        t.ds[k].encoding["dtype"] = "float32"
    t.save(out)
    print(f"wrote {out}: {t.ds.sizes}")
