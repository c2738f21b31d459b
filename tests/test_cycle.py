import math

import numpy as np
import pytest

from single_cilium import CiliumParams, limit_angle, simulate
from single_cilium.cycle import CycleError, limit_cycle, thrust_angle

TWO_PI = 2 * np.pi


@pytest.fixture(scope="module")
def cycle16():
    return limit_cycle(CiliumParams(200, 1, 16 * TWO_PI), degree=8)


def test_published_cycle(cycle16):
    c = cycle16
    assert c.flutter and c.status == "success"
    # the nonlinear period differs from 2 pi / beta by a few percent (published)
    assert 0.01 < abs(c.period - 2 * np.pi / 22.8022358) / c.period < 0.05
    # the filament pulls on its clamp along its axis: thrust angle a little above theta_lim
    assert c.theta_lim == pytest.approx(limit_angle(c.params))
    assert 0 < c.thrust_angle - c.theta_lim < 0.1
    assert c.thrust_norm < 0.2 * np.max(np.hypot(c.data.Fx, c.data.Fy))  # |Fbar| << |F(t)|
    assert c.floquet < 1 and c.floquet_trivial_error < 1e-5
    assert c.errors["thrust_norm"] < 1e-4 and c.errors["period"] < 1e-5
    assert c.tip_area != 0  # non-reciprocal stroke


def test_cycle_is_periodic_and_phase_zero_is_the_section(cycle16):
    tip = cycle16.data.theta.values[:, -1]
    assert tip[0] == pytest.approx(tip.mean(), abs=1e-8)  # tip angle crosses its mean at phase 0
    assert tip[1] > tip[0]  # upward


def test_against_long_time_integration(cycle16):
    """Brute force: integrate through the transient; the last period's mean force and the
    period agree with the shooting solution."""
    p = cycle16.params
    T = cycle16.period
    sim = simulate(p, 40 * T, mesh=cycle16.mesh, rtol=1e-9, n_out=40 * 64 + 1, amplitude=0.3,
                   error_estimate=False)
    F = sim.force[-65:-1]
    Fbar = F.mean(axis=0)
    assert np.hypot(*(Fbar - cycle16.thrust)) < 2e-3 * cycle16.thrust_norm


def test_mirror_symmetry(cycle16):
    m = limit_cycle(cycle16.params.mirrored(), degree=8, floquet=False, error_estimate=False)
    assert m.thrust_x == pytest.approx(-cycle16.thrust_x, rel=1e-7)
    assert m.thrust_y == pytest.approx(cycle16.thrust_y, rel=1e-7)
    assert m.thrust_angle == pytest.approx(-cycle16.thrust_angle, rel=1e-7)


def test_no_oscillation_is_a_result_not_an_error():
    c = limit_cycle(CiliumParams(50, 1, 0.0))
    assert not c.flutter and c.thrust_norm == 0 and math.isnan(c.period)
    assert "stable" in c.message


def test_thrust_angle_convention():
    # a force on the fluid pointing down the field (-e2) has phi = pi: thrust angle 0
    assert thrust_angle(0.0, -1.0) == pytest.approx(0.0)
    # tilted so that the filament pulls along theta = 0.3 (tangent (-sin, cos))
    assert thrust_angle(np.sin(0.3), -np.cos(0.3)) == pytest.approx(0.3)


@pytest.mark.parametrize("kw", [dict(n_phase=8), dict(tol=1.0)])
def test_bad_settings(kw):
    with pytest.raises(ValueError):
        limit_cycle(CiliumParams(200, 1, 0.0), **kw)


CUTOFF_200_1 = 162.77486240834992  # flutter_cutoff(200, 1) at degree 8


def test_half_percent_below_the_cutoff():
    """Small amplitude, growth rate ~0.005: the normal-form seed gets there (a transient would
    need hundreds of periods)."""
    c = limit_cycle(CiliumParams(200, 1, 0.995 * CUTOFF_200_1), degree=8, floquet=False, error_estimate=False)
    assert c.flutter and 0 < c.thrust_norm < 0.03
    assert c.work["period_maps"] < 400


def test_straight_filament_pushes_along_the_field():
    c = limit_cycle(CiliumParams(200, 1, 0.0), degree=6, n_phase=32, floquet=False, error_estimate=False)
    assert abs(c.thrust_angle) < 1e-10 and abs(c.thrust_x) < 1e-10 * c.thrust_norm
    assert abs(c.tip_area) < 1e-10  # symmetric figure-of-eight: no net area


@pytest.mark.parametrize("p", [CiliumParams(200, 0.2, 16 * TWO_PI), CiliumParams(200, 5, 16 * TWO_PI)])
def test_stable_fields_give_no_oscillation(p):
    c = limit_cycle(p, degree=6)
    assert not c.flutter and c.status == "no oscillation" and c.thrust_norm == 0


def test_strong_field():
    p = CiliumParams(500, 0.5, 16 * TWO_PI)
    with pytest.raises(CycleError, match="raise n_phase"):  # too few steps: a clear error
        limit_cycle(p, degree=6, n_phase=16, floquet=False, error_estimate=False)
    c = limit_cycle(p, degree=6, n_phase=64, floquet=False, error_estimate=False)
    assert c.flutter and 0 < c.thrust_angle - c.theta_lim < 0.1
