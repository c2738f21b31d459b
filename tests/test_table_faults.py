"""Faults of the thrust-table build, the single-cilium command line and numba's cache (issue 43):
no silent wrong or stale number, no "internal error", no file touched that the toolkit did not
write. Temporary folders only; tiny grids."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

_COMPILE = ("from cilia_runtime.threads import threadsafe_layer\n"
            "threadsafe_layer()\n"  # compiles (or loads) one cached parallel kernel
            "print('ok')\n")


def _python(code: str, cache: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300,
                          cwd=ROOT)


@pytest.mark.parametrize("damage", ["truncated index", "garbled data"])
def test_a_damaged_numba_cache_file_is_discarded_and_rebuilt(tmp_path, damage):
    """A cache index (``.nbi``) cut short, or a data file (``.nbc``) overwritten with garbage: the
    next run compiles the function anew with one warning naming the file (never an
    UnpicklingError), and the run after it reads a sound cache again (no warning)."""
    cache = tmp_path / "cache"
    first = _python(_COMPILE, cache)
    assert first.returncode == 0 and first.stdout.strip() == "ok", first.stderr[-2000:]
    suffix = ".nbi" if damage == "truncated index" else ".nbc"
    files = sorted(cache.rglob(f"threads._one_region-*{suffix}"))
    assert files, sorted(str(p) for p in cache.rglob("*"))
    bad = files[0]
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 2] if damage == "truncated index" else b"\x80\x04garbage" * 10)
    second = _python(_COMPILE, cache)
    assert second.returncode == 0 and second.stdout.strip() == "ok", second.stderr[-2000:]
    assert "Traceback" not in second.stderr and "discarded" in second.stderr and bad.name in second.stderr
    assert len(second.stderr.strip().splitlines()) == 1, second.stderr
    third = _python(_COMPILE, cache)
    assert third.returncode == 0 and third.stderr.strip() == "", third.stderr


# ------------------------------------------------------------------ the build's files
FAST = dict(degree=6, n_phase=32, n_s=17, error_estimate=False)


def test_a_build_removes_only_its_own_row_files(tmp_path):
    """A user's file in an existing ``TABLE.parts/`` survives the build (which removes only the
    row files it wrote, and keeps the folder that is then not empty)."""
    from concurrent.futures import ThreadPoolExecutor

    from single_cilium.table import build_table

    path, parts = tmp_path / "t.nc", tmp_path / "t.nc.parts"
    parts.mkdir()
    (parts / "notes.txt").write_text("mine")
    build_table(200, 1, [150.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    assert path.is_file() and (parts / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in parts.iterdir()) == ["notes.txt"]


@pytest.mark.parametrize("bad, match", [
    (dict(degree=2, error_estimate=True), r"degree must be an integer in \[4, 32\].*degree - 2.*got 2"),
    (dict(degree=40), r"degree must be an integer in \[2, 32\].*double precision.*got 40"),
    (dict(n_phase=1), r"n_phase must be an integer >= 16, got 1"),
    (dict(n_phase=10**8), r"n_phase = 100000000 .* hours.*n_phase must be at most \d+"),
    (dict(n_s=1), r"n_s must be an integer >= 2"),
])
def test_bad_settings_are_refused_before_anything_is_created(tmp_path, bad, match):
    """Bad settings are refused, named, with the valid range, before the row folder is made."""
    from single_cilium.table import build_table

    with pytest.raises(ValueError, match=match):
        build_table(200, 1, [150.0], path=tmp_path / "t.nc", **{**FAST, **bad})
    assert list(tmp_path.iterdir()) == []


def test_an_existing_file_is_replaced_only_with_overwrite(tmp_path, capsys):
    """``single-cilium table -o data.nc`` over an existing file (not a table) refuses it, exit 2,
    before any work; with ``--overwrite`` it is replaced."""
    from single_cilium.cli import main

    out = tmp_path / "data.nc"
    out.write_text("my data")
    argv = ["table", "--chi-E", "200", "--eta", "1", "--chi-N", "150", "--degree", "6", "--n-phase", "32",
            "--no-error-estimate", "--quiet", "-o", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and str(out) in err and "--overwrite" in err, err
    assert out.read_text() == "my data" and sorted(p.name for p in tmp_path.iterdir()) == ["data.nc"]
    assert main(argv + ["--overwrite"]) == 0
    from single_cilium.table import ThrustTable

    assert ThrustTable.load(out).ds.chi_N.values.tolist() == [150.0]


# ------------------------------------------------------------------ a scene's [table.build]
TINY = ('[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 3\nperiods = 0.5\nfield_shape = [6, 6]\nsnapshots = 0\n'
        'frames = 1\npreview = false\n')


@pytest.mark.slow  # 20 s: a real (failing) table build; the default run stays under 10 minutes on 2 cores
def test_a_table_build_that_cannot_converge_exits_3_naming_the_scene_keys(tmp_path, monkeypatch, capsys):
    """A render whose ``[table.build]`` meets a cycle that does not converge exits 3 with one line
    naming the row and the ``[table.build]`` keys to change (never exit 1 "internal error"); the
    rows finished before it are kept for the rerun."""
    from concurrent.futures import ThreadPoolExecutor

    import single_cilium.table as table_mod
    from ciliary_carpet.cli import main
    from single_cilium.cycle import CycleError

    real_build, real_cycle = table_mod.build_table, table_mod.limit_cycle

    def failing(p, **kw):
        if p.chi_N > 0:
            raise CycleError(f"{p}: shooting did not converge (injected); give a seed from a neighbouring chi_N or "
                             "raise the degree", 0.0)
        return real_cycle(p, **kw)

    monkeypatch.setattr(table_mod, "limit_cycle", failing)
    monkeypatch.setattr(table_mod, "build_table",
                        lambda *a, **kw: real_build(*a, executor=ThreadPoolExecutor(1), **kw))
    scene = tmp_path / "s.toml"
    # a still-fluid build (coupling = "none"): its rows are row_<i>.nc
    scene.write_text(TINY.replace("[carpet]\n", '[carpet]\ncoupling = "none"\n') + '[table]\nfile = "t.nc"\n'
                     '[table.build]\nn = 3\ndegree = 4\n')
    code = main(["render", str(scene), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 3, err
    errors = [line for line in err.splitlines() if line.startswith("ciliary-carpet:")]  # not the progress lines
    assert len(errors) == 1 and "Traceback" not in err and "internal error" not in err and "give a seed" not in err, err
    assert "table.build.n (now 3" in err and "table.build.degree (now 4)" in err and "chi_N = " in err, err
    assert not (tmp_path / "t.nc").exists() and (tmp_path / "t.nc.parts" / "row_0.nc").is_file()


def test_table_build_degree_below_the_error_estimate_is_a_scene_error(tmp_path):
    """``[table.build] degree = 2`` is refused when the scene is read, naming the key and its range
    (the build's error estimate compares with degree - 2), before anything is created."""
    from ciliary_carpet.scenes.scene import SceneError, load_scene

    scene = tmp_path / "s.toml"
    scene.write_text(TINY + '[table]\nfile = "t.nc"\n[table.build]\nn = 3\ndegree = 2\n')
    with pytest.raises(SceneError, match=r"degree.*\[4, 32\]|degree.*>= 4") as e:
        load_scene(scene)
    assert "got 0" not in str(e.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.toml"]


# ------------------------------------------------------------------ single-cilium: options, signals
@pytest.mark.parametrize("argv, names", [
    (["cycle", "--chi-E", "200", "--eta", "1", "--chi-N", "60", "--degree", "1000"], ["--degree", "[4, 32]"]),
    (["cycle", "--chi-E", "200", "--eta", "1", "--chi-N", "1e300"], ["--chi-N", "at most"]),
    (["cycle", "--chi-E", "200", "--eta", "1", "--chi-N", "60", "--n-phase", "100000000"],
     ["--n-phase", "hours", "at most"]),
    (["stability", "--chi-E", "200", "--eta", "1", "--chi-N", "1e300"], ["--chi-N", "at most"]),
    (["simulate", "--chi-E", "200", "--eta", "1", "--chi-N", "1e300", "--t-end", "1"], ["--chi-N", "at most"]),
    (["table", "--chi-E", "200", "--eta", "1", "--chi-N", "0:100:3", "--degree", "2"], ["--degree", "[4, 32]"]),
    (["table", "--chi-E", "200", "--eta", "1", "--chi-N", "0:100:3", "--n-phase", "1"], ["--n-phase", ">= 16"]),
])
def test_options_beyond_reason_are_refused_up_front_naming_the_option(tmp_path, capsys, argv, names):
    """A degree, step count or curvature whose cost is beyond reason (or below what the method
    needs) is refused before any work: exit 2, one line naming the option and its range or the
    largest sensible value; nothing is created."""
    from single_cilium.cli import main

    if argv[0] == "table":
        argv = argv + ["-o", str(tmp_path / "t.nc"), "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "internal error" not in err, err
    assert all(n in err for n in names), err
    assert list(tmp_path.iterdir()) == []


def test_a_signal_inside_a_compiled_kernel_waits_for_it_to_return():
    """A SIGTERM that arrives while the main thread is inside a compiled kernel (which may call
    back into the interpreter) is delivered once the kernel has returned, as Terminated."""
    import signal
    import time

    from cilia_runtime.signals import Terminated, native_call, terminate_as_interrupt

    with pytest.raises(Terminated):
        with terminate_as_interrupt():
            with native_call():
                os.kill(os.getpid(), signal.SIGTERM)
                end = time.monotonic() + 0.3
                while time.monotonic() < end:  # Python code runs here: the handler is called, and waits
                    pass
                inside = "no signal inside"
            assert inside == "no signal inside"
            time.sleep(5.0)  # the signal comes again within 50 ms


def test_a_signal_that_comes_back_through_compiled_code_exits_as_the_signal(monkeypatch, capsys):
    """A compiled function that returns with the signal's exception set (``SystemError: ...
    returned a result with an exception set``) ends the command as the signal does: 143 and one
    line, never "internal error"."""
    import single_cilium.cli as cli
    from cilia_runtime.signals import Terminated

    def interrupted(args):
        try:
            raise Terminated(15)
        except Terminated as exc:
            raise SystemError("CPUDispatcher(radau_steps) returned a result with an exception set") from exc

    monkeypatch.setattr(cli, "cmd_cycle", interrupted)
    assert cli.main(["cycle", "--chi-E", "200", "--eta", "1", "--chi-N", "60"]) == 143
    err = capsys.readouterr().err
    assert err.strip() == "single-cilium cycle: terminated by SIGTERM", err


@pytest.mark.slow
@pytest.mark.parametrize("signame, delay", [("SIGTERM", 1.8), ("SIGINT", 2.1), ("SIGHUP", 2.4), ("SIGTERM", 3.0)])
def test_a_signal_during_a_cycle_exits_with_its_status_and_one_line(signame, delay):
    """SIGTERM, SIGINT or SIGHUP at staggered times during ``single-cilium cycle`` (the first
    calls of its compiled kernels included, where a signal could crash the process or give a
    SystemError): exit 128 + signum with one line, or the default action's status when it lands
    before the handlers are installed; never a crash or a traceback (about 15 s each)."""
    import signal
    import time

    sig = getattr(signal, signame)  # one signal at one time per case: the cases together cover the window
    proc = subprocess.Popen([sys.executable, "-m", "single_cilium.cli", "cycle", "--chi-E", "200", "--eta", "1",
                             "--chi-N", "60", "--degree", "24", "--n-phase", "256"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode in (128 + sig, -sig), (delay, proc.returncode, err[-2000:])
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 1, (delay, err[-2000:])


@pytest.mark.parametrize("argv", [
    ["simulate", "--chi-E", "200", "--eta", "1", "--t-end", "0.01", "--n-out", "2", "--degree", "6",
     "--no-error-estimate", "--quiet", "-o", "{f}"],
    ["cycle", "--chi-E", "200", "--eta", "1", "--chi-N", "150", "--degree", "6", "--n-phase", "32",
     "--no-error-estimate", "-o", "{f}"],
    ["map", "--chi-N", "50", "--chi-E", "190,210", "--eta", "1,2", "--degree", "6", "--quiet", "--png", "{f}"],
])
def test_every_single_cilium_output_replaces_a_file_only_with_overwrite(tmp_path, capsys, argv):
    """``-o`` (and ``--png``) of every single-cilium command refuses an existing file before any
    work, exit 2 with one line naming it and ``--overwrite``; the file is unchanged."""
    from single_cilium.cli import main

    mine = tmp_path / "mine.dat"
    mine.write_text("my data")
    assert main([a.format(f=mine) for a in argv]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and str(mine) in err and "--overwrite" in err, err
    assert mine.read_text() == "my data" and sorted(p.name for p in tmp_path.iterdir()) == ["mine.dat"]


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux)")
def test_a_standard_output_that_cannot_be_written_is_named():
    """``single-cilium ... > /dev/full`` exits 2 with one line naming standard output (the
    result was computed; only printing it failed), never a traceback."""
    with open("/dev/full", "w") as full:
        p = subprocess.run([sys.executable, "-m", "single_cilium.cli", "equilibrium", "--chi-E", "200", "--chi-N",
                            "100"], stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip() == "single-cilium equilibrium: cannot write to standard output: No space left on device"
