"""A full disk (issue 21, point 6): NetCDF and VTK writes fail with one line naming the file and
"no space left on device", exit status 2, no partial file, the previous content intact, no
crash. On a real 1 MiB tmpfs mount, filled up (needs root to mount; skipped otherwise)."""
import errno
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ciliary_carpet.output.vtkfiles import OutputError, write_field, write_pvd

ROOT = Path(__file__).resolve().parent.parent
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
TINY = ('[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 3\nperiods = 0.5\nfield_shape = [6, 6]\nsnapshots = 0\n'
        'frames = 1\npreview = false\n')
PREVIOUS = b"the previous results, which must survive"


def _fill(folder: Path) -> None:
    """Fill the file system of ``folder`` to the last byte (bounded: the mount is 1 MiB)."""
    for size, name in ((4096, "filler"), (64, "crumbs")):
        fd = os.open(folder / name, os.O_WRONLY | os.O_CREAT)
        try:
            for _ in range((1 << 20) // size + 1):
                try:
                    os.write(fd, b"\0" * size)
                except OSError as exc:
                    assert exc.errno == errno.ENOSPC
                    break
            else:
                raise AssertionError("the 1 MiB mount did not fill up")
        finally:
            os.close(fd)


def _free(mnt: Path, nbytes: int) -> None:
    """Leave ``nbytes`` free on the full mount (a write that fills it midway: HDF5 crashed then)."""
    (mnt / "crumbs").unlink()
    os.truncate(mnt / "filler", (mnt / "filler").stat().st_size - nbytes)


@pytest.fixture
def full_disk(mount_tmpfs):
    """A 1 MiB tmpfs, holding a previous result, then filled up."""
    mnt = mount_tmpfs("small", "1m")
    for name in ("layout.nc", "sim.nc", "speed.vti", "s.pvd"):
        (mnt / name).write_bytes(PREVIOUS)
    _fill(mnt)
    return mnt


def _check(mnt: Path, name: str) -> None:
    assert (mnt / name).read_bytes() == PREVIOUS  # the previous content intact
    assert not [p.name for p in mnt.iterdir() if p.name.startswith(".")]  # no partial temporary


def _one_line(r: subprocess.CompletedProcess, name: str, exact: bool = True) -> str:
    assert r.returncode == 2, (r.returncode, r.stderr)  # not 139 (a crash) nor 1
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert (f"'{name}'" if exact else name) in lines[0], lines[0]  # the file itself, not a temporary
    assert "no space left on device" in lines[0], lines[0]
    return lines[0]


def test_design_layout_on_a_full_disk(full_disk, tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(TINY + '[target]\nkind = "uniform"\nangle = 10.0\n')
    r = subprocess.run([sys.executable, "-m", "ciliary_carpet.cli", "design", str(scene), "-o",
                        str(full_disk / "layout.nc"), "--overwrite"], capture_output=True, text=True, env=ENV,
                       timeout=240)
    _one_line(r, str(full_disk / "layout.nc"))
    _check(full_disk, "layout.nc")


def test_simulate_output_on_a_full_disk(full_disk):
    _free(full_disk, 65536)  # the file fills the disk midway (HDF5 segfaulted: exit 139)
    r = subprocess.run([sys.executable, "-m", "single_cilium.cli", "simulate", "--chi-E", "200", "--eta", "1",
                        "--t-end", "0.05", "--n-out", "2000", "--degree", "6", "--no-error-estimate", "--quiet", "--overwrite",
                        "-o", str(full_disk / "sim.nc")], capture_output=True, text=True, env=ENV, timeout=240)
    _one_line(r, str(full_disk / "sim.nc"))
    _check(full_disk, "sim.nc")


def test_vtk_writes_on_a_full_disk(full_disk, capfd):
    _free(full_disk, 65536)
    with pytest.raises(OutputError, match=r"speed\.vti.*no space left on device") as info:
        write_field(full_disk / "speed.vti", (0, 0, 0), (1, 1, 1), (40, 40, 40), {"speed": np.random.rand(64000)})
    assert info.value.errno == errno.ENOSPC and "\n" not in str(info.value)
    _check(full_disk, "speed.vti")
    entries = [(float(k), full_disk / "speed.vti") for k in range(2000)]
    with pytest.raises(OutputError, match=r"s\.pvd.*no space left on device"):
        write_pvd(full_disk / "s.pvd", entries)
    _check(full_disk, "s.pvd")
    assert capfd.readouterr().err == ""  # no VTK log lines


@pytest.mark.parametrize("free", [0, 8192])
def test_render_on_a_full_disk(full_disk, tmp_path, free):
    """Full to the last byte (the lock file cannot even record its holder), or two pages left
    (room for the lock file, not for the render): one line, nothing left behind."""
    if free:
        _free(full_disk, free)
    scene = tmp_path / "s.toml"
    scene.write_text(TINY)
    r = subprocess.run([sys.executable, "-m", "ciliary_carpet.cli", "render", str(scene), "-o", str(full_disk / "out")],
                       capture_output=True, text=True, env=ENV, timeout=240)
    _one_line(r, str(full_disk / ".out."), exact=False)  # a file of the render's staging folder
    assert not (full_disk / "out").exists()
    assert not [p.name for p in full_disk.iterdir() if p.name.startswith(".")]  # no staging, lock or temporary
