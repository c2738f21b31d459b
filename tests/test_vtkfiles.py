"""VTK output: files read back with plain vtk readers, atomic writes, input validation."""
import os
import pickle
import stat
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv
import vtk
from vtk.util.numpy_support import vtk_to_numpy

import cilia_runtime.files as single_cilium_files
from ciliary_carpet.output import vtkfiles
from ciliary_carpet.output.vtkfiles import (
    OutputError,
    PvdEntry,
    grid_points,
    write_cilia,
    write_field,
    write_pathlines,
    write_points,
    write_pvd,
)

REASONS = ("reached end time", "entered a cilium's swept region", "left the domain", "step size underflow")


def read(path):
    reader = vtk.vtkXMLImageDataReader() if str(path).endswith(".vti") else vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    return reader


def arr(data, name):
    a = data.GetArray(name)
    assert a is not None, f"missing array {name}"
    return vtk_to_numpy(a)


def cells(poly):
    out = []
    for c in range(poly.GetNumberOfCells()):
        ids = poly.GetCell(c).GetPointIds()
        out.append([ids.GetId(i) for i in range(ids.GetNumberOfIds())])
    return out


def strings(field, name):
    a = field.GetAbstractArray(name)
    assert isinstance(a, vtk.vtkStringArray)
    return [a.GetValue(i) for i in range(a.GetNumberOfValues())]


def time_steps(reader):
    return reader.GetOutputInformation(0).Get(vtk.vtkStreamingDemandDrivenPipeline.TIME_STEPS())


@pytest.fixture
def tracers():
    rng = np.random.default_rng(1)
    n = [5, 1, 3, 2]
    pts = [rng.normal(size=(k, 3)) for k in n]
    ts = [np.sort(rng.uniform(0, 2, size=k)) for k in n]
    vs = [rng.normal(size=(k, 3)) for k in n]
    return dict(points=pts, times=ts, velocities=vs, seed_ids=np.array([7, 3, 11, 0]),
                reasons=np.array([0, 1, 2, 3]), reason_names=REASONS)


# ------------------------------------------------------------------------------------ pathlines


def test_pathlines_read_back(tmp_path, tracers):
    out = write_pathlines(tmp_path / "sub" / "paths.vtp", **tracers)
    assert out == tmp_path / "sub" / "paths.vtp" and out.is_file()
    poly = read(out).GetOutput()
    n = [len(p) for p in tracers["points"]]
    assert poly.GetNumberOfPoints() == sum(n)
    assert poly.GetNumberOfCells() == poly.GetNumberOfLines() == 4
    X = vtk_to_numpy(poly.GetPoints().GetData())
    for k, ids in enumerate(cells(poly)):  # polyline k is exactly points[k], in order
        assert len(ids) == n[k]
        np.testing.assert_array_equal(X[ids], tracers["points"][k])
    pd, cd = poly.GetPointData(), poly.GetCellData()
    np.testing.assert_array_equal(arr(pd, "time"), np.concatenate(tracers["times"]))
    assert arr(pd, "time").dtype == np.float64
    v = np.concatenate(tracers["velocities"])
    np.testing.assert_array_equal(arr(pd, "velocity"), v)
    np.testing.assert_allclose(arr(pd, "speed"), np.linalg.norm(v, axis=1), rtol=1e-15)
    np.testing.assert_array_equal(arr(cd, "SeedIds"), [7, 3, 11, 0])
    np.testing.assert_array_equal(arr(cd, "TerminationReason"), [0, 1, 2, 3])
    assert arr(cd, "TerminationReason").dtype.kind == "i"
    assert cd.GetArray("ReasonForTermination") is None  # VTK's name, other codes: not used
    assert strings(poly.GetFieldData(), "TerminationReasonNames") == list(REASONS)
    np.testing.assert_allclose(arr(pd, "IntegrationTime"),
                               np.concatenate([t - t[0] for t in tracers["times"]]))
    assert pd.GetVectors().GetName() == "velocity"


def test_pathlines_validation(tmp_path, tracers):
    p = tmp_path / "p.vtp"
    bad = dict(tracers, points=[*tracers["points"][:3], np.full((2, 3), np.nan)])
    with pytest.raises(ValueError, match=r"points\[3\]"):
        write_pathlines(p, **bad)
    with pytest.raises(ValueError, match=r"points\[0\]"):
        write_pathlines(p, **dict(tracers, points=[np.zeros((5, 2)), *tracers["points"][1:]]))
    with pytest.raises(ValueError, match=r"times\[2\]"):
        write_pathlines(p, **dict(tracers, times=[*tracers["times"][:2], np.zeros(4), tracers["times"][3]]))
    with pytest.raises(ValueError, match=r"times\[0\]"):
        write_pathlines(p, **dict(tracers, times=[np.full(5, np.inf), *tracers["times"][1:]]))
    with pytest.raises(ValueError, match="velocities"):
        write_pathlines(p, **dict(tracers, velocities=tracers["velocities"][:3]))
    with pytest.raises(ValueError, match="seed_ids"):
        write_pathlines(p, **dict(tracers, seed_ids=[1, 2]))
    with pytest.raises(ValueError, match="reasons"):
        write_pathlines(p, **dict(tracers, reasons=[0, 1, 2, 4]))
    with pytest.raises(ValueError, match="reason_names"):
        write_pathlines(p, **dict(tracers, reason_names="abcd"))
    with pytest.raises(ValueError, match=r"points\[1\]"):
        write_pathlines(p, **dict(tracers, points=[tracers["points"][0], np.zeros((0, 3)), *tracers["points"][2:]]))
    with pytest.raises(ValueError, match=r"\.vtp"):
        write_pathlines(tmp_path / "p.vtk", **tracers)
    assert not any(tmp_path.iterdir())


# ---------------------------------------------------------------------------------------- field


def test_grid_points_order_matches_vtk(tmp_path):
    origin, spacing, shape = (1.0, -2.0, 0.5), (0.25, 0.5, 2.0), (4, 3, 2)
    X = grid_points(origin, spacing, shape)
    assert X.shape == (24, 3)
    nx, ny, _ = shape
    i, j, k = 3, 1, 1
    np.testing.assert_allclose(X[i + nx * (j + ny * k)], np.array(origin) + np.array([i, j, k]) * spacing)
    u = np.stack([np.sin(X[:, 0]), X[:, 1] * X[:, 2], np.ones(len(X))], axis=1)
    out = write_field(tmp_path / "u.vti", origin, spacing, shape,
                      {"velocity": u, "speed": np.linalg.norm(u, axis=1), "mask": X[:, 0] > 1.2,
                       "label": np.arange(24)}, time=0.75)
    reader = read(out)
    img = reader.GetOutput()
    assert img.GetDimensions() == shape
    np.testing.assert_allclose(img.GetOrigin(), origin)
    np.testing.assert_allclose(img.GetSpacing(), spacing)
    assert img.GetNumberOfPoints() == 24
    np.testing.assert_allclose([img.GetPoint(p) for p in range(24)], X, rtol=0, atol=1e-14)
    pd = img.GetPointData()
    np.testing.assert_array_equal(arr(pd, "velocity"), u)
    np.testing.assert_allclose(arr(pd, "speed"), np.linalg.norm(u, axis=1))
    np.testing.assert_array_equal(arr(pd, "mask"), (X[:, 0] > 1.2).astype(np.uint8))
    np.testing.assert_array_equal(arr(pd, "label"), np.arange(24))
    np.testing.assert_array_equal(arr(img.GetFieldData(), "TimeValue"), [0.75])
    assert time_steps(reader) == (0.75,)  # the XML reader reports TimeValue as the file's time

    # a field held as [i, j, k] arrays reaches the same order with order="F"
    a = X.reshape(2, 3, 4, 3).transpose(2, 1, 0, 3)  # a[i, j, k] = point (i, j, k)
    np.testing.assert_array_equal(a.reshape(24, 3, order="F"), X)


def test_field_without_time_and_nan_data(tmp_path):
    u = np.zeros((6, 3))
    u[2] = np.nan  # blanked point: allowed in data
    out = write_field(tmp_path / "f.vti", (0, 0, 0), (1, 1, 1), (3, 2, 1), {"velocity": u})
    img = read(out).GetOutput()
    assert img.GetDimensions() == (3, 2, 1)
    assert img.GetFieldData().GetArray("TimeValue") is None
    assert np.isnan(arr(img.GetPointData(), "velocity")[2]).all()


def test_field_validation(tmp_path):
    p = tmp_path / "f.vti"
    ok = dict(origin=(0, 0, 0), spacing=(1, 1, 1), shape=(2, 2, 2), arrays={"speed": np.ones(8)})
    for key, value, match in [
        ("origin", (0, np.nan, 0), "origin"),
        ("origin", (0, 0), "origin"),
        ("spacing", (1, 0, 1), "spacing"),
        ("shape", (2, 2), "shape"),
        ("shape", (2, 0, 2), "shape"),
        ("arrays", {"speed": np.ones(7)}, "speed"),
        ("arrays", {"velocity": np.ones((2, 2, 2, 3))}, "velocity"),
        ("arrays", {"name": np.array(["a"] * 8)}, "name"),
    ]:
        with pytest.raises(ValueError, match=match):
            write_field(p, **dict(ok, **{key: value}))
    with pytest.raises(ValueError, match="time"):
        write_field(p, **ok, time=np.nan)
    with pytest.raises(ValueError, match="spacing"):
        grid_points((0, 0, 0), (1, -1, 1), (2, 2, 2))
    assert not p.exists()


# ---------------------------------------------------------------------------------------- cilia


def test_cilia_read_back(tmp_path):
    rng = np.random.default_rng(2)
    C, n_s = 3, 6
    s = np.linspace(0, 1, n_s)
    shapes = rng.normal(size=(C, n_s, 3))
    drag = rng.normal(size=(C, n_s, 3))
    ids, chi, phase = np.array([4, 5, 9]), np.array([8.0, 16.0, 24.0]), np.array([0.0, 0.25, 1.0])
    out = write_cilia(tmp_path / "cilia.vtp", shapes, s, ids, chi, phase, drag=drag, time=3.5)
    reader = read(out)
    poly = reader.GetOutput()
    assert poly.GetNumberOfPoints() == C * n_s and poly.GetNumberOfLines() == C == poly.GetNumberOfCells()
    X = vtk_to_numpy(poly.GetPoints().GetData())
    for c, line in enumerate(cells(poly)):
        np.testing.assert_array_equal(X[line], shapes[c])
    cd, pd = poly.GetCellData(), poly.GetPointData()
    np.testing.assert_array_equal(arr(cd, "cilium_id"), ids)
    np.testing.assert_array_equal(arr(cd, "chi_N"), chi)
    np.testing.assert_array_equal(arr(cd, "phase"), [0.0, 0.25, 0.0])  # exactly 1 folds to 0
    np.testing.assert_array_equal(arr(pd, "arc_length"), np.tile(s, C))
    np.testing.assert_array_equal(arr(pd, "drag_density"), drag.reshape(-1, 3))
    assert time_steps(reader) == (3.5,)
    # the data in one raw (not base64) appended block, LZ4-compressed: a quarter smaller and three
    # times faster to make than base64 (vtkfiles._mesh_bytes)
    text = out.read_bytes()
    head = text[:text.index(b"<AppendedData")].decode("ascii")
    assert 'compressor="vtkLZ4DataCompressor"' in head and 'format="appended"' in head
    assert 'format="binary"' not in head
    assert b'<AppendedData encoding="raw">' in text

    out = write_cilia(tmp_path / "bare.vtp", shapes, s, ids, chi, phase)
    poly = read(out).GetOutput()
    assert poly.GetPointData().GetArray("drag_density") is None
    assert poly.GetFieldData().GetArray("TimeValue") is None


def test_cilia_validation(tmp_path):
    p = tmp_path / "c.vtp"
    ok = dict(shapes=np.zeros((2, 4, 3)), s=np.linspace(0, 1, 4), cilium_ids=[0, 1], chi_N=[1.0, 2.0],
              phase=[0.1, 0.2])
    nan_shapes = np.zeros((2, 4, 3))
    nan_shapes[1, 2, 0] = np.nan
    for key, value, match in [
        ("shapes", nan_shapes, "shapes"),
        ("shapes", np.zeros((2, 4)), "shapes"),
        ("s", np.linspace(0, 1, 5), "s must"),
        ("cilium_ids", [0, 1, 2], "cilium_ids"),
        ("cilium_ids", [0.5, 1], "cilium_ids"),
        ("chi_N", [1.0, np.inf], "chi_N"),
        ("phase", [0.1, 1.5], "phase"),
    ]:
        with pytest.raises(ValueError, match=match):
            write_cilia(p, **dict(ok, **{key: value}))
    with pytest.raises(ValueError, match="drag"):
        write_cilia(p, **ok, drag=np.zeros((2, 3, 3)))
    assert not p.exists()


# --------------------------------------------------------------------------------------- points


def test_points_read_back(tmp_path):
    X = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 0.8, 0]])
    out = write_points(tmp_path / "layout.vtp", X, {"chi_N": [8.0, 16.0, 24.0], "cilium_id": np.arange(3)})
    poly = read(out).GetOutput()
    assert poly.GetNumberOfPoints() == 3 and poly.GetNumberOfVerts() == 3 == poly.GetNumberOfCells()
    assert cells(poly) == [[0], [1], [2]]
    np.testing.assert_array_equal(vtk_to_numpy(poly.GetPoints().GetData()), X)
    np.testing.assert_array_equal(arr(poly.GetPointData(), "chi_N"), [8.0, 16.0, 24.0])
    np.testing.assert_array_equal(arr(poly.GetPointData(), "cilium_id"), [0, 1, 2])
    with pytest.raises(ValueError, match="points"):
        write_points(tmp_path / "x.vtp", [[0, 0, np.nan]], {})
    with pytest.raises(ValueError, match="chi_N"):
        write_points(tmp_path / "x.vtp", X, {"chi_N": [1.0, 2.0]})


# ------------------------------------------------------------------------------------------ pvd


def test_pvd(tmp_path):
    frames = tmp_path / "run" / "frames"
    files = []
    for t in (0.2, 0.0, 0.1):  # written out of order
        files.append(write_points(frames / f"p_{t:.1f}.vtp", np.zeros((1, 3)), {}))
    cil = write_points(frames / "c_0.0.vtp", np.zeros((1, 3)), {})
    entries = [(0.2, files[0]), PvdEntry(0.0, files[1]), (0.1, str(files[2]), 0), (0.0, cil, 1)]
    out = write_pvd(tmp_path / "run" / "series.pvd", entries)
    root = ET.parse(out).getroot()
    assert root.tag == "VTKFile" and root.get("type") == "Collection"
    assert root.get("version") == "0.1" and root.get("byte_order") == "LittleEndian"
    ds = root.find("Collection").findall("DataSet")
    assert [d.get("timestep") for d in ds] == ["0.0", "0.0", "0.1", "0.2"]
    assert [d.get("file") for d in ds] == ["frames/p_0.0.vtp", "frames/c_0.0.vtp", "frames/p_0.1.vtp",
                                           "frames/p_0.2.vtp"]
    assert [d.get("part") for d in ds] == ["0", "1", "0", "0"]
    assert all(d.get("group") == "" for d in ds)
    for d in ds:  # relative to the .pvd's folder
        assert not os.path.isabs(d.get("file")) and (out.parent / d.get("file")).is_file()


def test_pvd_validation(tmp_path):
    inside = write_points(tmp_path / "a" / "x.vtp", np.zeros((1, 3)), {})
    outside = write_points(tmp_path / "b.vtp", np.zeros((1, 3)), {})
    p = tmp_path / "a" / "s.pvd"
    with pytest.raises(ValueError, match="not inside"):
        write_pvd(p, [(0.0, outside)])
    with pytest.raises(ValueError, match="does not exist"):
        write_pvd(p, [(0.0, tmp_path / "a" / "missing.vtp")])
    with pytest.raises(ValueError, match="time"):
        write_pvd(p, [(np.nan, inside)])
    with pytest.raises(ValueError, match="twice"):
        write_pvd(p, [(0.0, inside), (0.0, inside)])
    with pytest.raises(ValueError, match="entries"):
        write_pvd(p, [(0.0,)])
    assert not p.exists()


# ------------------------------------------------------------------------------- atomic output


def _leftovers(folder):
    return [f.name for f in folder.iterdir() if f.name.startswith(".")]


def test_failed_save_leaves_target_and_no_temporary(tmp_path, tracers, monkeypatch):
    target = tmp_path / "paths.vtp"
    target.write_bytes(b"previous contents")
    real_write = os.write
    seen = []

    def broken_write(fd, data):
        real_write(fd, bytes(data)[:10])  # part of the temporary is written ...
        seen.append(os.path.basename(os.readlink(f"/proc/self/fd/{fd}")) if os.path.isdir("/proc/self/fd") else ".")
        raise RuntimeError("disk on fire")  # ... and then the write fails

    monkeypatch.setattr(single_cilium_files.os, "write", broken_write)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_pathlines(target, **tracers)
    assert seen and seen[0].startswith(".")  # hidden
    assert target.read_bytes() == b"previous contents"
    assert _leftovers(tmp_path) == []


def test_failed_pvd_write_leaves_target(tmp_path, monkeypatch):
    f = write_points(tmp_path / "x.vtp", np.zeros((1, 3)), {})
    target = tmp_path / "s.pvd"
    target.write_text("old")

    real_write = os.write

    def broken_write(fd, data):
        real_write(fd, b"<VTKFile")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(single_cilium_files.os, "write", broken_write)
    with pytest.raises(OutputError, match="s.pvd.*no space left on device"):
        write_pvd(target, [(0.0, f)])
    assert target.read_text() == "old"
    assert _leftovers(tmp_path) == []


def test_no_private_names_of_pyvista_or_vtk():
    """The writers use VTK's and pyvista's public API only (no attribute starting with '_')."""
    import ast

    tree = ast.parse(Path(vtkfiles.__file__).read_text())
    private = sorted({n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)
                      and n.attr.startswith("_") and not n.attr.startswith("__")})
    assert private == []


def test_vtk_writer_failure_is_an_error(tmp_path, tracers, monkeypatch):
    """VTK's errors (which pyvista's save only logs) are an OutputError naming the file."""
    def failing(mesh, path):
        raise pv.VTKExecutionError("ERROR:\nvtkXMLPolyDataWriter (0x1): Error writing the data")

    monkeypatch.setattr(vtkfiles, "_mesh_bytes", failing)
    with pytest.raises(OutputError, match=r"paths\.vtp.*VTK could not write.*Error writing the data"):
        write_pathlines(tmp_path / "paths.vtp", **tracers)
    assert not (tmp_path / "paths.vtp").exists()
    assert _leftovers(tmp_path) == []

    monkeypatch.setattr(vtkfiles, "_mesh_bytes", lambda mesh, path: b"")  # writes nothing
    with pytest.raises(OutputError, match="empty file"):
        write_pathlines(tmp_path / "paths.vtp", **tracers)
    assert _leftovers(tmp_path) == []


def test_overwrite_and_permissions(tmp_path, tracers):
    target = tmp_path / "paths.vtp"
    target.write_bytes(b"old")
    write_pathlines(target, **tracers)
    assert read(target).GetOutput().GetNumberOfLines() == 4
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~umask
    assert _leftovers(tmp_path) == []


def test_unwritable_folder(tmp_path, tracers):
    blocker = tmp_path / "file"
    blocker.write_text("I am a file")
    target = blocker / "sub" / "paths.vtp"
    with pytest.raises(OutputError, match="paths.vtp") as info:
        write_pathlines(target, **tracers)
    assert isinstance(info.value, OSError) and info.value.path == target
    with pytest.raises(OutputError, match="series.pvd"):
        write_pvd(blocker / "series.pvd", [])
    # the target is an existing folder: rename fails, nothing is left behind
    (tmp_path / "dir.vti").mkdir()
    with pytest.raises(OutputError, match="dir.vti"):
        write_field(tmp_path / "dir.vti", (0, 0, 0), (1, 1, 1), (2, 1, 1), {"speed": np.ones(2)})
    assert _leftovers(tmp_path) == []
    err = pickle.loads(pickle.dumps(info.value))  # e.g. raised on a dask worker
    assert isinstance(err, OutputError) and str(err) == str(info.value)


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root can write to read-only folders")
def test_read_only_folder(tmp_path, tracers):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(OutputError, match="Permission denied"):
            write_pathlines(ro / "paths.vtp", **tracers)
    finally:
        ro.chmod(0o755)


def test_permission_denied_is_output_error(tmp_path, tracers, monkeypatch):
    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(single_cilium_files.tempfile, "mkstemp", denied)
    with pytest.raises(OutputError, match=r"paths\.vtp.*Permission denied") as info:
        write_pathlines(tmp_path / "paths.vtp", **tracers)
    assert info.value.errno == 13
