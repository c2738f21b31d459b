import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import vtk
from vtk.util.numpy_support import vtk_to_numpy

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.cli import batch, main
from ciliary_carpet.design import DesignError, design_layout
from ciliary_carpet.render import RenderError, render
from ciliary_carpet.scenes.assembly import design
from ciliary_carpet.scenes.scene import load_scene
from ciliary_carpet.design.target import TargetError
from single_cilium.table import ThrustTable

DESIGNS = sorted((Path(__file__).parent.parent / "designs").glob("*.toml"))
# the bundled programs (one layout, two fields: a coupled design per state) render in the slow set
RENDERED = [pytest.param(p, marks=pytest.mark.slow) if p.stem.startswith("program_") else p for p in DESIGNS]


@pytest.fixture(scope="module")
def table():
    return ThrustTable.default()


def test_at_least_five_designs():
    names = {p.stem for p in DESIGNS}
    assert len(names) >= 5
    assert {"uniform_deflection", "focusing", "spreading", "shear_layer"} <= names


@pytest.mark.parametrize("path", RENDERED, ids=lambda p: p.stem)
def test_every_design_renders_and_meets_its_target(path, tmp_path):
    scene = load_scene(path).reduced()
    res = render(scene, tmp_path / scene.name)
    s = res.summary
    if scene.states:  # a program: every state met, a render folder each
        assert [q["name"] for q in s["states"]] == [st.name for st in scene.states]
        for q in s["states"]:
            assert q["met"] and q["residual_rms"] <= q["threshold"] and q["residual_error"] <= 0.5 * q["threshold"]
            sub = json.loads((res.out_dir / q["name"] / "summary.json").read_text())
            assert sub["design"]["met"] is True and sub["coupling"]["status"] == "converged"
            assert "pathlines.vtp" in res.files or f"{q['name']}/pathlines.vtp" in res.files
        assert "**Verdict: every state met, in the coupled model" in (res.out_dir / "program.md").read_text()
        return
    head = (res.out_dir / "summary.md").read_text().split("\n## ")[0]  # the lines before the first section
    if scene.target.kind != "none":
        assert s["design"]["residual_rms"] <= scene.target.residual
        # its error bar at most half the threshold: the verdict stands whatever the flow's error
        assert s["design"]["residual_error"] <= 0.5 * scene.target.residual
        # the verdict comes first and names its model: coupled, unless the scene says otherwise
        model = "coupled" if scene.carpet.coupling == "mean" else "uncoupled"
        assert f"**Verdict: target met, in the {model} model**" in head
        if model == "coupled":
            assert s["coupling"]["status"] == "converged" and s["coupling"]["residual"] <= s["coupling"]["rtol"]
        ds_layout = tmp_path / scene.name / "layout.nc"
        assert ds_layout.exists()
        assert "design.png" in res.files and s["design"]["cilia_near_cutoff"] >= 0
        r = vtk.vtkXMLPolyDataReader()
        r.SetFileName(str(res.out_dir / "design.vtp"))
        r.Update()
        pd = r.GetOutput().GetPointData()
        res_v = vtk_to_numpy(pd.GetArray("residual"))
        assert res_v.shape == (s["design"]["control_points"],)
        assert math.isclose(float(np.sqrt(np.mean(res_v ** 2))), s["design"]["residual_rms"], rel_tol=1e-6)
        assert vtk_to_numpy(pd.GetArray("target")).shape[1] == 3 and pd.GetArray("achieved") is not None
    for f in ("layout.vtp", "mean_field.vti", "pathlines.vtp", "cilia.pvd", "preview.png", "summary.json",
              "summary.md"):
        assert f in res.files
    # read back: path lines are polylines with the contract's arrays
    r = vtk.vtkXMLPolyDataReader()
    r.SetFileName(str(res.out_dir / "pathlines.vtp"))
    r.Update()
    pd = r.GetOutput()
    assert pd.GetNumberOfCells() == s["pathlines"]["tracers"]
    for name in ("time", "velocity", "speed"):
        assert pd.GetPointData().GetArray(name) is not None
    assert pd.GetCellData().GetArray("TerminationReason") is not None
    r = vtk.vtkXMLImageDataReader()
    r.SetFileName(str(res.out_dir / "mean_field.vti"))
    r.Update()
    v = vtk_to_numpy(r.GetOutput().GetPointData().GetArray("velocity"))
    assert v.shape == (np.prod(scene.output.field_shape), 3) and np.nanmax(np.abs(v)) > 0


def test_design_beats_the_local_layout_and_gradient_is_exact(table):
    bases = layout.square(6, 6, 2.0)
    c = Carpet(bases, 0.0, table, layout.random_phases(36, 0))
    ctrl = bases[(bases[:, 0] < 10) & (bases[:, 1] > 0)] + np.array([1.0, -1.0])
    ang = -0.4 * np.tanh((ctrl[:, 0] - 5) / 4)
    local = design_layout(c, ctrl, angles=ang, maxiter=0, outer=1)
    opt = design_layout(c, ctrl, angles=ang)
    assert opt.residual_rms < 0.5 * local.residual_rms
    assert opt.residual_rms < 0.03
    # mirror symmetry of the focusing layout about x = 5
    k = np.lexsort((bases[:, 1], bases[:, 0]))
    m = np.lexsort((bases[:, 1], 10 - bases[:, 0]))
    assert np.corrcoef(opt.chi_N[k], -opt.chi_N[m])[0, 1] > 0.9


def test_velocity_target_and_unreachable(table):
    bases = layout.square(4, 4, 2.0)
    c = Carpet(bases, 0.0, table)
    ctrl = bases + np.array([1.0, -1.0])
    truth = Carpet(bases, np.linspace(-80, 80, 16), table)
    U = truth.velocity(ctrl, CycleMean())[:, :2]
    d = design_layout(c, ctrl, velocities=U)
    assert d.kind == "velocity" and d.residual_rms < 0.05
    with pytest.raises(TargetError, match="cilium"):
        design_layout(c, ctrl, angles=np.full(16, math.radians(80)))
    with pytest.warns(UserWarning):
        d = design_layout(c, ctrl, angles=np.full(16, math.radians(80)), clip=True)
    assert len(d.clipped) == 16


def _scene_file(tmp_path, body, name="s.toml"):
    p = tmp_path / name
    p.write_text(body)
    return p


def test_output_folder_is_kept_and_atomic(tmp_path, monkeypatch):
    p = _scene_file(tmp_path, '[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 4\nperiods = 1.0\nfield_shape = [8, 8]\n'
                    'snapshots = 1\nframes = 2\npreview = false\n')
    out = tmp_path / "out"
    res = render(load_scene(p), out)
    before = (out / "summary.json").read_text()
    with pytest.raises(RenderError, match="kept"):
        render(load_scene(p), out)
    assert main(["render", str(p), "-o", str(out)]) == 2
    assert (out / "summary.json").read_text() == before
    # an interrupted re-render leaves the old folder and no staging folder
    import ciliary_carpet.output.fields as R

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(R, "write_pvd", boom)
    with pytest.raises(KeyboardInterrupt):
        render(load_scene(p), out, overwrite=True)
    assert (out / "summary.json").read_text() == before
    assert sorted(x.name for x in tmp_path.iterdir() if x.name.startswith(".")) == []
    assert set(res.files) == {x.name for x in out.iterdir()}


def test_cli_design_and_batch_resume(tmp_path):
    body = '[carpet]\nshape = [3, 3]\n[target]\nkind = "uniform"\nangle = 20.0\n[output]\nn_seeds = 4\n' \
           'periods = 1.0\nfield_shape = [8, 8]\nsnapshots = 0\nframes = 1\npreview = false\n'
    a = _scene_file(tmp_path, body, "a.toml")
    b = _scene_file(tmp_path, body.replace("20.0", "-20.0"), "b.toml")
    bad = _scene_file(tmp_path, body + "bogus = 1\n", "bad.toml")
    assert main(["design", str(a), "-o", str(tmp_path / "layout.nc")]) == 0
    import xarray as xr

    with xr.open_dataset(tmp_path / "layout.nc", engine="h5netcdf") as ds:
        assert ds.sizes["cilium"] == 9 and np.all(ds.chi_N.values > 0)
    out = tmp_path / "out"
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as ex:
        recs = batch([a, b, bad], out, executor=ex, progress=False)
    assert [r["status"] for r in recs] == ["done", "done", "failed"]
    assert "bogus" in recs[2]["message"]
    with ThreadPoolExecutor(2) as ex:
        recs = batch([a, b], out, executor=ex, progress=False)
    assert [r["status"] for r in recs] == ["skipped", "skipped"]
    os.utime(a, None)  # the scene changed: re-render it only
    t = (out / "a" / "summary.json").stat().st_mtime
    os.utime(a, (t + 5, t + 5))
    with ThreadPoolExecutor(2) as ex:
        recs = batch([a, b], out, executor=ex, progress=False, overwrite=True)
    assert recs[0]["status"] == "done"
    assert main(["batch", str(a), str(bad), "-o", str(out), "-j", "1"]) == 1


def test_batch_on_a_dask_cluster(tmp_path, monkeypatch):
    """A batch on a cluster of worker processes (as `dask worker` runs them), a scene with a
    target, named by paths relative to this process's folder, which is not the workers': its
    files land in the output folder named here, its layout.nc written on the worker. (Relative
    paths were the workers' own: "cannot read the scene file", and an output root relative to
    their folder; writing a NetCDF file there took a lock of the cluster that its scheduler did
    not know: every scene with a target failed, "Semaphore or Lock ... not known"; a worker in
    the scheduler's own process showed neither.)"""
    from distributed import LocalCluster

    body = '[carpet]\nshape = [2, 2]\n[target]\nkind = "uniform"\nangle = 20.0\nresidual = 0.5\n' \
           '[output]\nn_seeds = 3\nperiods = 1.0\nfield_shape = [8, 8]\nsnapshots = 0\nframes = 1\npreview = false\n'
    _scene_file(tmp_path, body, "a.toml")
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, protocol="tcp",
                      dashboard_address=None) as cl:
        monkeypatch.chdir(tmp_path)  # the workers started in another folder
        recs = batch(["a.toml"], "out", scheduler=cl.scheduler_address, progress=False)
    assert recs[0]["status"] == "done" and recs[0]["scene"] == "a.toml", recs
    summ = json.loads((tmp_path / "out" / "a" / "summary.json").read_text())
    assert summ["n_cilia"] == 4 and summ["design"] is not None
    assert (tmp_path / "out" / "a" / "layout.nc").stat().st_size > 0
