"""The filament in a uniform background flow U (CiliumParams.background; issue 27, first part).

The drag acts on the velocity relative to the stream, d = -eta ((v - U).t t + 2 (v - U).n n)
(field frame, e2 along the field, U in units of L / tau); F = -int d ds is the force the filament
exerts on the fluid (MODEL.md section 5).
"""
import math

import numpy as np
import pytest

from single_cilium import (CiliumParams, Filament, Mesh, equilibrium, limit_cycle, simulate, stability,
                           steady_state)
from single_cilium.cycle import mean_thrust
from single_cilium.orbit import ExactShooting
from single_cilium.stability import _hopf_alpha, _pencil, flutter_cutoff, spectrum

TWO_PI = 2 * np.pi
#: a stream with both components, at the published field chi_E = 200, eta = 1
STREAM = (1.5, -1.0)
P_STREAM = CiliumParams(200, 1, 16 * TWO_PI, STREAM)


@pytest.fixture(scope="module")
def stream_cycle():
    return limit_cycle(P_STREAM)


@pytest.fixture(scope="module")
def fine_cycle():
    """Degree 8, 256 steps per period: the reference of the refinement in time."""
    return limit_cycle(P_STREAM, degree=8, n_phase=256, floquet=False, error_estimate=False)


# ------------------------------------------------------------------------------ parameters
def test_background_is_a_validated_frozen_pair():
    p = CiliumParams(200, 1, 3, background=(1, -2))
    assert p.background == (1.0, -2.0) and all(isinstance(u, float) for u in p.background)
    assert p.has_background and not CiliumParams(200, 1, 3).has_background
    assert CiliumParams(200, 1, 3) == CiliumParams(200, 1, 3, (0.0, -0.0))  # default: fluid at rest
    assert repr(CiliumParams(200, 1, 3)) == "CiliumParams(chi_E=200.0, eta=1.0, chi_N=3.0)"
    assert p.mirrored() == CiliumParams(200, 1, -3, (-1, -2))
    assert p.with_background((0, 0)) == CiliumParams(200, 1, 3)
    with pytest.raises(AttributeError):
        p.background = (0.0, 0.0)
    for bad in [(math.nan, 0.0), (0.0, math.inf), 1.0, (1.0, 2.0, 3.0), ("a", 0.0)]:
        with pytest.raises(ValueError, match="background"):
            CiliumParams(200, 1, 3, bad)


def test_physical_background_flow_round_trip():
    L, tau = 100e-6, 2.0
    p = CiliumParams.from_physical(L, tau, 1e-15, 2e-3, 2e6, 1e6, background_flow=(1e-5, -2e-5))
    assert p.background == pytest.approx((0.2, -0.4), rel=1e-14)  # in units of L / tau
    back = p.to_physical(L, tau, 1e-15)
    assert back.background_flow == pytest.approx((1e-5, -2e-5), rel=1e-14)
    assert back.to_params().background == pytest.approx(p.background, rel=1e-14)


def test_closed_form_refuses_a_stream():
    p = CiliumParams(200, 1, 3, (0.0, 1.0))
    with pytest.raises(ValueError, match="steady_state"):
        equilibrium(p, [0.0, 1.0])


# ------------------------------------------------------------------------------ U = 0
# The values before the background flow existed (U = 0 must reproduce them). They are anchors from
# one machine, so the comparison allows what the computation itself does not pin down: simulate's
# adaptive Radau steps are accepted at rtol = 1e-8, and rounding that differs between machines (BLAS,
# numpy, numba) can change the accepted step sequence, which moves the forces by up to the global
# error, a small multiple of rtol of the force scale (4.7e-9 relative seen on a second machine); the
# cycle is converged to a scaled Newton residual of 1e-10 at a fixed discretisation. A change in the
# physics of the U = 0 path moves these numbers by far more (1e-4 and up).
TODAY_F = [[-0.0019118987265741838, -0.0011077948711905447], [-7.076774739095688e-05, -3.930497562564997e-05],
           [0.0008042080744364063, 0.00046890386880788914], [0.0013690178542616301, 0.0007971093929817649]]
TODAY_CYCLE = (0.2719537860647553, [0.4145826629557567, -0.6486983271769466])
SIM_RTOL = 1e-8  # simulate's default step tolerance, used below
NEWTON_TOL = 1e-10  # limit_cycle's default Newton tolerance


def test_zero_background_reproduces_todays_values():
    p = CiliumParams(200, 1, 16 * TWO_PI, background=(0.0, 0.0))
    sim = simulate(p, 0.02, n_out=5, error_estimate=False, rtol=SIM_RTOL)
    scale = np.max(np.abs(TODAY_F))
    np.testing.assert_allclose(sim.force[1:], TODAY_F, rtol=100 * SIM_RTOL, atol=100 * SIM_RTOL * scale)
    c = limit_cycle(p, degree=6, n_phase=32, floquet=False, error_estimate=False, tol=NEWTON_TOL)
    assert c.period == pytest.approx(TODAY_CYCLE[0], rel=10 * NEWTON_TOL)
    np.testing.assert_allclose(c.thrust, TODAY_CYCLE[1], rtol=10 * NEWTON_TOL)


# ------------------------------------------------------------------------------ closed forms
@pytest.mark.parametrize("U2", [1.3, -1.3])
def test_straight_filament_in_a_stream_along_itself(U2):
    """chi_N = 0 along the field, U = (0, U2): the filament stays straight and the fluid's drag on
    it is d = eta U2 t = eta U2 e2 per length (tangential coefficient eta), so the force it exerts
    on the fluid is F = -int d ds = -eta U2 e2 (L = 1)."""
    eta = 0.7
    p = CiliumParams(50, eta, 0.0, (0.0, U2))
    ss = steady_state(p)
    assert np.all(ss.theta == 0.0)
    np.testing.assert_allclose(ss.force, [0.0, -eta * U2], rtol=0, atol=1e-10)
    sim = simulate(p, 0.5, amplitude=0.0, n_out=6, error_estimate=False)  # from the exact straight state
    assert np.max(np.abs(sim.data.theta.values)) == 0.0
    np.testing.assert_allclose(sim.force, np.tile([0.0, -eta * U2], (6, 1)), rtol=0, atol=1e-10)
    # perturbed, the (stable) filament returns to it: the force too
    sim = simulate(p, 25.0, amplitude=1e-2, n_out=3, error_estimate=False)
    np.testing.assert_allclose(sim.force[-1], [0.0, -eta * U2], rtol=0, atol=1e-10)
    # no flutter here: the mean thrust is that force, not zero as in still fluid
    c = limit_cycle(p, degree=6)
    assert not c.flutter and c.status == "no oscillation" and "steady state" in c.message
    np.testing.assert_allclose(c.thrust, [0.0, -eta * U2], rtol=0, atol=1e-10)
    assert c.thrust_angle == pytest.approx(0.0 if U2 > 0 else math.pi, abs=1e-10)
    m = mean_thrust(p, degree=6)
    assert not m.flutter and m.status == "no oscillation" and math.isnan(m.period)
    np.testing.assert_allclose(m.thrust, [0.0, -eta * U2], rtol=0, atol=1e-10)
    assert m.error < 1e-12


def test_cantilever_in_a_weak_cross_flow():
    """Passive straight filament (chi_E = chi_N = 0) in a weak stream U = (U1, 0) across it: the
    normal drag 2 eta U1 per length is a uniform load on a clamped-free Euler-Bernoulli beam of
    unit stiffness, tip deflection q/8 = eta U1 / 4 along +e1 (downstream), tip slope q/6 (theta
    = -eta U1 / 3), force on the fluid -2 eta U1 e1; nonlinear corrections are O(U1^2) relative."""
    eta, U1 = 0.7, 1e-4
    ss = steady_state(CiliumParams(0.0, eta, 0.0, (U1, 0.0)), mesh=Mesh.uniform(2, 10))
    assert ss.x[-1] == pytest.approx(eta * U1 / 4, rel=1e-8)
    assert ss.theta[-1] == pytest.approx(-eta * U1 / 3, rel=1e-8)
    assert ss.force[0] == pytest.approx(-2 * eta * U1, rel=1e-8)


# ------------------------------------------------------------------------------ Jacobians
def test_stream_jacobian_and_linearisation_against_finite_differences():
    p = CiliumParams(200, 1, 16 * TWO_PI, STREAM)
    fil = Filament(p, Mesh.for_params(p, 6))
    y = fil.equilibrium_state()
    assert np.max(np.abs(fil.rhs(y))) < 1e-9  # a steady state of the discrete system
    # the compiled stage residual (U added to the velocity integrals) against numpy's f - M K
    # (U's drag as a separate load)
    rng = np.random.default_rng(3)
    Y = y + 0.1 * rng.standard_normal((3, fil.size)) * fil.scale
    K = rng.standard_normal((3, fil.size)) * fil.scale
    G = fil.residual(Y, K)
    np.testing.assert_allclose(G, fil.rhs(Y) - fil.mass_apply(Y, K), rtol=0, atol=1e-9 * np.max(np.abs(G)))
    theta, _ = fil.split(y)
    Jg = fil.stream_jacobian(theta)
    eps = 1e-7
    fd = np.empty_like(Jg)
    for j in range(1, fil.n):
        e = np.zeros(fil.n)
        e[j] = eps
        fd[:, j - 1] = (fil.stream_load(theta + e) - fil.stream_load(theta - e)) / (2 * eps)
    assert np.max(np.abs(Jg - fd)) < 1e-6 * np.max(np.abs(fd))
    # the stability pencil's J is df/dy at the steady state
    J, _, _ = _pencil(fil)
    fdJ = np.empty_like(J)
    for j in range(fil.size):
        e = np.zeros(fil.size)
        e[j] = eps * fil.scale[j]
        fdJ[:, j] = (fil.rhs(y + e) - fil.rhs(y - e)) / (2 * e[j])
    assert np.max(np.abs(J - fdJ)) < 1e-5 * np.max(np.abs(fdJ))


def test_monodromy_with_stream_matches_finite_differences():
    """The compiled step's exact derivatives (monodromy and d/dh) carry the stream's terms."""
    fil = Filament(P_STREAM, Mesh.for_params(P_STREAM, 6))
    st = stability(P_STREAM, mesh=fil.mesh, n_modes=1, check=False)
    y0 = fil.equilibrium_state() + 0.3 * np.real(fil.join(st.theta_modes[0], st.kappa_modes[0]))
    sh = ExactShooting(fil, 16)
    h = 0.27 / 16
    _, _, S, Sh = sh._steps(y0, h, 16, True)
    v = np.random.default_rng(1).standard_normal(y0.size) * fil.scale
    eps = 1e-6
    fd = (sh._steps(y0 + eps * v, h, 16, False)[0][-1] - sh._steps(y0 - eps * v, h, 16, False)[0][-1]) / (2 * eps)
    size = np.max(np.abs(fd) / fil.scale)
    assert np.max(np.abs(S @ v - fd) / fil.scale) < 1e-7 * size
    # (the still-fluid monodromy is off by percents here: the check can tell)
    S0 = ExactShooting(Filament(P_STREAM.with_background((0, 0)), fil.mesh), 16)._steps(y0, h, 16, True)[2]
    assert np.max(np.abs(S0 @ v - fd) / fil.scale) > 1e-3 * size
    up, down = sh._steps(y0, h * (1 + eps), 16, False)[0][-1], sh._steps(y0, h * (1 - eps), 16, False)[0][-1]
    fd = (up - down) / (2 * eps * h)
    assert np.max(np.abs(Sh - fd) / fil.scale) < 1e-6 * np.max(np.abs(fd) / fil.scale)


# ------------------------------------------------------------------------------ cycles
def test_stream_cycle(stream_cycle):
    c = stream_cycle
    assert c.flutter and c.status == "success" and c.params.background == STREAM
    assert abs(c.floquet_multipliers[0] - 1) < 1e-8 and c.floquet < 1
    assert c.data.attrs["background_U1"] == STREAM[0] and c.as_dict()["U2"] == STREAM[1]
    # the stream changes the thrust at O(eta |U|) (here it dominates it), and the period a little
    still = TODAY_CYCLE  # degree 6 / 32 steps: close enough for a qualitative comparison
    assert 0.9 < c.period / still[0] < 1.0
    assert np.hypot(*(c.thrust - np.array(still[1]))) > 1.0


def test_mirror_symmetry_with_stream(stream_cycle):
    """(chi_N, U1, U2) -> (-chi_N, -U1, U2) mirrors the cycle (e1 -> -e1)."""
    c = stream_cycle
    m = limit_cycle(c.params.mirrored())
    assert m.params == CiliumParams(200, 1, -16 * TWO_PI, (-STREAM[0], STREAM[1]))
    assert m.period == pytest.approx(c.period, rel=1e-9)
    assert m.thrust_x == pytest.approx(-c.thrust_x, rel=1e-8)
    assert m.thrust_y == pytest.approx(c.thrust_y, rel=1e-8)
    assert m.thrust_angle == pytest.approx(-c.thrust_angle, rel=1e-8)


def test_refinement_order_in_time_with_stream(fine_cycle):
    """As for U = 0 (tests/test_cycle.py): order > 4 in the steps per period (Radau IIA(5)),
    which the time error estimate (change / 15) assumes."""
    ref = fine_cycle
    kw = dict(degree=8, floquet=False, error_estimate=False)
    errs = []
    for n in (32, 64):
        c = limit_cycle(P_STREAM, n_phase=n, seed=ref, **kw)
        errs.append((abs(c.period / ref.period - 1), abs(c.thrust_norm / ref.thrust_norm - 1)))
    errs = np.array(errs)
    order = np.log2(errs[0] / errs[1])
    assert np.all(order > 4), order


def test_refinement_in_degree_with_stream(stream_cycle):
    """Spectral convergence in the degree: each +2 gains more than a factor 10 in |Fbar|."""
    kw = dict(n_phase=64, floquet=False, error_estimate=False, seed=stream_cycle)
    F = [limit_cycle(P_STREAM, degree=d, **kw).thrust_norm for d in (6, 8, 10, 12)]
    e = np.abs(np.array(F[:3]) - F[3])
    assert e[1] < 0.1 * e[0] and e[2] < 0.1 * e[1]


def test_error_estimate_holds_with_stream(stream_cycle):
    """The default cycle's error estimates bound its actual error (against degree 14, 256 steps)."""
    c = stream_cycle
    ref = limit_cycle(P_STREAM, degree=14, n_phase=256, seed=c, floquet=False, error_estimate=False)
    assert abs(c.period / ref.period - 1) <= c.errors["period"]
    assert abs(c.thrust_norm / ref.thrust_norm - 1) <= c.errors["thrust_norm"]
    assert abs(c.thrust_angle - ref.thrust_angle) <= c.errors["thrust_angle"]
    assert max(c.errors[k] for k in ("period", "thrust_norm", "thrust_angle")) < 1e-6
    # mean_thrust: the same cycle, its error a bound on the thrust vector's error
    m = mean_thrust(P_STREAM, seed=c)
    assert m.flutter and m.status == "success" and m.period == pytest.approx(c.period, rel=1e-9)
    assert np.hypot(*(m.thrust - ref.thrust)) <= m.error < 1e-6 * m.thrust_norm


def test_integrator_agrees_with_shooting_in_a_stream(fine_cycle):
    """simulate (Python Radau on Filament's residual) from the cycle's phase-0 state runs along
    the cycle found by the compiled period map: F(t) at the phase points agrees."""
    c = fine_cycle
    fil = Filament(c.params, c.mesh)
    theta, kappa = fil.split(c.state0)
    n = c.n_phase
    sim = simulate(c.params, c.period, state=(theta, kappa), mesh=c.mesh, rtol=1e-10, n_out=n + 1,
                   error_estimate=False)
    F = np.stack([c.data.Fx.values, c.data.Fy.values], -1)
    assert np.max(np.abs(sim.force[:-1][1:] - F[1:])) < 1e-6 * np.max(np.abs(F))


def test_continuation_in_the_stream():
    """Seeds at neighbouring U (same chi_N): the secant predictor along U2 converges in a few
    Newton steps to the cycle found from scratch."""
    kw = dict(degree=6, n_phase=32, floquet=False, error_estimate=False)

    def P(U2):
        return CiliumParams(200, 1, 16 * TWO_PI, (0.0, U2))

    c1 = limit_cycle(P(0.5), **kw)
    c2 = limit_cycle(P(1.0), seed=c1, **kw)
    c3 = limit_cycle(P(1.5), seed=[c1, c2], **kw)
    assert c3.work["newton"] <= 3
    scratch = limit_cycle(P(1.5), **kw)
    assert c3.period == pytest.approx(scratch.period, rel=1e-9)
    np.testing.assert_allclose(c3.thrust, scratch.thrust, rtol=0, atol=1e-8)


def test_flutter_cutoff_in_a_stream():
    """The cutoff in chi_N in a stream is where the oscillatory mode about the steady state in that
    stream crosses alpha = 0; U = (0, 0) gives today's cutoff."""
    xtol = 1e-10  # Brent's bracket, relative: the root is known to this, not to the last bit
    assert flutter_cutoff(200, 1, degree=8, xtol=xtol, background=(0.0, 0.0)).chi_N_cutoff == pytest.approx(
        162.77486240831666, rel=2 * xtol)
    U = (0.0, 2.0)
    c = flutter_cutoff(200, 1, degree=8, background=U)
    assert c.background == U and math.isfinite(c.chi_N_cutoff) and c.error < 1e-4
    for f, sign in ((1.0, 0), (0.99, 1), (1.01, -1)):
        p = CiliumParams(200, 1, f * c.chi_N_cutoff, U)
        a = _hopf_alpha(spectrum(p, Mesh.for_params(p, 8)))[0]
        assert (abs(a) < 1e-6) if sign == 0 else (np.sign(a) == sign)


def test_no_steady_state_in_the_stream_is_a_clear_error():
    """Near chi_N = chi_E the still-fluid equilibrium is marginal (across the field) and a weak
    stream against the field tips it over: no steady state, said so."""
    from single_cilium.cycle import CycleError

    p = CiliumParams(200, 1, 199.9998, (0.0, -2.0))
    with pytest.raises(RuntimeError, match="no steady state"):
        steady_state(p, degree=8)
    with pytest.raises(CycleError, match="no steady state"):
        limit_cycle(p, degree=8)
