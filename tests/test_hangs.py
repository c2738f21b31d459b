"""Hangs (issue 21, point 7): a --scheduler address that is not a Dask scheduler (an HTTP
server, as the dashboard's port is) fails within the bounded wait with a clear message, for
``batch`` and ``table``; an input path that is not a regular file (a named pipe) is refused at
once. Each command runs in a subprocess with a time limit, so that a regression fails instead
of hanging the suite. Loopback addresses only."""
import http.server
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
TINY = ('[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 3\nperiods = 0.5\nfield_shape = [6, 6]\nsnapshots = 0\n'
        'frames = 1\npreview = false\n')


@pytest.fixture
def http_port():
    """An HTTP server on a free loopback port (what a Dask dashboard is), for the test's duration."""
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    srv.daemon_threads = True
    t = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
    t.start()
    yield srv.server_address[1]
    srv.shutdown()
    srv.server_close()


def _run(args, limit: float = 60.0) -> tuple[subprocess.CompletedProcess, float]:
    t = time.monotonic()
    try:
        r = subprocess.run([sys.executable, "-m", *map(str, args)], capture_output=True, text=True, env=ENV,
                           timeout=limit)
    except subprocess.TimeoutExpired:
        pytest.fail(f"no answer within {limit:g} s: {' '.join(map(str, args))}")
    return r, time.monotonic() - t


def _one_line(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip() and "it/s]" not in ln and "%|" not in ln]  # not the bars
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("command", ["batch", "table"])
def test_scheduler_that_is_not_dask_fails_within_the_wait(tmp_path, http_port, command):
    address = f"tcp://127.0.0.1:{http_port}"
    if command == "batch":
        scene = tmp_path / "s.toml"
        scene.write_text(TINY)
        args = ["ciliary_carpet.cli", "batch", scene, "-o", tmp_path / "out", "--scheduler", address,
                "--scheduler-timeout", "3"]
    else:
        args = ["single_cilium.cli", "table", "--chi-E", "200", "--eta", "1", "--chi-N", "100:112:3", "--degree", "6",
                "--quiet", "-o", tmp_path / "t.nc", "--scheduler", address, "--scheduler-timeout", "3"]
    r, took = _run(args)
    assert r.returncode == 2, r.stderr
    line = _one_line(r.stderr)
    assert address in line and "Dask scheduler" in line and "3 s" in line, line
    assert took < 40
    assert not (tmp_path / "out").exists() and not (tmp_path / "t.nc").exists()


def test_named_pipes_as_inputs_are_refused_at_once(tmp_path):
    folder = tmp_path / "scenes"
    folder.mkdir()
    os.mkfifo(folder / "table.nc")
    os.mkfifo(folder / "ctl.csv")
    os.mkfifo(folder / "pipe.toml")
    (folder / "t.toml").write_text(TINY + '[table]\nfile = "table.nc"\n')
    (folder / "c.toml").write_text(TINY + '[target]\nkind = "points"\nfile = "ctl.csv"\n')
    for scene, key in (("t.toml", "table.file"), ("c.toml", "target.file"), ("pipe.toml", "pipe.toml")):
        r, took = _run(["ciliary_carpet.cli", "render", folder / scene, "-o", tmp_path / "o"], limit=30)
        assert r.returncode == 2, r.stderr
        line = _one_line(r.stderr)
        assert key in line and "not a regular file" in line, line
        assert not (tmp_path / "o").exists()
