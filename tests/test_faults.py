"""Fault injection: what a user can rely on under bad input, hostile scene files and dying
workers (issue 11, one test per numbered defect). Temporary folders only, tiny carpets."""
import json
import math
import os
import signal
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import ciliary_carpet.batch as carpet_batch
import ciliary_carpet.cli as carpet_cli
from ciliary_carpet.batch import batch
from ciliary_carpet.cli import main as carpet_main
from ciliary_carpet.render import MANIFEST, ResourceError, check_resources, render
from ciliary_carpet.scenes.scene import SceneError, load_scene, scene_from_dict
from single_cilium import CiliumParams, equilibrium, equilibrium_shape
from single_cilium.cli import main as cilium_main

ROOT = Path(__file__).resolve().parent.parent
TINY = ('[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 3\nperiods = 0.5\nfield_shape = [6, 6]\nsnapshots = 0\n'
        'frames = 1\npreview = false\n')


def _strict(text: str):
    """json.loads that rejects NaN / Infinity (what strict parsers do)."""
    def bad(c):
        raise ValueError(f"non-standard JSON constant {c}")

    return json.loads(text, parse_constant=bad)


def _scene(folder: Path, body: str = TINY, name: str = "s.toml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / name
    p.write_text(body)
    return p


def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _carpet(capsys, *argv):
    code = carpet_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _cilium(capsys, *argv):
    code = cilium_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


# ------------------------------------------------------------------------------ 1: outside the folder
@pytest.mark.parametrize("name", ["../victim", "/tmp/victim-abs", "a/b", "..", ".hidden"])
def test_1_scene_name_is_a_file_name_not_a_path(tmp_path, name):
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "precious.txt").write_text("mine")
    p = _scene(tmp_path / "scenes", f"name = {json.dumps(name)}\n" + TINY)
    with pytest.raises(SceneError, match="name must be a file name"):
        load_scene(p)
    recs = batch([p], tmp_path / "out", jobs=1, progress=False)
    assert recs[0]["status"] == "failed" and "name must be a file name" in recs[0]["message"]
    assert _tree(victim) == {"precious.txt": b"mine"}
    assert not Path("/tmp/victim-abs").exists()
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_1_batch_keeps_a_users_file_without_overwrite(tmp_path):
    p = _scene(tmp_path, TINY, "a.toml")
    (tmp_path / "out" / "a").mkdir(parents=True)
    (tmp_path / "out" / "a" / "notes.txt").write_text("mine")
    recs = batch([p], tmp_path / "out", jobs=1, progress=False)
    assert recs[0]["status"] == "failed" and "did not write" in recs[0]["message"]
    assert _tree(tmp_path / "out") == {"a/notes.txt": b"mine"}


# ------------------------------------------------------------------------------ 3: a dead worker
_REAL_RENDER_ONE = carpet_batch._render_one


def _kill_victim(scene_path, *args):
    """The batch task, except that the worker rendering ``victim.toml`` is killed (SIGKILL)."""
    if scene_path.endswith("victim.toml"):
        os.kill(os.getpid(), signal.SIGKILL)
    return _REAL_RENDER_ONE(scene_path, *args)


def test_3_batch_survives_a_killed_worker(tmp_path, monkeypatch):
    a = _scene(tmp_path, TINY, "a.toml")
    victim = _scene(tmp_path, TINY, "victim.toml")
    c = _scene(tmp_path, TINY, "c.toml")
    monkeypatch.setattr(carpet_batch, "_render_one", _kill_victim)
    recs = batch([a, victim, c], tmp_path / "out", jobs=2, progress=False)
    assert [r["status"] for r in recs] == ["done", "failed", "done"]
    assert "died (killed by SIGKILL" in recs[1]["message"] and "victim.toml" in recs[1]["message"]
    assert (tmp_path / "out" / "a" / "summary.json").is_file() and (tmp_path / "out" / "c" / "summary.json").is_file()
    assert not (tmp_path / "out" / "victim").exists()


def test_3_out_of_memory_scene_fails_alone_up_front(tmp_path):
    big = _scene(tmp_path, TINY.replace("n_seeds = 3", "n_seeds = 1000000000"), "big.toml")
    ok = _scene(tmp_path, TINY, "ok.toml")
    recs = batch([big, ok], tmp_path / "out", jobs=2, progress=False)
    assert [r["status"] for r in recs] == ["failed", "done"]
    assert "GB of memory" in recs[0]["message"] and "output.n_seeds" in recs[0]["message"]


# ------------------------------------------------------------------------------ 4: duplicate names
def test_4_duplicate_output_names_refused_up_front(tmp_path, capsys):
    a = _scene(tmp_path / "x", 'name = "same"\n' + TINY, "a.toml")
    b = _scene(tmp_path / "y", 'name = "same"\n' + TINY, "b.toml")
    code, _, err = _carpet(capsys, "batch", a, b, "-o", tmp_path / "out", "-j", "1")
    assert code == 2 and "same" in err and str(a) in err and str(b) in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------ 5: --overwrite
def test_5_overwrite_replaces_only_what_the_toolkit_wrote(tmp_path, capsys):
    p = _scene(tmp_path, TINY)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.tex").write_text("years of work")
    code, _, err = _carpet(capsys, "render", p, "-o", out)
    assert code == 2 and "did not write" in err and "thesis.tex" in err
    code, _, err = _carpet(capsys, "render", p, "-o", out, "--overwrite")  # beside the user's file
    assert code == 0, err
    assert (out / "thesis.tex").read_text() == "years of work" and (out / "summary.json").is_file()
    owned = set(json.loads((out / MANIFEST).read_text())["files"])
    assert "thesis.tex" not in owned and "summary.json" in owned
    before = (out / "summary.json").read_bytes()
    code, _, err = _carpet(capsys, "render", p, "-o", out, "--overwrite")  # replaces its own files only
    assert code == 0 and (out / "thesis.tex").read_text() == "years of work"
    assert (out / "summary.json").read_bytes() != before  # new timings
    assert {x.name for x in out.iterdir()} == owned | {"thesis.tex"}
    # a file with an output's name that the manifest does not list is never replaced
    q = tmp_path / "other"
    q.mkdir()
    (q / "preview.png").write_bytes(b"holiday photo")
    code, _, err = _carpet(capsys, "render", p, "-o", q, "--overwrite")
    assert code == 2 and "preview.png" in err and "not written by ciliary-carpet" in err
    assert _tree(q) == {"preview.png": b"holiday photo"}


# ------------------------------------------------------------------------------ 6: file paths
def test_6_scene_files_read_only_below_their_folder(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("CILIARY_CARPET_ALLOW_OUTSIDE_PATHS", "0")  # restored afterwards
    (tmp_path / "secret").mkdir()
    (tmp_path / "secret" / "key.txt").write_text("x,y,u,v\nTOPSECRET-LINE\n")
    body = TINY + '[target]\nkind = "points"\nfile = "../secret/key.txt"\n'
    p = _scene(tmp_path / "scenes", body)
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 2 and "target.file" in err and "outside the scene's folder" in err
    assert "TOPSECRET" not in err
    abs_body = TINY + f'[target]\nkind = "points"\nfile = "{tmp_path / "secret" / "key.txt"}"\n'
    with pytest.raises(SceneError, match="target.file"):
        load_scene(_scene(tmp_path / "scenes", abs_body, "abs.toml"))
    # a symbolic link inside the folder that points outside is outside
    (tmp_path / "scenes" / "link.csv").symlink_to(tmp_path / "secret" / "key.txt")
    with pytest.raises(SceneError, match="resolves to"):
        load_scene(_scene(tmp_path / "scenes", TINY + '[target]\nkind = "points"\nfile = "link.csv"\n', "l.toml"))
    # the documented flag lifts the rule (the file is then read: here a malformed control file)
    code, _, err = _carpet(capsys, "--allow-outside-paths", "render", p, "-o", tmp_path / "o")
    assert code == 2 and "outside the scene's folder" not in err
    assert load_scene(p, allow_outside=True).target.file == "../secret/key.txt"


def test_6_table_build_cannot_write_outside_the_scene_folder(tmp_path, capsys):
    body = TINY + '[table]\nfile = "../elsewhere/table.nc"\n[table.build]\nn = 3\n'
    p = _scene(tmp_path / "scenes", body)
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "scenes" / "o")
    assert code == 2 and "table.file" in err and "outside" in err
    assert not (tmp_path / "elsewhere").exists()


# ------------------------------------------------------------------------------ 7: exit codes
def test_7_huge_carpet_is_refused_up_front_with_the_estimate(tmp_path, capsys):
    p = _scene(tmp_path, TINY.replace("shape = [2, 2]", "shape = [100000, 100000]"))
    t = time.perf_counter()
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert time.perf_counter() - t < 5
    assert code == 2 and "GB of memory" in err and "carpet.shape" in err and "1e+10 cilia" in err
    assert "Traceback" not in err and not (tmp_path / "o").exists()


def test_7_unwritable_output_exits_2_with_one_line(tmp_path, capsys):
    p = _scene(tmp_path, TINY)
    (tmp_path / "afile").write_text("x")
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "afile" / "out")
    assert code == 2 and "afile" in err and len(err.strip().splitlines()) == 1
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "afile")
    assert code == 2 and "not a folder" in err
    (tmp_path / "dir.nc").mkdir()
    code, _, err = _carpet(capsys, "design", p, "-o", tmp_path / "dir.nc", "--overwrite")
    assert code == 2 and "dir.nc" in err and "Traceback" not in err
    code, _, err = _cilium(capsys, "simulate", "--chi-E", "200", "--eta", "1", "--t-end", "0.01", "--n-out", "2",
                           "--degree", "6", "--no-error-estimate", "--quiet", "-o", tmp_path / "dir.nc")
    assert code == 2 and "dir.nc" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("cmd", ["stability", "cycle"])
def test_7_folding_equilibrium_is_a_clear_exit_3(capsys, cmd):
    code, out, err = _cilium(capsys, cmd, "--chi-E=-200", "--eta", "1", "--chi-N", "1e-6", "--json")
    assert code == 3 and out == "" and "Traceback" not in err
    assert "equilibrium" in err and "chi_E < 0" in err and len(err.strip().splitlines()) == 1


def test_7_debug_flag_shows_the_traceback(tmp_path, capsys):
    p = _scene(tmp_path, TINY + "bogus = 1\n")
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 2 and "bogus" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(SceneError, match="bogus"):
        carpet_main(["--debug", "render", str(p), "-o", str(tmp_path / "o")])
    with pytest.raises(ValueError, match="eta"):
        cilium_main(["--debug", "simulate", "--chi-E", "200", "--eta", "-1", "--t-end", "1"])


def test_7_ctrl_c_exits_130_in_both_clis(tmp_path, capsys, monkeypatch):
    import single_cilium.cli as cil

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(cil, "flutter_cutoff", interrupt)
    code, _, err = _cilium(capsys, "cutoff", "--chi-E", "200", "--eta", "1")
    assert code == 130 and "interrupted" in err and "Traceback" not in err
    monkeypatch.setattr(carpet_cli, "_cmd_render", interrupt)
    code, _, err = _carpet(capsys, "render", _scene(tmp_path, TINY), "-o", tmp_path / "o")
    assert code == 130 and "interrupted" in err


def test_7_real_sigint_during_render(tmp_path):
    """SIGINT to a running ``ciliary-carpet render``: exit 130, one line, nothing left behind."""
    p = _scene(tmp_path, TINY.replace("periods = 0.5", "periods = 200").replace("shape = [2, 2]", "shape = [6, 6]")
               .replace("field_shape = [6, 6]", "field_shape = [60, 60]"))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "ciliary_carpet.cli", "render", str(p), "-o", str(tmp_path / "o")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    t = time.time()
    while time.time() - t < 60 and not any(x.name.endswith(".partial") for x in tmp_path.iterdir()):
        time.sleep(0.05)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err
    assert not (tmp_path / "o").exists() and not [x for x in tmp_path.iterdir() if x.name.startswith(".")]


def test_7_sigint_during_flow_evaluations_is_a_keyboard_interrupt():
    """A SIGINT that arrives while the flow's compiled kernels run reaches the caller as a
    KeyboardInterrupt, never as a SystemError ("returned a result with an exception set"), which
    a compiled function that starts other compiled functions' parallel regions gave for 1 to 3
    of 20 interrupts). 20 interrupts at seeded times during path-line-like evaluations."""
    import threading

    from ciliary_carpet.carpet import layout
    from ciliary_carpet.carpet.carpet import Carpet, Instant
    from single_cilium.table import ThrustTable

    c = Carpet(layout.square(10, 10, 2.0), np.full(100, 60.0), ThrustTable.default(), layout.random_phases(100, 3))
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(0, 18, 60), rng.uniform(0, 18, 60), np.zeros(60)])
    def evaluations(t):
        c.prepare(t + np.array([0.2, 0.3, 0.8, 1.0]) * 0.01, 1e-4)
        for q in (0.2, 0.3, 0.8, 1.0):
            c.velocity(pts[:int(rng.integers(1, 60))], Instant(t + q * 0.01), 1e-4)

    # everything compiled first: an interrupt that lands in numba's compiler can be swallowed by a
    # finalizer there ("Exception ignored in ... ObjectRef.__del__"), which would leave the loop
    # below running; each loop has a deadline too, so that a lost interrupt fails, never hangs
    evaluations(0.0)
    outcomes = []
    for _ in range(20):
        delay = 0.02 + 0.05 * rng.random()
        threading.Timer(delay, os.kill, (os.getpid(), signal.SIGINT)).start()
        t, end = 0.0, time.monotonic() + 30.0
        try:
            while True:
                if time.monotonic() > end:
                    outcomes.append("no KeyboardInterrupt within 30 s")
                    break
                evaluations(t)
                t += 0.01
        except KeyboardInterrupt:
            outcomes.append("KeyboardInterrupt")
        except SystemError as exc:
            outcomes.append(str(exc))
    assert outcomes == ["KeyboardInterrupt"] * 20, [o for o in outcomes if o != "KeyboardInterrupt"]


def test_7_sigint_to_a_table_build_stops_its_workers_and_keeps_finished_rows(tmp_path):
    """SIGINT to ``single-cilium table`` alone (not its group): exit 130 within seconds (the pool's
    workers are stopped, not waited for), and the same request resumes from the rows on disk."""
    out = tmp_path / "t.nc"
    args = [sys.executable, "-m", "single_cilium.cli", "table", "--chi-E", "200", "--eta", "1", "--chi-N",
            "100:112:25", "--degree", "6", "--n-phase", "32", "--no-error-estimate", "-o", str(out), "--quiet"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    parts = tmp_path / "t.nc.parts"
    t = time.time()
    while time.time() - t < 120 and not (parts.is_dir() and any(parts.glob("row_*.nc"))):
        time.sleep(0.05)
    t = time.time()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err, err
    assert time.time() - t < 10
    assert not out.exists() and 0 < len(list(parts.glob("row_*.nc"))) < 25
    done = subprocess.run(args + ["--json"], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["rows"] == 25 and out.exists() and not parts.exists()


def test_7_sigint_to_a_batch_stops_its_workers_cleanly(tmp_path):
    """SIGINT to the batch process alone (not its group): the workers are interrupted too, their
    staging folders removed, exit 130 within seconds."""
    slow = TINY.replace("periods = 0.5", "periods = 300")
    scenes = [_scene(tmp_path, slow, f"{n}.toml") for n in "ab"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "ciliary_carpet.cli", "batch", *map(str, scenes), "-o",
                             str(tmp_path / "out"), "-j", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env=env, text=True)
    t = time.time()
    while time.time() - t < 60 and not (tmp_path / "out").is_dir():
        time.sleep(0.05)
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    t = time.time()
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and time.time() - t < 30, err
    assert "Traceback" not in err and "interrupted" in err
    assert not any((tmp_path / "out").iterdir())


# ------------------------------------------------------------------------------ 8: strict JSON
def test_8_single_cilium_json_is_strict(tmp_path, capsys):
    runs = [
        ["equilibrium", "--chi-E", "50", "--chi-N", "100", "--json"],  # coiled: no limit angle
        ["cycle", "--chi-E", "1000", "--eta", "1", "--chi-N", "100", "--degree", "6", "--no-error-estimate", "--json"],
        ["stability", "--chi-E", "200", "--eta", "1", "--chi-N", "100", "--degree", "6", "--json"],
        ["cutoff", "--chi-E", "200", "--eta", "1", "--degree", "6", "--json"],
        ["simulate", "--chi-E", "200", "--eta", "1", "--chi-N", "100", "--t-end", "0.01", "--n-out", "3", "--degree",
         "6", "--no-error-estimate", "--quiet", "--json"],
        ["map", "--chi-N", "50", "--chi-E", "150,250", "--eta", "1", "--degree", "6", "--quiet", "--json"],
    ]
    for argv in runs:
        code, out, err = _cilium(capsys, *argv)
        assert code == 0, (argv, err)
        d = _strict(out)
        assert isinstance(d, dict)
        if argv[0] == "cycle":  # no flutter: the undefined period is null, and the reason is given
            assert d["period"] is None and "NaN" in d["non_finite"]["period"] and d["status"] == "no oscillation"


def test_8_carpet_json_and_summary_are_strict(tmp_path, capsys):
    p = _scene(tmp_path, TINY, "a.toml")
    code, out, err = _carpet(capsys, "render", p, "-o", tmp_path / "r", "--json")
    assert code == 0, err
    assert _strict(out)["out_dir"] == str(tmp_path / "r")
    summ = _strict((tmp_path / "r" / "summary.json").read_text())
    assert summ["n_cilia"] == 4 and "non_finite" not in summ
    code, out, err = _carpet(capsys, "batch", p, "-o", tmp_path / "b", "-j", "1", "--json")
    assert code == 0, err
    assert _strict(out)["scenes"][0]["status"] == "done"
    _strict((tmp_path / "b" / "a" / "summary.json").read_text())


# ------------------------------------------------------------------------------ 9: silent NaN
def test_9_equilibrium_beyond_1e155_is_finite_and_scale_invariant():
    """theta(s; c chi_E, c chi_N) = theta(c s; chi_E, chi_N) and x, y scale by 1/c: checked up to
    c = 1e299 (the closed form overflowed to NaN above ~1e154)."""
    t = np.linspace(0.0, 3.0, 13)
    for chi_E, chi_N in [(2.0, 1.0), (-2.0, 1.0), (1.0, 2.0), (3.0, -1.0)]:
        ref = equilibrium(CiliumParams(chi_E, 1, chi_N), t)
        xr, yr = equilibrium_shape(CiliumParams(chi_E, 1, chi_N), t)
        for c in (1e160, 1e250, 1e299):
            p = CiliumParams(chi_E * c, 1, chi_N * c)
            assert np.max(np.abs(equilibrium(p, t / c) - ref)) < 1e-14
            x, y = equilibrium_shape(p, t / c)
            assert np.max(np.abs(x * c - xr)) < 1e-14 and np.max(np.abs(y * c - yr)) < 1e-14
    with pytest.raises(ValueError, match="chi_E"):
        equilibrium(CiliumParams(1e305, 1, 0.0), [0.5])


def test_9_extreme_units_rejected_with_the_key(tmp_path, capsys):
    p = _scene(tmp_path, TINY + "[units]\nlength_m = 1e300\ntime_s = 1e-300\nviscosity_Pa_s = 1\n")
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 2 and "units.length_m" in err and not (tmp_path / "o").exists()
    p = _scene(tmp_path, TINY + "[units]\nlength_m = 1e-90\ntime_s = 1e90\nviscosity_Pa_s = 1\n", "v.toml")
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 2 and "velocity" in err


def test_9_periods_1e12_refused_not_a_misleading_success(tmp_path, capsys):
    p = _scene(tmp_path, TINY.replace("periods = 0.5", "periods = 1e12"))
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 2 and "output.periods" in err and "1e+12" in err and not (tmp_path / "o").exists()


def test_9_non_finite_summary_is_not_a_success(tmp_path, monkeypatch):
    import ciliary_carpet.output.summary as R

    monkeypatch.setattr(R, "non_finite", lambda s: {"mean_field.max_speed": "+inf"})
    p = _scene(tmp_path, TINY)
    with pytest.raises(R.RenderError, match="non-finite.*max_speed"):
        render(load_scene(p), tmp_path / "o")
    assert not (tmp_path / "o").exists() and not [x for x in tmp_path.iterdir() if x.name.startswith(".")]


# ------------------------------------------------------------------------------ 10: smaller ones
def test_10_unreachable_target_exits_3_in_strict_mode(tmp_path, capsys):
    p = _scene(tmp_path, TINY + '[target]\nkind = "uniform"\nangle = 85.0\nstrict = true\n')
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 3 and "reachable" in err and str(p) in err
    assert not (tmp_path / "o").exists()


def test_10_unreachable_target_gives_the_closest_flow_by_default(tmp_path, capsys):
    p = _scene(tmp_path, TINY + '[target]\nkind = "uniform"\nangle = 85.0\n')
    with pytest.warns(UserWarning, match="cannot make this target"):
        code, _, _ = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 0
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["design"]["residual_rms"] > 0.05


@pytest.mark.parametrize("extra,needle", [
    ("", "carpet.chi_N"),  # chi_N outside the table's range
    ('[target]\nkind = "uniform"\nangle = 10.0\ncontrol = [[1e300, 0.0]]\n', "target.control[0]"),
])
def test_10_messages_name_the_file_and_key(tmp_path, capsys, extra, needle):
    body = TINY.replace("shape = [2, 2]", "shape = [2, 2]\nchi_N = 500" if not extra else "shape = [2, 2]") + extra
    p = _scene(tmp_path, body)
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 2 and needle in err and str(p) in err


def test_10_preview_has_the_usual_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        res = render(load_scene(_scene(tmp_path, TINY.replace("preview = false", "preview = true"))), tmp_path / "o")
    finally:
        os.umask(old)
    modes = {f: stat.S_IMODE((res.out_dir / f).stat().st_mode) for f in res.files}
    assert modes["preview.png"] == 0o644 and set(modes.values()) == {0o644}
    assert stat.S_IMODE(res.out_dir.stat().st_mode) == 0o755


def test_10_staging_folder_of_a_killed_render_is_cleaned(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # a pid that no longer runs
    host = socket.gethostname()
    stale = tmp_path / f".o.{host}-{dead.pid}.abcd1234.partial"
    live = tmp_path / f".o.{host}-{os.getppid()}.abcd1234.partial"
    other = tmp_path / f".o.otherhost-{dead.pid}.abcd1234.partial"
    for d in (stale, live, other):
        d.mkdir()
        (d / "layout.vtp").write_text("half")
    render(load_scene(_scene(tmp_path, TINY)), tmp_path / "o")
    assert not stale.exists() and live.exists() and other.exists()


# ------------------------------------------------------------------------------ properties
_NUM = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**30, 10**30))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(chi_N=_NUM, spacing=_NUM, n_seeds=st.integers(-5, 10**12), periods=_NUM,
       shape=st.lists(st.integers(-3, 10**7), min_size=2, max_size=2), length=_NUM)
def test_scene_values_give_a_clear_error_or_a_finite_estimate(chi_N, spacing, n_seeds, periods, shape, length):
    data = {"carpet": {"shape": shape, "spacing": spacing, "chi_N": chi_N},
            "output": {"n_seeds": n_seeds, "periods": periods},
            "units": {"length_m": length, "time_s": 1.0, "viscosity_Pa_s": 1.0}}
    try:
        scene = scene_from_dict(data, None)
        est = check_resources(scene)
    except (SceneError, ResourceError) as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    assert all(math.isfinite(v) for v in (est.memory_bytes, est.pairs, est.steps, est.seconds))


@settings(max_examples=200, deadline=None)
@given(chi_E=st.floats(-1e300, 1e300), chi_N=st.floats(-1e300, 1e300), s=st.floats(0, 10))
def test_equilibrium_is_finite_or_a_clear_error(chi_E, chi_N, s):
    p = CiliumParams(chi_E, 1.0, chi_N)
    try:
        th = equilibrium(p, [s])
        x, y = equilibrium_shape(p, [s])
    except ValueError as exc:
        assert "beyond the range" in str(exc)
        return
    assert np.all(np.isfinite(th)) and np.all(np.isfinite(x)) and np.all(np.isfinite(y))
