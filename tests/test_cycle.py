import math

import numpy as np
import pytest

from single_cilium import CiliumParams, Filament, Mesh, limit_angle, simulate, stability
from single_cilium.cycle import CycleError, limit_cycle, thrust_angle
from single_cilium.orbit import METHODS, ExactShooting

TWO_PI = 2 * np.pi
# independent values (degree 10 / 128 steps of the previous Newton-Krylov shooting, and the
# published README numbers): period, |Fbar|, thrust angle at chi_E = 200, eta = 1
PUBLISHED = {8: (0.245011741, 1.03941484, 0.2804685),
             16: (0.271953703, 0.76987028, 0.5686738),
             24: (0.334199694, 0.20252374, 0.8743019)}


@pytest.fixture(scope="module")
def cycle16():
    return limit_cycle(CiliumParams(200, 1, 16 * TWO_PI))


def _check_published(c, k):
    T, F, a = PUBLISHED[k]
    assert c.status == "success"
    # within 1e-6 (the default rtol), and within the result's own error estimate (plus the
    # rounding of the reference values)
    assert abs(c.period / T - 1) <= min(1e-6, c.errors["period"] + 2e-9)
    assert abs(c.thrust_norm / F - 1) <= min(1e-6, c.errors["thrust_norm"] + 1e-8)
    assert abs(c.thrust_angle - a) <= min(1e-6, c.errors["thrust_angle"] + 5e-8)


def test_published_cycle(cycle16):
    c = cycle16
    assert c.flutter and c.method == "shooting"
    _check_published(c, 16)
    # the nonlinear period differs from 2 pi / beta by a few percent (published)
    assert 0.01 < abs(c.period - 2 * np.pi / 22.8022358) / c.period < 0.05
    assert c.theta_lim == pytest.approx(limit_angle(c.params))
    assert 0 < c.thrust_angle - c.theta_lim < 0.1
    assert c.thrust_norm < 0.2 * np.max(np.hypot(c.data.Fx, c.data.Fy))  # |Fbar| << |F(t)|
    assert c.tip_area != 0  # non-reciprocal stroke
    assert c.n_phase == c.data.sizes["phase"] and f"n_phase={c.n_phase} (chosen)" in c.message


def test_floquet_multipliers(cycle16):
    """Exact monodromy: the trivial multiplier is 1 to the Newton tolerance, the kappa at the
    clamp relaxes with exactly the Radau stability function R(-h)^n ~ exp(-T) (the previous
    method's floquet value), and the cycle is stable."""
    c = cycle16
    m = c.floquet_multipliers
    assert abs(m[0] - 1) == c.floquet_trivial_error < 1e-8
    assert c.floquet == pytest.approx(math.exp(-c.period), rel=1e-9)  # 0.76189, as before
    assert np.all(np.abs(m[1:]) <= c.floquet + 1e-12) and c.floquet < 1


def test_cost(cycle16):
    """Work counters, so that a slowdown fails: seed, 32 and 64 steps, error estimates."""
    w = cycle16.work
    assert cycle16.n_phase == 64
    assert w["newton"] <= 14 and w["period_maps"] <= 24
    assert w["factorizations"] <= 2600 and w["step_newton"] <= 6000


@pytest.mark.parametrize("k", [8, 24])
def test_other_published_curvatures(k):
    _check_published(limit_cycle(CiliumParams(200, 1, k * TWO_PI)), k)


def test_cycle_is_periodic_and_phase_zero_is_the_section(cycle16):
    tip = cycle16.data.theta.values[:, -1]
    assert tip[0] == pytest.approx(tip.mean(), abs=1e-8)  # tip angle crosses its mean at phase 0
    assert tip[1] > tip[0]  # upward


def test_step_sensitivities_match_finite_differences():
    """The compiled step's exact derivatives (monodromy and d/dh) against central differences."""
    p = CiliumParams(200, 1, 16 * TWO_PI)
    fil = Filament(p, Mesh.for_params(p, 6))
    st = stability(p, mesh=fil.mesh, n_modes=1, check=False)
    y0 = fil.equilibrium_state() + 0.3 * np.real(fil.join(st.theta_modes[0], st.kappa_modes[0]))
    sh = ExactShooting(fil, 16)
    h = 0.27 / 16
    Y, _, S, Sh = sh._steps(y0, h, 16, True)
    v = np.random.default_rng(1).standard_normal(y0.size) * fil.scale
    eps = 1e-6
    fd = (sh._steps(y0 + eps * v, h, 16, False)[0][-1] - sh._steps(y0 - eps * v, h, 16, False)[0][-1]) / (2 * eps)
    assert np.max(np.abs(S @ v - fd) / fil.scale) < 1e-7 * np.max(np.abs(fd) / fil.scale)
    up, down = sh._steps(y0, h * (1 + eps), 16, False)[0][-1], sh._steps(y0, h * (1 - eps), 16, False)[0][-1]
    fd = (up - down) / (2 * eps * h)
    assert np.max(np.abs(Sh - fd) / fil.scale) < 1e-6 * np.max(np.abs(fd) / fil.scale)


def test_refinement_order_in_time():
    """Observed order of the period and |Fbar| in the steps per period: at least 4 (Radau IIA
    is of order 5 at the step ends), which the time error estimate (change / 15) assumes."""
    p = CiliumParams(200, 1, 16 * TWO_PI)
    kw = dict(degree=8, floquet=False, error_estimate=False)
    ref = limit_cycle(p, n_phase=256, **kw)
    errs = []
    for n in (32, 64):
        c = limit_cycle(p, n_phase=n, seed=ref, **kw)
        errs.append((abs(c.period / ref.period - 1), abs(c.thrust_norm / ref.thrust_norm - 1)))
    errs = np.array(errs)
    order = np.log2(errs[0] / errs[1])
    assert np.all(order > 4), order


def test_refinement_in_degree():
    """Spectral convergence in the degree: each +2 gains more than a factor 10 in |Fbar|."""
    p = CiliumParams(200, 1, 16 * TWO_PI)
    kw = dict(n_phase=64, floquet=False, error_estimate=False)
    F = [limit_cycle(p, degree=d, **kw).thrust_norm for d in (6, 8, 10, 12)]
    e = np.abs(np.array(F[:3]) - F[3])
    assert e[1] < 0.1 * e[0] and e[2] < 0.1 * e[1]


def test_mirror_symmetry(cycle16):
    m = limit_cycle(cycle16.params.mirrored(), floquet=False, error_estimate=False)
    assert m.thrust_x == pytest.approx(-cycle16.thrust_x, rel=1e-7)
    assert m.thrust_y == pytest.approx(cycle16.thrust_y, rel=1e-7)
    assert m.thrust_angle == pytest.approx(-cycle16.thrust_angle, rel=1e-7)


def test_no_oscillation_is_a_result_not_an_error():
    c = limit_cycle(CiliumParams(50, 1, 0.0))
    assert not c.flutter and c.thrust_norm == 0 and math.isnan(c.period)
    assert c.status == "no oscillation" and "stable" in c.message


def test_thrust_angle_convention():
    # a force on the fluid pointing down the field (-e2) has phi = pi: thrust angle 0
    assert thrust_angle(0.0, -1.0) == pytest.approx(0.0)
    # tilted so that the filament pulls along theta = 0.3 (tangent (-sin, cos))
    assert thrust_angle(np.sin(0.3), -np.cos(0.3)) == pytest.approx(0.3)


@pytest.mark.parametrize("kw,match", [(dict(n_phase=8), "n_phase"), (dict(tol=1.0), "tol"),
                                      (dict(rtol=0.5), "rtol"), (dict(method="collocation"), "method")])
def test_bad_settings(kw, match):
    with pytest.raises(ValueError, match=match):
        limit_cycle(CiliumParams(200, 1, 0.0), **kw)


CUTOFF_200_1 = 162.77486240834992  # flutter_cutoff(200, 1) at degree 8


def test_near_the_cutoff():
    """0.999 x the cutoff: growth rate ~1e-3, amplitude ~sqrt(alpha): converges with its error
    estimate, within a bounded amount of work (a transient would need thousands of periods)."""
    c = limit_cycle(CiliumParams(200, 1, 0.999 * CUTOFF_200_1))
    assert c.status == "success" and 0 < c.thrust_norm < 0.01
    assert c.floquet < 1 and c.floquet > 0.99  # weakly attracting, as near a Hopf point
    assert c.work["period_maps"] <= 30 and c.work["newton"] <= 16
    # 0.995 x the cutoff against the previous method (degree 8 / 64 steps, ~1e-7 there)
    d = limit_cycle(CiliumParams(200, 1, 0.995 * CUTOFF_200_1), degree=8, n_phase=64, floquet=False,
                    error_estimate=False)
    assert d.period == pytest.approx(0.3562252824, rel=1e-8)
    assert d.thrust_norm == pytest.approx(0.0148200473, rel=1e-6)
    assert d.thrust_angle == pytest.approx(0.9459200742, abs=1e-7)


def test_straight_filament_pushes_along_the_field():
    c = limit_cycle(CiliumParams(200, 1, 0.0), degree=6, n_phase=32, floquet=False, error_estimate=False)
    # zero to the closure of the orbit sampled from phase 0 (residual <= 100 tol = 1e-8)
    assert abs(c.thrust_angle) < 1e-9 and abs(c.thrust_x) < 1e-9 * c.thrust_norm
    assert abs(c.tip_area) < 1e-9  # symmetric figure-of-eight: no net area


@pytest.mark.parametrize("p", [CiliumParams(200, 0.2, 16 * TWO_PI), CiliumParams(200, 5, 16 * TWO_PI)])
def test_stable_fields_give_no_oscillation(p):
    c = limit_cycle(p, degree=6)
    assert not c.flutter and c.status == "no oscillation" and c.thrust_norm == 0


def test_strong_field():
    p = CiliumParams(500, 0.5, 16 * TWO_PI)
    c = limit_cycle(p, degree=6, floquet=False, error_estimate=False)
    assert c.flutter and 0 < c.thrust_angle - c.theta_lim < 0.1 and c.n_phase >= 32


def test_failing_steps_say_what_to_change(monkeypatch):
    """A step whose Newton iteration fails: with n_phase given, the error says to raise it;
    chosen by the solver, the steps are doubled up to the limit, then a clear error."""
    p = CiliumParams(200, 1, 16 * TWO_PI)
    monkeypatch.setattr(ExactShooting, "step_maxiter", 1)
    with pytest.raises(CycleError, match=r"raise n_phase \(e.g. to 64\)"):
        limit_cycle(p, degree=6, n_phase=32, floquet=False, error_estimate=False)
    with pytest.raises(CycleError, match="fail even at 1024 steps per period"):
        limit_cycle(p, degree=6, floquet=False, error_estimate=False)


def test_heavy_drag_chooses_its_resolution():
    """eta = 20: the previous solver failed twice ("raise n_phase") before 256 steps by hand;
    now the resolution is chosen from the error estimate and reported."""
    c = limit_cycle(CiliumParams(200, 20, 16 * TWO_PI), degree=8, error_estimate=False)
    assert c.flutter and c.errors["time"] < 5e-7 and "(chosen)" in c.message
    assert c.status == "unchecked"


@pytest.mark.slow
def test_newton_krylov_cross_check(cycle16):
    """The previous method, kept as a method: same orbit on the same discretisation."""
    assert set(METHODS) == {"shooting", "newton-krylov"}
    p = cycle16.params
    a = limit_cycle(p, degree=8, n_phase=64, error_estimate=False)
    b = limit_cycle(p, degree=8, n_phase=64, error_estimate=False, method="newton-krylov")
    assert b.method == "newton-krylov"
    assert a.period == pytest.approx(b.period, rel=1e-9)
    assert a.thrust_norm == pytest.approx(b.thrust_norm, rel=1e-7)
    assert a.floquet == pytest.approx(b.floquet, rel=1e-6)
    assert abs(b.floquet_multipliers[0] - 1) < 1e-5


@pytest.mark.slow
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
