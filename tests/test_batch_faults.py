"""The batch, the command line's outputs and the output paths under the faults of issue 43: up to
date means the same contents of every input; --backend fmm renders; a link or a '..' at -o; a
standard output that cannot be written; a scheduler without workers; SIGTERM to a batch; the
batch's verdicts and index."""
import errno
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

import ciliary_carpet.batch as batch_module
from ciliary_carpet.batch import batch
from ciliary_carpet.cli import main as carpet_main
from ciliary_carpet.output.folder import MANIFEST, is_complete
from ciliary_carpet.render import RenderError
from ciliary_carpet.scenes.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
OUTPUT = ('[output]\nn_seeds = 3\nperiods = 0.5\nfield_shape = [6, 6]\nsnapshots = 0\nframes = 1\npreview = false\n'
          'ftle = false\n')
TINY = '[carpet]\nshape = [2, 2]\n' + OUTPUT
POINTS = '[carpet]\nshape = [2, 2]\n[target]\nkind = "points"\nfile = "t.csv"\nresidual = 1.0\n' + OUTPUT
CSV = "x,y,u,v\n0.5,0.5,0,-1\n1.5,0.5,0,-1\n"


def _scene(folder: Path, body: str = TINY, name: str = "s.toml", csv: str | None = None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    if csv is not None:
        (folder / "t.csv").write_text(csv)
    p = folder / name
    p.write_text(body)
    return p


def _batch(scenes, out, **kw) -> list:
    with ThreadPoolExecutor(1) as ex:
        return batch([str(s) for s in scenes], out, executor=ex, progress=False, **kw)


def _in_process(tasks, jobs, on_done, grace=2.5, on_start=None):
    """batch._run_local's stand-in: the tasks one after another in this process."""
    for t in tasks:
        if on_start is not None:
            on_start(t)
        on_done(batch_module._render_one(*t))


# ------------------------------------------------------------------------------ 1: up to date = same contents
def test_a_target_file_edited_with_an_older_time_renders_that_scene_again_and_only_it(tmp_path):
    a = _scene(tmp_path / "a", POINTS, "a.toml", csv=CSV)
    b = _scene(tmp_path / "b", POINTS, "b.toml", csv=CSV)
    out = tmp_path / "out"
    assert [r["status"] for r in _batch([a, b], out)] == ["done", "done"]
    assert [r["status"] for r in _batch([a, b], out)] == ["skipped", "skipped"]
    csv = tmp_path / "a" / "t.csv"
    csv.write_text(CSV.replace("1.5,0.5,0,-1", "1.5,0.5,0.2,-1"))
    os.utime(csv, (1, 1))  # older than the render: its contents decide
    assert not is_complete(out / "a", scene=load_scene(a))
    ra, rb = _batch([a, b], out)  # no overwrite: the edited scene alone is rendered again
    assert ra["status"] == "done" and "target.file" in ra["message"], ra
    assert rb["status"] == "skipped", rb
    assert is_complete(out / "a", scene=load_scene(a))


def test_every_input_a_scene_names_is_hashed_and_a_replaced_table_is_noticed(tmp_path):
    import shutil

    from ciliary_carpet.output.folder import input_records, inputs_differ, scene_inputs
    from single_cilium.lookup import DEFAULT_FILE, DEFAULT_FLOW_FILE

    shipped = ROOT / "single_cilium" / "data" / DEFAULT_FILE
    shutil.copy(shipped, tmp_path / "tab.nc")
    p = _scene(tmp_path, POINTS.replace("[target]", '[table]\nfile = "tab.nc"\n[target]'), csv=CSV)
    scene = load_scene(p)
    assert set(scene_inputs(scene)) == {"scene", "table.file", "target.file"}
    # file = "default": the shipped table the carpet reads, over the flow for the default coupled carpet
    assert scene_inputs(load_scene(_scene(tmp_path, TINY, "d.toml")))["table.file"].name == DEFAULT_FLOW_FILE
    out = tmp_path / "o"
    out.mkdir()
    (out / MANIFEST).write_text(json.dumps({"files": {}, "inputs": input_records(scene)}))
    assert inputs_differ(out, scene) == []
    data = bytearray((tmp_path / "tab.nc").read_bytes())
    data[-1] ^= 1  # another table, same size
    (tmp_path / "tab.nc").write_bytes(bytes(data))
    os.utime(tmp_path / "tab.nc", (1, 1))
    assert inputs_differ(out, scene) == ["table.file"]


def test_a_render_without_recorded_inputs_is_not_up_to_date_and_is_rendered_again(tmp_path):
    p = _scene(tmp_path, TINY)
    out = tmp_path / "out"
    assert _batch([p], out)[0]["status"] == "done"
    m = out / "s" / MANIFEST
    body = json.loads(m.read_text())
    del body["inputs"]  # as written before inputs were recorded
    m.write_text(json.dumps(body))
    assert not is_complete(out / "s", scene=load_scene(p))
    rec = _batch([p], out)[0]
    assert rec["status"] == "done" and "inputs changed" in rec["message"], rec
    assert "inputs" in json.loads(m.read_text())


def test_changed_inputs_never_touch_a_folder_holding_someone_elses_file(tmp_path):
    p = _scene(tmp_path, TINY)
    out = tmp_path / "out"
    assert _batch([p], out)[0]["status"] == "done"
    (out / "s" / "notes.txt").write_text("mine")
    before = {x.name: x.read_bytes() for x in (out / "s").iterdir()}
    p.write_text(TINY.replace("n_seeds = 3", "n_seeds = 4"))
    rec = _batch([p], out)[0]
    assert rec["status"] == "failed" and "already holds results" in rec["message"], rec
    assert {x.name: x.read_bytes() for x in (out / "s").iterdir()} == before


# ------------------------------------------------------------------------------ 2: --backend fmm
def test_backend_fmm_renders_and_the_summary_says_where_the_sums_ran(tmp_path, capsys):
    pytest.importorskip("fmm3dpy")
    p = _scene(tmp_path, TINY)
    assert carpet_main(["--backend", "fmm", "render", str(p), "-o", str(tmp_path / "o")]) == 0, \
        capsys.readouterr().err
    backend = json.loads((tmp_path / "o" / "summary.json").read_text())["backend"]
    assert backend.startswith("fmm") and "ranged sums: direct" in backend and "kernels other than" in backend


# ------------------------------------------------------------------------------ 3: links and '..' at -o
def test_design_never_replaces_a_symbolic_link(tmp_path, capsys):
    p = _scene(tmp_path, POINTS, csv=CSV)
    link = tmp_path / "link.nc"
    link.symlink_to("nowhere.nc")
    for extra in ([], ["--overwrite"]):
        assert carpet_main(["design", str(p), "-o", str(link), *extra]) == 2
        err = capsys.readouterr().err
        assert "symbolic link" in err and str(link) in err and str(p) not in err, err
        assert link.is_symlink() and os.readlink(link) == "nowhere.nc"
    target = tmp_path / "real.nc"
    target.write_text("old")
    link.unlink()
    link.symlink_to("real.nc")
    assert carpet_main(["design", str(p), "-o", str(link), "--overwrite"]) == 0  # written through the link
    assert "symbolic link" in capsys.readouterr().out
    assert link.is_symlink() and target.read_bytes()[:4] == b"\x89HDF"


def test_dotdot_after_a_missing_folder_makes_no_folder(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    p = _scene(tmp_path, POINTS, csv=CSV)
    assert carpet_main(["design", str(p), "-o", "dd/sub/../../o.nc"]) == 2
    assert "'..'" in capsys.readouterr().err
    assert carpet_main(["render", str(p), "-o", "dd/sub/../../o"]) == 2
    assert "'..'" in capsys.readouterr().err
    assert not (tmp_path / "dd").exists() and not (tmp_path / "o").exists() and not (tmp_path / "o.nc").exists()
    from ciliary_carpet.output.folder import check_parents

    (tmp_path / "dd" / "sub").mkdir(parents=True)
    check_parents("dd/sub/../../o")  # every folder before '..' exists: the path is the user's
    with pytest.raises(RenderError, match="does not exist"):
        check_parents("dd/x/y/../o")


# ------------------------------------------------------------------------------ 5: standard output
class _FullStdout(io.StringIO):
    def write(self, text):
        raise OSError(errno.ENOSPC, "No space left on device")


def test_a_standard_output_that_cannot_be_written_is_named_not_the_scene(tmp_path, capsys, monkeypatch):
    p = _scene(tmp_path, TINY)
    monkeypatch.setattr(sys, "stdout", _FullStdout())
    assert carpet_main(["render", str(p), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "cannot write to standard output: No space left on device" in err and str(p) not in err, err
    assert "is complete" in err
    assert is_complete(tmp_path / "o", scene=load_scene(p))


# ------------------------------------------------------------------------------ 4: a scheduler without workers
def test_a_scheduler_without_workers_is_said_and_the_wait_is_bounded(tmp_path, caplog):
    distributed = pytest.importorskip("distributed")
    from cilia_runtime.scheduler import SchedulerError

    p = _scene(tmp_path, TINY)
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster:
        got: list = []

        def run():
            try:
                batch([str(p)], tmp_path / "out", scheduler=cluster.scheduler_address, scheduler_timeout=1.5,
                      progress=False)
            except Exception as exc:  # noqa: BLE001
                got.append(exc)

        t = threading.Thread(target=run, daemon=True)
        start = time.monotonic()
        t.start()
        t.join(30)
        assert not t.is_alive(), "the batch waits for ever for a worker"
    assert time.monotonic() - start < 30
    assert got and isinstance(got[0], SchedulerError) and "no workers" in str(got[0]), got
    assert "has 0 worker" in caplog.text


def test_a_scheduler_without_dask_names_the_extra(tmp_path, capsys, monkeypatch):
    """Dask is an optional extra: without it, --scheduler is one line naming the extra, exit 2."""
    for name in ("distributed", "distributed.comm"):
        monkeypatch.setitem(sys.modules, name, None)  # import fails as if not installed
    p = _scene(tmp_path, TINY)
    code = carpet_main(["batch", str(p), "-o", str(tmp_path / "out"), "--scheduler", "tcp://127.0.0.1:1"])
    err = capsys.readouterr().err
    assert code == 2 and "pip install 'cilia-flow[dask]'" in err and "Traceback" not in err, err


# ------------------------------------------------------------------------------ 7: verdicts, index, Ctrl-C
def test_a_batch_prints_each_verdict_and_writes_its_index(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(batch_module, "_run_local", _in_process)
    a = _scene(tmp_path / "a", POINTS, "a.toml", csv=CSV)
    b = _scene(tmp_path / "b", TINY, "b.toml")
    out = tmp_path / "out"
    assert carpet_main(["batch", str(a), str(b), "-o", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "target met: rms residual" in lines[0] and "<= 1 allowed" in lines[0], lines
    assert "no target" in lines[1], lines
    idx = json.loads((out / "batch.json").read_text())["scenes"]
    assert [r["status"] for r in idx] == ["done", "done"] and idx[0]["verdict"] == "met"
    assert idx[0]["residual"] < idx[0]["threshold"] and idx[0]["folder"] == str(out / "a")
    assert "| " + str(a) + " | done | target met" in (out / "batch.md").read_text()


def test_an_interrupted_batch_says_what_finished_and_what_did_not(tmp_path, capsys, monkeypatch):
    def one_then_ctrl_c(tasks, jobs, on_done, grace=2.5, on_start=None):
        on_start(tasks[0])
        on_done(batch_module._render_one(*tasks[0]))
        on_start(tasks[1])
        raise KeyboardInterrupt

    monkeypatch.setattr(batch_module, "_run_local", one_then_ctrl_c)
    scenes = [_scene(tmp_path, TINY, f"{n}.toml") for n in "abc"]
    out = tmp_path / "out"
    assert carpet_main(["batch", *map(str, scenes), "-o", str(out)]) == 130
    err = capsys.readouterr().err.strip().splitlines()[-1]  # one line
    assert f"interrupted; finished: {scenes[0]} (done; no target); not finished: {scenes[1]}, {scenes[2]}" in err, err
    idx = json.loads((out / "batch.json").read_text())["scenes"]
    assert [r["status"] for r in idx] == ["done", "interrupted", "not started"]


def test_a_batch_index_never_replaces_a_file_it_did_not_write(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(batch_module, "_run_local", _in_process)
    out = tmp_path / "out"
    out.mkdir()
    (out / "batch.md").write_text("my notes")
    p = _scene(tmp_path, TINY)
    assert carpet_main(["batch", str(p), "-o", str(out)]) == 0
    assert (out / "batch.md").read_text() == "my notes" and (out / "batch.json").is_file()


# ------------------------------------------------------------------------------ 6: SIGTERM to a batch
STUBBORN = """
import os, signal, subprocess, sys, time

def task(folder):
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, signal.SIG_IGN)
    kid = subprocess.Popen([sys.executable, "-c", "import signal, time; signal.signal(signal.SIGINT, "
                            "signal.SIG_IGN); signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(60)"])
    with open(os.path.join(folder, f"pids.{os.getpid()}"), "w") as fh:
        fh.write(f"{os.getpid()} {kid.pid}")
    time.sleep(60)
    return {}
"""
RUN = """
import sys
from ciliary_carpet.batch import _run_local
from cilia_runtime.signals import terminate_as_interrupt
import stubborn
with terminate_as_interrupt():
    _run_local([(sys.argv[1],), (sys.argv[1],)], 2, print, func=stubborn.task)
"""


def test_sigterm_to_a_batch_kills_workers_that_ignore_it_and_what_they_started(tmp_path):
    """Workers that ignore SIGINT and SIGTERM (a render in numba's compiler, say), each with a
    process of its own that ignores them too: 4 s after SIGTERM to the batch none is left."""
    psutil = pytest.importorskip("psutil")
    (tmp_path / "stubborn.py").write_text(STUBBORN)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(tmp_path)]))
    proc = subprocess.Popen([sys.executable, "-c", RUN, str(tmp_path)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    pids: list = []
    try:
        end = time.monotonic() + 60
        while len(pids) < 4 and time.monotonic() < end:
            pids = [int(x) for f in tmp_path.glob("pids.*") for x in f.read_text().split()]
            time.sleep(0.05)
        assert len(pids) == 4, proc.stderr
        procs = [psutil.Process(x) for x in pids]
        proc.send_signal(signal.SIGTERM)
        time.sleep(4.0)
        alive = [k for k in procs if k.is_running() and k.status() != psutil.STATUS_ZOMBIE]
        assert proc.poll() is not None and not alive, (proc.poll(), alive)
    finally:
        for x in pids:
            try:
                os.kill(x, signal.SIGKILL)
            except ProcessLookupError:
                pass
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=10)


@pytest.mark.slow  # 19 s on 2 cores: two bundled scenes start rendering first
def test_sigterm_to_a_batch_leaves_no_process_of_it_after_4_s(tmp_path):
    psutil = pytest.importorskip("psutil")
    out = tmp_path / "out"
    scenes = [str(ROOT / "designs" / f"{n}.toml") for n in ("uniform_deflection", "focusing")]
    proc = subprocess.Popen([sys.executable, "-m", "ciliary_carpet.cli", "batch", *scenes, "-o", str(out), "-j", "2",
                             "--reduced"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONPATH=str(ROOT)))
    seen: dict = {}  # every descendant seen (psutil tells a reused pid from the process)

    def look():
        try:
            seen.update({k.pid: k for k in psutil.Process(proc.pid).children(recursive=True)})
        except psutil.NoSuchProcess:
            pass

    try:
        end = time.monotonic() + 90
        while time.monotonic() < end:  # both scenes rendering: each holds its folder's lock
            look()
            if out.is_dir() and len([x for x in out.iterdir() if x.name.endswith(".ciliary-carpet.lock")]) == 2:
                break
            time.sleep(0.05)
        else:
            pytest.fail("the two renders did not start")
        time.sleep(1.5)  # into their work
        look()
        proc.send_signal(signal.SIGTERM)
        t = time.monotonic()
        while time.monotonic() - t < 1.0:  # processes started while it stops count too
            look()
            time.sleep(0.05)
        time.sleep(max(0.0, 4.0 - (time.monotonic() - t)))
        alive = [k for k in seen.values() if k.is_running() and k.status() != psutil.STATUS_ZOMBIE]
        assert proc.poll() == 128 + signal.SIGTERM and not alive, (proc.poll(), alive)
        assert len(seen) >= 3  # the fork server, two workers (and their own pools and servers)
    finally:
        for k in seen.values():
            try:
                k.kill()
            except psutil.NoSuchProcess:
                pass
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=10)
