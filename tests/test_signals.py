"""SIGTERM and SIGHUP (kill, Slurm, systemd, Docker, a closed terminal) are handled like Ctrl-C
(issue 21, point 5): sent to the parent process alone of a real command, the workers are
stopped, the staging folder is removed, one line is printed and the exit status is 128 + signum."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

psutil = pytest.importorskip("psutil")

ROOT = Path(__file__).resolve().parent.parent
TINY = ('[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 3\nperiods = 0.5\nfield_shape = [6, 6]\nsnapshots = 0\n'
        'frames = 1\npreview = false\n')
ENV = dict(os.environ, PYTHONPATH=str(ROOT))


def _scene(folder: Path, body: str, name: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / name
    p.write_text(body)
    return p


def _wait_for(cond, limit: float) -> bool:
    end = time.monotonic() + limit
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.05)
    return False


@pytest.fixture
def started():
    """Popen objects a test starts: killed with their descendants at teardown, whatever failed."""
    procs: list = []
    yield procs
    for proc in procs:
        kids = _descendants(proc.pid)
        if proc.poll() is None:
            proc.kill()
        for k in kids:
            try:
                k.kill()
            except psutil.NoSuchProcess:
                pass
        try:
            proc.communicate(timeout=10)
        except (subprocess.TimeoutExpired, ValueError):
            pass


def _start(started: list, args: list) -> subprocess.Popen:
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV, text=True)
    started.append(proc)
    return proc


def _descendants(pid: int) -> list:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def _signal_and_check(proc: subprocess.Popen, sig: int, kids: list) -> str:
    """Send ``sig`` to ``proc`` alone; return its stderr after checking the exit status, the one
    line, and that none of ``kids`` (its descendants when it was signalled) outlives it."""
    t = time.monotonic()
    proc.send_signal(sig)
    try:
        try:
            _, err = proc.communicate(timeout=40)  # orphans holding its stderr would block here
        except subprocess.TimeoutExpired:
            pytest.fail(f"no exit within 40 s of {signal.Signals(sig).name} (orphaned workers?)")
        assert proc.returncode == 128 + sig, err
        assert time.monotonic() - t < 30
        lines = [ln for ln in err.strip().splitlines() if ln.strip() and "%|" not in ln]  # not the progress bars
        assert "Traceback" not in err and len(lines) == 1, err
        assert signal.Signals(sig).name in lines[0], err
        _, alive = psutil.wait_procs(kids, timeout=10)
        assert not [p for p in alive if p.is_running() and p.status() != psutil.STATUS_ZOMBIE], alive
    finally:  # never leave the processes this test started behind, whatever failed
        for p in kids:
            try:
                p.kill()
            except psutil.NoSuchProcess:
                pass
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    return err


def test_sigterm_to_a_batch_stops_its_workers_and_removes_staging(tmp_path, started):
    slow = TINY.replace("periods = 0.5", "periods = 300")
    scenes = [_scene(tmp_path, slow, f"{n}.toml") for n in "ab"]
    out = tmp_path / "out"
    proc = _start(started, [sys.executable, "-m", "ciliary_carpet.cli", "batch", *map(str, scenes), "-o", str(out),
                            "-j", "2"])
    # both workers rendering: a staging folder each
    assert _wait_for(lambda: out.is_dir() and len([x for x in out.iterdir() if x.name.endswith(".partial")]) == 2,
                     90), proc.stderr
    kids = _descendants(proc.pid)
    assert len(kids) >= 3  # the fork server and two workers
    err = _signal_and_check(proc, signal.SIGTERM, kids)
    assert "terminated" in err
    # staging folders removed, nothing placed: only the batch's index, which lists both as interrupted
    assert not out.exists() or {x.name for x in out.iterdir()} <= {"batch.json", "batch.md"}
    if (out / "batch.json").exists():
        assert {r["status"] for r in json.loads((out / "batch.json").read_text())["scenes"]} == {"interrupted"}


def test_sighup_to_a_render_removes_its_staging(tmp_path, started):
    p = _scene(tmp_path, TINY.replace("periods = 0.5", "periods = 200").replace("shape = [2, 2]", "shape = [6, 6]"),
               "s.toml")
    proc = _start(started, [sys.executable, "-m", "ciliary_carpet.cli", "render", str(p), "-o", str(tmp_path / "o")])
    assert _wait_for(lambda: any(x.name.endswith(".partial") for x in tmp_path.iterdir()), 60)
    time.sleep(0.3)
    _signal_and_check(proc, signal.SIGHUP, _descendants(proc.pid))
    assert not (tmp_path / "o").exists() and not [x for x in tmp_path.iterdir() if x.name.startswith(".")]


def test_sigterm_to_a_table_build_stops_its_pool_workers(tmp_path, started):
    out = tmp_path / "t.nc"
    args = [sys.executable, "-m", "single_cilium.cli", "table", "--chi-E", "200", "--eta", "1", "--chi-N",
            "100:112:25", "--degree", "6", "--n-phase", "32", "--no-error-estimate", "-o", str(out), "--quiet"]
    proc = _start(started, args)
    parts = tmp_path / "t.nc.parts"
    assert _wait_for(lambda: parts.is_dir() and any(parts.glob("row_*.nc")), 120)
    kids = _descendants(proc.pid)
    assert kids  # the pool's workers
    err = _signal_and_check(proc, signal.SIGTERM, kids)
    assert "single-cilium table: terminated by SIGTERM" in err
    assert not out.exists() and 0 < len(list(parts.glob("row_*.nc"))) < 25  # finished rows kept for the resume


def test_a_signal_inside_a_compiled_path_line_kernel_is_reported_as_the_signal(tmp_path, monkeypatch, capsys):
    """A signal handled while a numba function runs surfaces as a SystemError ("returned a result
    with an exception set") carrying the interrupt: a pool's task relabelling keeps the interrupt,
    and the command line exits 128 + signum with its one line, not "internal error" (CI saw exit 1
    when a SIGHUP landed in the path lines' reference run)."""
    import ciliary_carpet.cli as cli
    from cilia_runtime.pool import _relabel
    from cilia_runtime.signals import Terminated

    def kernel_hit():
        try:
            raise Terminated(signal.SIGHUP)
        except KeyboardInterrupt as k:
            raise SystemError("CPUDispatcher(<function _lists>) returned a result with an exception set") from k

    try:
        kernel_hit()
    except SystemError as exc:
        got = _relabel(exc, "path lines' error estimate: the reference run")
    assert isinstance(got, Terminated) and got.signum == signal.SIGHUP
    assert isinstance(_relabel(ValueError("bad"), "task"), ValueError)  # anything else keeps its label

    monkeypatch.setattr(cli, "_cmd_render", lambda a: kernel_hit())
    scene = tmp_path / "s.toml"
    scene.write_text('name = "s"\n')
    assert cli.main(["render", str(scene), "-o", str(tmp_path / "o")]) == 128 + signal.SIGHUP
    err = capsys.readouterr().err
    assert "internal error" not in err and "SIGHUP" in err, err
