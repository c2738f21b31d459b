"""The output folder's guarantees under the faults users meet (issue 21, points 1-4 and 8):
derived paths stay in the scene's folder, the manifest alone deletes nothing, outputs on another
filesystem, one render per folder, a swap that signals cannot split, stale results. Temporary
folders, tiny scenes; a real tmpfs mount when root; real signals sent to a rendering process."""
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

from ciliary_carpet.batch import batch
from ciliary_carpet.cli import main as carpet_main
from ciliary_carpet.render import MANIFEST, RenderError, is_complete, owned_files, render
from ciliary_carpet.scenes.scene import SceneError, load_scene
from ciliary_carpet.scenes.assembly import load_table

ROOT = Path(__file__).resolve().parent.parent
TINY = ('[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 3\nperiods = 0.5\nfield_shape = [6, 6]\nsnapshots = 0\n'
        'frames = 1\npreview = false\nftle = false\n')


def _scene(folder: Path, body: str = TINY, name: str = "s.toml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / name
    p.write_text(body)
    return p


def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _visible(folder: Path) -> set:
    return {p.name for p in folder.iterdir() if not p.name.startswith(".")}


def _whole(out: Path, n_seeds: int) -> None:
    """``out`` holds one render whole: complete, every file the toolkit's and unchanged, the
    render of the scene with ``n_seeds`` tracers."""
    assert is_complete(out)
    assert owned_files(out) == _visible(out) == set(json.loads((out / MANIFEST).read_text())["files"])
    assert json.loads((out / "summary.json").read_text())["scene_resolved"]["output"]["n_seeds"] == n_seeds


# ------------------------------------------------------------------------------ 1: derived paths
def test_table_row_folder_that_leaves_the_scene_folder_is_refused(tmp_path, monkeypatch):
    import single_cilium.table as T

    calls = []
    monkeypatch.setattr(T, "build_table", lambda *a, **k: calls.append(k.get("path")))
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "row_5.nc").write_text("not a row: a build would delete it")
    scenes = tmp_path / "scenes"
    body = TINY + '[table]\nfile = "t.nc"\n[table.build]\nn = 3\n'
    p = _scene(scenes, body)
    (scenes / "t.nc.parts").symlink_to(victim)  # the derived row folder points outside
    with pytest.raises(SceneError, match="row folder.*outside the scene's folder"):
        load_scene(p)
    # made a link only after the scene was read: refused just before the build
    (scenes / "t.nc.parts").unlink()
    scene = load_scene(p)
    (scenes / "t.nc.parts").symlink_to(victim)
    with pytest.raises(SceneError, match="row folder.*outside the scene's folder"):
        load_table(scene)
    assert calls == [] and _tree(victim) == {"row_5.nc": b"not a row: a build would delete it"}
    assert load_scene(p, allow_outside=True).table.file == "t.nc"  # the documented flag lifts the rule


def test_batch_output_folder_named_from_the_scene_stays_in_the_output_root(tmp_path, monkeypatch):
    monkeypatch.delenv("CILIARY_CARPET_ALLOW_OUTSIDE_PATHS", raising=False)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "notes.txt").write_text("mine")
    p = _scene(tmp_path / "scenes", TINY, "a.toml")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "a").symlink_to(victim)  # OUT/NAME is a link to elsewhere
    with ThreadPoolExecutor(1) as ex:
        recs = batch([p], tmp_path / "out", executor=ex, progress=False, overwrite=True)
    assert recs[0]["status"] == "failed" and "outside the output folder" in recs[0]["message"]
    assert _tree(victim) == {"notes.txt": b"mine"}


def test_a_long_folder_name_gives_bounded_staging_names(tmp_path):
    """The staging folder and lock file derived from a 240-byte folder name stay valid names."""
    out = tmp_path / ("x" * 240)
    res = render(load_scene(_scene(tmp_path, TINY)), out)
    assert "summary.json" in res.files
    assert not [x for x in tmp_path.iterdir() if x.name.startswith(".")]


# ------------------------------------------------------------------------------ 2: the manifest
@pytest.mark.parametrize("old_format", [False, True])
def test_an_edited_manifest_deletes_nothing_of_the_users(tmp_path, capsys, old_format):
    p = _scene(tmp_path, TINY)
    out = tmp_path / "o"
    assert carpet_main(["render", str(p), "-o", str(out)]) == 0

    def edit(extra):
        m = json.loads((out / MANIFEST).read_text())
        if old_format:  # a manifest from before the hashes: a plain list of names
            m["files"] = sorted(m["files"]) + sorted(extra)
        else:
            m["files"].update({k: {"size": 13, "sha256": "0" * 64} for k in extra})
        (out / MANIFEST).write_text(json.dumps(m))

    (out / "thesis.tex").write_text("years of work")
    edit(["thesis.tex"])
    assert carpet_main(["render", str(p), "-o", str(out), "--overwrite"]) == 0
    assert (out / "thesis.tex").read_text() == "years of work"
    assert "thesis.tex" not in json.loads((out / MANIFEST).read_text())["files"]
    # an output's name, listed, but a symbolic link to the user's file: kept, and the render refused
    (tmp_path / "photo.png").write_bytes(b"holiday")
    (out / "snapshot_007.vti").symlink_to(tmp_path / "photo.png")
    edit(["snapshot_007.vti"])
    capsys.readouterr()
    assert carpet_main(["render", str(p), "-o", str(out), "--overwrite"]) == 2
    assert "snapshot_007.vti" in capsys.readouterr().err
    assert (out / "snapshot_007.vti").is_symlink() and (tmp_path / "photo.png").read_bytes() == b"holiday"
    assert (out / "thesis.tex").read_text() == "years of work"


def test_an_output_changed_since_the_render_is_the_users(tmp_path, capsys):
    p = _scene(tmp_path, TINY)
    out = tmp_path / "o"
    assert carpet_main(["render", str(p), "-o", str(out)]) == 0
    (out / "summary.md").write_text("my notes on this run")  # listed in the manifest, edited since
    before = _tree(out)
    code = carpet_main(["render", str(p), "-o", str(out), "--overwrite"])
    _, err = capsys.readouterr()
    assert code == 2 and "summary.md" in err and "changed" in err
    assert _tree(out) == before


# ------------------------------------------------------------------------------ 3: another filesystem
@pytest.fixture
def tmpfs(tmp_path, mount_tmpfs):
    """A real tmpfs mounted at tmp_path/mnt (another filesystem than tmp_path)."""
    mnt = mount_tmpfs("mnt", "50m")
    assert os.stat(mnt).st_dev != os.stat(tmp_path).st_dev
    return mnt


def test_outputs_on_another_filesystem(tmp_path, tmpfs, capsys, monkeypatch):
    p = _scene(tmp_path, TINY)
    p2 = _scene(tmp_path, TINY.replace("n_seeds = 3", "n_seeds = 4"), "s2.toml")
    # -o on the mount point itself
    assert carpet_main(["render", str(p), "-o", str(tmpfs)]) == 0, capsys.readouterr().err
    _whole(tmpfs, 3)
    assert carpet_main(["render", str(p2), "-o", str(tmpfs), "--overwrite"]) == 0, capsys.readouterr().err
    _whole(tmpfs, 4)
    # -o on a symbolic link to a folder on the other filesystem
    (tmpfs / "scratch").mkdir()
    link = tmp_path / "link"
    link.symlink_to(tmpfs / "scratch")
    assert carpet_main(["render", str(p), "-o", str(link)]) == 0, capsys.readouterr().err
    _whole(link, 3)
    # a failure never deletes the previous render's files
    import ciliary_carpet.output.summary as R

    before = _tree(link)
    monkeypatch.setattr(R, "non_finite", lambda s: {"mean_field.max_speed": "+inf"})
    code = carpet_main(["render", str(p2), "-o", str(link), "--overwrite"])
    err = capsys.readouterr().err
    assert code == 2 and "non-finite" in err and "cross-device" not in err
    assert _tree(link) == before and {x.name for x in link.iterdir()} == _visible(link)
    assert not [x for x in tmp_path.iterdir() if x.name.startswith(".")]


# ------------------------------------------------------------------------------ 4: one render per folder
@pytest.mark.parametrize("existing", [False, True])
def test_a_second_render_of_the_same_folder_is_refused_at_once(tmp_path, monkeypatch, existing):
    import ciliary_carpet.output.fields as R

    p = _scene(tmp_path, TINY)
    out = tmp_path / "o"
    if existing:
        render(load_scene(p), out)
    paused, go = threading.Event(), threading.Event()
    real = R.write_pvd

    def slow(*a, **k):
        if threading.current_thread().name == "first":
            paused.set()
            go.wait(30)
        return real(*a, **k)

    monkeypatch.setattr(R, "write_pvd", slow)
    box = {}

    def first():
        try:
            box["res"] = render(load_scene(p), out, overwrite=True)
        except BaseException as exc:  # noqa: BLE001
            box["exc"] = exc

    t = threading.Thread(target=first, name="first")
    t.start()
    try:
        assert paused.wait(60)
        t0 = time.perf_counter()
        with pytest.raises(RenderError, match=f"{out} is being written by another ciliary-carpet render "
                                              f"\\(process {os.getpid()}"):
            render(load_scene(p), out, overwrite=True)
        assert time.perf_counter() - t0 < 5
    finally:
        go.set()
        t.join(60)
    assert "exc" not in box, box.get("exc")
    _whole(out, 3)
    assert {x.name for x in out.iterdir()} == _visible(out)  # no lock, stage or journal left
    assert not [x for x in tmp_path.iterdir() if x.name.startswith(".")]


def test_another_process_holding_the_folder_is_named(tmp_path):
    """The lock is between processes: a render is refused while another process holds the folder."""
    out = tmp_path / "o"
    out.mkdir()
    code = ("import sys, time\nfrom ciliary_carpet.output.folder import OutputFolder\n"
            "with OutputFolder(sys.argv[1], overwrite=True):\n    print('held', flush=True)\n    time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(out)], env=dict(os.environ, PYTHONPATH=str(ROOT)),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held", proc.stderr.read()
        with pytest.raises(RenderError, match=f"being written by another ciliary-carpet render \\(process {proc.pid} "):
            render(load_scene(_scene(tmp_path, TINY)), out)
    finally:
        proc.kill()
        proc.wait()
    render(load_scene(_scene(tmp_path, TINY)), out)  # a killed holder's lock is gone with it
    _whole(out, 3)


# ------------------------------------------------------------------------------ 4: the swap and signals
_SWAP = r"""
import os, sys, time
from pathlib import Path
out, ready, scene = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
real = {"rename": os.rename, "replace": os.replace}

def pausing(name):
    def f(src, dst, *a, **k):
        r = real[name](src, dst, *a, **k)
        if Path(dst) == out / "layout.vtp" and not ready.exists():  # the new render's first file is in
            ready.write_text("now")
            time.sleep(1)
        return r
    return f

os.rename, os.replace = pausing("rename"), pausing("replace")
from ciliary_carpet.render import render
from ciliary_carpet.scenes.scene import load_scene
render(load_scene(scene), out, overwrite=True)
"""


def _kill_mid_swap(tmp_path: Path, sig: int) -> tuple[Path, subprocess.CompletedProcess]:
    """Render n_seeds = 3 into tmp_path/o, then replace it with n_seeds = 4 in a process that is
    sent ``sig`` while it swaps the files."""
    p = _scene(tmp_path, TINY)
    p2 = _scene(tmp_path, TINY.replace("n_seeds = 3", "n_seeds = 4"), "s2.toml")
    out = tmp_path / "o"
    render(load_scene(p), out)
    ready = tmp_path / "ready"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", _SWAP, str(out), str(ready), str(p2)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t = time.time()
    while time.time() - t < 120 and not ready.exists() and proc.poll() is None:
        time.sleep(0.02)
    assert ready.exists(), proc.communicate()[1]
    proc.send_signal(sig)
    so, se = proc.communicate(timeout=60)
    return out, subprocess.CompletedProcess(proc.args, proc.returncode, so, se)


def test_sigterm_during_the_swap_does_not_split_it(tmp_path):
    """A real SIGTERM to a process replacing a render, sent while it moves the files (its default
    action, death, takes effect once the swap is whole)."""
    out, r = _kill_mid_swap(tmp_path, signal.SIGTERM)
    assert r.returncode == -signal.SIGTERM
    _whole(out, 4)


def test_ctrl_c_during_the_swap_does_not_split_it(tmp_path, monkeypatch):
    """A real SIGINT to this process while the swap moves the files: KeyboardInterrupt comes once
    the new render is whole, and nothing of the swap is left."""
    p = _scene(tmp_path, TINY)
    out = tmp_path / "o"
    render(load_scene(p), out)
    real = {"rename": os.rename, "replace": os.replace}

    def interrupting(name):
        def f(src, dst, *a, **k):
            r = real[name](src, dst, *a, **k)
            if Path(dst) == out / "layout.vtp":
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.2)
            return r
        return f

    monkeypatch.setattr(os, "rename", interrupting("rename"))
    monkeypatch.setattr(os, "replace", interrupting("replace"))
    with pytest.raises(KeyboardInterrupt):
        render(load_scene(_scene(tmp_path, TINY.replace("n_seeds = 3", "n_seeds = 4"), "s2.toml")), out,
               overwrite=True)
    monkeypatch.undo()
    _whole(out, 4)
    assert {x.name for x in out.iterdir()} == _visible(out)
    assert not [x for x in tmp_path.iterdir() if x.name.startswith(".")]


def test_a_render_killed_mid_swap_is_completed_by_the_next(tmp_path):
    out, r = _kill_mid_swap(tmp_path, signal.SIGKILL)
    assert r.returncode == -signal.SIGKILL
    assert not is_complete(out)  # half-way: not complete, and not passed off as such
    p3 = _scene(tmp_path, TINY.replace("n_seeds = 3", "n_seeds = 5"), "s3.toml")
    with pytest.raises(RenderError, match=r"already holds results \(complete"):
        render(load_scene(p3), out)  # without --overwrite: first completes the killed swap, then refuses
    _whole(out, 4)
    assert {x.name for x in out.iterdir()} == _visible(out)


# ------------------------------------------------------------------------------ 8: stale results
def test_a_reduced_render_is_not_up_to_date_for_the_full_scene(tmp_path):
    body = TINY.replace("shape = [2, 2]", "shape = [5, 5]")  # 25 cilia; --reduced keeps 16
    p = _scene(tmp_path, body, "a.toml")
    out = tmp_path / "out"
    with ThreadPoolExecutor(1) as ex:
        assert batch([p], out, executor=ex, progress=False, reduced=True)[0]["status"] == "done"
        assert batch([p], out, executor=ex, progress=False, reduced=True)[0]["status"] == "skipped"
        rec = batch([p], out, executor=ex, progress=False)[0]
    assert rec["status"] == "failed" and "other settings" in rec["message"] and "carpet.shape" in rec["message"]
    assert not is_complete(out / "a", scene=load_scene(p))
    assert is_complete(out / "a", scene=load_scene(p).reduced())
    p.write_text(body.replace("[carpet]", "tolerance = 0.01\n[carpet]"))  # another tolerance
    os.utime(p, (1, 1))  # older than the render: its contents decide, not its time
    assert not is_complete(out / "a", scene=load_scene(p).reduced())
