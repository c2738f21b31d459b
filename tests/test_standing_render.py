"""Standing carpets rendered end to end: a scene with ``[carpet] geometry = "standing"`` in, a
ParaView-ready folder out (ciliary_carpet.render, ciliary_carpet.output; MODEL.md section 6)."""
import json
import math
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import vtk
from vtk.util.numpy_support import vtk_to_numpy

from ciliary_carpet.render import render
from ciliary_carpet.scenes.scene import SceneError, load_scene, scene_from_dict

DESIGNS = Path(__file__).resolve().parents[1] / "designs"


@pytest.fixture(scope="module")
def pump(tmp_path_factory):
    """The bundled standing pump at reduced size (16 cilia, 16 x 16 field, 10 seeds, 2 periods)."""
    scene = load_scene(DESIGNS / "standing_pump.toml").reduced()
    return scene, render(scene, tmp_path_factory.mktemp("render") / scene.name)


def _read(path, kind):
    r = {"vtp": vtk.vtkXMLPolyDataReader, "vti": vtk.vtkXMLImageDataReader}[kind]()
    r.SetFileName(str(path))
    r.Update()
    return r.GetOutput()


def test_the_standing_render_writes_its_files_in_space(pump):
    """The folder holds every output; the summary says "standing" with the azimuths; the path
    lines start on the target plane z = h and stay in the fluid above the wall; the cilia's frames
    stand on the substrate in their turned beat planes."""
    scene, res = pump
    for f in ("layout.vtp", "layout.nc", "mean_field.vti", "mean_field_section.vti", "snapshots.pvd",
              "snapshots_section.pvd", "cilia.pvd", "pathlines.vtp", "particles.pvd", "ftle.vti", "preview.png",
              "open_in_paraview.py", "summary.json", "summary.md"):
        assert f in res.files, f
    s = json.loads((res.out_dir / "summary.json").read_text())
    assert s["geometry"] == "standing" and s["standing"]["wall_below_clamps"] == 0.0
    assert s["standing"]["azimuth_deg"]["min"] == s["standing"]["azimuth_deg"]["max"] == 30.0
    assert "Standing carpet" in (res.out_dir / "summary.md").read_text()
    pl = _read(res.out_dir / "pathlines.vtp", "vtp")
    pts = vtk_to_numpy(pl.GetPoints().GetData())
    assert pl.GetNumberOfCells() == s["pathlines"]["tracers"] >= 9 and pts.shape[1] == 3
    assert np.all(pts[:, 2] > 0.0)
    h = scene.output.height
    start = vtk_to_numpy(pl.GetPointData().GetArray("time")) == 0.0
    np.testing.assert_allclose(pts[start, 2], h)
    assert np.ptp(pts[:, :2], axis=0).max() > 0  # the tracers moved
    # the cilia: clamped on z = 0, above it, each in the vertical plane of its azimuth (30 deg)
    cil = _read(res.out_dir / "cilia_001.vtp", "vtp")
    c = vtk_to_numpy(cil.GetPoints().GetData())
    assert c[:, 2].min() >= -1e-12 and c[:, 2].max() > 0.5
    lay = _read(res.out_dir / "layout.vtp", "vtp")
    bases = vtk_to_numpy(lay.GetPoints().GetData())
    off = c[:, :2] - bases[np.argmin(np.linalg.norm(c[:, None, :2] - bases[None, :, :2], axis=2), axis=1), :2]
    e = np.array([math.cos(math.radians(30)), math.sin(math.radians(30))])
    np.testing.assert_allclose(off @ np.array([-e[1], e[0]]), 0.0, atol=1e-9)
    thrust = vtk_to_numpy(lay.GetPointData().GetArray("mean_thrust"))
    assert thrust.shape == (16, 3) and np.all(thrust[:, :2] @ e > 0)  # positive chi_N: pushes along psi


def test_the_fields_lie_on_the_target_plane_and_the_section_reaches_the_wall(pump):
    """mean_field.vti is the plane z = h, its flow along the azimuth over the carpet; the vertical
    section's velocity is zero on the wall (no slip) and grows up to the plane."""
    scene, res = pump
    plane = _read(res.out_dir / "mean_field.vti", "vti")
    b = plane.GetBounds()
    assert b[4] == b[5] == scene.output.height
    sec = _read(res.out_dir / "mean_field_section.vti", "vti")
    nx, ny, nz = sec.GetDimensions()
    assert ny == 1 and nz > 2 and sec.GetBounds()[4] == 0.0
    u = vtk_to_numpy(sec.GetPointData().GetArray("velocity")).reshape(nz, nx, 3)
    assert np.abs(u[0]).max() < 1e-12 * max(1.0, np.abs(u).max()) and np.abs(u[-1]).max() > 0
    # over the carpet (its x range) the flow above the cilia runs along the azimuth
    x = sec.GetOrigin()[0] + sec.GetSpacing()[0] * np.arange(nx)
    e = np.array([math.cos(math.radians(30)), math.sin(math.radians(30))])
    lay = _read(res.out_dir / "layout.vtp", "vtp")
    bx = vtk_to_numpy(lay.GetPoints().GetData())[:, 0]
    over = (x >= bx.min()) & (x <= bx.max())
    top = u[-1, over, :2] @ e
    assert np.all(top > 0) and np.all(np.abs(u[-1, over, :2] @ np.array([-e[1], e[0]])) < top)
    v = vtk_to_numpy(plane.GetPointData().GetArray("velocity"))
    fast = np.linalg.norm(v[:, :2], axis=1) > 0.5 * np.linalg.norm(v[:, :2], axis=1).max()
    ang = np.degrees(np.arctan2(v[fast, 1], v[fast, 0]))
    assert abs(np.median(ang) - 30.0) < 10.0


def test_layout_nc_carries_the_azimuth_and_the_omissions_are_sized_in_space(pump):
    """layout.nc holds chi_N and azimuth per cilium (degrees) with the mean thrust in space; the
    summary's omissions take the wall at each cilium's mean height and the interaction in 3D."""
    import xarray as xr

    scene, res = pump
    with xr.open_dataset(res.out_dir / "layout.nc", engine="h5netcdf") as ds:
        assert ds.attrs["geometry"] == "standing"
        np.testing.assert_allclose(ds["azimuth"].values, 30.0)
        np.testing.assert_allclose(ds["chi_N"].values, 92.0)
        assert ds["mean_thrust_z"].size == 16 and np.all(ds["centre_z"].values > 0.1)
    s = res.summary
    w = s["omissions"]["wall"]
    assert w["geometry"] == "standing" and 0.1 < w["height_min_L"] <= w["height_L"] <= w["height_max_L"] < 1.0
    assert w["drag_ratio_across_lowest"] >= w["drag_ratio_across"] > 1.0
    assert s["omissions"]["interaction"]["tip"]["median"] > 0
    # coupled by default: each cilium beats in the in-plane part of the others' mean flow
    cp = s["coupling"]
    assert cp["model"] == "mean" and cp["status"] == "converged" and cp["residual"] <= cp["rtol"]
    assert 0 < cp["median_speed_coupled"] < cp["median_speed_uncoupled"] and 0 <= cp["normal_flow"] < 1


def test_resolved_path_lines_from_a_line_of_seeds_stay_above_the_wall(tmp_path):
    """A small standing carpet, time-resolved path lines from the "line" of seeds: the seeds lie
    upstream of the carpet along its surface flow (the azimuth, 0 here: +x) at the target plane's
    height; the tracers move downstream and stay in the fluid above the wall, in the plan's domain."""
    scene = scene_from_dict({"name": "line", "carpet": {"geometry": "standing", "shape": [2, 2], "chi_N": 92.0},
                             "output": {"seeds": "line", "n_seeds": 4, "height": 1.2, "periods": 2.0,
                                        "pathline_model": "resolved", "field_shape": [8, 8], "snapshots": 0,
                                        "frames": 2, "ftle": False, "preview": False}})
    res = render(scene, tmp_path / "line")
    pl = _read(res.out_dir / "pathlines.vtp", "vtp")
    pts = vtk_to_numpy(pl.GetPoints().GetData())
    t = vtk_to_numpy(pl.GetPointData().GetArray("time"))
    start = pts[t == 0.0]
    assert start.shape == (4, 3) and np.allclose(start[:, 2], 1.2) and np.all(start[:, 0] < 0.0)
    assert np.all(pts[:, 2] > 0.0)
    cells = [[pl.GetCell(k).GetPointId(i) for i in range(pl.GetCell(k).GetNumberOfPoints())]
             for k in range(pl.GetNumberOfCells())]
    first, last = pts[[c[0] for c in cells]], pts[[c[-1] for c in cells]]
    assert np.all(last[:, 0] > first[:, 0])  # downstream: along +x
    s = res.summary["pathlines"]
    assert s["model"] == "resolved" and s["outcome"]["reached end time"] == 4


@pytest.mark.parametrize("data, key", [
    ({"field": {"direction": 10.0}, "carpet": {"geometry": "standing"}}, "field.direction"),
    ({"carpet": {"azimuth": 30.0}}, "carpet.azimuth"),
    ({"carpet": {"geometry": "standing", "azimuth": float("nan")}}, "carpet.azimuth"),
    ({"carpet": {"geometry": "standing", "shape": [2, 2], "azimuth": [0.0, 10.0, float("inf"), 0.0]}},
     r"carpet.azimuth\[2\]"),
    ({"carpet": {"geometry": "standing", "shape": [2, 2], "azimuth": [0.0, 10.0]}}, "carpet.azimuth"),
    ({"carpet": {"geometry": "standing", "azimuth": "north"}}, "carpet.azimuth"),
    ({"carpet": {"geometry": "standing", "wall": -1.0}}, "carpet.wall"),
    ({"carpet": {"wall": 0.0}}, "carpet.wall"),
    ({"output": {"height": 2.0}}, "output.height"),
    ({"carpet": {"geometry": "standing"}, "target": {"kind": "uniform"}}, "target"),
    ({"carpet": {"geometry": "upright"}}, "carpet.geometry"),
], ids=["direction", "azimuth-planar", "azimuth-nan", "azimuth-inf-in-list", "azimuth-list-length",
        "azimuth-type", "wall-negative", "wall-zero-planar", "height-planar", "target", "geometry"])
def test_keys_that_do_not_fit_the_geometry_are_scene_errors(data, key):
    with pytest.raises(SceneError, match=key):
        scene_from_dict(data)


def test_standing_defaults_and_per_cilium_azimuths():
    """A standing scene's defaults (wall 0, seeds "grid", height 1.5, azimuth 0) are resolved and
    written back; a planar scene's are as before; per-cilium azimuths follow the kept cilia
    when the scene is reduced."""
    st = scene_from_dict({"carpet": {"geometry": "standing"}})
    assert (st.carpet.wall, st.output.seeds, st.output.height) == (0.0, "grid", 1.5)
    assert np.all(st.carpet.azimuths() == 0.0)
    assert scene_from_dict(st.to_dict()) == st
    pl = scene_from_dict({})
    assert (pl.carpet.wall, pl.output.seeds, pl.output.height, pl.carpet.azimuth) == (None, "line", None, None)
    assert "geometry" not in pl.to_dict()["carpet"] and "height" not in pl.to_dict()["output"]
    psi = [float(k) for k in range(36)]
    big = scene_from_dict({"carpet": {"geometry": "standing", "shape": [6, 6], "azimuth": psi}})
    small = big.reduced(max_cilia=4)
    b6, b2 = big.carpet.bases(), small.carpet.bases()
    near = np.argmin(np.linalg.norm(b2[:, None] - b6[None], axis=2), axis=1)
    assert small.carpet.n_cilia == 4 and list(small.carpet.azimuths()) == [psi[i] for i in near]


def test_the_standing_script_opens_in_paraview(pump, tmp_path, request):
    """open_in_paraview.py of a standing render runs as ParaView's --script runs it (the harness
    of tests/test_paraview.py), loads the standing outputs and leaves a non-blank 3D view."""
    import matplotlib.image as mpimg
    from test_paraview import _RUN_AS_SCRIPT, _pvpython

    pv = _pvpython()
    env = dict(__import__("os").environ, DISPLAY=request.getfixturevalue("display"))
    _, res = pump
    runner = tmp_path / "run_as_script.py"
    runner.write_text(_RUN_AS_SCRIPT)
    shot = tmp_path / "shot.png"
    for attempt in range(4):  # a fresh Xvfb on a busy machine refuses some first connections (test_paraview.py)
        p = subprocess.run([pv, str(runner), str(res.out_dir / "open_in_paraview.py"), str(shot)], cwd=tmp_path,
                           capture_output=True, text=True, timeout=120, env=env)
        out = p.stdout + p.stderr
        if "bad X server connection" not in out:
            break
        time.sleep(2.0 * (attempt + 1))
    assert p.returncode == 0, out
    assert not [ln for ln in out.splitlines() if ln.strip() and not ln.startswith(("SOURCES", "AXES"))], out
    assert "AXES 1 x [L] y [L]" in out, out  # labelled axes in 3D too
    sources = out.split("SOURCES", 1)[1].splitlines()[0]
    for name in ("mean_field.vti", "mean_field_section.vti", "layout.vtp", "cilia.pvd", "pathlines.vtp",
                 "snapshots_section.pvd", "ftle.vti"):
        assert name in sources, sources
    img = mpimg.imread(shot)[..., :3]
    assert np.unique((img.reshape(-1, 3) * 255).round().astype(int), axis=0).shape[0] > 50 and img.std() > 0.05


from test_paraview import display  # noqa: E402,F401  (the virtual X server fixture, shared)


def test_an_integrator_stage_below_the_wall_takes_the_walls_flow():
    """A stage of a tracer next to a standing carpet's wall may land below it: the flow models
    give the wall's flow there (zero: no slip) instead of refusing the point; a planar carpet's
    points below its wall are still refused."""
    from ciliary_carpet.carpet import layout
    from ciliary_carpet.carpet.carpet import Carpet
    from ciliary_carpet.transport.flow import ResolvedFlow, SteadyMeanFlow, above_wall
    from single_cilium.table import ThrustTable

    table = ThrustTable.default()
    c = Carpet(layout.square(2, 2, 2.0), 92.0, table, None, wall=0.0, geometry="standing", azimuth=0.5)
    x = np.array([[1.0, 1.0, -0.3], [1.0, 1.0, 1.5], [5.0, -1.0, -1e-9]])
    assert np.array_equal(above_wall(c, x)[:, 2], [0.0, 1.5, 0.0]) and x[0, 2] == -0.3
    for flow in (ResolvedFlow(c, 1e-3), SteadyMeanFlow(c, (-10, 10, -10, 10, 0, 10), 1e-3)):
        u = flow.velocity(x, 0.1)
        assert np.abs(u[[0, 2]]).max() < 1e-14 and np.abs(u[1]).max() > 0
    planar = Carpet(layout.square(2, 2, 2.0), 92.0, table, None, wall=1.0)
    assert above_wall(planar, x) is x
    with pytest.raises(ValueError, match="below the wall"):
        ResolvedFlow(planar, 1e-3).velocity(np.array([[0.0, 0.0, -2.0]]), 0.1)
