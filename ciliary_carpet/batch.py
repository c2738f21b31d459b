"""``ciliary-carpet batch``: many scenes rendered, each in a worker process of its own, resumable.

:func:`batch` renders scene files into ``OUT/NAME`` on local worker processes (an isolated
:class:`~cilia_runtime.pool.ProcessPool`: a worker that dies fails only its own scene) or on a Dask
cluster, skips the scenes whose folders are up to date, and indexes what it did
(:func:`write_index`: ``batch.json``, ``batch.md``). The scene reading, error wording and warning
format it shares with the other commands are here too (:func:`read_scene`, :func:`one_line`,
:func:`plain_warnings`).
"""
from __future__ import annotations

import json
import logging
import os
import stat
import time as _time
import warnings
from concurrent.futures import Executor
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from cilia_runtime.files import strict_json, write_bytes
from cilia_runtime.pool import ProcessPool, Task, TaskResult, WorkerDied, pool_for_threads
from cilia_runtime.progress import Progress, TqdmProgress
from cilia_runtime.threads import ThreadBudget, threads_in_use
from single_cilium.table import TableError

from ciliary_carpet.carpet.coupling import CouplingError
from ciliary_carpet.design import DesignError
from ciliary_carpet.design.target import TargetError, UnreachableTargetError
from ciliary_carpet.output.folder import inputs_differ, only_toolkit_files
from ciliary_carpet.output.resources import available_memory, expected_memory, places_that_fit
from ciliary_carpet.output.vtkfiles import OutputError
from ciliary_carpet.render import SUMMARY, RenderError, is_complete, owned_files, render
from ciliary_carpet.scenes.paths import ALLOW_ENV
from ciliary_carpet.scenes.scene import Scene, SceneError, load_scene
from ciliary_carpet.stokes import CudaUnavailableError, backend_named

logger = logging.getLogger(__name__)

BAD_INPUT = (SceneError, TargetError, TableError, RenderError, OutputError, OSError, MemoryError, ValueError,
             CudaUnavailableError)
CANNOT_MAKE = (DesignError, UnreachableTargetError, CouplingError)  # before BAD_INPUT: a CouplingError is a ValueError


def outside_allowed() -> bool:
    """Whether scene files may name files, and a batch's scenes output folders, outside their own
    folders: ``--allow-outside-paths``, which the command line passes down as
    :data:`~ciliary_carpet.scenes.paths.ALLOW_ENV` (inherited by batch workers)."""
    return os.environ.get(ALLOW_ENV, "") == "1"


def read_scene(path: str, reduced: bool, backend: str | None = None) -> Scene:
    """The scene in the file ``path`` (SceneError naming the file when it cannot be read),
    ``backend`` overriding its own, reduced if ``reduced``."""
    p = Path(path)
    if p.exists() and not p.is_file():  # a named pipe would hang the reader
        raise SceneError(f"{path}: not a regular file (a folder, named pipe or device); a scene is a .toml file")
    try:
        s = load_scene(path, allow_outside=outside_allowed())
    except RecursionError:  # a value nested thousands deep: the TOML parser recurses
        raise SceneError(f"{path}: values nested too deeply to read (a scene needs a few levels)") from None
    if backend is not None:  # --backend overrides the scene's
        s = replace(s, backend=backend)
    return s.reduced() if reduced else s


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
        scene = read_scene(scene_path, reduced, backend)
        out = Path(out_root) / scene.name
        rec["out_dir"] = str(out)
        if scene.states:  # a program: a folder per state and program.json beside them
            rec.update(_render_program_task(scene, out, out_root, overwrite, max_seconds))
            rec["seconds"] = _time.perf_counter() - clock
            return rec
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
            render(scene, out, overwrite=overwrite or resume or again, max_seconds=max_seconds, within=None if outside_allowed() else out_root,
                   pool=pool_for_threads(places_that_fit(scene.needs(), threads_in_use()["numba"]), PRELOAD))
            why = f" again: its inputs changed ({', '.join(changed)})" if again else ""
            rec.update(status="done", message=f"rendered{why}")
            rec.update(_verdict(out))
    except Exception as exc:  # noqa: BLE001 -- one failing scene must not stop the others
        rec.update(status="failed", message=one_line(exc, scene_path))
    rec["seconds"] = _time.perf_counter() - clock
    return rec


def _program_record(out: Path) -> dict | None:
    """A program render's record (its ``program.json``), or None where there is none that this
    toolkit wrote (it is not strict JSON with the program's ``states``)."""
    try:
        p = json.loads((out / "program.json").read_text())
    except (OSError, ValueError):
        return None
    return p if isinstance(p, dict) and isinstance(p.get("states"), list) else None


def _render_program_task(scene, out: Path, out_root: str, overwrite: bool, max_seconds: float) -> dict:
    """A program scene of a batch: skipped when its program record and every state's folder are
    complete and current (:func:`is_complete` with the state's scene), else rendered
    (:func:`~ciliary_carpet.render.render_program`; its own earlier files are replaced, a
    state's folder by the output-folder rules); the record's verdict: every state met or not."""
    from ciliary_carpet.scenes.states import state_scenes

    pairs = state_scenes(scene)
    old = _program_record(out)
    if not overwrite and old is not None and all(is_complete(out / spec.name, scene=sc) for spec, sc in pairs):
        rec = {"status": "skipped", "message": "complete and up to date"}
    else:
        again = old is not None and all(only_toolkit_files(out / spec.name) for spec, _ in pairs
                                        if (out / spec.name).is_dir())
        render(scene, out, overwrite=overwrite or again, max_seconds=max_seconds,
               within=None if outside_allowed() else out_root)
        rec = {"status": "done", "message": f"rendered a program of {len(pairs)} states"}
    p = _program_record(out) or {}
    states = p.get("states") or []
    if states:
        worst = max(states, key=lambda q: (q["residual_rms"] / q["threshold"]) if q.get("threshold") else 0.0)
        rec.update(verdict="met" if all(q.get("met") for q in states) else "not met",
                   residual=worst.get("residual_rms"), threshold=worst.get("threshold"), residual_unit="rad")
        rec["message"] += f" (limiting state: {worst.get('name')})"
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


def verdict_text(r: dict) -> str:
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


def one_line(exc: BaseException, src: str | None = None) -> str:
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
            name = read_scene(str(p), reduced=False).name  # the name does not depend on --reduced
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


PRELOAD = ("ciliary_carpet.render",)
"""Modules the fork servers of the batch and of its renders' path lines import once, before they fork
a worker."""


def _run_local(tasks, jobs: int, on_done, grace: float = 2.5, on_start=None, func=None) -> None:
    """Each task in a fresh worker process, ``jobs`` at a time (an isolated
    :class:`~cilia_runtime.pool.ProcessPool`): a worker that dies (killed, out of memory) fails
    only its own scene, with its exit signal in the record. Interrupted, the running workers are
    stopped within about two ``grace`` periods (:func:`~cilia_runtime.pool.stop`), each with
    every process it started. ``on_start(task)`` is called as a task's worker starts,
    ``on_done(record)`` as it ends; ``func`` (default :func:`_render_one`, an importable
    function) runs each task and returns its record."""
    pool = ProcessPool(jobs, parent_works=False, lend_idle=False, isolated=True, grace=grace, preload=PRELOAD)

    def done(i: int, outcome) -> None:
        if isinstance(outcome, TaskResult):
            on_done(outcome.value)
        else:  # the worker died (or its task raised, which the batch's task does not)
            on_done(_died(tasks[i][0], outcome.reason if isinstance(outcome, WorkerDied) else type(outcome).__name__))

    pool.run([Task(str(t[0]), func or _render_one, tuple(t)) for t in tasks], desc="scenes", on_done=done,
             on_start=None if on_start is None else (lambda i: on_start(tasks[i])))


def _memory_per_task(scenes, reduced: bool, backend: str | None):
    """The memory a batch worker is expected to take, as a function of the number of processes
    its render runs the path lines in: the largest
    :func:`~ciliary_carpet.output.resources.expected_memory` of the batch's scenes (None if no
    scene can be read: each fails in its own task)."""
    loaded = []
    for p in scenes:
        try:
            loaded.append(read_scene(p, reduced, backend))
        except Exception:  # noqa: BLE001 -- a scene that cannot be read fails in its own task
            continue
    if not loaded:
        return None
    needs = [s.needs() for s in loaded]
    return lambda places: max(expected_memory(n, places) for n in needs)


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
    ``backend`` (a name of :data:`~ciliary_carpet.stokes.dispatch.BACKENDS`) overrides the scenes'.
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
    bar = TqdmProgress(delay=0.0) if progress else Progress()
    bar.start(len(tasks), "scenes")

    def on_done(rec):
        rec["scene"] = where.get(rec["scene"], rec["scene"])  # as the caller named it
        recs.append(rec)
        bar.update(len(recs))

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
        return read_scene(scene_path, reduced=False).name
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
        cells = [row["scene"], row["status"], verdict_text(r) or (row["message"] if row["status"] == "failed" else "-"),
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


