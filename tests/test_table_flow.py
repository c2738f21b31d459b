"""The thrust table over the background flow (issue 27): dims U_par, U_perp, chi_N; the flow
U = U_par e2 + U_perp e1 in the field frame (CiliumParams(..., background=(U_perp, U_par))).

The default tests use a small, coarse table (degree 6, 32 steps, no error estimates: seconds);
the shipped table (degree 8, 64 steps) is checked against a few fresh cycles of its own
discretisation (its interpolation error over many points is measured by
benchmarks/bench_table_flow.py --sections shipped).
"""
import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from single_cilium import CiliumParams, steady_state
from single_cilium.cycle import CycleError, limit_cycle
from single_cilium.stability import flutter_cutoff
from single_cilium.table import SCHEMA_VERSION, TableError, ThrustTable, build_table
from single_cilium.tablefile import REGIMES

FAST = dict(degree=6, n_phase=32, n_s=17, error_estimate=False)
GRID = [0.0, 80.0, 140.0, 180.0]
U = [-1.0, 0.0, 1.0]


def fresh(cN, up, uq):
    return limit_cycle(CiliumParams(200, 1, cN, (uq, up)), degree=6, n_phase=32, error_estimate=False, floquet=False)


@pytest.fixture(scope="module")
def flow(tmp_path_factory):
    path = tmp_path_factory.mktemp("f") / "flow.nc"
    with ThreadPoolExecutor(2) as ex:
        t = build_table(200, 1, GRID, U_par=U, U_perp=U, executor=ex, path=path, **FAST)
    return t, path


@pytest.fixture(scope="module")
def still():
    with ThreadPoolExecutor(2) as ex:
        return build_table(200, 1, GRID, executor=ex, **FAST)


def test_schema_rows_cutoffs_and_holes(flow):
    t, path = flow
    ds = t.ds
    assert ds.thrust_x.dims == ("U_par", "U_perp", "chi_N") and ds.x.dims == ("U_par", "U_perp", "chi_N", "phase", "s")
    assert ds.rest_fx.dims == ("U_par", "U_perp", "chi_N", "s")
    assert ds.attrs["schema_version"] == SCHEMA_VERSION == 2 and "U_perp e1" in ds.attrs["background_frame"]
    assert ds.attrs["build_U_par_grid"] == "-1,0,1" and ds.attrs["build_U_perp_grid"] == "-1,0,1"
    assert ds.U_par.attrs["units"] == "L / tau"
    c = ds.chi_N.values
    cut = ds.chi_N_cutoff.values
    assert c.size == len(GRID) + 9  # every flow's cutoff is a row of the shared grid
    # the cutoff moves with the flow: a stream along the field lowers it, one across +e1 raises it
    assert cut[2, 1] < cut[1, 1] < cut[0, 1] and cut[1, 0] < cut[1, 1] < cut[1, 2]
    assert cut[1, 1] == pytest.approx(flutter_cutoff(200, 1, degree=6).chi_N_cutoff, rel=1e-12)
    assert cut[0, 2] == pytest.approx(flutter_cutoff(200, 1, degree=6, background=(1.0, -1.0)).chi_N_cutoff, rel=1e-12)
    for i in range(3):
        for j in range(3):
            reg = ds.regime.values[i, j]
            own = np.isin(c, GRID) | (c == cut[i, j])
            assert np.all(reg[~own] == REGIMES.index("not_computed"))  # others' cutoffs: holes
            assert np.all(np.isnan(ds.period.values[i, j][~own]))
            k = list(c).index(cut[i, j])
            assert reg[k] == REGIMES.index("flutter") and ds.period.values[i, j, k] > 0
            assert np.array_equal(ds.flutter.values[i, j][own], (c[own] <= cut[i, j]).astype(np.int8))
            stable = own & (c > cut[i, j])  # no flutter: the thrust is the steady state's force
            assert np.all(reg[stable] == REGIMES.index("stable"))
            np.testing.assert_array_equal(ds.thrust_x.values[i, j][stable], ds.rest_thrust_x.values[i, j][stable])
    back = ThrustTable.load(path)
    assert back.ds.identical(ds) and back.U_range == ((-1.0, 1.0), (-1.0, 1.0))
    assert not path.with_name("flow.nc.parts").exists()


def test_zero_flow_reproduces_the_still_table(flow, still):
    """U = 0 is the still-fluid table: its rows agree with a still build to the Newton tolerance
    (different seeds), and the interpolation in U at U = 0 adds nothing but rounding."""
    t, _ = flow
    zero = t.ds.sel(U_par=0.0, U_perp=0.0)
    for cN in GRID:
        for k in ("period", "thrust_x", "thrust_y", "thrust_norm", "alpha", "beta", "theta_lim"):
            a, b = float(zero[k].sel(chi_N=cN)), float(still.ds[k].sel(chi_N=cN))
            assert a == pytest.approx(b, rel=1e-7, abs=1e-9, nan_ok=True), (cN, k)
        assert float(zero.rest_thrust_x.sel(chi_N=cN)) == 0.0 and float(zero.rest_thrust_y.sel(chi_N=cN)) == 0.0
    assert float(t.ds.chi_N_cutoff.sel(U_par=0, U_perp=0)) == still.ds.attrs["chi_N_cutoff"]
    for cN in (110.0, 140.0, -140.0, 170.0):
        r, s = t.at(cN), still.at(cN)  # U_par = U_perp = 0 by default
        for k in ("period", "thrust_x", "thrust_y", "floquet") + (("alpha",) if cN < 160 else ()):
            assert float(r[k]) == pytest.approx(float(s[k]), rel=1e-7, abs=1e-9, nan_ok=True), (cN, k)
        assert np.allclose(r.x.values, s.x.values, atol=1e-8, equal_nan=True)
        # at the grid flow the U interpolation is the flow's own table to rounding
        own = t._flow.knots[(1, 1)]
        assert float(r.thrust_y) == pytest.approx(float(own.scalar("thrust_y", cN)), rel=1e-14)
        # in a flow the thrust's norm and angle come from its interpolated components (the still
        # table splines them separately): the same at the rows, close between them
        assert float(r.thrust_angle) == pytest.approx(float(s.thrust_angle), abs=2e-2, nan_ok=True)
    for cN in GRID[1:3]:
        assert float(t.at(cN).thrust_angle) == pytest.approx(float(still.at(cN).thrust_angle), rel=1e-7)
    assert int(t.at(170.0).flutter) == 0 and float(t.at(170.0).thrust_norm) == 0.0


def test_interpolation_in_the_flow_against_fresh_cycles(flow):
    """Off the grid (in U and chi_N) the interpolant matches fresh cycles of the same
    discretisation within its own error estimate; measured here (U spacing 1 with 3 values, a
    parabola; chi_N rows 60-80 apart): |F - F_fresh| 9e-4 - 8e-3 against estimates of 5e-2 - 7e-2,
    period 3e-4 - 3e-3, angle 2e-4 - 5e-3 rad."""
    t, _ = flow
    for cN, up, uq in [(120.0, 0.4, -0.3), (140.0, -0.6, 0.7), (105.0, 0.9, 0.2), (-125.0, -0.2, 0.6)]:
        f = fresh(cN, up, uq)
        r = t.at(cN, U_par=up, U_perp=uq)
        assert bool(r.flutter) == f.flutter
        err = float(np.hypot(float(r.thrust_x) - f.thrust_x, float(r.thrust_y) - f.thrust_y))
        est = float(r.thrust_interpolation_error)
        assert err <= est < 0.1, (cN, up, uq, err, est)
        assert float(r.period) == pytest.approx(f.period, rel=1e-2)
        assert float(r.thrust_angle) == pytest.approx(f.thrust_angle, abs=1e-2)
        if cN > 0:  # (a mirrored cycle starts at the mirror image of phase 0: not a fresh cycle's phase 0)
            x = f.mesh.interpolate(f.data.x.values.T, t.ds.s.values).T
            assert np.max(np.abs(r.x.values - x)) < 2e-2


def test_no_flutter_above_the_cutoff_is_the_steady_force(flow):
    """Above the flow's cutoff the filament rests in the stream: the thrust is the force of its
    steady state (steady_state), not zero; the flutter flag follows the interpolated cutoff."""
    t, _ = flow
    up, uq = 0.5, -0.5
    C = t.cutoff(U_par=up, U_perp=uq)
    assert C == pytest.approx(flutter_cutoff(200, 1, degree=6, background=(uq, up)).chi_N_cutoff, rel=2e-3)
    cN = 175.0
    r = t.at(cN, U_par=up, U_perp=uq)
    ss = steady_state(CiliumParams(200, 1, cN, (uq, up)), degree=6)
    assert int(r.flutter) == 0 and math.isnan(float(r.period)) and np.all(np.isnan(r.x.values))
    np.testing.assert_allclose([float(r.thrust_x), float(r.thrust_y)], ss.force, atol=5e-3)
    np.testing.assert_allclose([float(r.rest_thrust_x), float(r.rest_thrust_y)], ss.force, atol=5e-3)
    cyc = t.cycles([cN, 120.0], U_par=up, U_perp=uq)
    assert cyc["flutter"].tolist() == [False, True]
    assert np.allclose(cyc["fx"][0], r.rest_fx.values[None, :]) and np.all(np.isnan(cyc["x"][0]))
    assert not fresh(cN, up, uq).flutter


def test_vectorised_scalars_and_derivatives(flow):
    t, _ = flow
    c = np.array([105.0, -120.0, 140.0, 175.0])
    up = np.array([0.3, -0.7, 0.0, 0.5])
    uq = np.array([0.1, 0.4, -0.9, -0.5])
    for name in ("thrust_x", "thrust_y", "thrust_norm", "thrust_angle", "period"):
        v = t.scalar(name, c, U_par=up, U_perp=uq)
        for i in range(c.size):
            assert v[i] == pytest.approx(float(t.at(c[i], U_par=up[i], U_perp=uq[i])[name]), rel=1e-12,
                                         nan_ok=True), (name, i)
    h = 1e-4
    for name in ("thrust_x", "thrust_y", "thrust_angle"):
        d = t.scalar(name, c[:3], nu=1, U_par=up[:3], U_perp=uq[:3])
        fd = (t.scalar(name, c[:3] + h, U_par=up[:3], U_perp=uq[:3])
              - t.scalar(name, c[:3] - h, U_par=up[:3], U_perp=uq[:3])) / (2 * h)
        np.testing.assert_allclose(d, fd, rtol=1e-5, atol=1e-8)
    cyc = t.cycles(c[:3], U_par=up[:3], U_perp=uq[:3])
    assert cyc["x"].shape == (3, 32, 17) and cyc["flutter"].all()
    assert np.array_equal(cyc["fy"][1], t.at(c[1], U_par=up[1], U_perp=uq[1]).fy.values)


def test_mirror_symmetry_is_used_and_holds(flow):
    """(chi_N, U_par, U_perp) -> (-chi_N, U_par, -U_perp) mirrors the cilium: the table holds
    chi_N >= 0 and serves negative chi_N by it, which a fresh cycle confirms."""
    t, _ = flow
    a, b = t.at(-135.0, U_par=0.4, U_perp=0.8), t.at(135.0, U_par=0.4, U_perp=-0.8)
    for k in ("thrust_x", "thrust_angle", "theta_lim"):
        assert float(a[k]) == -float(b[k])
    assert float(a.thrust_y) == float(b.thrust_y) and float(a.period) == float(b.period)
    assert np.array_equal(a.x.values, -b.x.values) and np.array_equal(a.fy.values, b.fy.values)
    f = fresh(-135.0, 0.4, 0.8)
    assert float(a.thrust_x) == pytest.approx(f.thrust_x, abs=5e-3) and float(a.thrust_x) < 0
    lo, hi = t.thrust_angle_range(U_par=0.4, U_perp=-0.8)
    a = 0.5 * (lo + hi)
    assert t.chi_N_for_angle(-a, U_par=0.4, U_perp=0.8) == pytest.approx(-t.chi_N_for_angle(a, U_par=0.4, U_perp=-0.8),
                                                                         rel=1e-12)


def test_angle_inversion_in_a_flow(flow):
    t, _ = flow
    lo, hi = t.thrust_angle_range(U_par=-0.5, U_perp=0.5)
    target = 0.5 * (lo + hi)
    c = t.chi_N_for_angle(target, U_par=-0.5, U_perp=0.5)
    assert float(t.at(c, U_par=-0.5, U_perp=0.5).thrust_angle) == pytest.approx(target, abs=1e-9)


def test_requests_that_cannot_be_served(flow, still):
    t, _ = flow
    with pytest.raises(TableError, match=r"U_par = 1.5 is outside the table's range \[-1, 1\]: no extrapolation"):
        t.at(120.0, U_par=1.5)
    with pytest.raises(TableError, match=r"U_perp = -1.2 is outside .*chi_N = -120 < 0 is served by its mirror image"):
        t.scalar("thrust_x", -120.0, U_perp=1.2)
    with pytest.raises(TableError, match="outside the table's range"):
        t.at(190.0, U_par=0.2)
    with pytest.raises(TableError, match="finite"):
        t.scalar("thrust_x", 120.0, U_par=np.nan)
    with pytest.raises(TableError, match="still fluid only.*U_par=.*U_perp="):
        still.at(120.0, U_par=0.5)
    assert float(still.at(120.0, U_par=0.0, U_perp=0.0).period) == float(still.at(120.0).period)


@pytest.mark.parametrize("kw,match", [(dict(U_par=[1.0, 0.0]), "U_par grid must be strictly increasing"),
                                      (dict(U_perp=[0.0, np.inf]), "U_perp grid contains NaN or inf"),
                                      (dict(U_par=[]), "non-empty")])
def test_bad_flow_grids(kw, match):
    with pytest.raises(ValueError, match=match):
        build_table(200, 1, [100.0], **kw)
    with pytest.raises(ValueError, match="one field"):
        build_table([180.0, 200.0], 1, [100.0], U_par=[0.0])


def test_resume_refuses_rows_of_another_flow_grid(tmp_path, flow):
    t, _ = flow
    path, parts = tmp_path / "t.nc", tmp_path / "t.nc.parts"
    parts.mkdir()
    row = t.ds.isel(U_par=[0], U_perp=[1], chi_N=[0]).drop_vars(["phase", "s", "chi_N_cutoff", "chi_N_cutoff_error"])
    row = row.drop_encoding()
    row.to_netcdf(parts / "row_-1_0_100.nc", engine="h5netcdf")
    with pytest.raises(TableError, match=r"U_par_grid = '-1,0,1' \(asked '-1,0'\)"):
        build_table(200, 1, [100.0], U_par=[-1.0, 0.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    with pytest.raises(TableError, match=r"kind = 'flow' \(asked 'field'\)"):  # a still build
        build_table(200, 1, [100.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    assert (parts / "row_-1_0_100.nc").exists() and not path.exists()


def test_resume_of_a_flow_build(tmp_path, monkeypatch):
    """A cycle that fails names its flow and the last good row; the same request resumes."""
    import single_cilium.table as table_mod

    real = table_mod.limit_cycle

    def failing(p, **kw):
        if p.background == (0.0, 1.0) and p.chi_N == 150.0:
            raise CycleError("injected failure", 0.0)
        return real(p, **kw)

    monkeypatch.setattr(table_mod, "limit_cycle", failing)
    path = tmp_path / "t.nc"
    with pytest.raises(CycleError, match=r"U_par = 1, U_perp = 0\): the cycle at chi_N = 150 did not converge .*"
                                         r"last good row before it: chi_N = 130.*resumes"):
        build_table(200, 1, [130.0, 150.0], U_par=[0.0, 1.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    done = sorted(f.name for f in (tmp_path / "t.nc.parts").glob("row_*.nc"))
    assert "row_1_0_130.nc" in done and "row_1_0_150.nc" not in done
    monkeypatch.setattr(table_mod, "limit_cycle", real)
    t = build_table(200, 1, [130.0, 150.0], U_par=[0.0, 1.0], executor=ThreadPoolExecutor(1), path=path, **FAST)
    assert t.ds.sizes["U_par"] == 2 and np.all(t.ds.flutter.values == 1) and path.exists()


def test_bad_flow_table_files(tmp_path, flow, still):
    t, _ = flow
    one_dim = tmp_path / "one_dim.nc"
    t.ds.isel(U_perp=0).drop_encoding().to_netcdf(one_dim, engine="h5netcdf")
    with pytest.raises(TableError, match="needs both dims"):
        ThrustTable.load(one_dim)
    v1 = tmp_path / "v1.nc"
    ds = t.ds.copy()
    ds.attrs["schema_version"] = 1
    ds.to_netcdf(v1, engine="h5netcdf")
    with pytest.raises(TableError, match="version 1 table cannot hold a background flow grid"):
        ThrustTable.load(v1)
    unsorted = tmp_path / "unsorted.nc"
    t.ds.isel(U_par=[2, 1, 0]).drop_encoding().to_netcdf(unsorted, engine="h5netcdf")
    with pytest.raises(TableError, match="U_par coordinate must be finite and strictly increasing"):
        ThrustTable.load(unsorted)
    no_regime = tmp_path / "no_regime.nc"
    still.ds.drop_vars("regime").to_netcdf(no_regime, engine="h5netcdf")
    with pytest.raises(TableError, match=r"version 2 table without \['regime'\]"):
        ThrustTable.load(no_regime)
    # a version 1 table (the shipped one) still loads, as still fluid
    d = ThrustTable.default()
    assert d.ds.attrs["schema_version"] == 1 and d.U_range == ((0.0, 0.0), (0.0, 0.0))
    assert np.all(d.rest("rest_thrust_x", [10.0, 170.0]) == 0.0)


def test_flows_without_flutter_and_without_a_steady_state():
    """A strong stream along the field suppresses flutter (no cutoff: rows fine, thrust the
    steady force); one against a weak field buckles the filament (divergence: no thrust, a
    clear error) or tips it over (no steady state: marked, a clear error)."""
    t = build_table(200, 1, [0.0, 50.0, 100.0], U_par=[5.0], executor=ThreadPoolExecutor(1), **FAST)
    assert np.all(t.ds.flutter.values == 0) and np.isnan(float(t.ds.chi_N_cutoff[0, 0]))
    r = t.at(50.0, U_par=5.0)
    ss = steady_state(CiliumParams(200, 1, 50.0, (0.0, 5.0)), degree=6)
    assert int(r.flutter) == 0
    np.testing.assert_allclose([float(r.thrust_x), float(r.thrust_y)], ss.force, rtol=1e-10)
    assert float(t.scalar("thrust_y", 70.0, U_par=5.0)) < 0  # the stream's drag, passed on to the fluid
    # buckled: chi_E = 5 against U_par = -30 diverges at chi_N = 0 and rests at 2.5
    b = build_table(5.0, 1, [0.0, 1.0, 2.5, 4.0], U_par=[-30.0], executor=ThreadPoolExecutor(1), **FAST)
    reg = b.ds.regime.values[0, 0]
    assert reg[0] == REGIMES.index("divergence") and reg[-1] == REGIMES.index("stable")
    assert np.isnan(b.ds.thrust_x.values[0, 0, 0]) and np.isfinite(b.ds.rest_thrust_x.values[0, 0, 0])
    with pytest.raises(TableError, match="unstable without flutter"):
        b.scalar("thrust_y", 0.5, U_par=-30.0)
    assert np.isfinite(b.scalar("thrust_y", 3.5, U_par=-30.0))
    # tipped over: near chi_N = chi_E a weak stream against the field leaves no steady state
    n = build_table(200, 1, [150.0, 199.9998], U_par=[-2.0], executor=ThreadPoolExecutor(1), **FAST)
    assert n.ds.regime.values[0, 0, -1] == REGIMES.index("no_steady_state")
    assert np.isnan(n.ds.thrust_x.values[0, 0, -1])
    with pytest.raises(TableError, match="no steady state known at chi_N = 199"):
        n.scalar("thrust_x", 199.0, U_par=-2.0)


def test_coiled_rows_in_a_flow():
    t = build_table(200, 1, [150.0, 190.0, 210.0], U_par=[0.5], executor=ThreadPoolExecutor(1), **FAST)
    reg = t.ds.regime.values[0, 0]
    assert reg[-1] == REGIMES.index("coiled") and t.ds.coiled.values[0, 0, -1] == 1
    assert np.isnan(t.ds.thrust_x.values[0, 0, -1])
    with pytest.raises(TableError, match="no steady state known at chi_N = 205"):
        t.at(205.0, U_par=0.5)


@pytest.fixture(scope="module")
def shipped():
    return ThrustTable.default(flow=True)


def test_shipped_flow_table_against_fresh_cycles(shipped):
    """The shipped table (degree 8, 64 steps; U spacing 0.5, chi_N spacing 10) at flows off its
    grid against fresh cycles of its discretisation: within its own estimate, and within the
    errors measured over 120 points by benchmarks/bench_table_flow.py --sections shipped (thrust
    at most 2.6e-4 |F|, period 1.9e-4, angle 1.8e-4 rad, shape x 3.6e-4; the estimate at least
    2.8 times the thrust's error). Measured at these points: |F - F_fresh| / |F| 4e-5 - 2e-4, the
    estimates 14-20 times the error."""
    for cN, up, uq in [(148.8, 0.6, 0.6),  # |U| = 0.85 (a carpet's flows), 0.9 of the cutoff
                       (129.5, -0.75, 0.75),  # the centre of a cell, |U| = 1.06, its largest error
                       (-129.0, -0.35, -0.85)]:  # negative chi_N: the mirror image
        f = limit_cycle(CiliumParams(200, 1, cN, (uq, up)), degree=8, n_phase=64, error_estimate=False,
                        floquet=False)
        r = shipped.at(cN, U_par=up, U_perp=uq)
        assert bool(r.flutter) and f.flutter
        err = float(np.hypot(float(r.thrust_x) - f.thrust_x, float(r.thrust_y) - f.thrust_y))
        est = float(r.thrust_interpolation_error)
        assert err <= est, (cN, up, uq, err, est)
        assert err <= 1e-3 * f.thrust_norm, (cN, up, uq, err, f.thrust_norm)
        assert float(r.period) == pytest.approx(f.period, rel=2e-4)
        assert float(r.thrust_angle) == pytest.approx(f.thrust_angle, abs=2e-4)
        if cN > 0:  # (a mirrored cycle starts at the mirror image of phase 0: not a fresh cycle's phase 0)
            x = f.mesh.interpolate(f.data.x.values.T, shipped.ds.s.values).T[::2]  # 32 of the 64 phases
            assert np.max(np.abs(r.x.values - x)) < 5e-4


def test_shipped_flow_table_is_compacted(shipped):
    """The shipped file is what tablefile.compact makes of the build: 32 of the 64 phase samples,
    float32 fields rounded to 13 mantissa bits, float64 scalars; under 20 MB."""
    from importlib import resources

    from single_cilium.lookup import DEFAULT_FLOW_FILE
    from single_cilium.tablefile import FIELDS, REST_FIELDS

    path = resources.files("single_cilium") / "data" / DEFAULT_FLOW_FILE
    assert Path(str(path)).stat().st_size < 20e6
    ds = shipped.ds
    assert ds.sizes["phase"] == 32 and ds.sizes["s"] == 65 and ds.attrs["build_n_phase"] == 64
    np.testing.assert_array_equal(ds.phase.values, np.arange(32) / 32)
    assert shipped.U_range == ((-1.5, 1.5), (-1.5, 1.5))
    assert ds.attrs["chi_E"] == 200.0 and ds.attrs["eta"] == 1.0 and "13 mantissa bits" in ds.attrs["storage"]
    for k in FIELDS + REST_FIELDS:
        v = ds[k].values
        assert v.dtype == np.float32, k
        low = v[np.isfinite(v)].view(np.uint32) & np.uint32((1 << 10) - 1)  # 23 - 13 bits dropped
        assert not np.any(low), k
    for k in ("period", "thrust_x", "thrust_y", "chi_N_cutoff"):
        assert ds[k].dtype == np.float64, k


def test_compact_keeps_the_scalars_and_rounds_the_fields(flow, tmp_path):
    """compact: scalars bit for bit, fields at every 2nd phase sample within 2**-14 relative (13
    mantissa bits), also after the round trip through its file."""
    from cilia_runtime.files import write_netcdf
    from single_cilium.tablefile import FIELDS, REST_FIELDS, compact

    t, path = flow
    ds = t.ds
    c = compact(ds)
    write_netcdf(c, tmp_path / "c.nc")
    back = ThrustTable.load(tmp_path / "c.nc").ds
    assert (tmp_path / "c.nc").stat().st_size < 0.5 * path.stat().st_size
    for d in (c, back):
        assert d.sizes["phase"] == ds.sizes["phase"] // 2 and d.sizes["s"] == ds.sizes["s"]
        np.testing.assert_array_equal(d.phase.values, ds.phase.values[::2])
        for k in ds.data_vars:
            if k in FIELDS + REST_FIELDS:
                ref = ds[k].values[..., ::2, :] if "phase" in ds[k].dims else ds[k].values
                v = d[k].values
                assert v.dtype == np.float32 and np.array_equal(np.isnan(v), np.isnan(ref)), k
                ok = np.isfinite(ref)
                assert np.all(np.abs(v[ok] - ref[ok]) <= 2.0 ** -14 * np.abs(ref[ok])), k
            else:
                assert d[k].dtype == ds[k].dtype, k
                assert np.array_equal(d[k].values, ds[k].values, equal_nan=d[k].dtype.kind == "f"), k
        for a in ("chi_E", "eta", "schema_version"):
            assert d.attrs[a] == ds.attrs[a]


# ------------------------------------------------------------------------------ command line
def _cli(capsys, *argv):
    from single_cilium.cli import main

    code = main(list(argv))
    o = capsys.readouterr()
    return code, o.out, o.err


def test_table_command_over_a_flow_grid(tmp_path, capsys):
    import json

    out = tmp_path / "flow.nc"
    code, o, err = _cli(capsys, "table", "--chi-E", "200", "--eta", "1", "--chi-N", "120,140", "--U-par=-1,1",
                        "--U-perp", "0", "-o", str(out), "--degree", "6", "--n-phase", "32", "--no-error-estimate",
                        "--quiet", "--json")
    assert code == 0, err
    d = json.loads(o)
    assert d["U_par"] == [-1.0, 1.0] and d["U_perp"] == [0.0] and d["rows"] == 4 and d["flutter_rows"] == 4
    assert d["divergence_rows"] == 0 and d["no_steady_state_rows"] == 0
    assert d["chi_N_cutoff"][0][0] > d["chi_N_cutoff"][1][0]  # a stream along the field lowers the cutoff
    t = ThrustTable.load(out)
    assert t.U_range == ((-1.0, 1.0), (0.0, 0.0)) and int(t.at(130.0, U_par=0.2).flutter) == 1
    with pytest.raises(TableError, match="U_perp = 0 only"):
        t.at(130.0, U_par=0.2, U_perp=0.1)
    from single_cilium.cli import build_parser
    args = build_parser().parse_args(["table", "--chi-E", "200", "--eta", "1", "--chi-N", "0", "-o", "x.nc",
                                      "--U-par", "default", "--U-perp", "default"])
    assert args.U_par.tolist() == args.U_perp.tolist() == [-2.0, -1.0, 0.0, 1.0, 2.0]
    code, _, err = _cli(capsys, "table", "--chi-E", "180,200", "--eta", "1", "--chi-N", "100", "--U-par", "0",
                        "-o", str(tmp_path / "x.nc"), "--quiet")
    assert code == 2 and "one field" in err
    code, _, err = _cli(capsys, "table", "--chi-E", "200", "--eta", "1", "--chi-N", "100", "--U-perp", "1,0",
                        "-o", str(tmp_path / "x.nc"), "--quiet")
    assert code == 2 and "U_perp grid must be strictly increasing" in err
