"""Each worker its share of the cores: numba and BLAS thread counts per worker process or task.

numba's parallel regions use as many threads as the machine has cores by default, and so does
the BLAS. Two batch workers on two cores then run four threads on two cores, and the path lines'
tens of thousands of short parallel regions wait at every barrier for a descheduled thread: the
batch can take longer than its renders one after another. A :class:`ThreadBudget` says how many
workers run at once and how many numba and BLAS threads each may use, with ``workers x numba x
blas <= cores``; :meth:`ThreadBudget.applied` sets it in the worker (``numba.set_num_threads``,
which is per thread, and threadpoolctl's BLAS limit) before the work starts, and
:func:`threads_in_use` reports it (the render's ``summary.json`` ``"threads"``).

Tasks in threads of one process (a Dask worker with several threads) run their compiled kernels
side by side: the kernels let go of the interpreter (numba's ``nogil``). numba's ``workqueue``
threading layer, which it takes where neither TBB nor OpenMP is installed, aborts the process
when two threads start parallel regions at once; under it a budget applied in a thread holds a
lock of the process, so that such tasks run one after another (:func:`threadsafe_layer`).
"""
from __future__ import annotations

import logging
import math
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit, prange

__all__ = ["ThreadBudget", "cores", "threads_in_use", "threadsafe_layer"]

logger = logging.getLogger(__name__)


@njit(cache=True, parallel=True)
def _one_region(x):  # pragma: no cover - compiled
    """One trivial parallel region (numba chooses its threading layer at the first one)."""
    for i in prange(x.shape[0]):
        x[i] = i

_LOCAL = threading.local()  # .budgets: the budgets applied in this thread, innermost last
_SERIAL = threading.RLock()  # held by applied budgets under a threading layer that is not thread-safe
_WARNED: list = []  # a threaded Dask worker was warned about (once per process)


def _active() -> list:
    if not hasattr(_LOCAL, "budgets"):
        _LOCAL.budgets = []
    return _LOCAL.budgets


def threadsafe_layer() -> bool:
    """Whether parallel kernels may start from several threads of this process at once: numba's
    threading layer (chosen at the first parallel region, made here if none ran yet) is TBB or
    OpenMP, not ``workqueue`` (which aborts the process: "Concurrent access has been detected")."""
    import numba

    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel region has run in this process yet: one, one thread at a time
        with _SERIAL:
            try:
                layer = numba.threading_layer()
            except ValueError:
                _one_region(np.zeros(2))  # numba chooses its layer at the first parallel region
                layer = numba.threading_layer()
    return layer != "workqueue"


def _host_threads(worker) -> int:
    """The threads of all the Dask workers on ``worker``'s host, by the scheduler's list (the
    workers of `dask worker --nworkers N` share the machine's cores); 0 where it cannot tell."""
    try:
        from distributed import get_client

        ws = get_client().scheduler_info(n_workers=-1)["workers"]
        host = ws[worker.address]["host"]
        return sum(int(v.get("nthreads", 1)) for v in ws.values() if v.get("host") == host)
    except Exception:  # noqa: BLE001 -- an older or unreachable scheduler: this worker's own threads
        return 0


def cores() -> int:
    """The cores this process may run on: its CPU affinity where the system tells (else the
    machine's count), at most the whole CPUs of its control group's quota (a container's
    ``--cpus``, rounded down, at least one: a thread beyond the quota waits at every barrier;
    :func:`cilia_runtime.cgroup.cpu_quota`)."""
    try:
        n = max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        n = max(1, os.cpu_count() or 1)
    from .cgroup import cpu_quota

    q = cpu_quota()
    if q is not None:
        n = min(n, max(1, math.floor(q + 1e-9)))
    return n


@dataclass(frozen=True)
class ThreadBudget:
    """How many workers run at once, and the numba and BLAS threads of each.

    Parameters
    ----------
    workers : int
        Worker processes (or Dask worker threads) running at the same time.
    numba : int
        Threads of numba's parallel regions in each worker.
    blas : int
        BLAS threads in each worker.
    """

    workers: int = 1
    numba: int = 1
    blas: int = 1

    def __post_init__(self) -> None:
        for name in ("workers", "numba", "blas"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"ThreadBudget.{name} must be an integer >= 1, got {v!r}")

    @property
    def threads(self) -> int:
        """Threads of all workers together, ``workers x numba x blas``."""
        return self.workers * self.numba * self.blas

    def as_dict(self) -> dict:
        """``{"numba": n, "blas": m, "workers": k}`` (for summaries)."""
        d = asdict(self)
        return {"numba": d["numba"], "blas": d["blas"], "workers": d["workers"]}

    @classmethod
    def for_batch(cls, n_tasks: int, *, jobs: int | None = None, threads: int | None = None,
                  n_cores: int | None = None, memory_per_task=None,
                  memory_available: float | None = None) -> "ThreadBudget":
        """The budget of a batch of ``n_tasks`` on ``n_cores`` (default: :func:`cores`).

        Workers: ``jobs`` if given, else as many as there are tasks and cores, and as fit the
        available memory: ``k`` workers whose task takes ``memory_per_task`` bytes (a number, or
        a function of the task's numba threads: a render runs its path lines in as many worker
        processes) within ``memory_available``, when both are known. numba threads per worker:
        ``threads`` if given, else the cores divided among the workers. BLAS: one thread (the
        matrices of a render are small; more processes use the cores better than more threads:
        benchmarks/bench_batch.py). Given ``jobs`` and ``threads`` are taken as they are, even
        beyond the cores (with a warning).
        """
        c = int(n_cores) if n_cores is not None else cores()

        def per_task(k: int) -> float:
            if memory_per_task is None:
                return 0.0
            n_k = max(1, int(threads)) if threads is not None else max(1, c // k)
            return float(memory_per_task(n_k) if callable(memory_per_task) else memory_per_task)

        if jobs is not None:
            k = max(1, int(jobs))
        else:
            k = max(1, min(int(n_tasks), c))
            if memory_available and math.isfinite(memory_available):
                while k > 1 and k * per_task(k) > memory_available:
                    k -= 1
        n = max(1, int(threads)) if threads is not None else max(1, c // k)
        budget = cls(workers=k, numba=n, blas=1)
        if budget.threads > c:
            logger.warning("%d workers x %d numba threads exceed the %d cores: they will wait for each other "
                           "(leave out --jobs or --threads to have them chosen)", k, n, c)
        return budget

    @classmethod
    def for_task(cls, n_cores: int | None = None) -> "ThreadBudget":
        """The budget of one task in the process running it: on a Dask worker, the cores divided
        among the threads of all the workers on its host (the scheduler's list: `dask worker
        --nworkers N` starts N processes that share the machine, and each would otherwise take
        every core for its numba threads); elsewhere the cores.

        Tasks in threads of one worker share its interpreter, where a render's path lines spend a
        good part of their time, so such tasks run slower than on as many workers of one thread
        each (benchmarks/results/bench_batch_dask.md). Such a worker is warned about, once."""
        c = int(n_cores) if n_cores is not None else cores()
        k = here = 1
        try:
            from distributed import get_worker

            w = get_worker()
            k = max(1, int(w.state.nthreads))
            here = max(k, _host_threads(w))
        except (ImportError, ValueError, AttributeError):  # not on a Dask worker
            pass
        if k > 1 and not _WARNED:
            _WARNED.append(k)
            logger.warning("this Dask worker runs %d tasks at once in threads of one process, which share its "
                           "interpreter: two renders took about twice as long as on two workers of one thread "
                           "each; start workers with one thread each (dask worker --nthreads 1 --nworkers N)", k)
        return cls(workers=here, numba=max(1, c // here), blas=1)

    @contextmanager
    def applied(self) -> Iterator["ThreadBudget"]:
        """Within the block, numba's parallel regions of this thread use at most ``numba``
        threads and the BLAS at most ``blas`` (restored after)."""
        import numba
        from threadpoolctl import threadpool_limits

        n = min(self.numba, int(numba.config.NUMBA_NUM_THREADS))
        guard = nullcontext() if threadsafe_layer() else _SERIAL  # (module docstring)
        with guard:
            before = numba.get_num_threads()
            numba.set_num_threads(n)
            active = _active()
            active.append(ThreadBudget(self.workers, n, self.blas))
            try:
                with threadpool_limits(limits=self.blas, user_api="blas"):
                    yield active[-1]
            finally:
                active.pop()
                numba.set_num_threads(before)



def threads_in_use() -> dict:
    """``{"numba": n, "blas": m, "workers": k}``: the threads numba's parallel regions and the
    BLAS use now in this thread (as the libraries report them), and the workers of the budget
    applied here (:meth:`ThreadBudget.applied`; 1 without one)."""
    import numba
    from threadpoolctl import threadpool_info

    blas = [i.get("num_threads", 1) for i in threadpool_info() if i.get("user_api") == "blas"]
    active = _active()
    return {"numba": int(numba.get_num_threads()), "blas": int(max(blas, default=1)),
            "workers": active[-1].workers if active else 1}
