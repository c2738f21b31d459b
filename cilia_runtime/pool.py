"""Where independent pieces of work run: in this process, or in worker processes.

Work is cut into :class:`Task` s (a function of the caller's module, a label, a cost) and handed to
a small strategy object that says where they run:

* :class:`InProcess`: one after another in this process, with the numba threads it has.
* :class:`ProcessPool`: ``processes`` worker processes, and this process as one more worker
  (``parent_works``), from before they start. Workers start from a fork server (never by forking
  this process: a process that has run the OpenMP-parallel kernels cannot fork safely), which imports
  the modules named in ``preload`` once, each worker with one numba thread and one BLAS thread
  (:class:`~cilia_runtime.threads.ThreadBudget`: workers x numba x BLAS threads never exceed the
  cores the caller gives). The biggest tasks go first (:attr:`Task.cost`). Large objects named
  in ``shared`` are pickled once and sent once to each worker, however many tasks use them.
  ``warm()`` starts the fork server ahead, while the caller has other work. A dispatcher thread
  starts and feeds the workers while this process works on its own task: compiled functions that
  let go of the interpreter (numba's ``nogil``) do not keep that thread waiting.
* :class:`ProcessPool` with ``isolated``: each task in a fresh process of its own, which exits
  after it (and may start processes of its own); a task that raises, or a worker that dies
  (killed, out of memory), fails that task only, and the others go on. A batch of renders runs
  so: one scene's crash or memory cannot touch another's.

Workers here are the worker processes and, with ``parent_works``, this process. With
``lend_idle`` (the default of a shared pool), idle cores are shared: the cores of workers left
without a task are given to the workers still running one, as extra numba threads, for as long
as those threads make the task faster (:class:`_Share`, consulted by long tasks through
:func:`adjust_threads`).

Both give the same numbers for the same tasks: a task runs the same code with one BLAS thread
wherever it runs; kernels whose numbers do not depend on the numba thread count give the same
numbers in any worker (:func:`pool_for_threads` picks the strategy of a thread count).

Progress: ``run(..., progress=)`` reports the tasks finished (:class:`~cilia_runtime.progress.Progress`)
as each ends.

Failures: a task that raises is re-raised in the caller, its message prefixed with the task's
label (e.g. ``"path lines: chunk 2 of 4 (tracers 50-74)"``), the worker's traceback chained; a
worker that dies is a :class:`WorkerDied` naming the task it ran and how the process ended
(:func:`exit_reason`). Either stops a shared pool at once (no hang). Ctrl-C, or SIGTERM / SIGHUP
under :func:`~cilia_runtime.signals.terminate_as_interrupt`, reaches the caller as a
KeyboardInterrupt: the workers, and every process each started, are stopped (:func:`stop`) before
it propagates, and the pool is closed on every path.

The machinery is this module's rather than :mod:`concurrent.futures`': a process pool executor
fails every pending task when one worker dies (no isolation), cannot say which task a dead
worker ran nor how it ended, has no way to stop its workers at once (only to wait for their
tasks), and no way for this process to run tasks alongside its workers or to share idle cores.

One concept over 500 lines: the process pool, its workers, their shared cores and their stop.
"""
from __future__ import annotations

import contextlib
import io
import logging
import os
import pickle
import signal
import threading
import time as _time
import traceback
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from cilia_runtime.progress import Progress
from cilia_runtime.signals import Terminated, interrupt_of, terminate_as_interrupt
from cilia_runtime.threads import ThreadBudget

logger = logging.getLogger(__name__)

__all__ = ["Task", "TaskResult", "InProcess", "ProcessPool", "WorkerDied", "pool_for_threads", "worker_context",
           "exit_reason", "stop", "adjust_threads"]

_PLACE = threading.local()  # .state: this thread's _Share while a pool task runs here

WINDOW_S = 0.3
"""Seconds of flow evaluations over which a worker measures its throughput (:class:`_Share`)."""
GAIN = 1.1
"""Extra numba threads from idle workers are kept only while the worker evaluates at least this
many times as fast with them as with one thread."""
RETRY_S = 15.0
"""Seconds a worker waits before it tries again extra threads that did not make it faster."""


class _Share:
    """Worker ``k``'s share of a pool's cores, and the governor that decides how much of it to use.

    ``arr[k]`` is the number of numba threads worker ``k`` may use now: one, plus the cores of
    idle workers given to it (:meth:`_PoolRun.set_busy`). A lower allowance is obeyed at the next
    :meth:`tick`. Extra threads are used only while they make the task faster: very short
    parallel regions wait at every barrier for a thread the system has descheduled, so on a
    machine that other jobs keep busy, two threads can be slower than one. The governor measures
    the throughput (work units per second, an evaluation of m points counting ``1 + m / 50``) over
    windows of :data:`WINDOW_S`, first with one thread; extra threads that are not :data:`GAIN`
    times as fast as one thread are given up for :data:`RETRY_S` seconds, then tried again."""

    def __init__(self, arr, k: int, current: int) -> None:
        self.arr, self.k, self.current = arr, k, current
        self.t0 = _time.perf_counter()
        self.units = 0.0
        self.rate: dict[int, float] = {}
        self.retry_at = 0.0

    def _set(self, n: int) -> None:
        import numba

        n = max(1, min(int(n), int(numba.config.NUMBA_NUM_THREADS)))
        if n != self.current:
            numba.set_num_threads(n)
            self.current = n

    def tick(self, points: int) -> None:
        allowed = int(self.arr[self.k])
        if self.current > allowed:  # the allowance dropped: obey it at once
            self._set(allowed)
            self.t0, self.units = _time.perf_counter(), 0.0
        self.units += 1.0 + points / 50.0
        now = _time.perf_counter()
        if now - self.t0 < WINDOW_S:
            return
        n = self.current
        self.rate[n] = self.units / (now - self.t0)
        self.t0, self.units = now, 0.0
        if n > 1 and self.rate[n] < GAIN * self.rate.get(1, 0.0):  # extra threads below GAIN: one
            self._set(1)
            self.retry_at = now + RETRY_S
        elif allowed > n and now >= self.retry_at and 1 in self.rate:
            self._set(allowed)


def adjust_threads(points: int = 1) -> None:
    """Called by long tasks between steps of ``points`` points each (a path line's flow
    evaluations): in a pool task with ``lend_idle``, set this worker's numba threads to its
    allowance now -- its own core and its share of the idle workers' cores -- while the extra
    threads make it faster (:class:`_Share`); elsewhere it does nothing."""
    st = getattr(_PLACE, "state", None)
    if st is not None:
        st.tick(points)


def _placed(arr, k: int):
    """Context: pool tasks run in this thread use worker ``k``'s allowance of numba threads in
    ``arr`` (:class:`_Share`); the thread's numba thread count is restored after."""

    @contextlib.contextmanager
    def cm():
        import numba

        before = numba.get_num_threads()
        _PLACE.state = _Share(arr, k, before)
        try:
            yield
        finally:
            _PLACE.state = None
            numba.set_num_threads(before)

    return cm()


@dataclass(frozen=True)
class Task:
    """One piece of work: ``func(*args, **kwargs)``, a module-level function (pickled by name).

    ``label`` names it in errors and summaries; ``cost`` (any unit, the same for all tasks of a
    run) orders them: the biggest first."""

    label: str
    func: Callable
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)
    cost: float = 1.0


@dataclass(frozen=True)
class TaskResult:
    """What a task returned, where it ran (``"parent"`` or ``"worker N"``) and its seconds."""

    value: Any
    where: str
    seconds: float


class WorkerDied(RuntimeError):
    """A worker process died (killed, out of memory) while it ran a task.

    Parameters
    ----------
    label : str
        The task it ran.
    reason : str
        How the process ended (:func:`exit_reason`)."""

    def __init__(self, label: str, reason: str) -> None:
        super().__init__(f"{label}: the worker process running it died ({reason})")
        self.label, self.reason = label, reason

    def __reduce__(self):
        return (type(self), (self.label, self.reason))


def _call(task: Task, where: str) -> TaskResult:
    t = _time.perf_counter()
    value = task.func(*task.args, **task.kwargs)
    return TaskResult(value, where, _time.perf_counter() - t)


def _relabel(exc: BaseException, label: str) -> BaseException:
    """``exc`` with its message prefixed by ``label`` (the same type where it can be rebuilt from
    one message, else a RuntimeError naming the type); a signal's interrupt, also one that a
    compiled function's SystemError carries (:func:`~cilia_runtime.signals.interrupt_of`), as
    itself: the command line reports the signal, not an internal error."""
    intr = interrupt_of(exc)
    if intr is not None:
        return intr
    msg = f"{label}: {exc}"
    try:
        new = type(exc)(msg)
        if str(new) != msg:
            raise TypeError
    except Exception:  # noqa: BLE001 -- an exception type with another constructor
        new = RuntimeError(f"{label}: {type(exc).__name__}: {exc}")
    return new


class InProcess:
    """Tasks one after another in this process, with its numba and BLAS threads as they are set.

    Parameters
    ----------
    budget : ThreadBudget, optional
        Applied around each task (:meth:`ThreadBudget.applied`); default none (the threads the
        caller has)."""

    processes = 0

    def __init__(self, budget: ThreadBudget | None = None) -> None:
        self.budget = budget

    def __repr__(self) -> str:
        return "InProcess()"

    @property
    def workers(self) -> int:
        """Tasks run at once: 1."""
        return 1

    def warm(self) -> None:
        """Nothing to start ahead (:meth:`ProcessPool.warm`)."""

    def run(self, tasks: Sequence[Task], *, shared: Sequence = (), progress: Progress | None = None
            ) -> list[TaskResult]:
        """Run ``tasks`` (biggest first) and return their results in the order of ``tasks``.
        ``shared`` is ignored (nothing is copied)."""
        progress = progress if progress is not None else Progress()
        out: list = [None] * len(tasks)
        progress.start(len(tasks), "tasks")
        try:
            for n, i in enumerate(_order(tasks), 1):
                try:
                    if self.budget is not None:
                        with self.budget.applied():
                            out[i] = _call(tasks[i], "parent")
                    else:
                        out[i] = _call(tasks[i], "parent")
                except Exception as exc:
                    raise _relabel(exc, tasks[i].label) from exc
                progress.update(n)
        finally:
            progress.close()
        return out


def _order(tasks: Sequence[Task]) -> list[int]:
    """Task indices, the biggest cost first (ties: in the given order)."""
    return sorted(range(len(tasks)), key=lambda i: (-float(tasks[i].cost), i))


_TRACKER_QUIET = "ignore::UserWarning:multiprocessing.resource_tracker"
"""The warnings filter the resource tracker of this process's workers starts with: a worker
stopped by SIGKILL (:func:`stop`, after its grace) cannot unregister the named semaphore numba's
parallel layer makes in it (its process lock), which the tracker then removes itself; its
"leaked semaphore" warning on stderr would be noise after a stop that left nothing else behind."""


def worker_context(preload: Sequence[str] = ()):
    """The multiprocessing context of worker processes: a fork server, or spawn where there is
    none; never fork. ``preload``: modules the fork server imports once, before it forks any
    worker (it takes those of the first call that starts it: one fork server per process). The
    resource tracker the workers share starts with :data:`_TRACKER_QUIET`."""
    import multiprocessing as mp
    import sys

    if _TRACKER_QUIET not in sys.warnoptions:  # the tracker takes this process's -W options when it starts
        sys.warnoptions.append(_TRACKER_QUIET)
    if "forkserver" in mp.get_all_start_methods():
        ctx = mp.get_context("forkserver")
        if preload:
            ctx.set_forkserver_preload(list(preload))
        return ctx
    return mp.get_context("spawn")


class _SharedPickler(pickle.Pickler):
    """Pickles the objects in ``shared`` as references (sent to each worker once)."""

    def __init__(self, file, keys: dict[int, int]) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self._keys = keys

    def persistent_id(self, obj):
        return self._keys.get(id(obj))


class _SharedUnpickler(pickle.Unpickler):
    def __init__(self, file, lookup: Callable[[int], Any]) -> None:
        super().__init__(file)
        self._lookup = lookup

    def persistent_load(self, pid):
        return self._lookup(int(pid))


def _dumps(obj, keys: dict[int, int]) -> bytes:
    buf = io.BytesIO()
    _SharedPickler(buf, keys).dump(obj)
    return buf.getvalue()


def _serve(conn, budget: ThreadBudget | None, name: str, allow=None, place: int = 0) -> None:
    """A worker process: shared objects and tasks from ``conn``, results back, until told to stop
    (None) or the parent goes away (its end of ``conn`` closes: between tasks the worker reads
    EOF, during a task a watcher thread sees it and exits at once, so that a parent killed with
    SIGKILL leaves no worker computing on). Ctrl-C (which reaches the whole process group) ends
    it quietly: the parent reports the interruption. ``budget`` (None: the threads it has) is
    applied around every task; ``allow``: the pool's numba-thread allowance of each worker,
    ``place``: this worker's index in it (:class:`_Share`)."""
    blobs: dict[int, bytes] = {}
    objects: dict[int, Any] = {}

    def lookup(key: int):
        if key not in objects:
            objects[key] = pickle.loads(blobs.pop(key))
        return objects[key]

    in_task = threading.Event()
    generation = [0]  # counts the tasks started

    def orphaned():  # the parent sends nothing while a task runs: input then is its end (it died)
        while True:
            in_task.wait()
            g = generation[0]
            try:
                ready = conn.poll(0.5)
            except (OSError, EOFError):
                ready = True
            # still the same task: the input came while it ran (not the next task's messages)
            if ready and in_task.is_set() and generation[0] == g:
                os._exit(1)

    threading.Thread(target=orphaned, name="orphan-watch", daemon=True).start()
    threads = budget.applied() if budget is not None else contextlib.nullcontext()
    place_cm = _placed(allow, place) if allow is not None else contextlib.nullcontext()
    try:  # SIGTERM (the parent stopping it) ends it like Ctrl-C: cleanly, its finalizers run
        with terminate_as_interrupt(), threads, place_cm:
            while True:
                try:
                    msg = conn.recv()
                except EOFError:
                    return
                if msg is None:
                    return
                kind, key = msg
                if kind == "shared":
                    blobs[key] = conn.recv_bytes()
                    continue
                payload = conn.recv_bytes()
                try:
                    task = _SharedUnpickler(io.BytesIO(payload), lookup).load()
                    generation[0] += 1
                    in_task.set()
                    try:
                        res = _call(task, name)
                    finally:
                        in_task.clear()
                    reply = ("ok", key, res)
                except Exception as exc:  # noqa: BLE001 -- sent back to the parent, which raises it
                    tb = traceback.format_exc()
                    try:
                        pickle.dumps(exc)
                    except Exception:  # noqa: BLE001 -- an exception that cannot be pickled: its words
                        exc = RuntimeError(f"{type(exc).__name__}: {exc}")
                    reply = ("error", key, (exc, tb))
                try:
                    conn.send(reply)
                except (BrokenPipeError, EOFError, OSError):
                    return
    except KeyboardInterrupt:
        pass
    finally:
        conn.close()


class _RemoteTraceback(Exception):
    def __init__(self, tb: str) -> None:
        super().__init__(tb)
        self.tb = tb

    def __str__(self) -> str:
        return self.tb



def exit_reason(code: int | None) -> str:
    """How a worker process ended, from its exit code: "killed by SIGKILL, e.g. out of memory" or
    "exit status N"."""
    if code is not None and code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"killed by {name}" + (", e.g. out of memory" if -code == signal.SIGKILL else "")
    return f"exit status {code}"


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


def stop(procs, grace: float, told: bool = False) -> None:
    """Stop the worker processes ``procs`` and every process each started: those ``told`` (Ctrl-C
    reached them too) get ``grace`` seconds to finish their cleanup first; then the ones still
    alive get SIGTERM (a worker ends on it like on Ctrl-C, its ``finally`` clauses run) and
    ``grace`` seconds more; then every process left in their trees is killed (SIGKILL) and the
    workers reaped."""
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
            try:
                os.kill(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        for pid, started in tree[p.pid][::-1]:
            if started is not None and _started(pid) == started:  # the same process, still there
                try:
                    os.kill(pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
        p.join(5.0)


class ProcessPool:
    """Tasks in ``processes`` worker processes (and this one, with ``parent_works``).

    Parameters
    ----------
    processes : int >= 1
        Worker processes at once, started from a fork server for each :meth:`run` and stopped
        at its end.
    parent_works : bool
        This process runs tasks too, from before the workers start: it has the imports and
        compiled kernels already, which a new worker must load first.
    lend_idle : bool
        Share idle cores: the cores of idle workers (a worker process with no task left, or this
        process once it has finished its own) are given to the workers still running a task, as
        extra numba threads, while those make the task faster (:func:`adjust_threads`): the
        last, longest task of a run does not run on one core while the others wait. Off: one
        numba thread in each worker.
    start_after : float
        With ``parent_works``: seconds to wait before starting workers (none start if this
        process has taken every task by then: a short run is not slowed by starting a pool).
    grace : float
        Seconds stopped workers get to exit after SIGTERM before SIGKILL (:func:`stop`).
    isolated : bool
        Each task in a fresh worker process that ends after it, with the threads it has (the task
        sets its own), not daemonic (it may start processes); a task that raises or a worker that
        dies fails that task only (:meth:`run`). Needs ``parent_works`` and ``lend_idle`` off.
    preload : sequence of str
        Modules the fork server imports before it forks a worker (:func:`worker_context`).

    The thread budget of a shared pool: :attr:`workers` (``processes + parent_works``) run at
    once, one BLAS thread each, one numba thread each while all are busy; the numba threads of
    all workers together never exceed :attr:`workers` (:func:`pool_for_threads` sizes the pool
    from the cores a caller may use)."""

    def __init__(self, processes: int, *, parent_works: bool = True, lend_idle: bool = True,
                 start_after: float = 0.5, grace: float = 2.0, isolated: bool = False,
                 preload: Sequence[str] = ()) -> None:
        if not (isinstance(processes, int) and processes >= 1):
            raise ValueError(f"ProcessPool: processes must be an integer >= 1, got {processes!r}")
        if isolated and (parent_works or lend_idle):
            raise ValueError("ProcessPool: an isolated pool runs every task in a worker of its own "
                             "(parent_works and lend_idle off)")
        self.processes = processes
        self.parent_works = bool(parent_works)
        self.lend_idle = bool(lend_idle)
        self.start_after = float(start_after)
        self.grace = float(grace)
        self.isolated = bool(isolated)
        self.preload = tuple(preload)
        self.startup: dict[str, float] = {}  # by worker: seconds from a run's start to its first task
        self.pids: list[int] = []  # the last run's worker processes

    def __repr__(self) -> str:
        if self.isolated:
            return f"ProcessPool({self.processes}, isolated=True)"
        return f"ProcessPool({self.processes}, parent_works={self.parent_works}, lend_idle={self.lend_idle})"

    @property
    def workers(self) -> int:
        """Tasks run at once: the worker processes, and this process if it works
        (``parent_works``)."""
        return self.processes + int(self.parent_works)

    def warm(self) -> None:
        """Start the fork server the workers are forked from (it imports ``preload``), so that
        it is ready when :meth:`run` needs workers: a caller with other work first calls it then;
        without it the first :meth:`run` starts the server."""
        if worker_context(self.preload).get_start_method() == "forkserver":
            from multiprocessing import forkserver

            forkserver.ensure_running()

    @property
    def budget(self) -> ThreadBudget | None:
        """One numba and one BLAS thread in each worker (more numba threads while other workers
        are idle, with ``lend_idle``); None when ``isolated`` (each task sets its own)."""
        return None if self.isolated else ThreadBudget(workers=self.workers, numba=1, blas=1)

    def run(self, tasks: Sequence[Task], *, shared: Sequence = (), progress: Progress | None = None,
            desc: str = "tasks", on_start: Callable[[int], None] | None = None,
            on_done: Callable[[int, Any], None] | None = None) -> list:
        """Run ``tasks`` (biggest first) and return their results in the order of ``tasks``.

        ``shared``: objects that tasks' arguments refer to, pickled once and sent once to each
        worker. ``progress`` counts the tasks finished (``desc`` names them). ``on_start(i)`` is
        called as task ``i`` starts, ``on_done(i, outcome)`` as it ends (in the pool's dispatcher
        thread for a worker's tasks). A shared pool: a task that raises, or a worker that dies,
        stops the others and raises here, the outcome is a :class:`TaskResult`. ``isolated``: the
        outcome of such a task is the exception (:class:`WorkerDied`, or the task's, relabelled),
        in place of its result, and the others go on. A KeyboardInterrupt stops the workers and
        propagates (module docstring)."""
        tasks = list(tasks)
        progress = progress if progress is not None else Progress()
        self.startup, self.pids = {}, []
        run = _PoolRun(self, tasks, shared, progress, on_start, on_done)
        progress.start(len(tasks), desc)
        try:
            return run.go()
        finally:
            progress.close()


class _PoolRun:
    """One :meth:`ProcessPool.run`: a dispatcher thread feeds the workers while the main thread
    works on tasks itself (with ``parent_works``). Workers are numbered from 0: this process
    first (if it works), then the worker processes; ``allow[place]`` is worker ``place``'s
    numba threads now."""

    def __init__(self, pool: ProcessPool, tasks: list[Task], shared: Sequence, progress: Progress,
                 on_start=None, on_done=None) -> None:
        self.pool, self.tasks, self.shared, self.progress = pool, tasks, list(shared), progress
        self.on_start, self.on_done = on_start, on_done
        self.queue = _order(tasks)
        self.results: list = [None] * len(tasks)
        self.lock = threading.Lock()
        self.abort = threading.Event()
        self.idle = threading.Event()  # set when this process has taken the last task
        self.failure: BaseException | None = None
        self.procs: list = []
        self.done = 0
        self.t0 = _time.perf_counter()
        self.ctx = worker_context(pool.preload)
        self.allow = self.ctx.Array("i", [1] * pool.workers, lock=False) if pool.lend_idle else None
        self.busy: set[int] = set()
        self.started = 0  # workers started

    def take(self) -> int | None:
        with self.lock:
            if self.abort.is_set() or not self.queue:
                return None
            return self.queue.pop(0)

    def set_busy(self, place: int, busy: bool) -> None:
        """Mark worker ``place`` busy or idle; once no task is left to hand out, share the idle
        workers' cores among the busy ones (``allow``)."""
        with self.lock:
            (self.busy.add if busy else self.busy.discard)(place)
            if self.allow is None:
                return
            n = self.pool.workers
            running = sorted(self.busy)
            spare = n - len(running) if not self.queue else 0
            for p in range(n):
                self.allow[p] = 1
            for r, p in enumerate(running):
                self.allow[p] = 1 + spare // len(running) + (1 if r < spare % len(running) else 0)

    def finished(self, i: int, res) -> None:
        """Task ``i`` ended with ``res`` (a TaskResult, or an isolated task's exception)."""
        with self.lock:
            self.results[i] = res
            self.done += 1
            n = self.done
        if self.on_done is not None:
            self.on_done(i, res)
        self.progress.update(n)

    def failed(self, i: int, exc: BaseException) -> bool:
        """Task ``i`` failed with ``exc``: its outcome in an isolated pool (True: go on), else the
        run's failure (False: stop)."""
        if self.pool.isolated:
            self.finished(i, exc)
            return True
        self.fail(exc)
        return False

    def fail(self, exc: BaseException) -> None:
        with self.lock:
            if self.failure is None:
                self.failure = exc
        self.abort.set()
        self.idle.set()

    def go(self) -> list:
        budget = self.pool.budget
        # this process takes the biggest task before the dispatcher can hand it to a worker (with
        # start_after 0 the dispatcher's thread could take it first)
        first = self.take() if self.pool.parent_works else None
        if first is not None:
            self.set_busy(0, True)
            if not self.queue:
                self.idle.set()
        dispatcher = threading.Thread(target=self.dispatch, args=(budget,), name="pool-dispatcher", daemon=True)
        dispatcher.start()
        try:
            if self.pool.parent_works:
                with budget.applied(), (_placed(self.allow, 0) if self.allow is not None
                                        else contextlib.nullcontext()):
                    while (i := first if first is not None else self.take()) is not None:
                        first = None
                        self.set_busy(0, True)
                        if not self.queue:
                            self.idle.set()
                        if self.on_start is not None:
                            self.on_start(i)
                        try:
                            res = _call(self.tasks[i], "parent")
                        except Exception as exc:
                            new = _relabel(exc, self.tasks[i].label)
                            new.__cause__ = exc
                            self.fail(new)
                            break
                        finally:
                            self.set_busy(0, False)
                        self.finished(i, res)
            self.idle.set()
            while dispatcher.is_alive():
                dispatcher.join(0.1)
        except BaseException as exc:  # Ctrl-C, SIGTERM: stop the workers before it propagates
            self.abort.set()
            # Ctrl-C in a terminal reaches the workers too; SIGTERM or SIGHUP reached this process only
            self.stop_all(told=isinstance(exc, KeyboardInterrupt) and not isinstance(exc, Terminated))
            while dispatcher.is_alive():
                dispatcher.join(0.1)
            raise
        if self.failure is not None:
            raise self.failure
        missing = [self.tasks[i].label for i, r in enumerate(self.results) if r is None]
        if missing:  # cannot happen without a failure; never return a partial result
            raise RuntimeError(f"tasks not run: {', '.join(missing)}")
        return self.results

    def stop_all(self, told: bool = False) -> None:
        """Stop the workers still alive, and what they started (:func:`stop`)."""
        with self.lock:
            procs = list(self.procs)
        stop(procs, self.pool.grace, told=told)

    def start_worker(self, keys: dict, blobs: list, conns: dict, running: dict, places: dict,
                     budget: ThreadBudget | None, place: int) -> None:
        """Start a worker process as worker ``place``, send it the shared objects and its first
        task."""
        self.started += 1
        name = f"worker {self.started}"
        here, there = self.ctx.Pipe(duplex=True)
        proc = self.ctx.Process(target=_serve, args=(there, budget, name, self.allow, place),
                                name=f"pool {name}", daemon=not self.pool.isolated)
        proc.start()
        there.close()
        with self.lock:
            self.procs.append(proc)
            self.pool.pids.append(proc.pid)
        conns[proc], places[proc] = here, (name, place)
        try:
            for k, blob in enumerate(blobs):
                here.send(("shared", k))
                here.send_bytes(blob)
        except (BrokenPipeError, OSError):
            pass  # died at once: seen below
        self.feed(proc, here, running, keys, place)
        if self.pool.isolated and proc not in running:  # its task could not be sent (failed): the next
            self.retire(proc, conns)
            if not self.abort.is_set() and self.queue:
                self.start_worker(keys, blobs, conns, running, places, budget, place)

    def retire(self, proc, conns: dict) -> None:
        """Tell an idle worker to end, and reap it."""
        conn = conns.pop(proc)
        try:
            conn.send(None)
        except (BrokenPipeError, OSError):
            pass
        proc.join(self.pool.grace)
        conn.close()

    def dispatch(self, budget: ThreadBudget | None) -> None:
        """The dispatcher thread: start the workers, send each the shared objects, then a task
        whenever it is idle (an isolated pool: a fresh worker for each task); collect results;
        stop the workers at the end (or on a failure)."""
        from multiprocessing.connection import wait as wait_any

        conns: dict = {}  # proc -> parent's end of its pipe
        running: dict = {}  # proc -> task index
        places: dict = {}  # proc -> (name, worker index)
        try:
            if self.pool.parent_works:  # short runs end in this process before a worker could start
                self.idle.wait(self.pool.start_after)
                if self.abort.is_set() or not self.queue:
                    return
            keys = {id(obj): k for k, obj in enumerate(self.shared)}
            blobs = [pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL) for obj in self.shared]
            first = int(self.pool.parent_works)
            for w in range(self.pool.processes):
                if self.abort.is_set() or not self.queue:
                    break
                self.start_worker(keys, blobs, conns, running, places, budget, first + w)
            if not self.pool.isolated:
                del blobs  # every worker has its copy (a large object's pickle may be hundreds of MB)
            while running:
                ready = wait_any([conns[p] for p in running] + [p.sentinel for p in running], timeout=0.1)
                if self.abort.is_set():
                    return
                for proc in list(running):
                    conn, (name, place) = conns[proc], places[proc]
                    i = running[proc]
                    if conn not in ready and proc.sentinel not in ready:
                        continue
                    try:
                        msg = conn.recv() if conn.poll() else None
                    except (EOFError, OSError):
                        msg = None
                    del running[proc]
                    self.set_busy(place, False)
                    if msg is None:
                        proc.join(1.0)
                        conns.pop(proc).close()
                        if not self.failed(i, WorkerDied(self.tasks[i].label, exit_reason(proc.exitcode))):
                            return
                    else:
                        kind, j, body = msg
                        if kind == "ok":
                            # a worker's start-up: from the run's start to its first result, less the task
                            self.pool.startup.setdefault(name, _time.perf_counter() - self.t0 - body.seconds)
                            self.finished(j, body)
                        else:
                            exc, tb = body
                            new = _relabel(exc, self.tasks[j].label)
                            new.__cause__ = _RemoteTraceback(tb)
                            if not self.failed(j, new):
                                return
                        if not self.pool.isolated:
                            self.feed(proc, conn, running, keys, place)
                            continue
                        self.retire(proc, conns)
                    if self.pool.isolated and not self.abort.is_set() and self.queue:
                        self.start_worker(keys, blobs, conns, running, places, budget, place)
        except BaseException as exc:  # noqa: BLE001 -- the main thread raises it
            self.fail(exc)
        finally:
            for proc, conn in conns.items():
                if proc not in running:
                    try:
                        conn.send(None)
                    except (BrokenPipeError, OSError):
                        pass
            if running or self.abort.is_set():
                self.stop_all()
            for proc, conn in conns.items():
                proc.join(self.pool.grace)
                conn.close()
            self.stop_all()

    def feed(self, proc, conn, running: dict, keys: dict, place: int) -> None:
        """Send ``proc`` the next task, if any."""
        i = self.take()
        if i is None:
            self.set_busy(place, False)  # the queue is empty: its core goes to the busy workers
            return
        try:
            payload = _dumps(self.tasks[i], keys)
        except Exception as exc:  # noqa: BLE001 -- an argument that cannot be pickled
            self.failed(i, _relabel(exc, self.tasks[i].label))
            return
        self.set_busy(place, True)
        try:
            conn.send(("task", i))
            conn.send_bytes(payload)
        except (BrokenPipeError, OSError):
            pass  # it died: its sentinel says so
        running[proc] = i
        if self.on_start is not None:
            self.on_start(i)


def pool_for_threads(threads: int, preload: Sequence[str] = ()) -> InProcess | ProcessPool:
    """The strategy for a caller that may use ``threads`` cores: :class:`InProcess` (one numba and
    one BLAS thread) for one, or in a daemonic process (which cannot start processes); else a
    :class:`ProcessPool` of ``threads - 1`` worker processes and this process (one numba and one
    BLAS thread each, idle workers' cores shared among the busy ones: ``threads`` threads in
    all), its fork server preloading ``preload``."""
    import multiprocessing as mp

    threads = int(threads)
    if threads <= 1 or mp.current_process().daemon:  # (a daemonic process, e.g. a Dask worker's, has no children)
        return InProcess(ThreadBudget(workers=1, numba=1, blas=1))
    return ProcessPool(threads - 1, parent_works=True, preload=preload)
