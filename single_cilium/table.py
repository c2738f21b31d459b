"""The thrust lookup table over the natural curvature chi_N, for one field (chi_E, eta) or over a
grid of field strengths chi_E (at one eta).

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
outside the requested grid are ignored. With a grid of chi_E (``build_table([180, 200, 220], eta,
chi_N)``) each worker walks its chunk of chi_N for every field in turn, continued in chi_N; a
neighbouring field's cycle at the same chi_N was measured to be a worse start than the field's
own Hopf mode, so there is no continuation across fields.

:class:`ThrustTable` wraps the Dataset of DESIGN.md (schema below), validates it on load,
interpolates it smoothly in chi_N (cubic splines on the flutter branch; for the shapes and
forces in ``sqrt(chi_c - chi_N)``, in which their Hopf onset is smooth), inverts the thrust
angle, and mirrors negative chi_N; a table over chi_E is interpolated in chi_E too, at fixed
fractions of each field's cutoff (:class:`ThrustTable`).

Schema (version 1): dims ``chi_N``, ``phase`` (uniform in [0, 1)), ``s`` (uniform in [0, 1]);
per chi_N ``flutter`` (int8 0/1), ``period``, ``thrust_norm``, ``thrust_angle``, ``thrust_x``,
``thrust_y``, ``theta_lim``, ``alpha``, ``beta``, ``floquet``, ``tip_area`` and the error
estimates ``period_error``, ``thrust_norm_error``, ``thrust_angle_error``,
``floquet_trivial_error``; per (chi_N, phase, s) ``x``, ``y``, ``fx``, ``fy`` (force per
length on the fluid, ``-d``); ``coiled`` (int8; 1 where ``|chi_N| > |chi_E|``: no equilibrium,
the row is not computed; absent from tables built before it, read as 0). Rows without flutter:
period NaN, thrust 0, cycle data NaN. Attributes ``chi_E``, ``eta``, ``chi_N_cutoff``,
``chi_N_cutoff_error`` and ``build_*`` (what the rows were computed for).

A table over chi_E has the same variables with a leading dimension ``chi_E`` (> 0, strictly
increasing): per (chi_E, chi_N) the scalars, per (chi_E, chi_N, phase, s) the fields, and per
chi_E ``chi_N_cutoff`` and ``chi_N_cutoff_error`` as variables (no ``chi_E`` attribute; the
``chi_N`` grid holds every field's cutoff, each a plain row for the other fields).
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
from scipy.interpolate import CubicSpline, make_interp_spline
from scipy.optimize import brentq

from . import __version__
from .files import write_netcdf
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
def _coiled(chi_E: float, chi_N: float) -> bool:
    """``|chi_E| < |chi_N|``: no fixed point, the filament coils (no limit angle, no row computed)."""
    return abs(chi_E) < abs(chi_N)


def _row(params: CiliumParams, cyc: LimitCycle | None, s_grid: np.ndarray, n_phase: int,
         alpha: float, beta: float, cutoff: bool = False) -> xr.Dataset:
    coiled = _coiled(params.chi_E, params.chi_N)
    try:
        tl = math.nan if coiled else limit_angle(params)
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
    ds["coiled"] = ((), np.int8(coiled))
    for k, v in fields.items():
        ds[k] = (("phase", "s"), v)
    return ds.expand_dims(chi_N=[params.chi_N])


def _grid_text(values) -> str:
    return ",".join(f"{float(v):.17g}" for v in values)


def _fingerprint(chi_E, eta: float, settings: dict) -> dict:
    """What a stored row was computed for (attrs ``build_*`` of each row file): a resumed build
    reuses a row only if all of these match. ``chi_E`` is a float (a table of one field:
    ``build_chi_E``) or the grid of a table over chi_E (``build_chi_E_grid``, the whole grid: its
    rows are continued from one another in chi_E)."""
    field = ({"build_chi_E": float(chi_E)} if np.ndim(chi_E) == 0
             else {"build_chi_E_grid": _grid_text(chi_E)})
    return {**field, "build_eta": float(eta), "build_degree": int(settings["degree"]),
            "build_n_phase": int(settings["n_phase"]), "build_n_s": len(settings["s"]),
            "build_error_estimate": int(bool(settings.get("error_estimate", True))),
            "build_tol": float(settings.get("tol", 1e-8)),
            "build_method": str(settings.get("method", "shooting")), "build_package_version": __version__}


def _row_key(r: xr.Dataset, chi_E: float) -> tuple[float, float]:
    """(chi_E, chi_N) of a one-row Dataset (``chi_E`` is the field of a one-field table)."""
    e = float(r.chi_E.values[0]) if "chi_E" in r.dims else float(chi_E)
    return e, float(r.chi_N.values[0])


def _row_file(parts, chi_E: float, chi_N: float, two_d: bool) -> Path:
    return Path(parts) / (f"row_{chi_E:.17g}_{chi_N:.17g}.nc" if two_d else f"row_{chi_N:.17g}.nc")


def _resume(parts: Path, wanted: set, want: dict, chi_E: float) -> dict[tuple[float, float], xr.Dataset]:
    """Rows of an interrupted build in ``parts`` that match the request (keys ``(chi_E, chi_N)``
    in ``wanted``); refuse any other."""
    done: dict[tuple[float, float], xr.Dataset] = {}
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
        key = _row_key(r, chi_E)
        if key in wanted:  # rows outside the requested grid are never merged in
            done[key] = r
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
    """Compute a contiguous run of chi_N rows for every field of ``chi_Es`` in turn, by
    continuation in chi_N (the parabola through the last three cycles of the same field); the
    first cycle of each field's run starts from its Hopf mode (:func:`limit_cycle` without a
    seed). Continuation in chi_E does not pay: the cycle of a neighbouring field at the same
    chi_N as seed (its deviation from its own equilibrium carried onto this field's mesh) cost
    1.3-1.4x the unseeded start for fields 2 to 10 apart and 1.4-4x for 20 apart (degree 8, 64
    steps, chi_N = 0 and 100 at chi_E = 200; 0.36-0.40 s unseeded). Rows at a field's own cutoff
    are left to the caller; coiled rows are only marked. Each row is written to ``parts`` if
    given. Runs with the thread budget in ``args`` (the pool's share of the cores per worker),
    or its Dask worker's share (:meth:`~single_cilium.threads.ThreadBudget.for_task`).
    Returns ``[(chi_E, chi_N, row)]``."""
    from .threads import ThreadBudget

    budget = args[7] if len(args) > 7 and args[7] is not None else ThreadBudget.for_task()
    with budget.applied():
        return _chunk_rows(args[:7])


def _chunk_rows(args):
    chi_Es, eta, chi_Ns, settings, parts, cutoffs, two_d = args
    degree, n_phase, s_grid = settings["degree"], settings["n_phase"], np.asarray(settings["s"])
    out = []
    for chi_E in chi_Es:
        seeds: list[LimitCycle] = []
        for cN in chi_Ns:
            if cN == cutoffs[chi_E]:
                seeds = []
                continue
            p = CiliumParams(chi_E, eta, cN)
            cyc = None
            if _coiled(chi_E, cN):  # no equilibrium to linearise about: marked, not computed
                alpha = beta = math.nan
                seeds = []
            else:
                st = stability(p, degree=degree, check=False, n_modes=1)
                alpha, beta = st.alpha, st.beta
                if st.regime == "flutter":
                    try:
                        cyc = limit_cycle(p, degree=degree, n_phase=n_phase, seed=seeds[-3:],
                                          tol=settings.get("tol", 1e-8),
                                          error_estimate=settings.get("error_estimate", True))
                    except CycleError as exc:
                        err = CycleError(f"thrust table (chi_E = {chi_E:g}, eta = {eta:g}): the cycle at "
                                         f"chi_N = {cN:.10g} did not converge ({exc})", exc.t)
                        err.chi_N, err.chi_E = float(cN), float(chi_E)
                        raise err from None
                    seeds.append(cyc)
                else:
                    seeds = []
            row = _row(p, cyc, s_grid, n_phase, alpha, beta)
            if two_d:
                row = row.expand_dims(chi_E=[float(chi_E)])
            row.attrs.update(_fingerprint(chi_Es if two_d else chi_E, eta, settings))
            if parts is not None:
                write_netcdf(row, _row_file(parts, chi_E, cN, two_d))
            out.append((float(chi_E), float(cN), row))
    return out


def _balanced_chunks(todo: np.ndarray, weight: np.ndarray, n_chunks: int) -> list[list[float]]:
    """Contiguous runs of the grid (each continued from its own start), one per worker, of equal
    work (``weight`` per grid point: a flutter row costs a cycle, a stable row about 5 % of one)."""
    if todo.size == 0:
        return []
    n_chunks = max(1, min(todo.size, n_chunks))
    cum = np.cumsum(weight)
    edges = np.searchsorted(cum, cum[-1] * np.arange(1, n_chunks) / n_chunks, side="right")
    return [c.tolist() for c in np.split(todo, edges) if c.size]


def _validated_chi_E(chi_E) -> np.ndarray | None:
    """None for one field (a float); the grid of a table over chi_E otherwise."""
    if np.ndim(chi_E) == 0:
        return None
    g = np.asarray(chi_E, dtype=float)
    if g.ndim != 1 or g.size < 2:
        raise ValueError(f"chi_E must be a number (one field) or a 1-d grid of at least 2 values, got {chi_E!r}")
    if not np.all(np.isfinite(g)):
        raise ValueError("chi_E grid contains NaN or inf")
    if np.any(np.diff(g) <= 0):
        raise ValueError("chi_E grid must be strictly increasing")
    if g[0] <= 0:
        raise ValueError(f"chi_E grid must be > 0, got {g[0]:g} (for chi_E < 0 any chi_N > 0 removes flutter: "
                         "there is no branch to interpolate between fields)")
    return g


def build_table(chi_E, eta: float, chi_N, *, degree: int = 8, n_phase: int = 64, n_s: int = 65,
                executor: Executor | None = None, scheduler: str | None = None,
                progress: Progress | None = None, path=None, error_estimate: bool = True,
                tol: float = 1e-8, scheduler_timeout: float | None = None) -> "ThrustTable":
    """Compute the thrust table of DESIGN.md over ``chi_N`` (>= 0, strictly increasing), for one
    field (``chi_E`` a number) or over a grid of field strengths (``chi_E`` a sequence).

    Parameters
    ----------
    chi_E : float or array_like
        The field strength: a number gives the table of one field (dims ``chi_N, phase, s``); a
        strictly increasing grid of at least two values > 0 gives a table over chi_E (dims
        ``chi_E, chi_N, phase, s``) that :class:`ThrustTable` interpolates in chi_E too (see
        there). Each field's rows are continued in chi_N; each worker walks its chunk of chi_N
        for every field in turn (continuation in chi_E does not pay, see ``_chunk``).
    eta : float
        The drag ratio.
    chi_N : array_like
        The grid; each field's flutter cutoff is added to it when it lies inside (on a chi_E
        grid every field gets every cutoff row; the row at a field's own cutoff is the zero-
        amplitude cycle). Rows with ``chi_N > |chi_E|`` (coiled: no equilibrium) are marked
        ``coiled = 1`` with no flutter, and not computed.
    degree, n_phase : discretisation of each cycle (see :func:`limit_cycle`).
    n_s : int
        Points of the uniform arc-length grid of the stored shapes and forces.
    executor : concurrent.futures.Executor, optional
        Where chunks run (default: a process pool over the machine's cores).
    scheduler : str, optional
        Address of a Dask distributed scheduler; its executor is used (the same code path).
    scheduler_timeout : float, optional
        Seconds to wait for ``scheduler`` to answer as a Dask scheduler (default 20, or the
        environment's ``CILIA_SCHEDULER_TIMEOUT``); an address that does not is an OSError
        (:class:`~single_cilium.scheduler.SchedulerError`) after that wait, never a hang.
    path : path-like, optional
        Where the table is written; finished rows are kept in ``<path>.parts/`` while building,
        so a rerun after an interruption computes only the missing rows (rows of another field,
        chi_E grid or settings are refused).
    error_estimate : bool
        Refinement error estimates per row (about doubles the cost); NaN without.
    tol : float
        Newton tolerance of each cycle on the scaled shooting residual (the row's quantities
        then carry errors of about that size, far below the discretisation error estimates).
    """
    grid_E = _validated_chi_E(chi_E)
    two_d = grid_E is not None
    fields = grid_E.tolist() if two_d else [float(chi_E)]
    bases = [CiliumParams(E, eta, 0.0) for E in fields]
    eta = bases[0].eta
    fields = [b.chi_E for b in bases]
    grid = np.atleast_1d(np.asarray(chi_N, dtype=float))
    if grid.ndim != 1 or grid.size == 0:
        raise ValueError("chi_N must be a non-empty 1-d grid")
    if not np.all(np.isfinite(grid)):
        raise ValueError("chi_N grid contains NaN or inf")
    if np.any(np.diff(grid) <= 0):
        raise ValueError("chi_N grid must be strictly increasing")
    if grid[0] < 0:
        raise ValueError("chi_N grid must be >= 0 (negative chi_N follow by mirror symmetry)")
    if not (0 < tol < 1e-3):
        raise ValueError(f"tol must lie in (0, 1e-3), got {tol}")
    cuts = {E: flutter_cutoff(E, eta, degree=degree) for E in fields}
    cutoff = {E: c.chi_N_cutoff for E, c in cuts.items()}
    lo, hi = grid[0], grid[-1]
    for chi_c in cutoff.values():
        if np.isfinite(chi_c) and lo < chi_c < hi:
            grid = np.unique(np.concatenate([grid[np.abs(grid - chi_c) > 1e-9 * chi_c], [chi_c]]))
    s_grid = np.linspace(0.0, 1.0, int(n_s))
    settings = {"degree": int(degree), "n_phase": int(n_phase), "s": s_grid.tolist(),
                "error_estimate": bool(error_estimate), "tol": float(tol)}
    keys = {(E, float(c)) for E in fields for c in grid}
    parts = None
    done: dict[tuple[float, float], xr.Dataset] = {}
    if path is not None:
        parts = Path(str(path) + ".parts")
        parts.mkdir(parents=True, exist_ok=True)
        done = _resume(parts, keys, _fingerprint(fields if two_d else fields[0], eta, settings), fields[0])
        if done:
            logger.info("build_table: resuming %s, %d of %d rows done", parts, len(done), len(keys))
    rows = dict(done)
    for E in fields:
        if (E, cutoff[E]) in keys:
            p = CiliumParams(E, eta, cutoff[E])
            r = _row(p, None, s_grid, int(n_phase), 0.0, cuts[E].beta, cutoff=True)
            rows[(E, cutoff[E])] = r.expand_dims(chi_E=[E]) if two_d else r
    # a chi_N point is computed for every field that lacks it (continuation runs over all fields)
    todo = np.array([c for c in grid if any((E, float(c)) not in rows for E in fields)])
    n_todo = sum((E, float(c)) not in rows for E in fields for c in todo)
    weight = np.array([sum((1.0 if c < cutoff[E] and not _coiled(E, c) else 0.05) if np.isfinite(cutoff[E])
                           else 1.0 for E in fields) for c in todo])
    progress = progress if progress is not None else Progress()
    progress.start(len(keys), "thrust table")
    progress.update(len(keys) - n_todo)
    own = None
    budget = None  # a Dask worker's task takes its worker's share; another executor's, the cores
    if executor is None:
        if scheduler is not None:
            from .scheduler import connect

            own = connect(scheduler, scheduler_timeout)
            executor = own.get_executor()
        else:
            from concurrent.futures import ProcessPoolExecutor

            from .threads import ThreadBudget, cores

            own = executor = ProcessPoolExecutor(max_workers=cores())
            budget = ThreadBudget(workers=cores(), numba=1, blas=1)  # a process per core, one thread each
    try:
        chunks = _balanced_chunks(todo, weight, os.cpu_count() or 1)
        tasks = [(fields, eta, c, settings, str(parts) if parts else None, cutoff, two_d, budget) for c in chunks]
        finished = len(keys) - n_todo
        try:
            for res in executor.map(_chunk, tasks):
                for E, c, r in res:
                    if (E, c) not in rows:  # rows resumed from disk stay as they were
                        rows[(E, c)] = r
                        finished += 1
                progress.update(finished)
        except CycleError as exc:
            failed, E_f = getattr(exc, "chi_N", math.inf), getattr(exc, "chi_E", fields[0])
            good = {c for (E, c) in rows if E == E_f}
            if parts:
                for f in parts.glob("row_*.nc"):
                    name = f.name[4:-3].split("_")
                    if len(name) == 1 or float(name[0]) == E_f:
                        good.add(float(name[-1]))
            before = [c for c in good if c < failed]
            last = f"chi_N = {max(before):.10g}" if before else "none"
            kept = (f"; the finished rows are kept in {parts}, and the same request resumes from them"
                    if parts is not None else "")
            raise CycleError(f"{exc}; last good row before it: {last}{kept}", exc.t) from None
    except BaseException:  # Ctrl-C or a failure: do not wait for the running chunks (their
        # finished rows are on disk for the resume); stop our own pool's workers now
        if own is not None and own is executor and hasattr(own, "_processes"):  # our process pool (a Dask
            # client's tasks are released when it closes below; Client.shutdown would stop the cluster)
            procs = list((getattr(own, "_processes", None) or {}).values())  # shutdown() forgets them
            own.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                proc.terminate()
        raise
    finally:
        progress.close()
        if own is not None:
            (own.close() if hasattr(own, "close") else own.shutdown())
    per_field = [xr.concat([rows[(E, c)] for c in grid.tolist()], dim="chi_N") for E in fields]
    ds = xr.concat(per_field, dim="chi_E") if two_d else per_field[0]
    ds = ds.assign_coords(phase=np.arange(n_phase) / n_phase, s=s_grid)
    ds.attrs = _fingerprint(fields if two_d else fields[0], eta, settings)  # what it was built for
    if two_d:
        ds["chi_N_cutoff"] = ("chi_E", np.array([cutoff[E] for E in fields]))
        ds["chi_N_cutoff_error"] = ("chi_E", np.array([cuts[E].error for E in fields]))
        ds.chi_N_cutoff.attrs.update(long_name="flutter cutoff chi_N of each field (NaN: none)", units="1")
        ds.chi_N_cutoff_error.attrs.update(long_name="error estimate of chi_N_cutoff", units="1")
        ds.chi_E.attrs.update(long_name="field strength chi_E", units="1")
    else:
        ds.attrs.update({"chi_E": fields[0], "chi_N_cutoff": cutoff[fields[0]],
                         "chi_N_cutoff_error": cuts[fields[0]].error})
    ds.attrs.update({
        "eta": eta, "schema_version": SCHEMA_VERSION, "package_version": __version__,
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
    "coiled": "1 if |chi_E| < |chi_N| (no equilibrium: the filament coils; not computed)",
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
    """The thrust table of one field, or over a grid of fields: a validated Dataset with
    interpolation and inversion.

    A table over chi_E (dims ``chi_E, chi_N``, from ``build_table([chi_E, ...], eta, chi_N)``)
    serves any field strength in :attr:`chi_E_range` through the keyword ``chi_E=`` of
    :meth:`at`, :meth:`scalar`, :meth:`cycles`, :meth:`thrust_angle_range` and
    :meth:`chi_N_for_angle` (required there; a one-field table accepts only its own chi_E).
    At a field value of the grid this is that field's table exactly. Between grid values the
    table of the field ``chi_E`` is interpolated at a fixed fraction ``r = chi_N / chi_c(chi_E)``
    of its flutter cutoff: the cutoff ``chi_c(chi_E)`` is interpolated (polynomial spline of
    degree ``min(3, n - 1)`` through the fields' cutoffs), every field's table is evaluated at
    ``r chi_c(chi_E_j)`` (so that the Hopf onsets line up), and each scalar, shape and force is
    interpolated across the fields by the same spline in chi_E; the nodes in ``r`` are those of
    the nearest field. Rows above ``chi_c(chi_E)`` have no flutter; ``alpha`` and ``beta`` there
    are linear in chi_E between the neighbouring fields (NaN where coiled).

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

    def __init__(self, ds: xr.Dataset, source: str = "<memory>"):
        self.ds = self._validate(ds, source)
        self._source = source
        self._fields: dict[float, ThrustTable] = {}
        if "chi_E" in self.ds.dims:
            self._init_grid()
            return
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

    def _table(self, chi_E) -> "ThrustTable":
        """The one-field table that serves ``chi_E`` (see the class docstring)."""
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
            self._fields[E] = ThrustTable(self._interpolated(E), f"{self._source} interpolated at chi_E = {E:g}")
        return self._fields[E]

    def _interpolated(self, E: float) -> xr.Dataset:
        """The one-field Dataset at ``E``, interpolated at fixed fractions of the cutoff."""
        Es = np.array(self._knots)
        tabs = [self._grid[e] for e in self._knots]
        k = min(3, Es.size - 1)

        def across(values):  # (n_fields, ...) -> value at E
            return make_interp_spline(Es, np.asarray(values), k=k, axis=0, check_finite=False)(E)

        cj = np.array([float(t.ds.attrs["chi_N_cutoff"]) for t in tabs])
        c = float(across(cj))
        # the fractions of the cutoff that every field's branch covers
        r_lo = max(t._branch[0] / cc for t, cc in zip(tabs, cj))
        r_hi = min(t._branch[-1] / cc for t, cc in zip(tabs, cj))
        to_cutoff = all(t._cut is not None for t in tabs)  # every branch ends at its cutoff row
        near = int(np.argmin(np.abs(Es - E)))
        r = tabs[near]._branch / cj[near]
        r = np.unique(np.concatenate([[r_lo, r_hi], r[(r > r_lo * (1 + 1e-12)) & (r < r_hi * (1 - 1e-12))]]))
        if to_cutoff:
            r[-1] = 1.0
        n = r.size
        scal = {}
        for name in SCALARS:
            vals = []
            for t, cc in zip(tabs, cj):
                x = np.clip(r * cc, t._branch[0], t._branch[-1])
                vals.append(t.scalar(name, x) if name in t._splines else np.full(n, np.nan))
            scal[name] = across(vals)
        cyc = [t.cycles(np.clip(r * cc, t._branch[0], t._branch[-1])) for t, cc in zip(tabs, cj)]
        fields = {name: across([cy[name] for cy in cyc]) for name in FIELDS}
        if to_cutoff:  # the last row is the zero-amplitude cycle at the cutoff, as in a one-field build
            for name in ("thrust_norm", "thrust_x", "thrust_y", "tip_area"):
                scal[name][-1] = 0.0
            scal["thrust_angle"][-1] = np.nan
            fields["fx"][-1] = fields["fy"][-1] = 0.0
        chi = r * c
        # rows of the grid above the cutoff: no flutter (none when a branch ends before its cutoff:
        # the table then ends with the branch)
        grid = self.ds.chi_N.values
        above = grid[grid > c * (1 + 1e-12)] if to_cutoff else grid[:0]
        m = above.size
        for name in SCALARS:
            scal[name] = np.concatenate([scal[name], np.full(m, np.nan)])
        for name in ("thrust_norm", "thrust_x", "thrust_y", "tip_area"):
            scal[name][n:] = 0.0
        for name in ("alpha", "beta"):  # linear in chi_E between the neighbouring fields
            col = self.ds[name].sel(chi_N=above).transpose("chi_N", "chi_E").values
            allE = self.ds.chi_E.values
            scal[name][n:] = [np.interp(E, allE, v) for v in col]
        for i, a in enumerate(above):
            p = CiliumParams(E, self.eta, float(a))
            try:
                scal["theta_lim"][n + i] = limit_angle(p) if not _coiled(E, a) else np.nan
            except NoLimitAngleError:
                scal["theta_lim"][n + i] = np.nan
        n_p, n_s = self.ds.sizes["phase"], self.ds.sizes["s"]
        for name in FIELDS:
            fields[name] = np.concatenate([fields[name], np.full((m, n_p, n_s), np.nan)])
        chi_all = np.concatenate([chi, above])
        out = xr.Dataset({name: ("chi_N", v) for name, v in scal.items()},
                         coords={"chi_N": chi_all, "phase": self.ds.phase.values, "s": self.ds.s.values})
        out["flutter"] = ("chi_N", np.r_[np.ones(n, np.int8), np.zeros(m, np.int8)])
        out["coiled"] = ("chi_N", np.array([_coiled(E, x) for x in chi_all], np.int8))
        for name, v in fields.items():
            out[name] = (("chi_N", "phase", "s"), v)
        err = float(across(self.ds.chi_N_cutoff_error.sel(chi_E=Es).values))
        out.attrs = {**self.ds.attrs, "chi_E": E, "chi_N_cutoff": c, "chi_N_cutoff_error": err,
                     "interpolated": f"in chi_E between the fields {_grid_text(Es)} at fixed chi_N / chi_N_cutoff"}
        return out

    def _u(self, chi_N):
        chi_N = np.asarray(chi_N, dtype=float)
        return np.sqrt(np.maximum(self._cut - chi_N, 0.0)) if self._cut is not None else chi_N

    @staticmethod
    def _validate(ds: xr.Dataset, source: str) -> xr.Dataset:
        missing = [k for k in SCALARS + FIELDS + ("flutter",) if k not in ds]
        if missing or "chi_N" not in ds.dims:
            raise TableError(f"{source}: not a thrust table (missing {missing or 'dim chi_N'})")
        two_d = "chi_E" in ds.dims
        if two_d:
            lack = [k for k in ("chi_N_cutoff", "chi_N_cutoff_error") if k not in ds]
            if lack:
                raise TableError(f"{source}: a table over chi_E without {lack}")
            e = ds.chi_E.values
            if np.any(~np.isfinite(e)) or np.any(np.diff(e) <= 0) or e[0] <= 0:
                raise TableError(f"{source}: chi_E coordinate must be finite, > 0 and strictly increasing")
        v = ds.attrs.get("schema_version")
        if v != SCHEMA_VERSION:
            raise TableError(f"{source}: table schema version {v!r}, this package reads version {SCHEMA_VERSION}: "
                             "rebuild it with build_table")
        for k in ("eta",) if two_d else ("chi_E", "eta"):
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

    def save(self, path) -> Path:
        """Write as NetCDF4/HDF5 (h5netcdf), atomically."""
        return write_netcdf(self.ds, path)

    @classmethod
    def load(cls, path) -> "ThrustTable":
        """Read and validate a table file; a missing, corrupt or foreign file raises TableError."""
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
        return cls(ds, str(path))

    @classmethod
    def default(cls) -> "ThrustTable":
        """The shipped table for (chi_E, eta) = (200, 1) (regenerate: ``python -m single_cilium.table``)."""
        return cls.load(resources.files("single_cilium") / "data" / DEFAULT_FILE)

    def at(self, chi_N: float, chi_E: float | None = None) -> xr.Dataset:
        """One row at any chi_N in the table's range (or its mirror image): cubic-spline
        interpolation of every scalar and of the cycle data on the flutter branch; rows outside
        the branch (no flutter) are interpolated as no-flutter rows. Negative chi_N by mirror
        symmetry (x, fx, thrust_x, thrust_angle, theta_lim and tip_area change sign).
        ``chi_E``: the field (required for a table over chi_E; see the class docstring)."""
        t = self._table(chi_E)
        if t is not self:
            return t.at(chi_N).assign_coords(chi_E=float(chi_E))
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
                row["coiled"] = row.coiled.copy(data=np.int8(_coiled(self.chi_E, a)))
        if c < 0:
            for k in ("x", "fx", "thrust_x", "thrust_angle", "theta_lim", "tip_area"):
                row[k] = -row[k]
        return row.assign_coords(chi_N=c)

    @property
    def flutter_range(self) -> tuple[float, float]:
        """The |chi_N| interval of the flutter branch (where the table has cycles); a table over
        chi_E has one per field: ``at(chi_N, chi_E=...).flutter``."""
        if "chi_E" in self.ds.dims:
            raise TableError("a table over chi_E has a flutter branch per field: ask at(chi_N, chi_E=...) "
                             "or thrust_angle_range(chi_E=...)")
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

    def scalar(self, name: str, chi_N, nu: int = 0, chi_E: float | None = None) -> np.ndarray:
        """A scalar column (e.g. ``"thrust_x"``, ``"period"``) or its ``nu``-th derivative in
        chi_N, vectorised over ``chi_N`` (any shape) and mirrored for negative chi_N
        (thrust_x, thrust_angle, theta_lim and tip_area are odd in chi_N, the rest even).
        Off the flutter branch the thrust columns are 0 and the others NaN. ``chi_E``: the field
        (required for a table over chi_E)."""
        if name not in SCALARS:
            raise KeyError(f"{name!r} is not a scalar column of the table ({', '.join(SCALARS)})")
        t = self._table(chi_E)
        if t is not self:
            return t.scalar(name, chi_N, nu)
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

    def cycles(self, chi_N, chi_E: float | None = None) -> dict[str, np.ndarray]:
        """The cycle data of many cilia at once: ``x, y, fx, fy`` of shape (n, phase, s) for the
        1-d array ``chi_N`` (n,), with ``flutter`` (n,) bool; non-fluttering rows are zero
        (a still filament exerts no force) with their equilibrium shape left NaN.
        Negative chi_N by mirror symmetry (x and fx change sign). ``chi_E``: the field (required
        for a table over chi_E)."""
        t = self._table(chi_E)
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

    def thrust_angle_range(self, chi_E: float | None = None) -> tuple[float, float]:
        """The thrust angles the computed flutter rows reach (chi_N >= 0) under the field ``chi_E``
        (required for a table over chi_E)."""
        t = self._table(chi_E)
        if t is not self:
            return t.thrust_angle_range()
        a, b = self._angle_branch()
        vals = self._angle(np.linspace(a, b, 2001))
        return float(vals.min()), float(vals.max())

    def chi_N_for_angle(self, angle: float, chi_E: float | None = None) -> float:
        """The chi_N whose mean thrust points at ``thrust_angle = angle`` (inverse on the monotone
        branch; a negative angle gives a negative chi_N by mirror symmetry) under the field
        ``chi_E`` (required for a table over chi_E)."""
        t = self._table(chi_E)
        if t is not self:
            return t.chi_N_for_angle(angle)
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
