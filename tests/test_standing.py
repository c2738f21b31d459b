"""Standing carpets: cilia clamped on the substrate z = 0, the field along +z, each beat plane
turned by its azimuth psi (MODEL.md section 6, ciliary_carpet.carpet.geometry)."""
import math

import numpy as np
import pytest

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean, Instant
from ciliary_carpet.stokes import make_kernel, stokeslet_velocity, Wall
from single_cilium.table import ThrustTable


@pytest.fixture(scope="module")
def table():
    return ThrustTable.default()


@pytest.fixture(scope="module")
def random_carpet(table):
    rng = np.random.default_rng(0)
    n = 16
    return Carpet(layout.square(4, 4, 2.0), rng.uniform(-150, 150, n), table, rng.random(n), wall=0.0,
                  geometry="standing", azimuth=rng.uniform(0, 2 * math.pi, n))


def _points(rng, m=300, top=3.0):
    return np.concatenate([rng.uniform(-5, 5, (m, 2)), rng.uniform(0, top, (m, 1))], axis=1)


def test_the_cilia_stand_on_the_substrate(random_carpet):
    """Every clamp lies on z = 0 and every filament point above it; the force centres lie in the
    beat planes, at heights between 0 and L."""
    c = random_carpet
    pos, frc, _ = c.state_in_space(0.3)
    np.testing.assert_allclose(pos[:, 0, :2], c.bases, atol=1e-12)
    assert np.all(pos[:, 0, 2] == 0.0) and pos[..., 2].min() >= 0.0
    cen = c.in_space("centres")
    assert np.all((cen[:, 2] > 0.1) & (cen[:, 2] < 1.0))
    e_psi = np.column_stack([np.cos(c.azimuth), np.sin(c.azimuth)])
    off = cen[:, :2] - c.bases
    np.testing.assert_allclose(off[:, 0] * e_psi[:, 1] - off[:, 1] * e_psi[:, 0], 0.0, atol=1e-12)


@pytest.mark.parametrize("when", [CycleMean(), Instant(0.37)], ids=["mean", "instant"])
def test_no_slip_on_the_substrate(random_carpet, when):
    """The velocity vanishes on the wall (to rounding), resolved and at the levels of detail."""
    rng = np.random.default_rng(1)
    p = _points(rng)
    p[:, 2] = 0.0
    for tol in (0.0, 1e-3):
        u = random_carpet.evaluate(p, when, tol).velocity
        assert np.abs(u).max() < 1e-14


@pytest.mark.parametrize("when", [CycleMean(), Instant(0.37)], ids=["mean", "instant"])
def test_levels_of_detail_hold_their_bound_and_calibration(table, when):
    """Against the resolved sum on 10 x 10 random standing cilia, the levels of detail err by at
    most their rigorous bound (which takes the wall's Taylor constants for any direction: the beat
    planes are vertical), and, with the calibration LOD_SLACK_STANDING, by at most 0.2 tol times
    the far-field scale sum_j S_j / (8 pi mu |x - c_j|) (measured 0.037 mean, 0.17 instant)."""
    from ciliary_carpet.carpet.carriers import LOD_SLACK_STANDING

    rng = np.random.default_rng(2)
    n = 100
    c = Carpet(layout.square(10, 10, 2.0), rng.uniform(0, 150, n), table, rng.random(n), wall=0.0,
               geometry="standing", azimuth=rng.uniform(0, 2 * math.pi, n))
    assert c.carriers.of_mean.slack == LOD_SLACK_STANDING
    p = np.column_stack([rng.uniform(-5, 23, (300, 2)), rng.uniform(0.0, 4.0, 300)])
    ref = c.evaluate(p, when, 0.0).velocity
    S = (np.linalg.norm(c.cycles.F_mean, axis=1) if isinstance(when, CycleMean) else c.cycles.F_rms) * c.flutter
    scale = (S[None] / np.linalg.norm(p[:, None] - c.in_space("centres")[None], axis=-1)).sum(1) / (8 * math.pi * c.mu)
    for tol in (1e-2, 1e-3, 1e-4):
        s = c.evaluate(p, when, tol)
        err = np.linalg.norm(s.velocity - ref, axis=1)
        assert np.all(err <= s.error_bound * (1 + 1e-9) + 1e-14)
        assert np.all(err <= 0.2 * tol * scale)
        cheap = sum(v for k, v in s.pairs.items() if k != "resolved")
        assert cheap > 0.5 * sum(s.pairs.values())  # the test exercises the carriers


def test_taylor_constants_cover_any_direction():
    """The wall's Taylor constants for any direction (C*_WALL_ANY) bound the sampled source
    derivatives of the (regularised) Blake tensor for sources and forces of every direction near
    and far from the wall; the in-plane constants do not (so a standing carpet needs these)."""
    from ciliary_carpet.stokes.kernel import C1_WALL, C1_WALL_ANY, C3_WALL_ANY

    rng = np.random.default_rng(3)
    best = {1: 0.0, 3: 0.0}
    for i in range(1200):
        hgt = 10 ** rng.uniform(-2.5, 1)
        x = rng.normal(size=3)
        x[2] = rng.uniform(-hgt, 3)
        R = np.linalg.norm(x)
        h, f = rng.normal(size=3), rng.normal(size=3)
        h, f = h / np.linalg.norm(h), f / np.linalg.norm(f)
        k = make_kernel(Wall(-hgt), 0.0 if i % 2 else 0.02 * R)
        for order in best:
            e = (1e-4 if order == 1 else 2e-3) * R
            steps, weights, div = ((-1, 1), (-1, 1), 2 * e) if order == 1 else \
                ((-2, -1, 1, 2), (-1, 2, -2, 1), 2 * e ** 3)
            if min(sg * e * h[2] for sg in steps) <= -hgt:
                continue
            u = [stokeslet_velocity(x[None], (sg * e * h)[None], f[None], mu=1 / (8 * math.pi), kernel=k)[0]
                 for sg in steps]
            best[order] = max(best[order], np.linalg.norm(sum(w * v for w, v in zip(weights, u)) / div) * R ** (order + 1))
    assert C1_WALL < best[1] <= C1_WALL_ANY
    assert 60.0 < best[3] <= C3_WALL_ANY


def test_mirror_and_rotation(table, random_carpet):
    """(chi_N, psi) and (-chi_N, psi + pi) are the same cilium; turning every azimuth and base by
    a turns the flow by a about e_z (both to rounding)."""
    c = random_carpet
    rng = np.random.default_rng(4)
    p = _points(rng, 200)
    mirror = Carpet(c.bases, -c.chi_N, table, c.phases, wall=0.0, geometry="standing", azimuth=c.azimuth + math.pi)
    a = 0.7
    R = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    turned = Carpet(c.bases @ R[:2, :2].T, c.chi_N, table, c.phases, wall=0.0, geometry="standing",
                    azimuth=c.azimuth + a)
    for when in (CycleMean(), Instant(0.37)):
        u = c.evaluate(p, when, 0.0).velocity
        scale = np.abs(u).max()
        assert np.abs(mirror.evaluate(p, when, 0.0).velocity - u).max() < 1e-13 * scale
        assert np.abs(turned.evaluate(p @ R.T, when, 0.0).velocity - u @ R.T).max() < 1e-13 * scale


def test_standing_in_free_space_is_the_planar_carpet_turned(table):
    """Without a wall, a row of standing cilia with psi = 0 is the planar row (field along +y)
    turned by 90 degrees about the x axis (y -> z): the flows agree to rounding, resolved and at
    the levels of detail (the same carriers, turned)."""
    rng = np.random.default_rng(5)
    bases = np.column_stack([np.arange(5) * 2.0, np.zeros(5)])
    chi, ph = rng.uniform(-150, 150, 5), rng.random(5)
    planar = Carpet(bases, chi, table, ph)
    standing = Carpet(bases, chi, table, ph, geometry="standing")
    Q = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # the planar frame -> the standing one
    p = rng.normal(size=(200, 3)) * 3
    for when in (CycleMean(), Instant(0.37)):
        for tol in (0.0, 1e-3):
            up = planar.evaluate(p, when, tol).velocity
            us = standing.evaluate(p @ Q.T, when, tol).velocity
            assert np.abs(up @ Q.T - us).max() < 1e-13 * np.abs(up).max()


def test_uniform_carpet_drives_the_force_layer_plug(table):
    """Far above the middle of a large uniform standing carpet the mean flow is the plug of a
    force layer: U = n sum(z f_t) / mu = n (F_t c_z + D_zt) / mu (n cilia per area, F_t the mean
    tangential force, c_z its centre's height, D_zt the first moment about it; MODEL.md section 6),
    along e_psi. A finite carpet of width W falls short by O(z / W) (the missing far fields of the
    cilia beyond its edge, each decaying as 1/r^3): measured 5.6 % at z = 2, W = 90 L. Extrapolated
    in 1/W from W = 60 and 90 L, the flow at z = 2 and 3 L matches U to 1 %."""
    psi, sp = 0.3, 1.5
    e = np.array([math.cos(psi), math.sin(psi), 0.0])
    speeds = {}
    for n in (40, 60):
        b = layout.square(n, n, sp)
        b = b - b.mean(axis=0)
        c = Carpet(b, 92.0, table, wall=0.0, geometry="standing", azimuth=psi)
        F, D, cz = c.cycles.F_mean[0], c.cycles.D_mean[0], c.cycles.centre[0, 1]
        U = (F[0] * cz + D[1, 0]) / sp ** 2 / c.mu
        z = np.array([2.0, 3.0])
        s = c.evaluate(np.column_stack([0 * z, 0 * z, z]), CycleMean(), 1e-5)
        assert np.all(s.error_bound < 0.01 * U)
        speeds[n * sp] = s.velocity @ e / U
    (w1, r1), (w2, r2) = speeds.items()
    assert np.all((r1 < r2) & (r2 < 1.0))  # the edge deficit shrinks as the carpet grows
    extrapolated = r2 + (r2 - r1) * (1 / w2) / (1 / w1 - 1 / w2)
    np.testing.assert_allclose(extrapolated, 1.0, atol=0.01)


def test_bad_standing_input(table):
    b = layout.square(2, 2, 2.0)
    with pytest.raises(ValueError, match="azimuth is for standing"):
        Carpet(b, 50.0, table, azimuth=0.3)
    with pytest.raises(ValueError, match="field is along \\+z"):
        Carpet(b, 50.0, table, geometry="standing", direction=0.2)
    with pytest.raises(ValueError, match="azimuth must be 4 finite"):
        Carpet(b, 50.0, table, geometry="standing", azimuth=[0.0, np.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match="geometry must be one of"):
        Carpet(b, 50.0, table, geometry="upright")
    with pytest.raises(ValueError, match="needs a thrust table over the background flow"):  # (a still-fluid table)
        Carpet(b, 50.0, table, geometry="standing", coupling="mean")
    with pytest.raises(ValueError, match="distance >= 0"):
        Carpet(b, 50.0, table, geometry="standing", wall=-1.0)
    c = Carpet(b, 50.0, table, geometry="standing", wall=0.0)
    with pytest.raises(ValueError, match="three-dimensional"):
        c.evaluate(np.zeros((3, 2)), CycleMean())
    with pytest.raises(ValueError, match="below the wall"):
        c.evaluate(np.array([[0.0, 0.0, -0.1]]), CycleMean())
