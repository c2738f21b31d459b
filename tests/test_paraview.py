"""The render's ParaView script, run in a real ParaView as ``paraview --script=`` runs it, and
the render's one time base (the cilia beat on over the path lines' whole time range).

The ParaView test needs ``pvpython`` (Debian: ``apt-get install python3-paraview``) and a
display: ``$DISPLAY``, or ``Xvfb`` (Debian: ``apt-get install xvfb``) for a virtual one that the
test starts (Debian's ParaView renders through X only). Without them it is skipped, saying why.
"""
from __future__ import annotations

import os
import random
import shutil
import subprocess
import time
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from ciliary_carpet.render import render
from ciliary_carpet.scenes.scene import scene_from_dict

TINY = {"name": "tiny", "carpet": {"lattice": "square", "shape": [2, 2], "spacing": 2.0, "chi_N": 3.0},
        "output": {"n_seeds": 4, "periods": 2.0, "field_shape": [10, 10], "snapshots": 2, "frames": 8}}

# what --script does: the script's text runs with no __file__ and sys.argv == [''] (checked with
# paraview 5.11 under xvfb-run); then a screenshot of the view it left
_RUN_AS_SCRIPT = """
import sys
script, shot = sys.argv[1], sys.argv[2]
sys.argv = ['']
namespace = {'__name__': '__main__'}
exec(compile(open(script).read(), '<--script>', 'exec'), namespace)
assert '__file__' not in namespace
from paraview.simple import GetActiveView, GetSources, SaveScreenshot
names = sorted(k[0] for k in GetSources())
print('SOURCES', names)
view = GetActiveView()
print('AXES', view.AxesGrid.Visibility, view.AxesGrid.XTitle, view.AxesGrid.YTitle)
view.ViewSize = [800, 600]
SaveScreenshot(shot, view, ImageResolution=[800, 600])
"""


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return render(scene_from_dict(TINY), tmp_path_factory.mktemp("render") / "tiny")


@pytest.fixture(scope="module")
def display():
    """``$DISPLAY``, else a virtual X server started here on a random display number (Xvfb's
    -displayfd reports when it is ready). Not :99 (xvfb-run's) nor the lowest free one: a server
    that this machine's /tmp does not show (another container sharing the network namespace,
    hence the abstract X sockets) can hold those, and a client would reach it and be refused.
    Skips without either."""
    if os.environ.get("DISPLAY"):
        yield os.environ["DISPLAY"]
        return
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        pytest.skip("no display for ParaView: no $DISPLAY and no Xvfb (Debian: apt-get install xvfb)")
    rng = random.Random()
    for _ in range(5):
        number = rng.randrange(1000, 30000)
        r, w = os.pipe()
        server = subprocess.Popen([xvfb, f":{number}", "-displayfd", str(w), "-screen", "0", "1280x1024x24",
                                   "-nolisten", "tcp"], pass_fds=(w,), stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        os.close(w)
        with os.fdopen(r) as fh:
            ready = fh.readline().strip()  # written once the server accepts connections; "" if it died
        if ready:
            break
        server.wait(timeout=30)
    else:
        pytest.skip("Xvfb did not start")
    try:
        yield f":{ready}"
    finally:
        server.terminate()
        server.wait(timeout=30)


def _pvpython():
    pv = shutil.which("pvpython")
    if pv is None:
        pytest.skip("ParaView's pvpython is not on the PATH (Debian: apt-get install python3-paraview)")
    return pv


def test_script_opens_the_render_in_paraview_as_script_does(tiny, tmp_path, request):
    import matplotlib.image as mpimg

    cmd = [_pvpython()]
    env = dict(os.environ, DISPLAY=request.getfixturevalue("display"))
    runner = tmp_path / "run_as_script.py"
    runner.write_text(_RUN_AS_SCRIPT)
    shot = tmp_path / "shot.png"
    elsewhere = tmp_path / "elsewhere"  # another working folder, with nothing of the render in it
    elsewhere.mkdir()
    for attempt in range(4):  # on a busy machine a fresh Xvfb has refused ParaView's first connections
        p = subprocess.run(cmd + [str(runner), str(tiny.out_dir / "open_in_paraview.py"), str(shot)], cwd=elsewhere,
                           capture_output=True, text=True, timeout=120, env=env)
        out = p.stdout + p.stderr
        if "bad X server connection" not in out:
            break
        time.sleep(2.0 * (attempt + 1))
    assert p.returncode == 0, out
    lines = [ln for ln in out.splitlines() if ln.strip() and not ln.startswith(("SOURCES", "AXES"))]
    assert "AXES 1 x [L] y [L]" in out, out  # labelled axes, in the files' length unit
    assert not lines, out  # no error, no warning, nothing printed
    sources = out.split("SOURCES", 1)[1].splitlines()[0]
    for name in ("mean_field.vti", "layout.vtp", "cilia.pvd", "pathlines.vtp", "particles.pvd", "snapshots.pvd",
                 "ftle.vti"):
        assert name in sources, sources
    img = mpimg.imread(shot)[..., :3]
    colours = np.unique((img.reshape(-1, 3) * 255).round().astype(int), axis=0)
    assert colours.shape[0] > 50 and img.std() > 0.05, (colours.shape, img.std())


def _pvd_times(path):
    return [float(d.get("timestep")) for d in ET.parse(path).getroot().iter("DataSet")]


def test_cilia_and_snapshots_beat_over_the_path_lines_time_range(tiny):
    import json

    s = json.loads((tiny.out_dir / "summary.json").read_text())
    end = s["pathlines"]["duration"]
    beat = s["beat"]["period"]
    cilia = _pvd_times(tiny.out_dir / "cilia.pvd")
    particles = _pvd_times(tiny.out_dir / "particles.pvd")
    assert cilia[0] <= min(particles) and cilia[-1] >= max(particles) >= end * (1 - 1e-9)
    assert cilia[-1] >= end and np.all(np.diff(cilia) > 0)
    # the one-beat frame files reused by phase: frame k at every k-th time of each beat
    files = [d.get("file") for d in ET.parse(tiny.out_dir / "cilia.pvd").getroot().iter("DataSet")]
    n = TINY["output"]["frames"]
    assert len(set(files)) == n and files[n] == files[0] and np.isclose(cilia[n], beat)
    snaps = _pvd_times(tiny.out_dir / "snapshots.pvd")
    assert snaps[-1] >= end


def test_summary_speaks_in_units_and_beats(tiny):
    md = (tiny.out_dir / "summary.md").read_text()
    assert "times in tau" in md and "L/tau" in md and "beats)" in md  # durations: tau and beats of the cilia
    assert "fidelity" not in md and "pass 1" not in md  # the code's words are gone
