"""Each batch worker gets its share of the cores (issue 23, point 1): the budget the batch sets
(workers x numba threads x BLAS threads <= cores), and the threads each render reports using."""
import json

import numba
import pytest

import cilia_runtime.threads as threads_mod
from ciliary_carpet.batch import batch
from cilia_runtime.threads import ThreadBudget

TINY = ('[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 3\nperiods = 0.5\nfield_shape = [6, 6]\nsnapshots = 0\n'
        'frames = 1\npreview = false\n')


def test_default_budget_fits_the_cores():
    assert ThreadBudget.for_batch(2, n_cores=2) == ThreadBudget(workers=2, numba=1, blas=1)
    assert ThreadBudget.for_batch(1, n_cores=2) == ThreadBudget(workers=1, numba=2, blas=1)
    assert ThreadBudget.for_batch(3, n_cores=8) == ThreadBudget(workers=3, numba=2, blas=1)
    # memory: two copies of the largest scene fit
    assert ThreadBudget.for_batch(4, n_cores=8, memory_per_task=3e9, memory_available=7e9).workers == 2
    assert ThreadBudget.for_batch(4, n_cores=8, memory_per_task=3e9, memory_available=1e9).workers == 1
    # a task's memory as a function of its threads (a render's places): fewer workers take more each
    per = {1: 3e9, 2: 4.5e9}.__getitem__
    assert ThreadBudget.for_batch(2, n_cores=2, memory_per_task=per, memory_available=7e9) == ThreadBudget(2, 1, 1)
    assert ThreadBudget.for_batch(2, n_cores=2, memory_per_task=per, memory_available=5e9) == ThreadBudget(1, 2, 1)
    assert ThreadBudget.for_batch(2, n_cores=2, memory_per_task=per, memory_available=1e9) == ThreadBudget(1, 2, 1)
    for c in range(1, 17):
        for n in range(1, 20):
            b = ThreadBudget.for_batch(n, n_cores=c)
            assert b.workers * b.numba * b.blas <= c and b.workers == min(n, c)
    # --jobs and --threads are taken as given
    assert ThreadBudget.for_batch(5, jobs=3, threads=4, n_cores=2) == ThreadBudget(workers=3, numba=4, blas=1)
    with pytest.raises(ValueError, match="numba"):
        ThreadBudget(workers=1, numba=0)


def _scenes(tmp_path, names):
    out = []
    for n in names:
        p = tmp_path / f"{n}.toml"
        p.write_text(TINY)
        out.append(p)
    return out


def _threads(folder):
    return json.loads((folder / "summary.json").read_text())["threads"]


def test_batch_sets_each_workers_threads(tmp_path, monkeypatch):
    monkeypatch.setattr(threads_mod, "cores", lambda: 2)  # the batch's view of the machine: 2 cores
    scenes = _scenes(tmp_path, "ab")
    recs = batch(scenes, tmp_path / "out", progress=False)
    assert [r["status"] for r in recs] == ["done", "done"], recs
    for n in "ab":  # two workers, one numba thread and one BLAS thread each
        assert _threads(tmp_path / "out" / n) == {"numba": 1, "blas": 1, "workers": 2}


def test_budget_applied_sets_numba_and_blas_threads():
    """--jobs 1 --threads 2: what a worker applies, and what the render then reports."""
    b = ThreadBudget.for_batch(1, jobs=1, threads=2, n_cores=2)
    before = numba.get_num_threads()
    with b.applied():
        assert threads_mod.threads_in_use() == {"numba": min(2, numba.config.NUMBA_NUM_THREADS), "blas": 1,
                                                "workers": 1}
    assert numba.get_num_threads() == before


def test_dask_task_takes_its_workers_share(tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    monkeypatch.setattr(threads_mod, "cores", lambda: 2)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cl, \
            distributed.Client(cl) as client:
        recs = batch(_scenes(tmp_path, "a"), tmp_path / "out", executor=client.get_executor(), progress=False)
    assert recs[0]["status"] == "done", recs
    assert _threads(tmp_path / "out" / "a") == {"numba": 1, "blas": 1, "workers": 2}


def test_a_threaded_dask_worker_is_warned_about_once(monkeypatch, caplog):
    """A Dask worker with several threads: its tasks share the cores and one interpreter; the
    budget says so once per process (workers of one thread each render about twice as fast)."""
    import types

    distributed = pytest.importorskip("distributed")
    worker = types.SimpleNamespace(state=types.SimpleNamespace(nthreads=2))
    monkeypatch.setattr(distributed, "get_worker", lambda: worker)
    monkeypatch.setattr(threads_mod, "_WARNED", [])
    with caplog.at_level("WARNING", logger="cilia_runtime.threads"):
        assert ThreadBudget.for_task(n_cores=4) == ThreadBudget(workers=2, numba=2, blas=1)
        ThreadBudget.for_task(n_cores=4)
    said = [r.getMessage() for r in caplog.records if "--nthreads 1" in r.getMessage()]
    assert len(said) == 1 and "2 tasks at once" in said[0]


def test_dask_workers_on_one_host_share_its_cores(monkeypatch):
    """`dask worker --nworkers 2 --nthreads 1`: two processes on one host; each task takes half
    the cores, not all of them (the workers elsewhere do not count)."""
    import types

    distributed = pytest.importorskip("distributed")
    me = types.SimpleNamespace(address="tcp://a:1", state=types.SimpleNamespace(nthreads=1))
    ws = {"tcp://a:1": {"host": "a", "nthreads": 1}, "tcp://a:2": {"host": "a", "nthreads": 1},
          "tcp://b:1": {"host": "b", "nthreads": 4}}
    client = types.SimpleNamespace(scheduler_info=lambda n_workers=5: {"workers": ws if n_workers == -1 else {}})
    monkeypatch.setattr(distributed, "get_worker", lambda: me)
    monkeypatch.setattr(distributed, "get_client", lambda: client)
    assert ThreadBudget.for_task(n_cores=4) == ThreadBudget(workers=2, numba=2, blas=1)
    monkeypatch.setattr(distributed, "get_client", lambda: (_ for _ in ()).throw(ValueError("no scheduler")))
    assert ThreadBudget.for_task(n_cores=4) == ThreadBudget(workers=1, numba=4, blas=1)  # it cannot tell


def test_a_batch_on_two_dask_worker_processes_shares_the_cores(tmp_path):
    """Two worker processes of one thread on this host (as `dask worker --nworkers 2 --nthreads 1`
    starts them): each render reports half the cores as its numba threads and 2 workers."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        recs = batch(_scenes(tmp_path, "ab"), tmp_path / "out", scheduler=cl.scheduler_address, progress=False)
    assert [r["status"] for r in recs] == ["done", "done"], recs
    want = min(max(1, threads_mod.cores() // 2), numba.config.NUMBA_NUM_THREADS)
    for n in "ab":
        assert _threads(tmp_path / "out" / n) == {"numba": want, "blas": 1, "workers": 2}


def test_two_scenes_side_by_side_on_one_threaded_dask_worker(tmp_path, monkeypatch):
    """Two tasks of a Dask worker with two threads run in one process at once, and the compiled
    functions let go of the interpreter (nogil), so their kernels really run side by side: both
    renders finish, each with its share of numba threads (one), and two copies of one scene give
    the same numbers as each other."""
    distributed = pytest.importorskip("distributed")
    monkeypatch.setattr(threads_mod, "cores", lambda: 2)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cl, \
            distributed.Client(cl) as client:
        recs = batch(_scenes(tmp_path, "ab"), tmp_path / "out", executor=client.get_executor(), progress=False)
    assert [r["status"] for r in recs] == ["done", "done"], recs
    got = [json.loads((tmp_path / "out" / n / "summary.json").read_text()) for n in "ab"]
    for s in got:  # (the BLAS's count is the process's: a task ending gives it back under the other)
        assert s["threads"]["numba"] == 1 and s["threads"]["workers"] == 2
    a, b = ({"field": s["mean_field"], "steps": s["pathlines"]["work"]["steps"],
             "end": {k: s["pathlines"]["end_point_error"][k] for k in ("max", "median")}} for s in got)
    assert a == b and a["field"]["max_speed"] > 0


_WORKQUEUE = """
import threading, numpy as np
from cilia_runtime.threads import ThreadBudget, threadsafe_layer
from ciliary_carpet.stokes import stokeslet_velocity
rng = np.random.default_rng(1)
x, y, f = rng.random((300, 3)), rng.random((2000, 3)) + 2, rng.random((2000, 3))
out = {}
def task(k):
    with ThreadBudget(2, 1, 1).applied():
        for _ in range(100):
            out[k] = stokeslet_velocity(x, y, f)
ts = [threading.Thread(target=task, args=(k,)) for k in range(2)]
[t.start() for t in ts]
[t.join() for t in ts]
print(threadsafe_layer(), np.array_equal(out[0], out[1]))
"""


def test_tasks_in_threads_take_turns_under_the_workqueue_layer():
    """numba's workqueue layer aborts the process when two threads start parallel regions at
    once (the kernels let go of the interpreter, so they can): two tasks in threads, each under
    its budget, then run one after the other instead, and finish."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_THREADING_LAYER="workqueue")
    p = subprocess.run([sys.executable, "-c", _WORKQUEUE], capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.split() == ["False", "True"]  # the workqueue layer ran, both tasks got the same numbers


def test_render_takes_threads_from_the_command_line(tmp_path, capsys):
    """`ciliary-carpet render --threads 1` renders on one numba thread (summary.json says so) and
    gives the threads back afterwards; --threads 0 is bad input (exit 2)."""
    from ciliary_carpet.cli import main

    before = numba.get_num_threads()
    (scene,) = _scenes(tmp_path, ["solo"])
    assert main(["render", str(scene), "-o", str(tmp_path / "out"), "--threads", "1", "--json"]) == 0
    used = json.loads((tmp_path / "out" / "summary.json").read_text())["threads"]
    assert used["numba"] == 1 and used["workers"] == 1
    assert numba.get_num_threads() == before
    with pytest.raises(SystemExit) as e:
        main(["render", str(scene), "-o", str(tmp_path / "out2"), "--threads", "0"])
    assert e.value.code == 2 and "must be an integer >= 1" in capsys.readouterr().err
