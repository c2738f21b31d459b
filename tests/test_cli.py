import json

import numpy as np
import pytest
import xarray as xr

from single_cilium import CiliumParams, equilibrium, limit_angle
from single_cilium.cli import main


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_equilibrium_json(capsys):
    code, out, _ = run(capsys, "equilibrium", "--chi-E", "200", "--chi-N", "100.53", "--s", "0,0.5,1", "--json")
    assert code == 0
    d = json.loads(out)
    p = CiliumParams(200, 1, 100.53)
    assert d["theta"] == pytest.approx(equilibrium(p, [0, 0.5, 1]).tolist(), abs=1e-15)
    assert d["theta_lim"] == pytest.approx(limit_angle(p))
    assert d["y"][-1] > 0.8  # the unrolled filament reaches up along the field


def test_equilibrium_coiled_has_no_limit_angle(capsys):
    code, out, _ = run(capsys, "equilibrium", "--chi-E", "50", "--chi-N", "100.53", "--json")
    d = json.loads(out)
    assert code == 0 and d["theta_lim"] is None and "coil" in d["theta_lim_note"]


def test_simulate_writes_netcdf(tmp_path, capsys):
    path = tmp_path / "run.nc"
    code, out, err = run(capsys, "simulate", "--chi-E", "200", "--eta", "1", "--chi-N", "100.53",
                         "--t-end", "0.05", "--n-out", "6", "--degree", "8", "-o", str(path), "--json", "--quiet")
    assert code == 0, err
    d = json.loads(out)
    ds = xr.open_dataset(path, engine="h5netcdf")
    assert ds.sizes["time"] == 6 and ds.attrs["chi_E"] == 200.0
    assert np.isfinite(d["error_time"]) and d["error_time"] < 1e-3


@pytest.mark.parametrize("argv,needle", [
    (["simulate", "--chi-E", "200", "--eta", "-1", "--t-end", "1"], "eta"),
    (["simulate", "--chi-E", "200", "--eta", "1", "--t-end", "0"], "t_end"),
    (["equilibrium", "--chi-E", "nan"], "chi_E"),
])
def test_bad_input_exit_code_2(capsys, argv, needle):
    code, _, err = run(capsys, *argv)
    assert code == 2 and needle in err


def test_stability_json(capsys):
    code, out, _ = run(capsys, "stability", "--chi-E", "200", "--eta", "1", "--chi-N", "100.53", "--json")
    d = json.loads(out)
    assert code == 0 and d["regime"] == "flutter"
    assert {"alpha", "beta", "regime", "period_estimate"} <= set(d)
    assert d["period_estimate"] == pytest.approx(2 * np.pi / d["beta"])


def test_cutoff_json(capsys):
    code, out, _ = run(capsys, "cutoff", "--chi-E", "200", "--eta", "1", "--json")
    d = json.loads(out)
    assert code == 0 and 150 < d["chi_N_cutoff"] < 180 and d["beta"] > 0


def test_map_writes_netcdf_and_png(tmp_path, capsys):
    nc, png = tmp_path / "map.nc", tmp_path / "map.png"
    code, out, err = run(capsys, "map", "--chi-N", "50.27", "--chi-E", "150:250:3", "--eta", "0.5:1.5:3",
                         "-o", str(nc), "--png", str(png), "--quiet", "--json")
    assert code == 0, err
    d = json.loads(out)
    ds = xr.open_dataset(nc, engine="h5netcdf")
    assert ds.alpha.shape == (3, 3) and d["flutter_points"] == int((ds.regime == 1).sum())
    assert png.stat().st_size > 1000


def test_map_rejects_unsorted_grid(capsys):
    code, _, err = run(capsys, "map", "--chi-N", "0", "--chi-E", "200,100", "--eta", "1", "--quiet")
    assert code == 2 and "increasing" in err


def test_cycle_json(capsys):
    code, out, err = run(capsys, "cycle", "--chi-E", "200", "--eta", "1", "--chi-N", "150.8", "--degree", "6",
                         "--no-error-estimate", "--json")
    assert code == 0, err
    d = json.loads(out)
    keys = {"period", "thrust_norm", "thrust_angle", "thrust_x", "thrust_y", "theta_lim", "floquet", "flutter",
            "period_error", "thrust_norm_error", "thrust_angle_error"}
    assert keys <= set(d) and d["flutter"] is True
    assert d["thrust_angle"] > d["theta_lim"] > 0


def test_table_command(tmp_path, capsys):
    out = tmp_path / "t.nc"
    code, o, err = run(capsys, "table", "--chi-E", "200", "--eta", "1", "--chi-N", "150,170", "-o", str(out),
                       "--degree", "6", "--n-phase", "32", "--no-error-estimate", "--quiet", "--json")
    assert code == 0, err
    d = json.loads(o)
    assert d["rows"] == 3 and d["flutter_rows"] == 2 and out.exists()


def test_table_command_rejects_nan_grid(tmp_path, capsys):
    code, _, err = run(capsys, "table", "--chi-E", "200", "--eta", "1", "--chi-N", "1,nan", "-o",
                       str(tmp_path / "t.nc"), "--quiet")
    assert code == 2 and "NaN" in err


def test_table_command_over_a_chi_E_grid(tmp_path, capsys):
    out = tmp_path / "t2.nc"
    code, o, err = run(capsys, "table", "--chi-E", "190,210", "--eta", "1", "--chi-N", "80:120:3", "-o", str(out),
                       "--degree", "6", "--n-phase", "32", "--no-error-estimate", "--tol", "1e-7", "--quiet",
                       "--json")
    assert code == 0, err
    d = json.loads(o)
    assert d["chi_E"] == [190.0, 210.0] and d["rows"] == 6 and d["flutter_rows"] == 6 and d["coiled_rows"] == 0
    assert 140 < d["chi_N_cutoff"][0] < d["chi_N_cutoff"][1] < 180
    from single_cilium.table import TableError, ThrustTable
    t = ThrustTable.load(out)
    assert t.ds.attrs["build_tol"] == 1e-7 and t.chi_E_range == (190.0, 210.0)
    assert int(t.at(105.0, chi_E=200.0).flutter) == 1
    # the fields share rows up to 120 / 174.9 of their cutoffs: at chi_E = 200 (cutoff 162.8) up to 111.7
    with pytest.raises(TableError, match="outside the table's range"):
        t.at(113.0, chi_E=200.0)


def test_table_command_rejects_bad_tol(tmp_path, capsys):
    code, _, err = run(capsys, "table", "--chi-E", "200", "--eta", "1", "--chi-N", "100", "-o",
                       str(tmp_path / "t.nc"), "--tol", "0.1", "--quiet")
    assert code == 2 and "tol must lie in" in err and not (tmp_path / "t.nc").exists()
