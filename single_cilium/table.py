"""The thrust lookup table over the natural curvature chi_N: the front door (``build_table``,
:class:`ThrustTable`, :class:`TableError`) and the builder.

A table is for one field (chi_E, eta), for a grid of field strengths chi_E (at one eta), or for
one field over a grid of uniform background flows ``(U_par, U_perp)`` (the filament in the mean
flow its neighbours make; frame and signs in :mod:`single_cilium.flowtable`). The reader,
:class:`ThrustTable`, is in :mod:`single_cilium.lookup`; the file schema in
:mod:`single_cilium.tablefile`; what a row holds, the fingerprint of its file and the resume in
:mod:`single_cilium.tablerows`.

:func:`build_table` computes limit cycles (:func:`~single_cilium.cycle.limit_cycle`) on a grid
of chi_N by continuation: each worker walks a contiguous chunk of the grid (chunks of equal
work, one per core), predicting every cycle from the last three by a parabola in chi_N, so that
a row costs two Newton steps with the exact monodromy plus its error estimates. It runs on any
``concurrent.futures.Executor`` (default: a local process pool; with ``scheduler=ADDRESS``, a
Dask distributed cluster through its executor). It finds the flutter cutoff
(:func:`~single_cilium.stability.flutter_cutoff`, in each background flow) and puts a row exactly
there. With ``path`` every finished row is kept on disk at once (with ``build_*`` attributes
recording the field, the grid of fields or flows, settings and package version it was computed
for), so an interrupted build resumes where it stopped; rows of a build with any other field,
grid or settings are refused, never merged, and rows outside the requested grid are ignored.

With a grid of chi_E (``build_table([180, 200, 220], eta, chi_N)``) each worker walks its chunk
of chi_N for every field in turn, continued in chi_N, each field's first cycle from its own Hopf
mode (there is no continuation across fields: a neighbouring field's cycle is a worse start).
With a grid of flows (``build_table(200, 1, chi_N, U_par=..., U_perp=...)``) each worker walks
its chunk for every flow in turn, the flows in a snake order through the grid (each the
neighbour of the last), and a flow's first cycle of the chunk (or the first after a gap in its
branch) starts from the neighbouring flow's cycle at the same chi_N instead of the Hopf mode;
continuation in chi_N carries the rest. The costs of these starts are in
``benchmarks/results/bench_table_flow.md``.

One concept over 500 lines: the build of a thrust table, its rows, resume and file.
"""
from __future__ import annotations

import logging
import math
import os
from concurrent.futures import Executor
from pathlib import Path

import numpy as np
import xarray as xr

from .version import __version__
from cilia_runtime.files import write_netcdf
from .cycle import CycleError, LimitCycle, check_cycle_cost, check_degree, limit_cycle
from .lookup import DEFAULT_FILE, DEFAULT_FLOW_FILE, ThrustTable
from .mesh import Mesh
from .params import CiliumParams
from cilia_runtime.progress import Progress
from .radau import ConvergenceError
from .stability import flutter_cutoff, stability
from .tablefile import FIELDS, FRAME, REST_FIELDS, SCHEMA_VERSION, TableError, coiled, with_attrs
from .tablerows import TableGrid, hole, rest_state, resume, row

logger = logging.getLogger(__name__)

__all__ = ["build_table", "ThrustTable", "TableError", "SCHEMA_VERSION", "DEFAULT_U"]

#: The default grid of each background-flow component (``U_par``, ``U_perp``; ``L / tau``): the
#: flows a carpet of the bundled size induces at its cilia (median about 0.3-0.5 L / tau at
#: 10 x 10), up to where the stream's drag ``eta |U|`` per length matches the largest thrust
#: ``|Fbar| = 1.1`` of chi_E = 200, eta = 1 and beyond (a coupled carpet's iteration visits
#: flows past its solution); every flow of it has a flutter cutoff at chi_E = 200, eta = 1.
DEFAULT_U = np.linspace(-2.0, 2.0, 5)


def _chunk(args):
    """Compute a contiguous run of chi_N rows for every column of the grid in turn, by
    continuation in chi_N (the parabola through the last three cycles of the same column); the
    first cycle of each column's run starts from its Hopf mode (:func:`limit_cycle` without a
    seed), or, over a grid of flows, from the previous column's cycle at the same chi_N (the
    columns come in a snake order: each a neighbour of the last); there is no continuation in
    chi_E (a neighbouring field's cycle is a worse start than the Hopf mode). Rows at a column's own cutoff and another flow's cutoff are left to
    the caller; coiled rows are only marked. Each row is written to ``parts`` if given. Runs
    with the thread budget in ``args`` (the pool's share of the cores per worker), or its Dask
    worker's share (:meth:`~cilia_runtime.threads.ThreadBudget.for_task`).
    Returns ``[(key, row)]``."""
    from cilia_runtime.threads import ThreadBudget

    budget = args[-1] if args[-1] is not None else ThreadBudget.for_task()
    with budget.applied():
        return _chunk_rows(*args[:-1])


def _chunk_rows(grid: TableGrid, eta: float, chi_Ns, settings: dict, parts, skip: dict):
    degree, n_phase, s_grid = settings["degree"], settings["n_phase"], np.asarray(settings["s"])
    fp = grid.fingerprint(eta, settings)
    out = []
    before: dict[float, LimitCycle] = {}  # the previous column's cycles (a neighbouring flow)
    for col in grid.columns:
        E, up, uq = col
        seeds: list[LimitCycle] = []
        mine: dict[float, LimitCycle] = {}
        for cN in chi_Ns:
            if cN in skip[col]:  # its own cutoff (the branch ends: no seeds across) or another's
                seeds = [] if skip[col][cN] else seeds
                continue
            p = CiliumParams(E, eta, cN, (uq, up))
            cyc = None
            rest = None
            alpha = beta = math.nan
            if coiled(E, cN):  # no equilibrium to linearise about: marked, not computed
                regime = "coiled"
                seeds = []
            else:
                try:
                    st = stability(p, degree=degree, check=False, n_modes=1)
                except RuntimeError as exc:  # in a flow: no steady state (a fold)
                    if not p.has_background or isinstance(exc, ConvergenceError):
                        raise
                    logger.info("build_table: no steady state at %s (%s)", p, exc)
                    regime, st = "no_steady_state", None
                    seeds = []
                if st is not None:
                    alpha, beta, regime = st.alpha, st.beta, st.regime
                    rest = rest_state(p, degree, s_grid)
                if regime == "flutter":
                    start = seeds[-3:] or ([before[cN]] if cN in before else [])
                    try:
                        cyc = limit_cycle(p, degree=degree, n_phase=n_phase, seed=start,
                                          tol=settings.get("tol", 1e-8),
                                          error_estimate=settings.get("error_estimate", True))
                    except CycleError as exc:
                        where = f"chi_E = {E:g}, eta = {eta:g}" + (f", U_par = {up:g}, U_perp = {uq:g}"
                                                                   if grid.kind == "flow" else "")
                        why = str(exc).replace("; give a seed from a neighbouring chi_N or raise the degree", "")
                        err = CycleError(f"thrust table ({where}): the cycle at chi_N = {cN:.10g} did not converge "
                                         f"({why}); a finer chi_N grid (each cycle starts from its neighbours')"
                                         + (", a finer flow grid" if grid.kind == "flow" else "")
                                         + " or a higher degree may converge", exc.t)
                        err.key = (float(E), float(up), float(uq), float(cN))
                        raise err from None
                    seeds.append(cyc)
                    mine[cN] = cyc
                else:
                    seeds = []
            r = grid.expand(row(p, cyc, s_grid, n_phase, alpha, beta, regime, rest), col)
            r.attrs.update(fp)
            key = (float(E), float(up), float(uq), float(cN))
            if parts is not None:
                write_netcdf(r, grid.file(parts, key))
            out.append((key, r))
        before = mine
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


def _validated_flow(name: str, values) -> np.ndarray:
    g = np.atleast_1d(np.asarray(values, dtype=float))
    if g.ndim != 1 or g.size == 0:
        raise ValueError(f"{name} must be a number or a non-empty 1-d grid, got {values!r}")
    if not np.all(np.isfinite(g)):
        raise ValueError(f"{name} grid contains NaN or inf")
    if np.any(np.diff(g) <= 0):
        raise ValueError(f"{name} grid must be strictly increasing")
    return g + 0.0  # -0.0 -> 0.0


def _snake(U_par: np.ndarray, U_perp: np.ndarray) -> list[tuple[float, float]]:
    """The flows of the grid in a snake order (each a neighbour of the last)."""
    return [(float(up), float(uq)) for i, up in enumerate(U_par) for uq in (U_perp if i % 2 == 0 else U_perp[::-1])]


def build_table(chi_E, eta: float, chi_N, *, U_par=None, U_perp=None, degree: int = 8, n_phase: int = 64,
                n_s: int = 65, executor: Executor | None = None, scheduler: str | None = None,
                progress: Progress | None = None, path=None, error_estimate: bool = True,
                tol: float = 1e-8, scheduler_timeout: float | None = None, overwrite: bool = False) -> ThrustTable:
    """Compute the thrust table of DESIGN.md over ``chi_N`` (>= 0, strictly increasing), for one
    field (``chi_E`` a number), over a grid of field strengths (``chi_E`` a sequence), or for
    one field over a grid of background flows (``U_par``, ``U_perp``).

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
        The grid; each field's (or flow's) flutter cutoff is added to it when it lies inside (on
        a chi_E grid every field gets every cutoff row; on a flow grid each flow's cutoff row is
        computed for that flow only, the others marked ``not_computed``; the row at a cutoff is
        the zero-amplitude cycle). Rows with ``chi_N > |chi_E|`` (coiled: no equilibrium) are
        marked ``coiled = 1`` with no flutter, and not computed.
    U_par, U_perp : float or array_like, optional
        A grid of uniform background flows (strictly increasing, finite; one value or more
        each; the other defaults to ``[0]``): ``U = U_par e2 + U_perp e1`` in the field frame,
        units ``L / tau`` (``CiliumParams(..., background=(U_perp, U_par))``; signs in
        :mod:`single_cilium.flowtable`; :data:`DEFAULT_U` for both covers a bundled-size
        carpet). The table gets the leading dims ``U_par, U_perp`` and is interpolated in the
        flow by :class:`ThrustTable`; negative chi_N are served by the mirror image, at
        ``-U_perp``, so give a ``U_perp`` grid symmetric about 0. One field only (``chi_E`` a
        number). Rows: flutter, ``stable`` (the thrust is the steady state's force in the flow),
        ``divergence`` (an unstable steady state without flutter: NaN) or ``no_steady_state``
        (the flow tips the filament over: NaN); a flow may suppress flutter altogether or keep
        it up to the coiled filament (no cutoff: its rows are fine, but the flows around it are
        not interpolated).
    degree, n_phase : discretisation of each cycle (see :func:`limit_cycle`): ``degree`` in
        ``[4, MAX_DEGREE]`` (``[2, MAX_DEGREE]`` without ``error_estimate``), ``n_phase`` an
        integer >= 16 whose cycle is estimated within
        :data:`~single_cilium.cycle.MAX_CYCLE_SECONDS`.
    n_s : int
        Points (>= 2) of the uniform arc-length grid of the stored shapes and forces.
    executor : concurrent.futures.Executor, optional
        Where chunks run (default: a process pool over the machine's cores).
    scheduler : str, optional
        Address of a Dask distributed scheduler; its executor is used (the same code path).
    scheduler_timeout : float, optional
        Seconds to wait for ``scheduler`` to answer as a Dask scheduler (default 20, or the
        environment's ``CILIA_SCHEDULER_TIMEOUT``); an address that does not is an OSError
        (:class:`~cilia_runtime.scheduler.SchedulerError`) after that wait, never a hang.
    path : path-like, optional
        Where the table is written; finished rows are kept in ``<path>.parts/`` while building,
        so a rerun after an interruption computes only the missing rows (rows of another field,
        chi_E grid, flow grid or settings are refused, and so is a ``row_*.nc`` there that cannot
        be read: none is removed). Once the table is written, the build removes the row files
        of this build and then the folder if it is empty (any other file keeps it). Every
        argument is checked before anything is created.
    overwrite : bool
        Replace an existing file at ``path`` (default: refuse it, before any work; an
        interrupted build leaves no file at ``path``, only its rows).
    error_estimate : bool
        Refinement error estimates per row (about doubles the cost); NaN without.
    tol : float
        Newton tolerance of each cycle on the scaled shooting residual (the row's quantities
        then carry errors of about that size, far below the discretisation error estimates).

    Raises
    ------
    ValueError
        A bad grid or setting (named), or an existing ``path`` without ``overwrite``.
    CycleError
        A cycle that did not converge, naming the row and the last good one before it (the
        finished rows are kept with ``path``, and the same request resumes from them).
    TableError
        Rows in ``<path>.parts/`` of another build, or a file there that cannot be read.
    """
    grid_E = _validated_chi_E(chi_E)
    flow = U_par is not None or U_perp is not None
    if flow and grid_E is not None:
        raise ValueError("a table over the background flow is for one field: give chi_E as a number (a table "
                         "over both chi_E and the flow is not supported)")
    kind = "chi_E" if grid_E is not None else ("flow" if flow else "field")
    fields = grid_E.tolist() if grid_E is not None else [float(chi_E)]
    bases = [CiliumParams(E, eta, 0.0) for E in fields]
    eta = bases[0].eta
    fields = [b.chi_E for b in bases]
    flows = ((_validated_flow("U_par", 0.0 if U_par is None else U_par),
              _validated_flow("U_perp", 0.0 if U_perp is None else U_perp)) if flow else None)
    columns = ([(fields[0], up, uq) for up, uq in _snake(*flows)] if flow else [(E, 0.0, 0.0) for E in fields])
    grid_spec = TableGrid(kind, columns, fields, flows)
    cN_grid = np.atleast_1d(np.asarray(chi_N, dtype=float))
    if cN_grid.ndim != 1 or cN_grid.size == 0:
        raise ValueError("chi_N must be a non-empty 1-d grid")
    if not np.all(np.isfinite(cN_grid)):
        raise ValueError("chi_N grid contains NaN or inf")
    if np.any(np.diff(cN_grid) <= 0):
        raise ValueError("chi_N grid must be strictly increasing")
    if cN_grid[0] < 0:
        raise ValueError("chi_N grid must be >= 0 (negative chi_N follow by mirror symmetry)")
    if not (0 < tol < 1e-3):
        raise ValueError(f"tol must lie in (0, 1e-3), got {tol}")
    degree = check_degree(degree, error_estimate)
    if not (float(n_phase).is_integer() and n_phase >= 16):
        raise ValueError(f"n_phase must be an integer >= 16, got {n_phase!r}")
    if not (float(n_s).is_integer() and n_s >= 2):
        raise ValueError(f"n_s must be an integer >= 2, got {n_s!r}")
    n_phase, n_s = int(n_phase), int(n_s)
    check_cycle_cost(Mesh.for_params(CiliumParams(max(fields, key=abs), eta, 0.0), degree), n_phase)
    if path is not None:
        target = Path(path)
        if target.is_dir():
            raise ValueError(f"{target}: is a folder; the table path must name a file")
        if target.exists() and not overwrite:
            raise ValueError(f"{target} exists: a table build replaces a file only when asked to (overwrite=True, "
                             "--overwrite); choose another path or remove it")
    cuts = {col: flutter_cutoff(col[0], eta, degree=degree, background=(col[2], col[1])) for col in columns}
    cutoff = {col: c.chi_N_cutoff for col, c in cuts.items()}
    lo, hi = cN_grid[0], cN_grid[-1]
    user = set(cN_grid.tolist())
    grid = cN_grid
    for chi_c in cutoff.values():
        if np.isfinite(chi_c) and lo < chi_c < hi:
            grid = np.unique(np.concatenate([grid[np.abs(grid - chi_c) > 1e-9 * chi_c], [chi_c]]))
    grid_list = [float(c) for c in grid]
    # per column the rows it does not continue through: True its own cutoff (the branch ends),
    # False another flow's cutoff (a hole in a flow grid)
    skip = {col: {float(cutoff[col]): True} if float(cutoff[col]) in grid_list else {} for col in columns}
    if kind == "flow":
        for col in columns:
            for c in grid_list:
                if c not in user and c != cutoff[col]:
                    skip[col][c] = False
    s_grid = np.linspace(0.0, 1.0, int(n_s))
    settings = {"degree": int(degree), "n_phase": int(n_phase), "s": s_grid.tolist(),
                "error_estimate": bool(error_estimate), "tol": float(tol)}
    own = {(col[0], col[1], col[2], c) for col in columns for c in grid_list if c not in skip[col] or skip[col][c]}
    parts = None
    rows: dict[tuple, xr.Dataset] = {}
    ours: set[Path] = set()  # the row files of this build in parts
    if path is not None:  # absolute: a Dask worker writes the rows from its own folder
        parts = Path(os.path.abspath(str(path) + ".parts"))
        parts.mkdir(parents=True, exist_ok=True)
        rows = resume(parts, grid_spec, own, grid_spec.fingerprint(eta, settings), fields[0], ours)
        if rows:
            logger.info("build_table: resuming %s, %d of %d rows done", parts, len(rows), len(own))
    for col in columns:
        E, up, uq = col
        for c, is_own in skip[col].items():
            p = CiliumParams(E, eta, c, (uq, up))
            if is_own:
                r = row(p, None, s_grid, int(n_phase), 0.0, cuts[col].beta, "flutter",
                         rest_state(p, degree, s_grid), cutoff=True)
            else:
                r = hole(E, c, s_grid, int(n_phase))
            rows[(E, up, uq, c)] = grid_spec.expand(r, col)
    todo = np.array([c for c in grid_list if any((*col, c) not in rows for col in columns)])
    n_todo = sum((*col, float(c)) not in rows for col in columns for c in todo)
    weight = np.array([sum((1.0 if c < cutoff[col] and not coiled(col[0], c) else 0.05)
                           if np.isfinite(cutoff[col]) else 1.0 for col in columns) for c in todo])
    progress = progress if progress is not None else Progress()
    progress.start(len(own), "thrust table")
    progress.update(len(own) - n_todo)
    _run(grid_spec, eta, todo, weight, settings, parts, skip, rows, executor, scheduler, scheduler_timeout,
         progress, len(own) - n_todo, fields[0])
    ds = _assemble(grid_spec, rows, grid_list, n_phase, s_grid)
    ds.attrs = grid_spec.fingerprint(eta, settings)  # what it was built for
    if kind == "field":
        ds.attrs.update({"chi_E": fields[0], "chi_N_cutoff": cutoff[columns[0]],
                         "chi_N_cutoff_error": cuts[columns[0]].error})
    else:
        dims = ("chi_E",) if kind == "chi_E" else ("U_par", "U_perp")
        shape = (len(fields),) if kind == "chi_E" else (flows[0].size, flows[1].size)
        order = columns if kind == "chi_E" else [(fields[0], up, uq) for up in flows[0] for uq in flows[1]]
        ds["chi_N_cutoff"] = (dims, np.array([cutoff[col] for col in order]).reshape(shape))
        ds["chi_N_cutoff_error"] = (dims, np.array([cuts[col].error for col in order]).reshape(shape))
        ds.chi_N_cutoff.attrs.update(long_name=f"flutter cutoff chi_N of each {dims[0] if kind == 'chi_E' else 'flow'} "
                                               "(NaN: none)", units="1")
        ds.chi_N_cutoff_error.attrs.update(long_name="error estimate of chi_N_cutoff", units="1")
        if kind == "chi_E":
            ds.chi_E.attrs.update(long_name="field strength chi_E", units="1")
        else:
            ds.attrs.update({"chi_E": fields[0], "background_frame": FRAME})
    ds.attrs.update({
        "eta": eta, "schema_version": SCHEMA_VERSION, "package_version": __version__,
        "field_direction": "e2 (angles anticlockwise from e2)",
        "discretisation": f"Mesh.for_params(params, degree={degree}); {n_phase} Radau IIA(5) steps per period; "
                          f"shooting (exact monodromy) to a scaled residual of {tol:g}",
        "thrust_convention": "thrust = mean force on the fluid -<int d ds>; thrust_angle = phi_Fbar - pi",
    })
    if kind == "flow":  # its rows of other flows' cutoffs are NaN: compressed (losslessly) to nearly nothing,
        # and the cycle data by about 1.5 (151 MB -> 47 MB for flows 5 x 5, chi_N 0:190:20, 64 x 65)
        for k in FIELDS + REST_FIELDS:
            ds[k].encoding.update(zlib=True, complevel=4, shuffle=True)
    table = ThrustTable(with_attrs(ds))
    if path is not None:
        table.save(path)
        _remove_rows(parts, ours | {grid_spec.file(parts, k) for k in own})
    return table


def _remove_rows(parts: Path, files: set) -> None:
    """Remove this build's row files from ``parts`` (and their temporaries left by a killed
    writer), then ``parts`` itself if that leaves it empty; any other file stays."""
    for f in files:
        f.unlink(missing_ok=True)
        for tmp in parts.glob(f".{f.name}.*.part"):  # files.write_bytes' temporaries
            tmp.unlink(missing_ok=True)
    try:
        parts.rmdir()
    except OSError:
        logger.warning("build_table: kept %s: it holds files this build did not write", parts)


def _run(grid: TableGrid, eta, todo, weight, settings, parts, skip, rows, executor, scheduler, scheduler_timeout,
         progress, finished: int, chi_E: float) -> None:
    """Compute the missing rows into ``rows`` on the executor (default: a process pool)."""
    own = None
    budget = None  # a Dask worker's task takes its worker's share; another executor's, the cores
    if executor is None:
        if scheduler is not None:
            from cilia_runtime.scheduler import connect

            own = connect(scheduler, scheduler_timeout)
            executor = own.get_executor()
        else:
            from concurrent.futures import ProcessPoolExecutor

            from cilia_runtime.threads import ThreadBudget, cores

            own = executor = ProcessPoolExecutor(max_workers=cores())
            budget = ThreadBudget(workers=cores(), numba=1, blas=1)  # a process per core, one thread each
    try:
        from cilia_runtime.threads import cores

        chunks = _balanced_chunks(todo, weight, cores())
        tasks = [(grid, eta, c, settings, str(parts) if parts else None, skip, budget) for c in chunks]
        try:
            for res in executor.map(_chunk, tasks):
                for key, r in res:
                    if key not in rows:  # rows resumed from disk stay as they were
                        rows[key] = r
                        finished += 1
                progress.update(finished)
        except CycleError as exc:
            failed = getattr(exc, "key", (chi_E, 0.0, 0.0, math.inf))
            good = {k[3] for k in rows if k[:3] == failed[:3]}
            if parts:
                for f in parts.glob("row_*.nc"):
                    k = grid.key_of_file(f, chi_E)
                    if k[:3] == failed[:3]:
                        good.add(k[3])
            before = [c for c in good if c < failed[3]]
            last = f"chi_N = {max(before):.10g}" if before else "none"
            kept = (f"; the finished rows are kept in {parts}, and the same request resumes from them"
                    if parts is not None else "")
            raise CycleError(f"{exc}; last good row before it: {last}{kept}", exc.t) from None
    except BaseException:  # Ctrl-C or a failure: do not wait for the running chunks (their
        # finished rows are on disk for the resume); stop our own pool's workers now
        if own is not None and own is executor and hasattr(own, "_processes"):  # our process pool (a Dask
            # client's tasks are released when it closes below; Client.shutdown would stop the cluster)
            procs = list((getattr(own, "_processes", None) or {}).values())  # shutdown() forgets them
            manager = getattr(own, "_executor_manager_thread", None)
            own.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                proc.terminate()
            # wait (briefly) until the workers are gone and the pool's manager thread has closed its
            # pipes: left running, it closes them while this process exits, and its queue's feeder
            # thread then writes to a closed descriptor (OSError: [Errno 9] Bad file descriptor)
            for proc in procs:
                proc.join(5.0)
            if manager is not None:
                manager.join(5.0)
        raise
    finally:
        progress.close()
        if own is not None:
            (own.close() if hasattr(own, "close") else own.shutdown())


def _assemble(grid: TableGrid, rows: dict, grid_list: list, n_phase: int, s_grid: np.ndarray) -> xr.Dataset:
    """The table Dataset from its rows (dims as the kind of grid)."""
    def column(col):
        return xr.concat([rows[(*col, c)] for c in grid_list], dim="chi_N")

    if grid.kind == "flow":
        E = grid.fields[0]
        ds = xr.combine_nested([[column((E, float(up), float(uq))) for uq in grid.flows[1]] for up in grid.flows[0]],
                               concat_dim=["U_par", "U_perp"])
    elif grid.kind == "chi_E":
        ds = xr.concat([column(col) for col in grid.columns], dim="chi_E")
    else:
        ds = column(grid.columns[0])
    return ds.assign_coords(phase=np.arange(n_phase) / n_phase, s=s_grid)


SHIPPED_FLOW = np.linspace(-1.5, 1.5, 7)
"""The flow grid of the shipped table over the background flow (each component, L / tau)."""
SHIPPED_FLOW_CHI_N = np.linspace(0.0, 190.0, 20)
"""Its chi_N grid (plus each flow's cutoff row): 1.05 x the largest cutoff over the grid's flows."""


if __name__ == "__main__":  # regenerate the shipped tables
    import argparse

    from .tablefile import compact

    ap = argparse.ArgumentParser(description="regenerate a shipped thrust table (chi_E=200, eta=1): over chi_N in "
                                 "still fluid, or with --flow over the background flow (about 5 minutes on 2 cores)")
    ap.add_argument("--n", type=int, default=41, help="chi_N grid points in [0, cutoff] (default 41)")
    ap.add_argument("--flow", action="store_true", help="the table over the background flow (SHIPPED_FLOW)")
    args = ap.parse_args()
    if args.flow:
        out = Path(__file__).parent / "data" / DEFAULT_FLOW_FILE
        t = build_table(200.0, 1.0, SHIPPED_FLOW_CHI_N, U_par=SHIPPED_FLOW, U_perp=SHIPPED_FLOW)
        write_netcdf(compact(t.ds), out)
    else:
        cut = flutter_cutoff(200.0, 1.0, degree=8).chi_N_cutoff
        grid = np.linspace(0.0, cut, args.n)[:-1]
        grid = np.concatenate([grid, [cut + 0.05 * cut]])
        out = Path(__file__).parent / "data" / DEFAULT_FILE
        t = build_table(200.0, 1.0, grid)
        for k in FIELDS:  # shapes and force densities in float32: 1e-7, far below the interpolation error
            t.ds[k].encoding["dtype"] = "float32"
        t.save(out)
    print(f"wrote {out}: {dict(ThrustTable.load(out).ds.sizes)}")
