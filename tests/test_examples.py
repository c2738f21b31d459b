"""Examples never rot: each is imported and its result checked."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load(name):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_flutter_onset():
    ex = load("flutter_onset")
    # the oscillation period is close to 2 pi / beta with beta ~ 22.81 (fit in test_dynamics)
    assert ex.period == pytest.approx(2 * 3.141592653589793 / 22.81, rel=5e-3)
    assert 0.2 < ex.growth_rate < 0.8
    assert ex.sim.error < 3e-4


def test_stability_maps(monkeypatch):
    monkeypatch.setenv("CILIA_EXAMPLE_QUICK", "1")
    ex = load("stability_maps")
    tiny = 0.01 * 2 * 3.141592653589793
    # chi_N = 0 flutters somewhere for chi_E < 0; the tiny curvature removes that part
    neg0 = ex.study_a[0.0][0].sel(chi_E=slice(-50, -20)).regime
    negt = ex.study_a[tiny][0].sel(chi_E=slice(-50, -20)).regime
    assert (neg0 == 1).any() and not (negt == 1).any()
    assert len(ex.study_a[0.0][1].branches) == 2 and len(ex.study_a[tiny][1].branches) == 1
    crit = [ex.lowest_critical_chi_E_b[k] for k in (0, 8, 16, 24)]
    assert all(a < b for a, b in zip(crit, crit[1:]))  # raising chi_N raises the critical chi_E


def test_cilium_cycles(monkeypatch):
    monkeypatch.setenv("CILIA_EXAMPLE_QUICK", "1")
    ex = load("cilium_cycles")
    T, norm, angle, lim, area = zip(*[ex.summary[k] for k in (8, 16, 24)])
    assert all(a > b for a, b in zip(norm, norm[1:]))  # thrust falls as chi_N grows
    assert all(0 < a - l < 0.1 for a, l in zip(angle, lim))  # a little above theta_lim
    assert all(a < b for a, b in zip(T, T[1:]))  # the beat slows down


def test_thrust_curve():
    ex = load("thrust_curve")
    assert ex.thrust_norm[0] > 4 * ex.thrust_norm[-20]  # falls towards the cutoff
    assert abs(ex.thrust_norm[-1]) < 1e-12  # zero at the cutoff
    ok = np.isfinite(ex.thrust_angle)
    assert np.all(ex.thrust_angle[ok] >= ex.theta_lim[ok] - 1e-6)


def test_pathlines_single_filament(monkeypatch, tmp_path):
    monkeypatch.setenv("CILIA_EXAMPLE_QUICK", "1")
    monkeypatch.setenv("CILIA_EXAMPLE_OUT", str(tmp_path))
    mod = load("pathlines_single_filament")
    d = mod.deflection
    assert abs(d["straight"]) < 1e-9
    # the curved filament steers the flow like the straight one under the tilted field
    assert d["curved"] > 20 and abs(d["curved"] - d["tilted"]) < 2.0
    assert (tmp_path / "curved_pathlines.vtp").exists() and (tmp_path / "tilted_mean_field.vti").exists()
    assert all(p.reason.max() <= 3 for p in mod.paths.values())


def test_carpet_flows():
    ex = load("carpet_flows")
    assert 0.1 < ex.speed_mean < 10 and 0 < ex.bound_mean < 1e-2 * ex.speed_mean * 10
    assert ex.end_points.shape[0] == 8 and np.all(np.isfinite(ex.end_points))
    # the tracers moved: the mean flow carries them away from their seeds over 20 tau
    assert np.linalg.norm(ex.end_points[:, :2] - ex.seeds, axis=1).max() > 1.0
    assert np.isfinite(ex.mixing_number)


def test_design_a_scene():
    ex = load("design_a_scene")
    assert ex.scene_rms <= ex.scene.target.residual  # the bundled scene meets its threshold
    assert ex.focus_rms < 0.05 and 5 < ex.pattern_max_deg < 60


def test_coupled_carpet():
    ex = load("coupled_carpet")
    assert ex.residual <= 1e-3 and 1 <= ex.steps <= 6
    # the cilia push against the flow they make: 5 x 5 at spacing 2, 0.284 L/tau coupled against
    # 0.426 uncoupled (benchmarks/results/bench_coupling.md)
    assert 0.6 < ex.speed_ratio < 0.75 and 0.27 < ex.coupled_speed < 0.30


def test_standing_carpet():
    ex = load("standing_carpet")
    assert ex.mixer_rms < 0.1 and ex.mixer_error < 0.05
    assert ex.wall_speed < 1e-12  # no slip on the substrate


@pytest.mark.slow
def test_program_switch():
    ex = load("program_switch")
    # one cilium's angle changes by at most 0.149 rad between chi_E = 150 and 200 (the tables)
    assert ex.largest_change == pytest.approx(0.149, abs=2e-3)
    # the mixture of cilia meets both fields: 0.1 rad each, error bars at most half of it
    assert ex.low_rms <= 0.1 and ex.high_rms <= 0.1 and max(ex.low_error, ex.high_error) <= 0.05
    assert ex.resting_low > 0
