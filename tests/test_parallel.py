"""Path lines in independent chunks, in this process or a pool of worker processes (issue 23:
cilia_runtime.pool): the same numbers wherever the chunks run, the workers' thread
budget, clear errors for a failing chunk or a dead worker, no worker left after an interrupt."""
import os
import time

import numba
import numpy as np
import pytest

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.transport.flow import Flow, ResolvedFlow
from cilia_runtime.pool import InProcess, ProcessPool, Task, WorkerDied, pool_for_threads
from ciliary_carpet.transport.pathlines import chunks, join_pathlines, pathline_tasks, pathlines
from single_cilium.table import ThrustTable
from cilia_runtime.threads import threads_in_use


@pytest.fixture(scope="module")
def carpet():
    return Carpet(np.array([[0.0, 0.0], [3.0, 0.0]]), [4.0, -4.0], ThrustTable.default(), phases=[0.3, 0.1])


def _seeds(n=12):
    return np.column_stack([np.linspace(-3, 6, n), np.full(n, 2.0), np.full(n, 0.5)])


class Failing(Flow):
    """The carpet's flow, but a NaN-free error for points beyond x = 4 (the last chunk's seeds)."""

    name = "failing"

    def __init__(self, carpet):
        self.carpet = carpet

    def velocity(self, x, t):
        if np.any(x[:, 0] > 4.0):
            raise FloatingPointError("the flow failed here")
        return ResolvedFlow(self.carpet, 1e-3).velocity(x, t)


def _threads_here():
    return threads_in_use()


def _die():
    os._exit(7)


def _sleep(s):
    time.sleep(s)
    return os.getpid()


def _lent_threads(timeout):
    """Poll the place's share of the cores (as path lines do between evaluations)."""
    from cilia_runtime.pool import adjust_threads

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        adjust_threads()
        if numba.get_num_threads() > 1:
            break
        time.sleep(0.02)
    return numba.get_num_threads()


def test_chunks_do_not_depend_on_the_workers():
    assert [c.tolist() for c in chunks(5, None)] == [[0, 1, 2, 3, 4]]
    parts = chunks(10, 4)  # ceil(10 / 4) = 3 chunks, sizes within one of each other
    assert [p.size for p in parts] == [4, 3, 3] and np.array_equal(np.concatenate(parts), np.arange(10))
    assert len(chunks(3, 200)) == 1
    with pytest.raises(ValueError, match="chunk_size"):
        chunks(3, 0)


def test_chunks_in_a_pool_are_bit_identical_to_in_process(carpet):
    """The same chunks in this process and in worker processes: the same numbers, bit for bit; the
    join keeps the seed order and sums the work; each chunk is one pathlines run."""
    flow, seeds = ResolvedFlow(carpet, 1e-3), _seeds()
    kw = dict(rtol=1e-6, atol=1e-6, samples_per_period=8)
    with pool_for_threads(1).budget.applied():
        here = pathlines(flow, seeds, (0.0, 2.0), chunk_size=5, **kw)
    pool = ProcessPool(2, parent_works=False)
    there = pathlines(flow, seeds, (0.0, 2.0), chunk_size=5, pool=pool, **kw)
    assert here.stats["chunks"] == there.stats["chunks"] == 3
    assert set(there.stats["chunks_by_place"]) <= {"worker 1", "worker 2"}
    assert there.stats["workers"] == 2
    assert np.array_equal(there.seed_ids, np.arange(12)) and np.array_equal(here.reason, there.reason)
    for a, b, c, d in zip(here.points, there.points, here.velocities, there.velocities):
        assert np.array_equal(a, b) and np.array_equal(c, d)
    # each chunk is the run of its own seeds, in the whole run's domain
    tasks = pathline_tasks(flow, seeds, (0.0, 2.0), chunk_size=5, **kw)
    assert [t.label for t in tasks] == [f"path lines: chunk {k} of 3 (tracers {a}-{b})"
                                        for k, (a, b) in enumerate([(0, 3), (4, 7), (8, 11)], 1)]
    alone = pathlines(flow, seeds[4:8], (0.0, 2.0), domain=tasks[1].kwargs["domain"], **kw)
    assert all(np.array_equal(a, b) for a, b in zip(alone.points, here.points[4:8]))
    joined = join_pathlines([alone, alone])
    assert joined.stats["steps"] == 2 * alone.stats["steps"] and len(joined.points) == 8


def test_workers_take_the_thread_budget():
    """Each worker runs its tasks with one numba and one BLAS thread (the pool's budget: places x
    numba x BLAS = the cores given); an idle place's core goes to a busy one."""
    pool = ProcessPool(2, parent_works=False, lend_idle=False)
    res = pool.run([Task(f"t{k}", _threads_here) for k in range(2)])
    assert [r.value for r in res] == [{"numba": 1, "blas": 1, "workers": 2}] * 2
    assert pool_for_threads(1).budget.threads == 1 and pool_for_threads(3).workers == 3
    if numba.config.NUMBA_NUM_THREADS >= 2:  # one task, two workers: the idle one's core is lent
        (r,) = ProcessPool(2, parent_works=False).run([Task("lent", _lent_threads, (20.0,))])
        assert r.value == 2


def test_compiled_functions_let_go_of_the_interpreter():
    """The compiled functions of the package that Python calls and that write into arrays they
    are given release the GIL (``nogil``): the pool's dispatcher thread starts and feeds the
    workers while this process's path lines compute (beside a 30 x 30 main run a worker took
    1.35-1.44 s to its first task without it, 0.64-0.75 s with it, 0.5 s of which the pool's
    ``start_after``). Those that return arrays keep it: returning them after a SIGINT arrived
    without the GIL gave "returned a result with an exception set" (test_faults.py test 7)."""
    import ast
    import importlib
    import inspect
    import pkgutil
    import textwrap

    from numba.core.registry import CPUDispatcher

    import ciliary_carpet

    def returns_value(f) -> bool:
        tree = ast.parse(textwrap.dedent(inspect.getsource(f.py_func)))
        return any(isinstance(n, ast.Return) and n.value is not None for n in ast.walk(tree.body[0]))

    entry = {}
    for m in pkgutil.walk_packages(ciliary_carpet.__path__, "ciliary_carpet."):
        mod = importlib.import_module(m.name)
        for name, f in vars(mod).items():
            if (isinstance(f, CPUDispatcher) and f.py_func.__module__ == mod.__name__
                    and f.targetoptions.get("inline") != "always"):
                entry[f"{mod.__name__}.{name}"] = (bool(f.targetoptions.get("nogil")), returns_value(f))
    assert len(entry) >= 20 and sum(r for _, r in entry.values()) >= 3, sorted(entry)  # the walk found them
    assert [k for k, (nogil, ret) in entry.items() if nogil == ret] == []
    assert "ciliary_carpet.stokes.direct._ranged32" in entry and not entry["ciliary_carpet.carpet.traversal._lists"][0]


def test_warm_starts_the_fork_server_ahead():
    """ProcessPool.warm starts the fork server the workers come from (a render calls it before its
    design); a run after it uses that server; InProcess has nothing to start."""
    from multiprocessing import forkserver

    assert InProcess().warm() is None
    pool = ProcessPool(1, parent_works=False)
    pool.warm()
    pid = forkserver._forkserver._forkserver_pid
    assert pid is not None and os.path.exists(f"/proc/{pid}")
    res = pool.run([Task("t", _threads_here)])
    assert res[0].where == "worker 1" and forkserver._forkserver._forkserver_pid == pid


def test_a_chunk_whose_flow_raises_is_named(carpet):
    for pool in (InProcess(), ProcessPool(1, parent_works=False)):
        with pytest.raises(FloatingPointError, match=r"path lines: chunk 3 of 3 \(tracers 8-11\): the flow failed"):
            pathlines(Failing(carpet), _seeds(), (0.0, 0.5), chunk_size=4, pool=pool)


def test_a_dead_worker_is_named_and_nothing_hangs():
    t = time.monotonic()
    with pytest.raises(WorkerDied, match=r"chunk that dies: the worker process running it died \(exit status 7\)"):
        ProcessPool(1, parent_works=False).run([Task("chunk that dies", _die), Task("other", _sleep, (0.01,))])
    assert time.monotonic() - t < 20


def test_this_process_takes_the_biggest_task_before_any_worker(monkeypatch):
    """With parent_works, this process takes the biggest task before the dispatcher can hand it to
    a worker, however late its thread runs (start_after 0: the dispatcher starts at once; here
    this process's thread waits, once the dispatcher runs, until it has handed a task out). The
    biggest task cannot be pickled, so a worker given it would fail the run."""
    import threading

    from cilia_runtime import pool as parallel

    real = parallel._PoolRun.take
    main = threading.main_thread()

    def late(self):  # this process's thread takes its first task only once a running dispatcher took one
        if threading.current_thread() is main and not getattr(self, "_late", False):
            self._late = True
            end = time.monotonic() + 20
            while (any(t.name == "pool-dispatcher" for t in threading.enumerate()) and len(self.queue) == 2
                   and time.monotonic() < end):
                time.sleep(0.01)
        return real(self)

    monkeypatch.setattr(parallel._PoolRun, "take", late)
    local = lambda: "here"  # noqa: E731 - not picklable
    res = ProcessPool(1, parent_works=True, start_after=0.0).run(
        [Task("biggest", local, cost=2.0), Task("small", _sleep, (0.01,), cost=1.0)])
    assert res[0].value == "here" and res[0].where == "parent"


def test_interrupt_stops_the_workers():
    """Ctrl-C in this process (here: raised by its own task once the worker runs a long task)
    stops the worker: no orphan, and quickly."""
    pool = ProcessPool(1, parent_works=True, start_after=0.0, grace=0.5)

    def parent_task():  # the biggest: this process takes it; the worker gets the long one
        end = time.monotonic() + 30
        while not pool.pids and time.monotonic() < end:
            time.sleep(0.01)
        time.sleep(1.0)
        raise KeyboardInterrupt

    t = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        pool.run([Task("parent", parent_task, cost=2.0), Task("long", _sleep, (60.0,), cost=1.0)])
    assert pool.pids and time.monotonic() - t < 30
    for pid in pool.pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_lent_threads_are_kept_only_while_they_pay(monkeypatch):
    """The governor of a place's lent cores: one thread measured first, then the lent threads;
    given back when they evaluate slower (a busy machine), tried again later, kept when faster,
    and given back at once when the budget shrinks."""
    from cilia_runtime import pool as parallel

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread here")
    clock = [0.0]
    monkeypatch.setattr(parallel._time, "perf_counter", lambda: clock[0])
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        arr = [2]
        share = parallel._Share(arr, 0, 1)

        def run(seconds, per_eval):  # evaluations of 50 points (2 units each), per_eval seconds apiece
            for _ in range(int(round(seconds / per_eval))):
                clock[0] += per_eval
                share.tick(50)

        run(0.4, 0.01)  # one thread: 200 units/s measured, then the lent thread is taken
        assert share.current == 2 and numba.get_num_threads() == 2
        run(0.4, 0.02)  # slower with two: given back
        assert share.current == 1 and numba.get_num_threads() == 1
        retry_at = share.retry_at
        run(parallel.RETRY_S / 2, 0.01)
        assert share.current == 1  # not yet tried again
        while share.current == 1 and clock[0] < retry_at + 1.0:
            run(0.01, 0.01)
        assert share.current == 2 and clock[0] >= retry_at  # tried again
        run(1.0, 0.005)  # twice as fast: kept
        assert share.current == 2
        arr[0] = 1  # a place became busy: back to its share at once
        share.tick(50)
        assert share.current == 1 and numba.get_num_threads() == 1
    finally:
        numba.set_num_threads(before)


def test_flow_is_the_same_on_any_thread_count(carpet):
    """What lets a place take lent threads mid-run without changing the numbers: the flow's
    kernels give bit-identical velocities on one and on two numba threads."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread here")
    x = np.random.default_rng(0).uniform([-4, -3, 0.05], [7, 3, 2], (40, 3))
    flow = ResolvedFlow(carpet, 1e-4)
    before = numba.get_num_threads()
    try:
        out = []
        for n in (1, 2):
            numba.set_num_threads(n)
            out.append(flow.velocity(x, 0.37))
    finally:
        numba.set_num_threads(before)
    assert np.array_equal(out[0], out[1])


def test_render_is_the_same_on_a_pool(tmp_path):
    """A render's path lines and error estimate are the same, bit for bit, in this process and on
    a pool (the reference run in a worker); the summary says where each ran."""
    import json

    from ciliary_carpet.render import render
    from ciliary_carpet.scenes.scene import load_scene

    scene_file = tmp_path / "tiny.toml"
    # uncoupled: the coupling's size is then an estimate computed for the summary (a coupled
    # carpet says its own, from the solve)
    scene_file.write_text('[carpet]\nshape = [2, 2]\ncoupling = "none"\n[output]\nn_seeds = 3\nperiods = 0.5\n'
                          'field_shape = [6, 6]\n'
                          'snapshots = 0\nframes = 1\npreview = false\nftle = false\n')
    scene = load_scene(scene_file)
    render(scene, tmp_path / "one", pool=pool_for_threads(1))
    render(scene, tmp_path / "two", pool=ProcessPool(1, parent_works=False))
    assert (tmp_path / "one" / "pathlines.vtp").read_bytes() == (tmp_path / "two" / "pathlines.vtp").read_bytes()
    s1, s2 = (json.loads((tmp_path / d / "summary.json").read_text())["pathlines"] for d in ("one", "two"))
    e1, e2 = s1["end_point_error"], s2["end_point_error"]
    assert (e1["max"], e1["median"]) == (e2["max"], e2["median"])
    assert e1["work"]["where"] == "parent" and e2["work"]["where"] == "worker 1"
    assert s2["work"]["chunks_by_place"] == {"worker 1": 1} and s2["parallel"]["places"] == 1


def test_summary_computations_run_beside_the_path_lines(tmp_path):
    """On a pool of two places the summary's own computations (what the model leaves out, the size
    of the coupling) run as tasks of the path lines' pool, after the reference run, and give the
    numbers they give in this process; the summary's seconds say where they ran."""
    import json

    from ciliary_carpet.render import render
    from ciliary_carpet.scenes.scene import load_scene

    scene_file = tmp_path / "tiny.toml"
    # uncoupled: the coupling's size is then an estimate computed for the summary (a coupled
    # carpet says its own, from the solve)
    scene_file.write_text('[carpet]\nshape = [2, 2]\ncoupling = "none"\n[output]\nn_seeds = 3\nperiods = 0.5\n'
                          'field_shape = [6, 6]\n'
                          'snapshots = 0\nframes = 1\npreview = false\nftle = false\n')
    scene = load_scene(scene_file)
    render(scene, tmp_path / "one", pool=pool_for_threads(1))
    render(scene, tmp_path / "two", pool=pool_for_threads(2))
    s1, s2 = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("one", "two"))
    assert s1["omissions"] == s2["omissions"] and s1["coupling"] == s2["coupling"]
    assert s2["coupling"]["status"] == "not solved"
    assert "omissions_beside_pathlines" not in s1["seconds"] and s1["seconds"]["omissions"] > 0
    assert s2["seconds"]["omissions"] == 0 and s2["seconds"]["omissions_beside_pathlines"] > 0
    assert s2["seconds"]["coupling_beside_pathlines"] > 0
