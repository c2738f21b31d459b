import math
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from single_cilium import CiliumParams
from single_cilium.cycle import limit_cycle
from single_cilium.stability import flutter_cutoff
from single_cilium.table import SCHEMA_VERSION, TableError, ThrustTable, build_table

FAST = dict(degree=6, n_phase=32, n_s=17, error_estimate=False)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    path = tmp_path_factory.mktemp("t") / "table.nc"
    with ThreadPoolExecutor(2) as ex:
        t = build_table(200, 1, [130.0, 145.0, 170.0], executor=ex, path=path, **FAST)
    return t, path


def test_rows_and_cutoff(small):
    t, path = small
    ds = t.ds
    c = ds.chi_N.values
    assert c.size == 4 and 160 < c[2] < 165  # the cutoff row, exactly at the Hopf point
    assert ds.attrs["chi_N_cutoff"] == c[2]
    assert ds.flutter.values.tolist() == [1, 1, 1, 0]
    assert float(ds.thrust_norm[2]) == 0 and math.isnan(float(ds.period[3]))
    assert float(ds.thrust_norm[3]) == 0 and np.all(np.isnan(ds.x.values[3]))
    assert np.all(np.diff(ds.thrust_norm.values[:3]) < 0)  # thrust falls towards the cutoff
    assert np.all(ds.thrust_angle.values[:2] > ds.theta_lim.values[:2])
    assert ds.thrust_norm.attrs["units"] == "1"
    assert path.exists() and not path.with_name("table.nc.parts").exists()


def test_save_load_round_trip(small):
    t, path = small
    back = ThrustTable.load(path)
    assert np.array_equal(back.ds.thrust_x.values, t.ds.thrust_x.values)


def test_row_matches_a_fresh_cycle(small):
    t, _ = small
    c = limit_cycle(CiliumParams(200, 1, 145.0), degree=6, n_phase=32, error_estimate=False, floquet=False)
    r = t.at(145.0)
    assert float(r.period) == pytest.approx(c.period, rel=1e-9)
    assert float(r.thrust_norm) == pytest.approx(c.thrust_norm, rel=1e-7)


def test_mirror_and_range(small):
    t, _ = small
    a, b = t.at(140.0), t.at(-140.0)
    assert float(b.thrust_angle) == -float(a.thrust_angle) and float(b.thrust_x) == -float(a.thrust_x)
    assert np.array_equal(b.x.values, -a.x.values) and np.array_equal(b.y.values, a.y.values)
    with pytest.raises(TableError, match="outside the table's range"):
        t.at(100.0)
    with pytest.raises(TableError, match="finite"):
        t.at(float("nan"))


def test_angle_inversion(small):
    t, _ = small
    lo, hi = t.thrust_angle_range()
    target = 0.5 * (lo + hi)
    c = t.chi_N_for_angle(target)
    assert float(t.at(c).thrust_angle) == pytest.approx(target, abs=1e-10)
    assert t.chi_N_for_angle(-target) == pytest.approx(-c)
    with pytest.raises(TableError, match=r"not achievable.*must lie in \["):
        t.chi_N_for_angle(hi + 0.1)
    # an array of angles (a design's, one per cilium): each distinct one solved once, the same numbers
    many = np.array([[target, -target, lo], [target, 0.5 * (lo + target), target]])
    got = t.chi_N_for_angle(many)
    assert got.shape == many.shape
    assert np.array_equal(got, [[t.chi_N_for_angle(float(a)) for a in row] for row in many])
    with pytest.raises(TableError, match="not achievable"):
        t.chi_N_for_angle(np.array([target, hi + 0.1]))


def test_bad_files(tmp_path, small):
    t, _ = small
    junk = tmp_path / "junk.nc"
    junk.write_bytes(b"this is not HDF5" * 10)
    with pytest.raises(TableError, match="not a readable"):
        ThrustTable.load(junk)
    foreign = tmp_path / "foreign.nc"
    xr.Dataset({"a": ("x", [1.0])}).to_netcdf(foreign, engine="h5netcdf")
    with pytest.raises(TableError, match="not a thrust table"):
        ThrustTable.load(foreign)
    old = tmp_path / "old.nc"
    ds = t.ds.copy()
    ds.attrs["schema_version"] = SCHEMA_VERSION + 1
    ds.to_netcdf(old, engine="h5netcdf")
    with pytest.raises(TableError, match="schema version"):
        ThrustTable.load(old)
    with pytest.raises(TableError, match="no such"):
        ThrustTable.load(tmp_path / "missing.nc")


@pytest.mark.parametrize("grid,match", [([1.0, np.nan], "NaN"), ([2.0, 1.0], "increasing"), ([], "non-empty"),
                                        ([-1.0, 1.0], ">= 0")])
def test_bad_grids(grid, match):
    with pytest.raises(ValueError, match=match):
        build_table(200, 1, grid)


def test_interrupted_build_resumes(tmp_path):
    path = tmp_path / "t.nc"
    parts = tmp_path / "t.nc.parts"
    with ThreadPoolExecutor(1) as ex:
        first = build_table(200, 1, [150.0], executor=ex, **FAST)
    parts.mkdir()
    row = first.ds.isel(chi_N=[0]).drop_vars(["phase", "s"]).copy(deep=True)
    row["tip_area"][:] = 12345.0  # a marker: a recomputed row would not carry it
    row.to_netcdf(parts / "row_150.nc", engine="h5netcdf")
    (parts / "row_155.nc").write_bytes(b"cut short")  # not a row this build wrote (it writes them whole)
    with pytest.raises(TableError, match=r"row_155.nc: not a readable row .*left as it is"):
        build_table(200, 1, [150.0, 155.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    assert (parts / "row_155.nc").read_bytes() == b"cut short" and not path.exists()
    (parts / "row_155.nc").unlink()
    with ThreadPoolExecutor(1) as ex:
        t = build_table(200, 1, [150.0, 155.0], executor=ex, path=path, **FAST)
    assert float(t.ds.tip_area.sel(chi_N=150.0)) == 12345.0
    assert np.isfinite(float(t.ds.period.sel(chi_N=155.0)))
    assert not parts.exists()


def test_dask_local_cluster(tmp_path, monkeypatch):
    """A table built on a cluster of worker processes (as `dask worker` runs them) gives the
    numbers of a local build; its file named relative to this process's folder, which is not
    the workers': their finished rows go beside it, not into their own folder."""
    import dask.distributed as distributed
    theirs = Path.cwd()
    name = f"t{os.getpid()}.nc"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, protocol="tcp",
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        monkeypatch.chdir(tmp_path)
        t = build_table(200, 1, [150.0], scheduler=cluster.scheduler_address, path=name, **FAST)
    assert (tmp_path / name).is_file() and not (theirs / (name + ".parts")).exists()
    local = build_table(200, 1, [150.0], executor=ThreadPoolExecutor(1), **FAST)
    assert float(t.ds.thrust_norm[0]) == float(local.ds.thrust_norm[0])


def test_default_table_recomputes_and_interpolates():
    """The shipped table: rows recompute to their stored values, and the interpolant matches a
    freshly computed cycle between rows to 1e-3 relative."""
    t = ThrustTable.default()
    assert t.chi_E == 200 and t.eta == 1
    deg = 8
    c = t.ds.chi_N.values
    k = int(np.argmin(np.abs(c - 100)))
    row = limit_cycle(CiliumParams(200, 1, c[k]), degree=deg, n_phase=64, floquet=False, error_estimate=False)
    assert float(t.ds.thrust_norm[k]) == pytest.approx(row.thrust_norm, rel=1e-6)
    assert float(t.ds.period[k]) == pytest.approx(row.period, rel=1e-8)
    mid = 0.5 * (c[k] + c[k + 1])
    fresh = limit_cycle(CiliumParams(200, 1, mid), degree=deg, n_phase=64, floquet=False, error_estimate=False)
    r = t.at(mid)
    assert float(r.thrust_norm) == pytest.approx(fresh.thrust_norm, rel=1e-3)
    assert float(r.thrust_angle) == pytest.approx(fresh.thrust_angle, rel=1e-3)
    assert float(r.period) == pytest.approx(fresh.period, rel=1e-3)
    shape_err = np.max(np.abs(r.x.values - fresh.mesh.interpolate(fresh.data.x.values.T, t.ds.s.values).T))
    assert shape_err < 1e-3
    # the last interval before the cutoff, where the amplitude grows like sqrt(chi_c - chi_N)
    mid = 0.5 * (c[-3] + c[-2])
    fresh = limit_cycle(CiliumParams(200, 1, mid), degree=deg, n_phase=64, floquet=False, error_estimate=False)
    r = t.at(mid)
    assert float(r.thrust_norm) == pytest.approx(fresh.thrust_norm, rel=1e-3)
    assert np.max(np.abs(r.y.values - fresh.mesh.interpolate(fresh.data.y.values.T, t.ds.s.values).T)) < 1e-3


def test_vectorised_cycles_and_scalars_match_at():
    t = ThrustTable.default()
    c = np.array([-60.0, 0.0, 33.3, 120.0, 165.0])
    cyc = t.cycles(c)
    assert cyc["flutter"].tolist() == [True, True, True, True, False]
    for i, ch in enumerate(c[:4]):
        row = t.at(ch)
        for k in ("x", "y", "fx", "fy"):
            assert np.array_equal(cyc[k][i], row[k].values)
        assert t.scalar("thrust_x", ch) == pytest.approx(float(row.thrust_x), abs=1e-12)
        assert t.scalar("period", ch) == pytest.approx(float(row.period), abs=1e-15)
    assert np.all(cyc["fx"][4] == 0) and np.all(np.isnan(cyc["x"][4]))
    assert t.scalar("thrust_x", 165.0) == 0.0 and np.isnan(t.scalar("period", 165.0))
    # derivatives: odd/even mirror rules against central differences
    h = 1e-4
    for name in ("thrust_x", "thrust_y", "period"):
        d = t.scalar(name, c[:4], nu=1)
        fd = (t.scalar(name, c[:4] + h) - t.scalar(name, c[:4] - h)) / (2 * h)
        np.testing.assert_allclose(d, fd, rtol=1e-5, atol=1e-9)
    with pytest.raises(TableError, match="outside"):
        t.cycles([500.0])
    with pytest.raises(TableError, match="finite"):
        t.scalar("thrust_x", np.nan)
    with pytest.raises(KeyError, match="scalar column"):
        t.scalar("x", 1.0)


def _interrupted(tmp_path, grid, chi_E=200.0):
    """A build into ``t.nc`` whose rows are left in ``t.nc.parts`` as an interruption leaves them."""
    path = tmp_path / "t.nc"
    parts = tmp_path / "t.nc.parts"
    with ThreadPoolExecutor(1) as ex:
        first = build_table(chi_E, 1, grid, executor=ex, **FAST)
    parts.mkdir()
    for c in grid:
        first.ds.sel(chi_N=[c]).drop_vars(["phase", "s"]).to_netcdf(parts / f"row_{c:.17g}.nc", engine="h5netcdf")
    return path, parts


def test_resume_refuses_rows_of_another_field(tmp_path):
    """Issue 11 item 2: rows computed for chi_E = 200 are never merged into a chi_E = 220 table."""
    path, parts = _interrupted(tmp_path, [150.0])
    with pytest.raises(TableError, match=r"row_150.nc: .*other settings \(chi_E = 200.0 \(asked 220.0\)\).*remove"):
        build_table(220, 1, [150.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    assert not path.exists() and (parts / "row_150.nc").exists()  # nothing written, nothing lost
    # other discretisation settings are refused the same way
    with pytest.raises(TableError, match=r"n_phase = 32 \(asked 16\)"):
        build_table(200, 1, [150.0], executor=ThreadPoolExecutor(1), path=path, **{**FAST, "n_phase": 16})


def test_resume_ignores_rows_outside_the_grid(tmp_path):
    path, parts = _interrupted(tmp_path, [150.0])
    with ThreadPoolExecutor(1) as ex:
        t = build_table(200, 1, [155.0], executor=ex, path=path, **FAST)
    assert t.ds.chi_N.values.tolist() == [155.0]


@pytest.mark.parametrize("value", [float("nan"), "two hundred", float("inf")])
def test_table_attribute_not_a_number(tmp_path, small, value):
    """Issue 11 item 9: a table whose chi_E is NaN or not a number fails validation, naming the
    file and the attribute."""
    t, _ = small
    bad = tmp_path / "bad.nc"
    ds = t.ds.copy()
    ds.attrs["chi_E"] = value
    ds.to_netcdf(bad, engine="h5netcdf")
    with pytest.raises(TableError, match=rf"{bad.name}: attribute 'chi_E' = .* is not a finite number"):
        ThrustTable.load(bad)


def test_failed_row_names_the_last_good_row(tmp_path, monkeypatch):
    """A continuation that fails reports the row and the last good one; the rows before it are
    kept, and the same request resumes from them."""
    import single_cilium.table as table_mod
    from single_cilium.cycle import CycleError

    real = table_mod.limit_cycle

    def failing(p, **kw):
        if p.chi_N == 155.0:
            raise CycleError("injected failure", 0.0)
        return real(p, **kw)

    monkeypatch.setattr(table_mod, "limit_cycle", failing)
    path = tmp_path / "t.nc"
    with pytest.raises(CycleError, match=r"chi_N = 155 did not converge .*last good row before it: "
                                         r"chi_N = 150.*resumes"):
        build_table(200, 1, [150.0, 155.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    assert (tmp_path / "t.nc.parts" / "row_150.nc").exists() and not path.exists()
    monkeypatch.setattr(table_mod, "limit_cycle", real)
    t = build_table(200, 1, [150.0, 155.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    assert t.ds.sizes["chi_N"] == 2 and path.exists()


# ------------------------------------------------------------------------------ tables over chi_E
GRID_E = [180.0, 200.0, 220.0]


@pytest.fixture(scope="module")
def over_chi_E(tmp_path_factory):
    path = tmp_path_factory.mktemp("t2") / "table2d.nc"
    with ThreadPoolExecutor(2) as ex:
        t = build_table(GRID_E, 1, np.linspace(0.0, 190.0, 11), executor=ex, path=path, **FAST)
    return t, path


def test_chi_E_grid_rows_cutoffs_and_coiled(over_chi_E):
    t, path = over_chi_E
    ds = t.ds
    assert ds.flutter.dims == ("chi_E", "chi_N") and ds.x.dims == ("chi_E", "chi_N", "phase", "s")
    cut = ds.chi_N_cutoff.values
    assert 130 < cut[0] < cut[1] < cut[2] < 190  # the cutoff grows with the field
    c = ds.chi_N.values
    assert all(x in c for x in cut) and c.size == 11 + 3  # every field's cutoff is a row of every field
    for i, E in enumerate(GRID_E):
        fl = ds.flutter.values[i].astype(bool)
        assert np.array_equal(fl, c <= cut[i])  # no flutter above the field's own cutoff
        assert np.array_equal(ds.coiled.values[i].astype(bool), c > E)  # chi_E = 180: 186.8 and 190 coil
        assert float(ds.thrust_norm[i, list(c).index(cut[i])]) == 0.0
    assert ds.coiled.values[0, -1] == 1 and np.isnan(float(ds.theta_lim[0, -1])) and np.isnan(float(ds.alpha[0, -1]))
    assert ds.attrs["build_chi_E_grid"] == "180,200,220" and "chi_E" not in ds.attrs
    # round trip: the chi_E dimension, its cutoffs and every row come back
    back = ThrustTable.load(path)
    assert back.ds.chi_E.values.tolist() == GRID_E
    assert back.ds.identical(t.ds)
    assert back.chi_E_range == (180.0, 220.0) and back.chi_N_range == (0.0, 190.0)


def test_chi_E_grid_values_are_the_fields_tables(over_chi_E):
    """At a field of the grid the table is that field's own table: a one-field build agrees."""
    t, _ = over_chi_E
    one = build_table(200, 1, [60.0, 76.0], executor=ThreadPoolExecutor(1), **FAST)
    r2, r1 = t.at(76.0, chi_E=200), one.at(76.0)
    assert float(r2.chi_E) == 200
    assert float(r2.period) == pytest.approx(float(r1.period), rel=1e-7)
    assert float(r2.thrust_norm) == pytest.approx(float(r1.thrust_norm), rel=1e-6)


def test_chi_E_interpolation_against_fresh_cycles(over_chi_E):
    """Between the fields (chi_E = 190, 210: half way between grid values 20 apart) the
    interpolant matches fresh cycles of the same discretisation: measured 1.6e-4 - 2.3e-4 in
    period, 2.3e-4 - 2e-3 in |thrust| up to 0.9 chi_c, 2.6e-4 rad in angle, 3e-4 in the cutoff."""
    t, _ = over_chi_E
    for E in (190.0, 210.0):
        cut = flutter_cutoff(E, 1.0, degree=6).chi_N_cutoff
        sub = t._table(E)
        assert sub.ds.attrs["chi_N_cutoff"] == pytest.approx(cut, rel=5e-4)
        for cN in (50.0, 0.9 * cut):
            fresh = limit_cycle(CiliumParams(E, 1, cN), degree=6, n_phase=32, error_estimate=False, floquet=False)
            r = t.at(cN, chi_E=E)
            assert int(r.flutter) == 1
            assert float(r.period) == pytest.approx(fresh.period, rel=5e-4)
            assert float(r.thrust_norm) == pytest.approx(fresh.thrust_norm, rel=3e-3)
            assert float(r.thrust_angle) == pytest.approx(fresh.thrust_angle, abs=5e-4)
            x = fresh.mesh.interpolate(fresh.data.x.values.T, t.ds.s.values).T
            assert np.max(np.abs(r.x.values - x)) < 1e-3
        assert int(t.at(1.01 * cut, chi_E=E).flutter) == 0  # above its own cutoff: no flutter
        assert t.scalar("thrust_x", 1.01 * cut, chi_E=E) == 0.0


def test_chi_E_knob_inversion_and_vectorised(over_chi_E):
    t, _ = over_chi_E
    lo, hi = t.thrust_angle_range(chi_E=205.0)
    target = 0.5 * (lo + hi)
    c = t.chi_N_for_angle(target, chi_E=205.0)
    assert float(t.at(c, chi_E=205.0).thrust_angle) == pytest.approx(target, abs=1e-10)
    assert t.chi_N_for_angle(-target, chi_E=205.0) == pytest.approx(-c)
    cyc = t.cycles([-50.0, 100.0, 185.0], chi_E=205.0)
    assert cyc["flutter"].tolist() == [True, True, False]
    assert np.array_equal(cyc["x"][1], t.at(100.0, chi_E=205.0).x.values)
    assert t.scalar("thrust_x", -50.0, chi_E=205.0) == pytest.approx(-float(t.at(50.0, chi_E=205.0).thrust_x))
    # the stronger field turns the same curvature into a smaller angle (its cutoff lies further out)
    assert t.scalar("thrust_angle", 100.0, chi_E=215.0) < t.scalar("thrust_angle", 100.0, chi_E=185.0)


def test_chi_E_requests_that_cannot_be_served(over_chi_E, small):
    t, _ = over_chi_E
    with pytest.raises(TableError, match=r"spans chi_E in \[180, 220\]: say which field"):
        t.at(50.0)
    with pytest.raises(TableError, match=r"chi_E = 230 is outside the table's range \[180, 220\]"):
        t.at(50.0, chi_E=230.0)
    with pytest.raises(TableError, match="no single chi_E"):
        t.chi_E
    with pytest.raises(TableError, match="flutter branch per field"):
        t.flutter_range
    one, _ = small
    assert float(one.at(140.0, chi_E=200).period) == float(one.at(140.0).period)
    with pytest.raises(TableError, match=r"for chi_E = 200 only .*chi_E grid"):
        one.at(140.0, chi_E=210.0)


@pytest.mark.parametrize("grid,match", [([200.0], "at least 2"), ([220.0, 200.0], "increasing"),
                                        ([-10.0, 200.0], "> 0"), ([np.nan, 200.0], "NaN")])
def test_bad_chi_E_grids(grid, match):
    with pytest.raises(ValueError, match=match):
        build_table(grid, 1, [100.0])


def test_resume_fingerprint_includes_the_chi_E_grid(tmp_path, over_chi_E):
    """Rows of a build over one chi_E grid are refused by a build over another (continued from
    other fields) and by a one-field build."""
    t, _ = over_chi_E
    path, parts = tmp_path / "t.nc", tmp_path / "t.nc.parts"
    parts.mkdir()
    row = t.ds.isel(chi_E=[1], chi_N=[3]).drop_vars(["phase", "s", "chi_N_cutoff", "chi_N_cutoff_error"])
    row.to_netcdf(parts / "row_200_57.nc", engine="h5netcdf")
    with pytest.raises(TableError, match=r"chi_E_grid = None \(asked '180,210'\)|chi_E_grid = '180,200,220' "
                                         r"\(asked '180,210'\)"):
        build_table([180.0, 210.0], 1, [57.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    with pytest.raises(TableError, match=r"chi_E = None \(asked 200.0\)"):
        build_table(200.0, 1, [57.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    assert (parts / "row_200_57.nc").exists() and not path.exists()


def test_failed_row_of_a_chi_E_grid_names_its_field(tmp_path, monkeypatch):
    import single_cilium.table as table_mod
    from single_cilium.cycle import CycleError

    real = table_mod.limit_cycle

    def failing(p, **kw):
        if (p.chi_E, p.chi_N) == (210.0, 57.0):
            raise CycleError("injected failure", 0.0)
        return real(p, **kw)

    monkeypatch.setattr(table_mod, "limit_cycle", failing)
    path = tmp_path / "t.nc"
    with pytest.raises(CycleError, match=r"chi_E = 210, eta = 1\): the cycle at chi_N = 57 did not converge .*"
                                         r"last good row before it: chi_N = 50.*resumes"):
        build_table([190.0, 210.0], 1, [50.0, 57.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    assert sorted(f.name for f in (tmp_path / "t.nc.parts").glob("row_*.nc")) == [
        "row_190_50.nc", "row_190_57.nc", "row_210_50.nc"]
