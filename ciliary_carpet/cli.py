"""``ciliary-carpet``: render scenes, design layouts, batch many scenes.

    ciliary-carpet render designs/NAME.toml -o out/NAME [--overwrite] [--reduced] [--json]
    ciliary-carpet design designs/NAME.toml -o layout.nc [--overwrite]
    ciliary-carpet batch designs/*.toml -o out/ [-j N] [--scheduler ADDRESS [--scheduler-timeout S]] [--overwrite]
                         [--reduced] [--json]

Options before the command: ``--debug`` (show the traceback of a failure), ``--allow-outside-paths``
(let scene files name table and target files outside their own folder), ``--max-hours H`` (the time
a scene may need, default 24), ``--backend NAME`` (the evaluator of the flow sums, overriding the scenes'
``backend``: auto, direct, fmm, cuda, cuda-fp32, cuda-fp32-acc64), ``-v`` (log progress).

Exit status: 0 success; 1 some scenes of a batch failed (each with its reason), or an internal
error; 2 bad input (scene, table, target file, output folder, resources: the message names the file,
key or value; also an output that cannot be written, e.g. no space left on device); 3 a target the
cilia cannot make; 130 interrupted (Ctrl-C); 143 terminated (SIGTERM: kill, Slurm, systemd, Docker) and
129 hung up (SIGHUP), handled like Ctrl-C: workers stopped, nothing half-written left behind.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import stat
import sys
import time as _time
import warnings
from concurrent.futures import Executor
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from cilia_runtime.files import strict_json, write_bytes, write_netcdf
from cilia_runtime.progress import TqdmProgress
from cilia_runtime.signals import Terminated, exit_status, interrupt_of, terminate_as_interrupt
from single_cilium.table import TableError
from cilia_runtime.threads import ThreadBudget, threads_in_use

from ciliary_carpet.carpet.coupling import CouplingError
from ciliary_carpet.design import DesignError
from ciliary_carpet.scenes.assembly import design
from ciliary_carpet.design.target import TargetError, UnreachableTargetError
from ciliary_carpet.output.resources import available_memory, expected_memory, places_that_fit
from ciliary_carpet.output.vtkfiles import OutputError
from ciliary_carpet.output.folder import check_parents, inputs_differ, only_toolkit_files
from ciliary_carpet.render import SUMMARY, RenderError, check_resources, is_complete, owned_files, render
from ciliary_carpet.scenes.paths import ALLOW_ENV
from ciliary_carpet.scenes.scene import Scene, SceneError, load_scene
from ciliary_carpet.stokes import BACKENDS, CudaUnavailableError, backend_named
from ciliary_carpet.transport.parallel import exit_reason, pool_for_threads, worker_context

logger = logging.getLogger(__name__)

BAD_INPUT = (SceneError, TargetError, TableError, RenderError, OutputError, OSError, MemoryError, ValueError,
             CudaUnavailableError)
CANNOT_MAKE = (DesignError, UnreachableTargetError, CouplingError)  # before BAD_INPUT: a CouplingError is a ValueError


def _scene(path: str, reduced: bool, backend: str | None = None) -> Scene:
    p = Path(path)
    if p.exists() and not p.is_file():  # a named pipe would hang the reader
        raise SceneError(f"{path}: not a regular file (a folder, named pipe or device); a scene is a .toml file")
    try:
        s = load_scene(path, allow_outside=os.environ.get(ALLOW_ENV, "") == "1")
    except RecursionError:  # a value nested thousands deep: the TOML parser recurses
        raise SceneError(f"{path}: values nested too deeply to read (a scene needs a few levels)") from None
    if backend is not None:  # --backend overrides the scene's
        s = replace(s, backend=backend)
    return s.reduced() if reduced else s


class OutputPathError(RenderError):
    """An output path the command refuses before any work (its message names the path, not the scene)."""


class StdoutError(OSError):
    """Standard output cannot be written (a full disk, a closed pipe); the message says so."""


def _emit(text: str) -> None:
    """Write ``text`` to standard output and flush it: :class:`StdoutError` when it cannot be
    written (later writes, and the interpreter's last flush, then go nowhere)."""
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except OSError as exc:
        try:  # what is left in the buffer must not fail again at exit
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        except (OSError, AttributeError, ValueError):
            pass
        raise StdoutError(exc.errno, f"cannot write to standard output: {exc.strerror or exc}") from None


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return v


def _cmd_render(a) -> int:
    scene = _scene(a.scene, a.reduced, a.backend)
    budget = ThreadBudget.for_task()  # every core, or this Dask worker's share
    if a.threads is not None:
        budget = replace(budget, numba=a.threads)
    # the path lines on as many processes as numba threads (one: in this process), as memory allows
    pool = pool_for_threads(places_that_fit(scene, budget.numba))
    with budget.applied():
        res = render(scene, a.output, overwrite=a.overwrite, progress=TqdmProgress(delay=0.5),
                     max_seconds=a.max_hours * 3600, pool=pool)
    s = res.summary
    try:
        if a.json:
            _emit(strict_json({"out_dir": str(res.out_dir), "files": list(res.files), "design": s.get("design"),
                               "seconds": s["seconds"]}) + "\n")
        else:  # the summary's head (title, scene, verdict); the whole of it is one file away
            head = (res.out_dir / "summary.md").read_text().split("\n## ", 1)[0].rstrip()
            _emit(head + "\n\n")
            _emit(f"wrote {len(res.files)} files to {res.out_dir}; the whole summary: "
                  f"{res.out_dir / 'summary.md'}\n")
    except StdoutError as exc:
        raise StdoutError(exc.errno, f"{exc.strerror}; the render in {res.out_dir} is complete (its summary.md "
                                     f"says what it holds)") from None
    return 0


def _layout_path(given: str, overwrite: bool) -> Path:
    """:func:`_layout_file`, its refusals as :class:`OutputPathError` (naming the path, not the scene)."""
    try:
        return _layout_file(given, overwrite)
    except RenderError as exc:
        raise OutputPathError(str(exc)) from None


def _layout_file(given: str, overwrite: bool) -> Path:
    """The file ``design -o`` writes: ``given``; through it, when it is a symbolic link to a
    regular file and ``overwrite`` (the link is kept, its file replaced). RenderError, before any
    work, for an existing path without ``overwrite``, any other symbolic link (a dangling one
    included: it is the user's, never replaced), a folder, or a ``..`` after a missing folder
    (:func:`~ciliary_carpet.output.folder.check_parents`)."""
    out = Path(given)
    if out.is_symlink():
        to = os.readlink(out)
        if not overwrite:
            raise RenderError(f"{out} is a symbolic link (to {to}); it is kept: pass --overwrite to write the "
                              f"layout into the file it points to, or name another file with -o")
        if not out.is_file():
            raise RenderError(f"{out} is a symbolic link to {to}, which is not an existing file; the link is kept: "
                              f"name the file itself with -o")
        return Path(os.path.realpath(out))
    if os.path.lexists(out) and not overwrite:
        raise RenderError(f"{out} exists; it is kept: pass --overwrite to replace it")
    if out.is_dir():
        raise RenderError(f"{out} is a folder; the layout is a file (.nc)")
    check_parents(out)
    return out


def _cmd_design(a) -> int:
    out = _layout_path(a.output, a.overwrite)
    scene = _scene(a.scene, a.reduced, a.backend)
    check_resources(scene, max_seconds=a.max_hours * 3600)
    backend_named(scene.backend)  # backend "cuda" without a GPU: CudaUnavailableError before any work
    d, carpet = design(scene)
    if d is None:
        raise SceneError(f"{scene.source_name}: the scene has no [target] to design for")
    write_netcdf(d.to_dataset(carpet), out)
    through = f" (the file the symbolic link {a.output} points to)" if str(out) != a.output else ""
    _emit(f"{d.message}\nwrote {out}{through}\n")
    return 0


@contextmanager
def plain_warnings(prog: str = "ciliary-carpet"):
    """Within: each warning shown once, as one plain line ``PROG: warning: MESSAGE`` on stderr
    (no source path, no code line, not repeated however often or wherever it is raised). Only
    how a warning is formatted changes: the filters stay, and so does whatever records them."""
    seen: set = set()
    before = warnings.formatwarning

    def plain(message, category, filename, lineno, line=None) -> str:
        text = " ".join(str(message).split())
        if text in seen:
            return ""
        seen.add(text)
        return f"{prog}: warning: {text}\n"

    warnings.formatwarning = plain
    try:
        yield
    finally:
        warnings.formatwarning = before


def _render_one(scene_path: str, out_root: str, overwrite: bool, reduced: bool, max_seconds: float = 86400.0,
                backend: str | None = None, budget: ThreadBudget | None = None, threads: int | None = None) -> dict:
    """One batch task (runs in a worker): never raises (but Ctrl-C), returns a record. It runs
    with ``budget`` (local workers: the batch's), or on a Dask worker with its share of the
    cores (:meth:`ThreadBudget.for_task`; ``threads`` numba threads if given)."""
    if budget is None:
        budget = ThreadBudget.for_task()
        if threads is not None:
            budget = replace(budget, numba=max(1, int(threads)))
    with budget.applied(), plain_warnings():
        return _render_task(scene_path, out_root, overwrite, reduced, max_seconds, backend)


def _render_task(scene_path: str, out_root: str, overwrite: bool, reduced: bool, max_seconds: float,
                 backend: str | None) -> dict:
    clock = _time.perf_counter()
    rec = {"scene": scene_path}
    try:
        scene = _scene(scene_path, reduced, backend)
        out = Path(out_root) / scene.name
        rec["out_dir"] = str(out)
        complete = not overwrite and is_complete(out)
        if complete and is_complete(out, scene=scene):  # made with these settings from these inputs
            rec.update(status="skipped", message="complete and up to date")
            rec.update(_verdict(out))
        else:
            # a render interrupted while replacing a folder leaves its manifest without summary.json:
            # finish it (only the files it wrote are replaced)
            resume = out.is_dir() and owned_files(out) is not None and not (out / SUMMARY).is_file()
            # a complete render of inputs that changed since is rendered again, when every file in
            # its folder is the toolkit's (unchanged); one of other settings alone asks for overwrite
            changed = inputs_differ(out, scene) if complete else []
            again = bool(changed) and only_toolkit_files(out)
            render(scene, out, overwrite=overwrite or resume or again, max_seconds=max_seconds, within=out_root,
                   pool=pool_for_threads(places_that_fit(scene, threads_in_use()["numba"])))
            why = f" again: its inputs changed ({', '.join(changed)})" if again else ""
            rec.update(status="done", message=f"rendered{why}")
            rec.update(_verdict(out))
    except Exception as exc:  # noqa: BLE001 -- one failing scene must not stop the others
        rec.update(status="failed", message=_one_line(exc, scene_path))
    rec["seconds"] = _time.perf_counter() - clock
    return rec


def _verdict(out: Path) -> dict:
    """The design's verdict of the render in ``out`` (its summary.json), for a batch record:
    ``verdict`` ("met", "not met", or "no target"), with ``residual`` (rms), ``threshold`` and
    ``residual_unit`` where the scene has a target; ``{}`` when the summary cannot be read."""
    try:
        d = json.loads((out / SUMMARY).read_text()).get("design")
    except (OSError, ValueError, AttributeError):
        return {}
    if not isinstance(d, dict):
        return {"verdict": "no target"}
    rec = {"residual": d.get("residual_rms"), "threshold": d.get("residual_threshold"),
           "residual_unit": d.get("residual_unit")}
    rec["verdict"] = "met" if d.get("met") is True else "not met" if d.get("met") is False else "designed"
    return rec


def _verdict_text(r: dict) -> str:
    """A record's verdict in words: "target met: rms residual 0.014 rad <= 0.05"."""
    v = r.get("verdict")
    if v is None:
        return ""
    if v == "no target":
        return "no target"
    unit = f" {r['residual_unit']}" if r.get("residual_unit") else ""
    res = f"rms residual {r['residual']:.3g}{unit}" if isinstance(r.get("residual"), (int, float)) else ""
    if v == "designed" or not isinstance(r.get("threshold"), (int, float)):
        return f"designed: {res}" if res else "designed"
    return f"target {v}: {res} {'<=' if v == 'met' else '>'} {r['threshold']:g} allowed"


def _one_line(exc: BaseException, src: str | None = None) -> str:
    """The message of ``exc`` on one line, naming ``src`` if it does not already."""
    msg = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, MemoryError):
        msg = f"out of memory ({msg}): make the scene smaller"
    elif isinstance(exc, OSError) and exc.filename is not None and str(exc.filename) not in msg:
        msg = f"{exc.filename}: {exc.strerror or msg}"
    elif not isinstance(exc, BAD_INPUT + CANNOT_MAKE):
        msg = f"{type(exc).__name__}: {msg}"
    if src is not None and str(src) not in msg:
        msg = f"{src}: {msg}"
    return msg


def _check_names(scenes) -> None:
    """Refuse, before any work, a batch in which two scenes have the same output folder."""
    seen: dict = {}
    for p in scenes:
        try:
            name = _scene(str(p), reduced=False).name  # the name does not depend on --reduced
        except SceneError:
            continue  # reported by its own task
        if name in seen:
            raise SceneError(f"{seen[name]} and {p} both render into the folder '{name}' (scene name); "
                             f"give one of them another name = \"...\" (nothing was rendered)")
        seen[name] = p


def _died(scene_path: str, why: str) -> dict:
    return {"scene": scene_path, "status": "failed", "seconds": 0.0,
            "message": f"{scene_path}: the worker process rendering it died ({why}); its output folder was left "
                       f"unchanged"}


def _worker(func, task, conn) -> None:
    """A batch worker process: one task, its record sent back on ``conn``. SIGTERM and SIGHUP
    (a scheduler stopping the whole job) interrupt it like Ctrl-C, so that its render removes its
    staging folder."""
    try:
        with terminate_as_interrupt():
            conn.send(func(*task))
    except KeyboardInterrupt:  # Ctrl-C reaches the whole process group: the parent reports it
        pass
    finally:
        conn.close()


def _run_local(tasks, jobs: int, on_done, grace: float = 2.5, on_start=None, func=None) -> None:
    """Each task in a fresh worker process, ``jobs`` at a time: a worker that dies (killed, out
    of memory) fails only its own scene, with its exit signal in the record. Interrupted, the
    running workers are stopped within about two ``grace`` periods (:func:`_stop`), each with
    every process it started. ``on_start(task)`` is called as a task's worker starts; ``func``
    (default :func:`_render_one`, an importable function) runs each task."""
    from multiprocessing.connection import wait as wait_any

    ctx = worker_context()
    pending = list(tasks)
    running: dict = {}  # process -> (task, receiving end)
    try:
        while pending or running:
            while pending and len(running) < jobs:
                t = pending.pop(0)
                recv, send = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_worker, args=(func or _render_one, t, send))
                proc.start()
                send.close()
                running[proc] = (t, recv)
                if on_start is not None:
                    on_start(t)
            by_sentinel = {p.sentinel: p for p in running}
            for sentinel in wait_any(list(by_sentinel)):
                proc = by_sentinel[sentinel]
                t, recv = running.pop(proc)
                try:
                    rec = recv.recv() if recv.poll() else None
                except EOFError:  # died before sending
                    rec = None
                proc.join()
                recv.close()
                on_done(rec if rec is not None else _died(t[0], exit_reason(proc.exitcode)))
    except BaseException as exc:
        # Ctrl-C in a terminal reaches the workers too; SIGTERM or SIGHUP reached this process only
        _stop(list(running), grace, told=isinstance(exc, KeyboardInterrupt) and not isinstance(exc, Terminated))
        raise
    finally:
        _stop(list(running), grace, told=False)


def _started(pid: int) -> str | None:
    """When process ``pid`` started (``/proc/PID/stat``, clock ticks since boot), None if it is gone:
    with the pid, it names one process (a pid may be reused once its process has ended)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _descendants(pid: int) -> list[tuple[int, str | None]]:
    """The processes ``pid`` started, and theirs, recursively (Linux: ``/proc/PID/task/*/children``;
    elsewhere none), parents before children, as (pid, :func:`_started`)."""
    found: list[int] = []
    todo = [pid]
    while todo:
        p = todo.pop(0)
        try:
            tasks = os.listdir(f"/proc/{p}/task")
        except OSError:
            continue
        for t in tasks:
            try:
                with open(f"/proc/{p}/task/{t}/children") as fh:
                    kids = [int(k) for k in fh.read().split()]
            except (OSError, ValueError):
                continue
            for k in kids:
                if k not in found:
                    found.append(k)
                    todo.append(k)
    return [(k, _started(k)) for k in found]


def _stop(procs, grace: float, told: bool) -> None:
    """Stop the worker processes ``procs`` and every process each started (its render's path-line
    workers and fork server): those ``told`` (Ctrl-C reached them too) get ``grace`` seconds to
    finish their cleanup first; then the ones still alive get SIGTERM (a render removes its
    staging folder on it) and ``grace`` seconds more; then every process left in their trees is
    killed (SIGKILL) and the workers reaped. A staging folder a killed render leaves is hidden, and
    the next render of that folder removes it."""
    procs = [p for p in procs if p.is_alive()]
    if not procs:
        return
    tree = {p.pid: _descendants(p.pid) for p in procs}  # before a worker ends: its orphans are found no more
    for sig in ((None, signal.SIGTERM) if told else (signal.SIGTERM,)):
        alive = [p for p in procs if p.is_alive()]
        if not alive:
            break
        for p in alive:
            tree[p.pid] = list(dict.fromkeys(tree[p.pid] + _descendants(p.pid)))
            if sig is not None:
                try:
                    os.kill(p.pid, sig)
                except ProcessLookupError:
                    pass
        end = _time.monotonic() + grace
        for p in alive:
            p.join(max(0.0, end - _time.monotonic()))
    for p in procs:
        if p.is_alive():
            tree[p.pid] = list(dict.fromkeys(tree[p.pid] + _descendants(p.pid)))
        if p.is_alive():
            os.kill(p.pid, signal.SIGKILL)
        for pid, started in tree[p.pid][::-1]:
            if started is not None and _started(pid) == started:  # the same process, still there
                try:
                    os.kill(pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
        p.join(grace)


def _memory_per_task(scenes, reduced: bool, backend: str | None):
    """The memory a batch worker is expected to take, as a function of its render's places: the
    largest :func:`~ciliary_carpet.output.resources.expected_memory` of the batch's scenes (None
    if no scene can be read: each fails in its own task)."""
    loaded = []
    for p in scenes:
        try:
            loaded.append(_scene(p, reduced, backend))
        except Exception:  # noqa: BLE001 -- a scene that cannot be read fails in its own task
            continue
    if not loaded:
        return None
    return lambda places: max(expected_memory(s, places) for s in loaded)


def batch(scenes, out_root, *, executor: Executor | None = None, scheduler: str | None = None,
          jobs: int | None = None, threads: int | None = None,
          overwrite: bool = False, reduced: bool = False, progress: bool = True,
          max_seconds: float = 86400.0, backend: str | None = None,
          scheduler_timeout: float | None = None, records: list | None = None) -> list[dict]:
    """Render many scene files into ``out_root/NAME``.

    Default: each scene in a fresh worker process, ``jobs`` at a time, so that a worker that
    dies (killed, out of memory) fails only its own scene. Each worker gets its share of the
    cores (:class:`~cilia_runtime.threads.ThreadBudget`): ``jobs`` (default: as many as there
    are scenes and cores, and as fit the available memory) times ``threads`` numba threads
    (default: the cores divided among the workers) times one BLAS thread; on Dask each task
    gets the cores of its worker divided among the worker's threads. Each render's summary
    names the threads it used (``"threads"``). With ``scheduler``: a Dask
    distributed cluster, through ``Client(scheduler).get_executor()``; or any ``executor``. The
    workers get the scenes and ``out_root`` as absolute paths (a relative one is this process's:
    a Dask worker runs in its own folder, and on other machines the paths must be on a shared
    filesystem); the records name the scenes as given.
    Two scenes with the same name (output folder) are a SceneError before anything runs.
    Resumable: a scene whose folder holds a complete render up to date for it (the same settings,
    and every file it read -- the scene, its table, its target file -- with the same contents:
    :func:`~ciliary_carpet.output.folder.is_complete`) is skipped; one interrupted while replacing an
    older render is rendered again; a complete render whose inputs changed since is rendered again
    in its folder when every file there is ciliary-carpet's, unchanged
    (:func:`~ciliary_carpet.output.folder.only_toolkit_files`); one made from the same inputs with
    other settings (``reduced``, ``backend``, another package version) is kept unless
    ``overwrite``, and reported as failed; files ciliary-carpet did not write are never changed
    (:func:`~ciliary_carpet.render.render`). So a batch without ``overwrite`` after an edit
    renders exactly the scenes whose inputs changed.
    ``backend`` (a name of :data:`~ciliary_carpet.stokes.evaluator.BACKENDS`) overrides the scenes'.
    ``scheduler_timeout`` bounds the wait for ``scheduler`` to answer as a Dask scheduler (default
    20 s, or ``CILIA_SCHEDULER_TIMEOUT``): an address that does not (e.g. the dashboard's HTTP port)
    is an OSError after that wait, as is a scheduler that has no worker and gets none within it
    (a warning says it is waiting). Interrupted (Ctrl-C, or SIGTERM/SIGHUP under the command line),
    the local workers are stopped, each with every process it started, within a few seconds
    (they remove their staging folders when they can); on Dask the scenes not yet started are
    cancelled (a running render is left to finish or fail whole).
    Returns one record per scene (``status`` done / skipped / failed, ``message`` with the reason,
    ``seconds``, ``out_dir``; for a render in its folder ``verdict`` -- "met", "not met", "designed"
    or "no target" -- with ``residual``, ``threshold`` and ``residual_unit`` from its summary.json),
    in the order of ``scenes``; ``records``, a list given, gets each record as its scene ends
    (what finished, when interrupted). The batch's index, ``out_root/batch.json`` and
    ``out_root/batch.md`` (:func:`write_index`), lists them, also when interrupted (the scenes not
    finished then with status "interrupted" or "not started"); a batch in which no scene was
    rendered or found up to date only updates an index a batch made before."""
    from tqdm.auto import tqdm

    scenes = [str(s) for s in scenes]
    _check_names(scenes)
    if backend is not None:
        backend_named(backend)  # backend "cuda" without a GPU: CudaUnavailableError before any work
    # the workers get absolute paths: a Dask worker runs in its own folder, where a relative scene
    # is not found and a relative output root is another folder than the one named here
    where = {os.path.abspath(s): s for s in scenes}
    tasks = [(os.path.abspath(s), os.path.abspath(str(out_root)), overwrite, reduced, max_seconds, backend)
             for s in scenes]
    budget = None
    if executor is None and scheduler is None:
        budget = ThreadBudget.for_batch(len(tasks), jobs=jobs, threads=threads,
                                        memory_per_task=_memory_per_task(scenes, reduced, backend) if jobs is None
                                        else None, memory_available=available_memory())
        logger.info("batch: %d workers x %d numba threads x %d BLAS threads", budget.workers, budget.numba,
                    budget.blas)
        tasks = [t + (budget,) for t in tasks]
    else:
        tasks = [t + (None, threads) for t in tasks]
    recs: list = records if records is not None else []
    started: set = set()
    bar = tqdm(total=len(tasks), desc="scenes", disable=not progress)

    def on_done(rec):
        rec["scene"] = where.get(rec["scene"], rec["scene"])  # as the caller named it
        recs.append(rec)
        bar.update(1)

    client = None
    whole = False
    try:
        if executor is None and scheduler is None:
            _run_local(tasks, budget.workers, on_done, on_start=lambda t: started.add(where.get(t[0], t[0])))
        else:
            if executor is None:
                from cilia_runtime.scheduler import connect

                client = connect(scheduler, scheduler_timeout, workers=1)
                executor = client.get_executor()
            started.update(scenes)  # on Dask: submitted, maybe running
            futs = {executor.submit(_render_one, *t): t for t in tasks}
            try:
                for f in futs:
                    try:
                        on_done(f.result())
                    except Exception as exc:  # noqa: BLE001 -- a dead worker (BrokenProcessPool, KilledWorker)
                        on_done(_died(futs[f][0], type(exc).__name__))
            except BaseException:  # interrupted: the scenes not started yet are not started
                for f in futs:
                    f.cancel()
                raise
        whole = True
    finally:
        bar.close()
        if client is not None:
            client.close()
        order = {s: k for k, s in enumerate(scenes)}
        done = {r["scene"] for r in recs}
        rest = [] if whole else [{"scene": sc, "status": "interrupted" if sc in started else "not started",
                                  "seconds": None, "message": "interrupted" if sc in started else "not started",
                                  "out_dir": str(Path(out_root) / _name_of(sc))}
                                 for sc in scenes if sc not in done]
        listed = sorted(recs + rest, key=lambda r: order.get(r["scene"], len(order)))
        if listed:  # a batch that rendered or checked no scene makes no index (it updates one made before)
            write_index(out_root, listed, create=any(r["status"] in ("done", "skipped") for r in listed))
    return sorted(recs, key=lambda r: order[r["scene"]])


INDEX = ("batch.json", "batch.md")
"""The batch index's files in the output root (:func:`write_index`)."""
_INDEX_MARK = "written by ciliary-carpet batch"


def _name_of(scene_path: str) -> str:
    """The output folder name of a scene (its ``name``; the file's stem if it cannot be read)."""
    try:
        return _scene(scene_path, reduced=False).name
    except Exception:  # noqa: BLE001 -- an unreadable scene: its record says why
        return Path(scene_path).stem


def _ours(path: Path) -> bool:
    """Whether ``path`` is absent, or a regular file a batch wrote (its mark in the first 200 bytes)."""
    if not os.path.lexists(path):
        return True
    try:
        if not stat.S_ISREG(os.lstat(path).st_mode):
            return False
        with open(path, "rb") as fh:
            return _INDEX_MARK.encode() in fh.read(200)
    except OSError:
        return False


def write_index(out_root, recs: list[dict], create: bool = True) -> None:
    """Write the batch index into ``out_root``: ``batch.json`` (strict JSON: ``written_by``, and
    ``scenes``: the records -- scene, status, verdict, residual, threshold, seconds, folder,
    message) and ``batch.md`` (a table of the same), each atomically. A file of those names that a
    batch did not write (no mark of it, or not a regular file) is kept, and that index file not
    written (a warning says so); an index that cannot be written is a warning, not a failure of
    the renders. Nothing is written when ``out_root`` is not a folder (no render made it), nor,
    unless ``create``, when it holds no index a batch wrote (only such an index is updated)."""
    root = Path(out_root)
    if not root.is_dir():  # no scene reached its folder: nothing to index, and no folder made for it
        return
    if not create and not any(os.path.lexists(root / n) and _ours(root / n) for n in INDEX):
        return
    rows = [{"scene": r.get("scene"), "status": r.get("status"), "verdict": r.get("verdict"),
             "residual": r.get("residual"), "threshold": r.get("threshold"), "residual_unit": r.get("residual_unit"),
             "seconds": r.get("seconds"), "folder": r.get("out_dir"), "message": r.get("message")} for r in recs]
    lines = [f"<!-- {_INDEX_MARK} -->", "# Batch", "",
             "| scene | status | verdict | seconds | folder |", "| --- | --- | --- | --- | --- |"]
    for r, row in zip(recs, rows):
        sec = f"{row['seconds']:.1f}" if isinstance(row["seconds"], (int, float)) else "-"
        cells = [row["scene"], row["status"], _verdict_text(r) or (row["message"] if row["status"] == "failed" else "-"),
                 sec, row["folder"] or "-"]
        lines.append("| " + " | ".join(str(c).replace("|", "\\|").replace("\n", " ") for c in cells) + " |")
    texts = {"batch.json": strict_json({"written_by": _INDEX_MARK, "scenes": rows}) + "\n",
             "batch.md": "\n".join(lines) + "\n"}
    for name, text in texts.items():
        path = root / name
        if not _ours(path):
            logger.warning("%s was not written by a ciliary-carpet batch; it is kept, and the batch's index is not "
                           "written there", path)
            continue
        try:
            write_bytes(path, text.encode())
        except OSError as exc:
            logger.warning("cannot write the batch index %s: %s", path, exc)


def _line(r: dict) -> str:
    """One scene of a batch in words: status, scene, seconds, what happened and the verdict."""
    v = _verdict_text(r)
    sec = f"  ({r['seconds']:.1f} s)" if isinstance(r.get("seconds"), (int, float)) else ""
    return f"{r['status']:8s} {r['scene']}{sec}  {r['message']}{'; ' + v if v else ''}"


def _cmd_batch(a) -> int:
    finished: list = []
    try:
        recs = batch(a.scenes, a.output, scheduler=a.scheduler, jobs=a.jobs, threads=a.threads,
                     overwrite=a.overwrite, reduced=a.reduced, max_seconds=a.max_hours * 3600, backend=a.backend,
                     scheduler_timeout=a.scheduler_timeout, records=finished)
    except KeyboardInterrupt:  # the one line main prints says which scenes finished and which did not
        done = {r["scene"] for r in finished}
        left = [sc for sc in a.scenes if sc not in done]
        fin = ", ".join(f"{r['scene']} ({r['status']}{'; ' + _verdict_text(r) if _verdict_text(r) else ''})"
                        for r in finished)
        a.note = (f"finished: {fin or 'none'}; not finished: {', '.join(left) or 'none'}"
                  f"{' (run the batch again to render them)' if left else ''}; ")
        raise
    n = {k: sum(r["status"] == k for r in recs) for k in ("done", "skipped", "failed")}
    if a.json:
        _emit(strict_json({"scenes": recs, "done": n["done"], "skipped": n["skipped"], "failed": n["failed"]}) + "\n")
    else:
        _emit("".join(_line(r) + "\n" for r in recs)
              + f"{n['done']} rendered, {n['skipped']} up to date, {n['failed']} failed; index: "
                f"{Path(a.output) / 'batch.md'}\n")
    return 1 if n["failed"] else 0


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("cilia-flow")
    except PackageNotFoundError:
        from single_cilium import __version__

        return __version__


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="ciliary-carpet", description=__doc__.split("\n\n")[0].replace("``", ""))
    ap.add_argument("-v", "--verbose", action="store_true", help="log progress messages")
    ap.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    ap.add_argument("--debug", action="store_true", help="show the traceback of a failure")
    ap.add_argument("--allow-outside-paths", action="store_true",
                    help="let scene files name table/target files outside their own folder (trusted scenes only)")
    ap.add_argument("--max-hours", type=float, default=24.0,
                    help="refuse scenes estimated to need longer than this (default 24)")
    ap.add_argument("--backend", choices=BACKENDS, default=None,
                    help="evaluator of the flow sums, overriding the scenes' backend (cuda: an NVIDIA GPU, "
                         "pip install 'cilia-flow[gpu]')")
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render", help="design (if the scene has a target), run the flow, write VTK/PNG/summary")
    r.add_argument("scene")
    r.add_argument("-o", "--output", required=True, help="output folder")
    r.add_argument("--overwrite", action="store_true",
                   help="replace the files an earlier render wrote there (never other files)")
    r.add_argument("--reduced", action="store_true", help="a small version of the scene (quick look)")
    r.add_argument("--json", action="store_true", help="print a JSON summary (strict JSON)")
    r.add_argument("--threads", type=_positive_int, default=None,
                   help="numba threads of the render, and places of its path lines (default: every core it may "
                        "use -- its CPU affinity, a container's CPU quota -- with path-line places as memory "
                        "allows; fewer when other jobs share the machine, where many threads wait for each other); "
                        "summary.json says what it used")
    d = sub.add_parser("design", help="write only the designed layout (NetCDF)")
    d.add_argument("scene")
    d.add_argument("-o", "--output", required=True, help="layout file (.nc)")
    d.add_argument("--overwrite", action="store_true")
    d.add_argument("--reduced", action="store_true")
    b = sub.add_parser("batch", help="render many scenes (a process per scene, or a Dask cluster), resumable")
    b.add_argument("scenes", nargs="+")
    b.add_argument("-o", "--output", required=True, help="output root; each scene goes to OUTPUT/NAME")
    b.add_argument("-j", "--jobs", type=int, default=None,
                   help="local worker processes at once (default: as many as scenes and cores allow, and as fit "
                        "the available memory -- a container's or a batch job's limit where it has one)")
    b.add_argument("--threads", type=int, default=None,
                   help="numba threads per worker (default: the cores divided among the workers; one BLAS thread "
                        "each); each render's summary.json says what it used under \"threads\"")
    b.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:port)")
    b.add_argument("--scheduler-timeout", dest="scheduler_timeout", type=float, default=None, metavar="SECONDS",
                   help="how long to wait for the scheduler to answer before giving up (default 20, or "
                        "$CILIA_SCHEDULER_TIMEOUT)")
    b.add_argument("--overwrite", action="store_true")
    b.add_argument("--reduced", action="store_true")
    b.add_argument("--json", action="store_true", help="print the records as strict JSON")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if not (a.max_hours > 0):
        ap.error(f"--max-hours must be > 0, got {a.max_hours}")
    if a.allow_outside_paths:
        os.environ[ALLOW_ENV] = "1"  # inherited by batch workers
    src = getattr(a, "scene", None)
    try:
        # SIGTERM, SIGHUP: the Ctrl-C cleanup, exit 128 + signum; warnings as plain lines, once each
        with terminate_as_interrupt(), plain_warnings():
            return {"render": _cmd_render, "design": _cmd_design, "batch": _cmd_batch}[a.cmd](a)
    except StdoutError as exc:
        print(f"ciliary-carpet: {exc.strerror}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        return _interrupted(a, exc)
    except CANNOT_MAKE as exc:
        if a.debug:
            raise
        print(f"ciliary-carpet: {_one_line(exc, src)}", file=sys.stderr)
        return 3
    except BAD_INPUT as exc:
        if a.debug:
            raise
        print(f"ciliary-carpet: {_one_line(exc, None if isinstance(exc, OutputPathError) else src)}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 -- a bug: one line, the traceback with --debug
        if interrupt_of(exc) is not None:  # a signal handled inside compiled code (a SystemError carries it)
            return _interrupted(a, interrupt_of(exc))
        if a.debug:
            raise
        print(f"ciliary-carpet: internal error: {_one_line(exc, src)} (rerun with --debug for the traceback)",
              file=sys.stderr)
        return 1


def _interrupted(a, exc: KeyboardInterrupt) -> int:
    """Ctrl-C or a signal: one line, exit 128 + signum (130 for Ctrl-C)."""
    how = str(exc) if isinstance(exc, Terminated) else "interrupted"
    print(f"ciliary-carpet: {how}; {getattr(a, 'note', '')}nothing half-written was left in the output folder",
          file=sys.stderr)
    return exit_status(exc)


if __name__ == "__main__":
    sys.exit(main())
