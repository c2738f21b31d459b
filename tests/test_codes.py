"""Codes and noise (issue 21, point 9): long scene names, deeply nested TOML, huge target
velocities and a read-only install each give the documented exit status and one line."""
import os
import shutil
import subprocess
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from ciliary_carpet.batch import batch
from ciliary_carpet.cli import main as carpet_main

ROOT = Path(__file__).resolve().parent.parent
TINY = ('[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 3\nperiods = 0.5\nfield_shape = [6, 6]\nsnapshots = 0\n'
        'frames = 1\npreview = false\n')


def _carpet(capsys, *argv):
    code = carpet_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_long_scene_name_renders_or_is_refused_up_front(tmp_path, capsys):
    """A 240-byte name (a legal file name) must not fail late on a derived name ("File name too
    long" from the staging folder, exit 1); a name beyond 255 bytes is refused by the name check."""
    name = "n" * 240
    p = tmp_path / "s.toml"
    p.write_text(f'name = "{name}"\n' + TINY)
    with ThreadPoolExecutor(1) as ex:  # the batch's task in this process (no fork server to start)
        recs = batch([p], tmp_path / "out", executor=ex, progress=False)
    assert recs[0]["status"] == "done", recs
    assert (tmp_path / "out" / name / "summary.json").is_file()
    assert not [x for x in (tmp_path / "out").iterdir() if x.name.startswith(".")]
    p.write_text(f'name = "{"n" * 256}"\n' + TINY)
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 2 and "longer than 255 bytes" in err and len(err.strip().splitlines()) == 1


def test_deeply_nested_toml_is_bad_input(tmp_path, capsys):
    p = tmp_path / "deep.toml"
    p.write_text("x = " + "[" * 3000 + "]" * 3000 + "\n" + TINY)
    code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "nested too deeply" in err and str(p) in err
    assert not (tmp_path / "o").exists()


def test_huge_target_velocities_one_line_no_numpy_warnings(tmp_path, capsys):
    (tmp_path / "t.csv").write_text("x,y,u,v\n0,1,1e300,1e300\n1,1,1e300,-1e300\n2,1,1e300,1e300\n")
    p = tmp_path / "s.toml"
    p.write_text(TINY + '[target]\nkind = "points"\nfile = "t.csv"\n')
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # an overflow warning fails the test
        code, _, err = _carpet(capsys, "render", p, "-o", tmp_path / "o")
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "t.csv" in err and "u = 1e+300" in err, err


def _remount_read_only(folder: Path) -> bool:
    r = subprocess.run(["mount", "--bind", str(folder), str(folder)], capture_output=True)
    if r.returncode != 0:
        return False
    r = subprocess.run(["mount", "-o", "remount,bind,ro", str(folder)], capture_output=True)
    if r.returncode != 0:
        subprocess.run(["umount", str(folder)], capture_output=True)
        return False
    return True


def test_read_only_install_and_home_fall_back_to_a_temporary_numba_cache(tmp_path):
    """The packages on a read-only mount, HOME read-only too: ``--help`` works, with one warning."""
    if os.name != "posix" or os.geteuid() != 0:
        pytest.skip("a read-only bind mount needs root (as a user, chmod the install and HOME instead)")
    ro = tmp_path / "ro"
    for pkg in ("ciliary_carpet", "single_cilium"):
        shutil.copytree(ROOT / pkg, ro / "site" / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.nc"))
    (ro / "home").mkdir()
    if not _remount_read_only(ro):
        pytest.skip("cannot make a read-only bind mount here")
    try:
        env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
        env.update(PYTHONPATH=str(ro / "site"), HOME=str(ro / "home"))
        r = subprocess.run([sys.executable, "-m", "ciliary_carpet.cli", "--help"], capture_output=True, text=True,
                           env=env, timeout=120, cwd=tmp_path)
    finally:
        subprocess.run(["umount", "-l", str(ro)], capture_output=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "usage: ciliary-carpet" in r.stdout and str(ro / "site") not in r.stdout
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "NUMBA_CACHE_DIR" in lines[0] and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert str(ro / "site") in lines[0]  # the copy on the read-only mount was imported
