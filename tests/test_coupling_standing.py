"""Coupled standing carpets: each standing cilium beats in the part of the others' mean flow that
lies in its beat plane, U_j = (u . e_psi_j, u . e_z) at its force centre in space
(:mod:`ciliary_carpet.carpet.coupling`, MODEL.md section 6).

The table is a small, coarse one over the flow (degree 6, 32 phases, 17 s points, chi_N 60 ... 120,
flows -1, 0, 1 in each component: about 15 s to build on 2 cores); the coupled flows of these
carpets stay well inside it.
"""
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest

from single_cilium.table import build_table

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.carpet.coupling import (CouplingError, CouplingResponse, _operator, _thrust_derivative, couple,
                                            coupling_estimate)

FAST = dict(degree=6, n_phase=32, n_s=17, error_estimate=False)
GRID = [60.0, 80.0, 100.0, 120.0]


@pytest.fixture(scope="module")
def flow():
    with ThreadPoolExecutor(2) as ex:
        return build_table(200, 1, GRID, U_par=[-1.0, 0.0, 1.0], U_perp=[-1.0, 0.0, 1.0], executor=ex, **FAST)


def _frames(psi):
    """e_psi (N, 3), e_z (3,) and the horizontal normal e_z x e_psi (N, 3) of beat planes psi (N,)."""
    psi = np.asarray(psi, dtype=float)
    e_psi = np.column_stack([np.cos(psi), np.sin(psi), np.zeros_like(psi)])
    return e_psi, np.array([0.0, 0.0, 1.0]), np.column_stack([-np.sin(psi), np.cos(psi), np.zeros_like(psi)])


def _standing(bases, chi, table, psi, **kw):
    n = len(bases)
    return Carpet(np.asarray(bases, float), chi, table, layout.random_phases(n, 0), wall=0.0, geometry="standing",
                  azimuth=psi, **kw)


def test_one_standing_cilium_feels_nothing(flow):
    """Its own resolved mean line is exactly what others_mean_flow removes: zero to rounding, so
    the coupled flow is still fluid."""
    one = _standing(np.zeros((1, 2)), 92.0, flow, 0.4)
    cen = one.in_space("centres")
    own = one.velocity(cen, CycleMean(), 0.0)
    assert np.abs(own).max() > 1e-2  # what is removed is not small
    for tol in (0.0, 1e-4):
        assert np.abs(one.others_mean_flow(tol=tol)).max() <= 1e-14 * np.abs(own).max()
    c = _standing(np.zeros((1, 2)), 92.0, flow, 0.4, coupling="mean")
    r = c.coupled
    assert r.converged and r.contraction == 0.0 and r.normal_flow == 0.0
    assert r.background.shape == (1, 2) and not np.any(r.background) and not np.any(r.uncoupled)
    assert c.background is None or not np.any(c.background)
    assert not np.any(CouplingResponse(c).apply(np.ones((1, 2))))  # nothing answers its own push


def test_two_standing_cilia_solve_their_equation(flow):
    """Two cilia of different curvature (their centres at different heights) and beat planes:
    the solve converges; independently, each one's background is the others' mean flow at its
    centre in space, projected on its own e_psi and e_z; what it cannot feel (along
    e_z x e_psi) is the reported normal flow; the Newton operator has no self term at any
    centre and its dense form (CouplingResponse) is the same matrix."""
    bases, chi, psi = np.array([[0.0, 0.0], [1.6, 0.7]]), np.array([92.0, 70.0]), np.array([0.3, 2.0])
    plain = _standing(bases, chi, flow, psi)
    # the others' flow is that of the other cilium alone (resolved), at the centre in space
    cen = plain.in_space("centres")
    assert abs(cen[0, 2] - cen[1, 2]) > 0.01  # (0.39 and 0.41 L)
    for j in (0, 1):
        alone = _standing(bases[[1 - j]], chi[[1 - j]], flow, psi[[1 - j]])
        u = alone.velocity(cen[[j]], CycleMean(), 0.0)
        np.testing.assert_allclose(plain.others_mean_flow([j], tol=0.0), u, rtol=1e-11, atol=1e-13 * np.abs(u).max())

    # on the substrate, 1.75 L apart, the coupling changes the flows by 0.3 %: solved to 1e-6
    r = couple(plain, tol=1e-7, rtol=1e-6)
    c = r.carpet
    assert r.converged and r.residual <= 1e-6
    np.testing.assert_array_equal(c.background, r.background)
    e_psi, e_z, normal = _frames(c.azimuth)
    u = replace(c, coupling="none", background=c.background).others_mean_flow(tol=1e-7)  # (2, 3) in space
    M = np.column_stack([np.sum(u * e_psi, axis=1), u @ e_z])
    assert np.abs(M - c.background).max() <= 1e-6 * np.abs(M).max()
    assert np.abs(M - r.uncoupled).max() > 100 * np.abs(M - c.background).max()  # the coupling is felt
    w = np.sum(u * normal, axis=1)
    assert r.normal_flow == pytest.approx(np.abs(w).max() / np.abs(c.background).max(), rel=1e-9)
    assert r.normal_flow > 0.1

    c = _standing(bases, chi, flow, psi, coupling="mean")  # at the default tolerances
    assert c.coupled.converged and np.abs(c.background - r.background).max() <= 2e-3 * np.abs(M).max()
    A = _operator(c)
    for j in (0, 1):  # a force on cilium j alone: nothing at its own centre, the other's flow at the other
        f = np.zeros((2, 2))
        f[j] = [0.7, -0.4]
        Af = A(f.ravel()).reshape(2, 2)
        assert np.abs(Af[j]).max() <= 1e-12 * np.abs(Af[1 - j]).max()
    rng = np.random.default_rng(0)
    f = rng.standard_normal(4)
    R = CouplingResponse(c)
    P = _thrust_derivative(c, c.background)
    PA = np.stack([np.einsum("jab,jb->ja", P, A(e).reshape(2, 2)).ravel() for e in np.eye(4)], axis=1)
    # R.apply(dF) = ((I - P A)^-1 - I) dF
    np.testing.assert_allclose(R.apply(f.reshape(2, 2)).ravel(), np.linalg.solve(np.eye(4) - PA, f) - f,
                               rtol=1e-10, atol=1e-14)


def test_free_space_row_is_the_planar_row_turned(flow):
    """Without a wall, a row of standing cilia with psi = 0 is the planar row (field along +y)
    turned by 90 degrees about the x axis (flows agree to rounding, tests/test_standing.py): so
    are their coupled solves, U in the beat plane (e_x, e_z) being the planar (e_x, e_y)."""
    rng = np.random.default_rng(5)
    bases = np.column_stack([np.arange(4) * 1.5, np.zeros(4)])
    chi, ph = rng.uniform(65, 115, 4), rng.random(4)
    p = Carpet(bases, chi, flow, ph, coupling="mean")
    s = Carpet(bases, chi, flow, ph, geometry="standing", coupling="mean")
    assert p.coupled.converged and s.coupled.converged
    scale = np.abs(p.background).max()
    assert np.abs(p.background - p.coupled.uncoupled).max() > 0.05 * scale
    np.testing.assert_allclose(s.background, p.background, rtol=0, atol=1e-12 * scale)
    assert s.coupled.normal_flow == pytest.approx(0.0, abs=1e-12)  # the row lies in its beat plane


def test_turning_every_beat_plane_turns_the_problem(flow):
    """Bases turned by a about the origin and every psi by a: the same U_j in each cilium's own
    frame, to the solver's tolerance. (chi_N, psi) -> (-chi_N, psi + pi), the same cilia, turns
    each frame's e_psi over: U_perp changes sign, U_par does not."""
    b = layout.square(3, 3, 2.0)
    rng = np.random.default_rng(3)
    chi = rng.uniform(70, 110, 9)
    psi = rng.uniform(-0.5, 0.5, 9)
    a = 0.9
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    c0 = _standing(b, chi, flow, psi, coupling="mean")
    ca = _standing(b @ rot.T, chi, flow, psi + a, coupling="mean")
    assert c0.coupled.converged and ca.coupled.converged
    scale = np.abs(c0.background).max()
    err = np.abs(ca.background - c0.background).max() / scale
    assert err <= 2 * (c0.coupled.residual + ca.coupled.residual) + 1e-4, err
    cm = _standing(b, -chi, flow, psi + math.pi, coupling="mean")
    assert cm.coupled.converged
    err = np.abs(cm.background * np.array([-1.0, 1.0]) - c0.background).max() / scale
    assert err <= 2 * (c0.coupled.residual + cm.coupled.residual) + 1e-4, err


def test_uniform_standing_carpet_is_slowed_by_its_coupling(flow):
    """4 x 4 cilia, chi_N = 92, psi = 30 deg, spacing 2 L on the substrate (wall = 0): each cilium
    beating in the others' co-flow pushes less, so the coupled flows are 3 to 7 % slower than the
    uncoupled ones at every cilium (measured: median speed 0.01346 against 0.01387 L / tau, the
    median relative change 4.3 %, the largest 7.4 %; two Newton steps). The flow in each beat
    plane is mostly along e_psi (U_perp 0.005 ... 0.017, U_par -0.0003 ... 0.0031 L / tau); the
    others' flow normal to the beat planes is reported (measured 0.31 of the largest U). The linear
    drag estimate gives the same direction and size (median relative change 5.5 %)."""
    c = _standing(layout.square(4, 4, 2.0), 92.0, flow, math.radians(30.0), coupling="mean")
    r = c.coupled
    assert r.converged and r.residual <= 1e-3 and r.iterations <= 3
    s, s0 = np.linalg.norm(r.background, axis=1), np.linalg.norm(r.uncoupled, axis=1)
    assert np.all((s < 0.985 * s0) & (s > 0.9 * s0)), s / s0
    ch = r.change()
    # the numbers measured, within 5 % (the coarse table's interpolation, the evaluation's tol)
    assert ch["median_speed_coupled"] == pytest.approx(0.01346, rel=0.05)
    assert ch["median_speed_uncoupled"] == pytest.approx(0.01387, rel=0.05)
    assert 0.025 < ch["relative_change_median"] < 0.065
    assert np.all(r.background[:, 0] > 0) and np.all(np.abs(r.background[:, 1]) < 0.4 * r.background[:, 0])
    assert math.isfinite(r.normal_flow) and 0.1 < r.normal_flow < 0.6
    assert s.max() < 0.05  # far inside the table's flow grid
    est = coupling_estimate(replace(c, coupling="none", background=None))
    # the same M(0): the estimate's at tol 1e-4, the solve's at its loose LOOSE_TOL = 1e-2 (6e-4
    # apart here, above the wall: the bound is relative to the far fields, the flow small)
    assert est["median_speed_uncoupled"] == pytest.approx(ch["median_speed_uncoupled"], rel=2e-3)
    assert est["median_speed_coupled"] < est["median_speed_uncoupled"]
    assert est["relative_change_median"] == pytest.approx(ch["relative_change_median"], rel=0.5)


def test_bad_standing_coupling_input(flow):
    b = layout.square(2, 2, 2.0)
    for bad in (np.zeros((4, 3)), np.zeros(4), np.zeros((3, 2)), np.full((4, 2), np.nan)):
        with pytest.raises(ValueError, match=r"background must be 4 finite flows in each cilium's beat plane"):
            _standing(b, 92.0, flow, 0.3, background=bad)
    with pytest.raises(CouplingError, match="needs a thrust table over the background flow"):
        _standing(b, 92.0, flow.in_still_fluid(), 0.3, coupling="mean")
    # a background in the beat plane is read by the table in that frame (U_perp, U_par)
    U = np.tile([0.3, -0.2], (4, 1))
    c = _standing(b, 92.0, flow, 0.3, background=U)
    assert np.allclose(c.periods, flow.scalar("period", 92.0, U_par=-0.2, U_perp=0.3), rtol=1e-12)
    np.testing.assert_array_equal(c.background, U)
    with pytest.raises(CouplingError, match="flow grid"):  # a coupled flow outside the table's grid
        couple(_standing(b, 92.0, flow, 0.3, viscosity=1e-4))
