"""Tests of single_cilium.equilibrium: closed forms, ODE checks, limits, shapes, input checks."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad, solve_ivp

from single_cilium.equilibrium import (
    NoLimitAngleError,
    equilibrium,
    equilibrium_shape,
    limit_angle,
)
from single_cilium.params import CiliumParams

TWO_PI = 2.0 * math.pi


def P(chi_E: float, chi_N: float = 0.0) -> CiliumParams:
    return CiliumParams(chi_E=chi_E, eta=1.0, chi_N=chi_N)


def wrap(a: np.ndarray) -> np.ndarray:
    """Angle modulo 2 pi, in [-pi, pi)."""
    return (np.asarray(a) + math.pi) % TWO_PI - math.pi


S = np.linspace(0.0, 1.0, 401)


# ---------------------------------------------------------------------------------------------
# the special closed forms of MODEL.md section 3
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("chi_N", [0.0, 0.01 * TWO_PI, 16 * TWO_PI, -24 * TWO_PI, 3.7])
@pytest.mark.parametrize("phi", [0.0, 0.3, -1.0])
def test_arc_when_chi_E_is_zero(chi_N, phi):
    s = np.linspace(0.0, 2.5, 301)
    theta = equilibrium(P(0.0, chi_N), s, phi)
    np.testing.assert_allclose(theta, phi + chi_N * s, rtol=0, atol=1e-12)


@pytest.mark.parametrize("chi_E", [-50.0, -3.0, 0.5, 3.0, 200.0, 1e4])
@pytest.mark.parametrize("phi", [0.0, 0.3, -1.0, 2.5])
def test_chi_N_zero(chi_E, phi):
    with np.errstate(over="ignore"):
        expected = 2.0 * np.arctan(math.tan(phi / 2) * np.exp(-chi_E * S))
    np.testing.assert_allclose(equilibrium(P(chi_E, 0.0), S, phi), expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "chi_E, chi_N, phi",
    [
        (200.0, 100.0, math.asin(0.5)),  # stable
        (3.0, -1.0, math.asin(-1.0 / 3.0)),
        (1e4, 16 * TWO_PI, math.asin(16 * TWO_PI / 1e4)),
        (-3.0, 1.0, math.asin(-1.0 / 3.0)),  # unstable, chi_E < 0 (departure ~ e^3 * 1e-16)
        (-3.0, 1.0, math.pi - math.asin(-1.0 / 3.0)),  # the stable one for chi_E < 0
        (-1e4, 0.0, 0.0),  # unstable, exactly
        (5.0, 5.0, math.pi / 2),  # chi_E = chi_N: pi/2
        (5.0, -5.0, -math.pi / 2),  # chi_E = -chi_N: -pi/2
        (-5.0, 5.0, -math.pi / 2),
        (0.0, 0.0, 1.2),
    ],
)
def test_constant_solutions_at_fixed_points(chi_E, chi_N, phi):
    s = np.linspace(0.0, 3.0, 301)
    theta = equilibrium(P(chi_E, chi_N), s, phi)
    np.testing.assert_allclose(theta, phi, rtol=0, atol=1e-12)
    x, y = equilibrium_shape(P(chi_E, chi_N), s, phi)
    np.testing.assert_allclose(x, -math.sin(phi) * s, rtol=0, atol=1e-12)
    np.testing.assert_allclose(y, math.cos(phi) * s, rtol=0, atol=1e-12)


def _chi_E_equals_pm_chi_N(chi_E: float, chi_N: float, s: np.ndarray, phi: float) -> np.ndarray:
    # MODEL.md: chi_E = +-chi_N: theta = -+pi/2 + 2 arctan(tan(phi/2 +- pi/4) + chi_N s)
    sign = 1.0 if chi_E == chi_N else -1.0
    return -sign * math.pi / 2 + 2.0 * np.arctan(math.tan(phi / 2 + sign * math.pi / 4) + chi_N * s)


@pytest.mark.parametrize("chi_N", [0.01 * TWO_PI, 1.0, 16 * TWO_PI, -24 * TWO_PI])
@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("phi", [0.0, 0.3, -1.0])
def test_chi_E_equals_pm_chi_N_and_its_neighbourhood(chi_N, sign, phi):
    exact = _chi_E_equals_pm_chi_N(sign * chi_N, chi_N, S, phi)
    theta = equilibrium(P(sign * chi_N, chi_N), S, phi)
    np.testing.assert_allclose(theta, exact, rtol=0, atol=1e-12)
    for rel in (1e-12, -1e-12):  # on both sides: hyperbolic and coiled formulas
        theta = equilibrium(P(sign * chi_N * (1.0 + rel), chi_N), S, phi)
        np.testing.assert_allclose(theta, exact, rtol=0, atol=1e-9)


@pytest.mark.parametrize("chi_N", [1e4, -1e4])
@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("rel", [1e-12, -1e-12])
def test_sensitivity_near_chi_E_equals_pm_chi_N_is_the_true_one(chi_N, sign, rel):
    # Near the semi-stable fixed point the exact solution moves by -chi_N * rel * s / 3 (linearised
    # about theta_0 = pi/2 - 2/(chi_N s)): 3e-9 for |chi_N| = 1e4, so the 1e-9 agreement of the
    # previous test cannot hold there, and the closed form must reproduce this shift.
    near = equilibrium(P(sign * chi_N * (1 + rel), chi_N), 1.0)
    d = near - equilibrium(P(sign * chi_N, chi_N), 1.0)
    assert d == pytest.approx(-chi_N * rel / 3.0, rel=2e-3)


def _q_formula(chi_E: float, chi_N: float, s: np.ndarray, phi: float) -> np.ndarray:
    r = chi_E / chi_N
    q = np.sqrt(complex(1.0 - r * r))
    z = -chi_N * s * q / 2.0 + np.arctan((r - math.tan(phi / 2)) / q)
    th = 2.0 * np.arctan(r - q * np.tan(z))
    assert np.max(np.abs(th.imag)) < 1e-12
    return th.real


@pytest.mark.parametrize(
    "chi_E, chi_N, phi",
    [
        (200.0, 100.0, 0.0),
        (200.0, 100.0, 0.3),
        (50.0, 0.01 * TWO_PI, -1.0),
        (1.5, -1.0, 0.4),
        (2.0, 1.0, -1.0),
        (3.0, 5.0, 0.1),  # coiled, q real
        (50.0, 16 * TWO_PI, 0.0),  # coiled, many windings: compared modulo 2 pi
        (-50.0, 16 * TWO_PI, 0.3),
        (-5.0, 3.0, 0.0),  # folds over past pi: modulo 2 pi
        (-3.0, 1.0, 0.2),
        # (-200, 0.01*2pi, 0) is left out: there the q-formula in double precision is off by 1.5e-10
        # (checked against it in 50 digits, which agrees with `equilibrium` to 1e-15).
    ],
)
def test_general_q_formula(chi_E, chi_N, phi):
    theta = equilibrium(P(chi_E, chi_N), S, phi)
    diff = wrap(theta - _q_formula(chi_E, chi_N, S, phi))
    np.testing.assert_allclose(diff, 0.0, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# ODE residual and an independent numerical solution
# ---------------------------------------------------------------------------------------------
GRID_E = [-1e4, -200.0, -50.0, 0.0, 50.0, 200.0, 1e4]
GRID_N = [0.0, 0.01 * TWO_PI, 16 * TWO_PI, 24 * TWO_PI, -16 * TWO_PI]
GRID_PHI = [0.0, 0.3, -1.0]


def _derivative(params: CiliumParams, s: np.ndarray, phi: float, h: float) -> np.ndarray:
    """Sixth-order central difference of theta."""
    c = np.array([-1.0, 9.0, -45.0, 0.0, 45.0, -9.0, 1.0]) / 60.0
    return sum(ck * equilibrium(params, s + k * h, phi) for ck, k in zip(c, range(-3, 4))) / h


@pytest.mark.parametrize("chi_E", GRID_E)
@pytest.mark.parametrize("chi_N", GRID_N)
def test_ode_residual(chi_E, chi_N):
    scale = abs(chi_E) + abs(chi_N) + 1.0
    h = 1e-2 / scale
    s = 3 * h + np.concatenate([np.geomspace(1e-6, 1e-2, 40), np.linspace(0.01, 1.2, 120)])
    for phi in GRID_PHI:
        p = P(chi_E, chi_N)
        theta = equilibrium(p, s, phi)
        res = _derivative(p, s, phi, h) + chi_E * np.sin(theta) - chi_N
        assert np.max(np.abs(res)) < 1e-9 * scale, (phi, np.max(np.abs(res)))


@pytest.mark.parametrize("chi_E", GRID_E)
def test_against_dop853(chi_E):
    # All (chi_N, phi) of the grid are integrated together as uncoupled components (the step is set
    # by the hardest one). Beyond ~50 boundary-layer widths 1/|chi_E| the solution sits at a fixed
    # point to e^-50: for |chi_E| = 1e4 the explicit solver is run over the layer only (stiffness
    # would cost seconds) and the rest is compared to the fixed point it reached, refined by Newton.
    # (For chi_E = -1e4 and small chi_N the fold sits near s = ln(2|chi_E|/chi_N)/|chi_E| = 1.3e-3.)
    cases = [(chi_N, phi) for chi_N in GRID_N for phi in GRID_PHI]
    chi_N_vec = np.array([c[0] for c in cases])
    s_end = 1.0 if abs(chi_E) < 1e3 else 60.0 / abs(chi_E)
    s = np.linspace(0.0, s_end, 101)
    sol = solve_ivp(
        lambda _, y: chi_N_vec - chi_E * np.sin(y),
        (0.0, s_end),
        np.array([c[1] for c in cases]),
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
        t_eval=s,
    )
    assert sol.success
    for i, (chi_N, phi) in enumerate(cases):
        theta = equilibrium(P(chi_E, chi_N), s, phi)
        # the solver's error grows with the winding: 1e-9 relative to |theta|
        tol = 1e-9 * (1.0 + np.abs(theta)).max()
        np.testing.assert_allclose(theta, sol.y[i], rtol=0, atol=tol, err_msg=f"{chi_N=}, {phi=}")
        if s_end < 1.0:
            t = sol.y[i, -1]
            if chi_N - chi_E * math.sin(t) != 0.0:
                for _ in range(3):
                    t -= (chi_N - chi_E * math.sin(t)) / (-chi_E * math.cos(t))
            rest = equilibrium(P(chi_E, chi_N), np.linspace(s_end, 1.0, 50), phi)
            np.testing.assert_allclose(rest, t, rtol=0, atol=1e-12, err_msg=f"{chi_N=}, {phi=}")


@pytest.mark.parametrize("chi_E", [1e4, -1e4])
@pytest.mark.parametrize("chi_N", GRID_N + [1e4 * (1 - 1e-12), -1e4, 0.5e4])
def test_large_chi_E_is_finite(chi_E, chi_N):
    s = np.concatenate([np.linspace(0.0, 1.0, 2001), np.geomspace(1e-12, 1e-3, 200)])
    p = P(chi_E, chi_N)
    for phi in [0.0, 0.3, -1.0, 3.0]:
        theta = equilibrium(p, s, phi)
        x, y = equilibrium_shape(p, s, phi)
        assert np.all(np.isfinite(theta)) and np.all(np.isfinite(x)) and np.all(np.isfinite(y))
        assert np.all(np.hypot(x, y) <= s * (1 + 1e-12) + 1e-15)  # unit-speed curve from the origin


# ---------------------------------------------------------------------------------------------
# coiled regime: continuity and windings; mirror symmetry
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("chi_E", [0.0, 50.0, -50.0, 150.0, -0.999 * 24 * TWO_PI])
@pytest.mark.parametrize("phi", [0.0, 2.0])
@pytest.mark.parametrize("chi_N", [24 * TWO_PI, -24 * TWO_PI])
def test_coiled_is_continuous_and_counts_windings(chi_E, phi, chi_N):
    s = np.linspace(0.0, 3.0, 60001)
    theta = equilibrium(P(chi_E, chi_N), s, phi)
    jumps = np.abs(np.diff(theta))
    assert jumps.max() <= (abs(chi_E) + abs(chi_N)) * (s[1] - s[0]) * (1 + 1e-6)
    assert np.all(np.sign(chi_N) * np.diff(theta) > 0)  # monotone
    period = TWO_PI / math.sqrt((abs(chi_N) - chi_E) * (abs(chi_N) + chi_E))
    k = np.arange(0, int(3.0 / period) + 1)
    windings = (equilibrium(P(chi_E, chi_N), k * period, phi) - phi) / TWO_PI
    np.testing.assert_allclose(windings, np.sign(chi_N) * k, rtol=0, atol=2e-12)


def test_windings_of_the_arc():
    assert equilibrium(P(0.0, 8 * TWO_PI), 1.0) == pytest.approx(16 * math.pi, abs=1e-12)
    theta = equilibrium(P(0.0, -8 * TWO_PI), 1.0, 0.5)
    assert theta == pytest.approx(0.5 - 16 * math.pi, abs=1e-12)


@pytest.mark.parametrize("chi_E", GRID_E + [3.0, -1.0])
def test_mirror_symmetry(chi_E):
    s = np.linspace(0.0, 1.5, 151)
    for chi_N in [0.0, 0.01 * TWO_PI, 16 * TWO_PI, 24 * TWO_PI, 3.0, -1.0]:
        for phi in [0.0, 0.3, -1.0]:
            a = equilibrium(P(chi_E, chi_N), s, phi)
            b = equilibrium(P(chi_E, -chi_N), s, -phi)
            assert np.max(np.abs(a + b)) <= 1e-15
            xa, ya = equilibrium_shape(P(chi_E, chi_N), s, phi)
            xb, yb = equilibrium_shape(P(chi_E, -chi_N), s, -phi)
            assert np.max(np.abs(xa + xb)) <= 1e-15 and np.max(np.abs(ya - yb)) <= 1e-15


# ---------------------------------------------------------------------------------------------
# limit angle
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "chi_E, chi_N, expected",
    [
        (200.0, 100.0, math.pi / 6),
        (200.0, -100.0, -math.pi / 6),
        (200.0, 0.0, 0.0),
        (1e4, 16 * TWO_PI, math.asin(16 * TWO_PI / 1e4)),
        (7.0, 7.0, math.pi / 2),
        (7.0, -7.0, -math.pi / 2),
        (-200.0, 0.01 * TWO_PI, math.pi + math.asin(0.01 * TWO_PI / 200)),  # folds over
        (-200.0, -0.01 * TWO_PI, -math.pi - math.asin(0.01 * TWO_PI / 200)),
        (-200.0, 0.0, 0.0),  # stays at the unstable fixed point
        (-7.0, 7.0, 1.5 * math.pi),  # = -pi/2 mod 2 pi, reached by increasing theta
        (0.0, 0.0, 0.0),
    ],
)
def test_limit_angle_values(chi_E, chi_N, expected):
    assert limit_angle(P(chi_E, chi_N)) == pytest.approx(expected, abs=1e-15)


@pytest.mark.parametrize(
    "chi_E, chi_N, s_far, tol",
    [
        (200.0, 100.0, 50.0, 1e-12),
        (200.0, -16 * TWO_PI, 50.0, 1e-12),
        (200.0, 0.0, 50.0, 1e-12),
        (-200.0, 0.01 * TWO_PI, 50.0, 1e-12),
        (-200.0, 100.0, 50.0, 1e-12),
        (-200.0, 0.0, 50.0, 0.0),
        (200.0, 200.0, 50.0, 2.0 / (200.0 * 50.0) * 1.01),  # algebraic approach, 2/(chi_N s)
        (-200.0, 200.0, 50.0, 2.0 / (200.0 * 50.0) * 1.01),
    ],
)
def test_equilibrium_approaches_limit_angle(chi_E, chi_N, s_far, tol):
    p = P(chi_E, chi_N)
    assert abs(equilibrium(p, s_far) - limit_angle(p)) <= tol


@pytest.mark.parametrize(
    "chi_E, chi_N", [(0.0, 1.0), (0.0, -16 * TWO_PI), (50.0, 16 * TWO_PI), (-99.0, 100.0)]
)
def test_no_limit_angle_when_coiled(chi_E, chi_N):
    with pytest.raises(NoLimitAngleError, match="coils") as info:
        limit_angle(P(chi_E, chi_N))
    assert isinstance(info.value, ValueError)
    assert "|chi_E| >= |chi_N|" in str(info.value)


# ---------------------------------------------------------------------------------------------
# shape
# ---------------------------------------------------------------------------------------------
def _quad_shape(params: CiliumParams, phi: float, s_end: float) -> tuple[float, float]:
    """x, y by adaptive quadrature of the tangent, on pieces that resolve the layer and the coil."""
    theta = lambda t: float(equilibrium(params, t, phi))  # noqa: E731
    breaks = set(np.arange(0.0, s_end, 0.05)) | {s_end}
    if abs(params.chi_E) > 1.0:  # boundary layer (or fold) within ~30/|chi_E| of the clamp
        breaks |= set(2.0 ** np.arange(-3.0, 6.0) / abs(params.chi_E))
    breaks = sorted(b for b in breaks if b <= s_end)
    x = y = 0.0
    for a, b in zip(breaks[:-1], breaks[1:]):
        x += quad(lambda t: -math.sin(theta(t)), a, b, epsabs=1e-14, epsrel=1e-14)[0]
        y += quad(lambda t: math.cos(theta(t)), a, b, epsabs=1e-14, epsrel=1e-14)[0]
    return x, y


@pytest.mark.parametrize(
    "chi_E, chi_N, phi",
    [
        (200.0, 16 * TWO_PI, 0.0),  # boundary layer at the clamp
        (1e4, 24 * TWO_PI, 0.3),
        (-1e4, 0.01 * TWO_PI, 0.0),  # fold near s = 1e-3
        (-200.0, 0.0, -1.0),
        (50.0, 24 * TWO_PI, -1.0),  # coiled
        (1e-9, 16 * TWO_PI, 0.0),  # nearly an arc: x, y would be 0/0 in the naive forms
        (0.0, 0.01 * TWO_PI, 0.3),
        (16 * TWO_PI * (1 + 1e-12), 16 * TWO_PI, 0.3),  # chi_E ~ chi_N
        (-16 * TWO_PI * (1 - 1e-12), 16 * TWO_PI, 0.0),
        (0.7, 0.3, 2.5),
        (-1e-3, 1e-4, 1.0),
    ],
)
def test_shape_against_quadrature(chi_E, chi_N, phi):
    p = P(chi_E, chi_N)
    s_end = np.array([0.37, 1.0])
    x, y = equilibrium_shape(p, s_end, phi)
    for i, se in enumerate(s_end):
        xr, yr = _quad_shape(p, phi, float(se))
        assert abs(x[i] - xr) < 1e-12 and abs(y[i] - yr) < 1e-12, (se, x[i] - xr, y[i] - yr)


@pytest.mark.parametrize(
    "chi_E, chi_N, phi",
    [
        (200.0, 16 * TWO_PI, 0.0),
        (50.0, -24 * TWO_PI, 0.3),
        (0.0, 3.0, 0.0),
        (-50.0, 1.0, -1.0),
        (3.0, 3.0, 0.2),
    ],
)
def test_shape_has_unit_speed_along_the_tangent(chi_E, chi_N, phi):
    p = P(chi_E, chi_N)
    h = 1e-2 / (abs(chi_E) + abs(chi_N) + 1.0)
    s = np.linspace(3 * h, 1.0, 200)
    c = np.array([-1.0, 9.0, -45.0, 0.0, 45.0, -9.0, 1.0]) / 60.0
    pts = [equilibrium_shape(p, s + k * h, phi) for k in range(-3, 4)]
    dx = sum(ck * q[0] for ck, q in zip(c, pts)) / h
    dy = sum(ck * q[1] for ck, q in zip(c, pts)) / h
    theta = equilibrium(p, s, phi)
    np.testing.assert_allclose(np.hypot(dx, dy), 1.0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(dx, -np.sin(theta), rtol=0, atol=1e-9)
    np.testing.assert_allclose(dy, np.cos(theta), rtol=0, atol=1e-9)
    x0, y0 = equilibrium_shape(p, 0.0, phi)
    assert x0 == 0.0 and y0 == 0.0


def test_shapes_follow_the_input():
    s = np.linspace(0.0, 1.0, 12).reshape(3, 4)
    p = P(200.0, 100.0)
    assert equilibrium(p, s).shape == (3, 4)
    x, y = equilibrium_shape(p, s)
    assert x.shape == y.shape == (3, 4)
    assert equilibrium(p, 0.5).shape == ()
    np.testing.assert_array_equal(equilibrium(p, s).ravel(), equilibrium(p, s.ravel()))


# ---------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("func", [equilibrium, equilibrium_shape])
def test_bad_input(func):
    p = P(200.0, 100.0)
    with pytest.raises(ValueError, match=r"\bs\b"):
        func(p, [0.1, float("nan")])
    with pytest.raises(ValueError, match=r"\bs\b"):
        func(p, [0.1, float("inf")])
    with pytest.raises(ValueError, match=r"\bs\b.*>= 0"):
        func(p, [0.1, -1e-3])
    with pytest.raises(ValueError, match=r"\bs\b"):
        func(p, [0.1 + 1j])
    with pytest.raises(ValueError, match="phi"):
        func(p, [0.1], float("nan"))
    with pytest.raises(ValueError, match="phi"):
        func(p, [0.1], "a")


@pytest.mark.parametrize("chi_E", [0.0, 5e-324, -5e-324])
@pytest.mark.parametrize("chi_N", [5e-324, -5e-324, 1e-310])
def test_subnormal_curvatures_are_finite(chi_E, chi_N):
    """Halving a subnormal chi_N rounds it to 0, which made the coiled branch divide by w = 0
    (hypothesis found chi_E = 0, chi_N = 5e-324). Such a filament is straight to within a
    subnormal: theta = chi_N s, and the shape is finite."""
    s = np.linspace(0.0, 1.0, 5)
    params = CiliumParams(chi_E, 1.0, chi_N)
    theta = equilibrium(params, s)
    shape = equilibrium_shape(params, s)
    assert np.all(np.isfinite(theta))
    assert all(np.all(np.isfinite(v)) for v in shape)
    assert np.max(np.abs(theta - chi_N * s)) <= 1e-323


@pytest.mark.parametrize("chi_N", [5e-324, 1e-320, 1e-300])
def test_reversed_field_with_the_smallest_curvatures_flips_where_the_perturbation_has_grown(chi_N):
    """chi_E = -746 (the field against the clamped filament), chi_N at the smallest doubles: the
    filament stays up until chi_N e^{|chi_E| s} has grown to O(1), then flips. For 5e-324 that is
    beyond s = 1 (theta(1) = 0.0064, not pi); every shape keeps |r(s)| <= s (exp(-|chi_E| s)
    underflows before 2 exp(-|chi_E| s) / T does: the flip was once placed at the clamp)."""
    p = CiliumParams(-746.0, 1.0, chi_N)
    s = np.linspace(0.0, 1.0, 11)
    x, y = equilibrium_shape(p, s)
    assert np.all(np.hypot(x, y) <= s + 1e-6)
    th = float(equilibrium(p, [1.0])[0])
    if chi_N == 5e-324:
        assert 0.0 < th < 0.01 and y[-1] > 0.999
    else:  # flipping before s = 1: the tip turns back down
        assert th > 2.5 and y[-1] < 1.0 - 1e-3
