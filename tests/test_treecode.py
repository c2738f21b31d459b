"""The treecode of the design model: accuracy against the direct sum, its order in theta, the
exact transpose, the design gradient through it, and bad input."""
import math

import numpy as np
import pytest

from ciliary_carpet import design as design_mod
from ciliary_carpet import layout
from ciliary_carpet.kernel import RegularisedBlake, Wall, make_kernel
from ciliary_carpet.stokeslet import Direct, stokeslet_velocity
from ciliary_carpet.treecode import Treecode
from single_cilium.table import ThrustTable

_E = np.array([[1.0, 0.0], [-0.5, math.sqrt(3) / 2], [-0.5, -math.sqrt(3) / 2]])


def _scene(nx=24, ny=20, seed=0):
    """Three carriers per cilium around jittered lattice points (the design model's sources) and
    control points at the cell centres, forces mostly along -y (a carpet pushing one way)."""
    rng = np.random.default_rng(seed)
    b = layout.square(nx, ny, 2.0)
    cen = b + rng.uniform(-0.3, 0.3, b.shape)
    y = np.c_[(cen[:, None, :] + 0.35 * _E[None]).reshape(-1, 2), np.zeros(3 * len(b))]
    x = np.c_[b + 1.0, np.zeros(len(b))]
    f = np.c_[rng.standard_normal((len(y), 2)) * 0.3 + [0.0, -1.0], np.zeros(len(y))]
    w = np.c_[rng.standard_normal((len(x), 2)), np.zeros(len(x))]
    return x, y, f, w


@pytest.mark.parametrize("wall", [None, Wall(z=-0.5)])
def test_treecode_matches_direct_and_converges_in_theta(wall):
    x, y, f, w = _scene()
    k = make_kernel(wall)
    ud = stokeslet_velocity(x, y, f, kernel=k, backend=Direct())
    err = {}
    for theta in (0.4, 0.3, 0.2):
        tc = Treecode(x, y, k, 1.0, Direct(), theta=theta)
        u = tc.apply(f)
        err[theta] = np.linalg.norm(u - ud, axis=1).max() / np.linalg.norm(ud, axis=1).max()
        assert tc.work["pairs"] < tc.work["direct_pairs"]
    # the default (0.3): below 1e-3 relative (measured 2e-4 free, 5e-4 with the wall)
    assert err[0.3] < 1e-3
    # third order in the cell size over distance: halving theta gains about 8x (measured 9-13x)
    assert err[0.4] / err[0.2] > 5.0
    assert err[0.2] < err[0.3] < err[0.4]


@pytest.mark.parametrize("wall", [None, Wall(z=-0.5)])
def test_treecode_adjoint_is_the_exact_transpose(wall):
    x, y, f, w = _scene(18, 15, seed=1)
    tc = Treecode(x, y, make_kernel(wall), 1.3, Direct())
    lhs = float(np.sum(tc.apply(f) * w))
    rhs = float(np.sum(f * tc.adjoint(w)))
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)
    # and it approximates the direct adjoint sum
    gd = stokeslet_velocity(y, x, w, 1.3, kernel=make_kernel(wall), backend=Direct())
    g = tc.adjoint(w)
    assert np.linalg.norm(g - gd) / np.linalg.norm(gd) < 1e-2


@pytest.fixture(scope="module")
def table():
    return ThrustTable.default()


def test_design_model_gradient_through_the_treecode(monkeypatch, table):
    """With the treecode forced on, the design model's gradient is still exact for its velocity."""
    monkeypatch.setattr(design_mod, "TREE_PAIRS", 0)
    from ciliary_carpet.carpet import Carpet

    b = layout.square(8, 6, 2.0)
    c = Carpet(b, np.zeros(len(b)), table, layout.random_phases(len(b), 0))
    X = b[:-1] + 1.0
    rng = np.random.default_rng(2)
    chi = rng.uniform(-120, 120, len(b))
    dm = design_mod.DesignModel(c, X, chi)
    assert dm.tree is not None
    g_u = rng.standard_normal((len(X), 2))
    g = dm.gradient(chi, g_u)
    h = 1e-4
    for j in (0, 17, 40):
        e = np.zeros(len(b))
        e[j] = h
        fd = (np.sum(dm.velocity(chi + e) * g_u) - np.sum(dm.velocity(chi - e) * g_u)) / (2 * h)
        assert abs(fd - g[j]) <= 1e-6 * max(1.0, abs(fd))


def test_treecode_bad_input():
    x, y, f, w = _scene(6, 5)
    k = make_kernel(None)
    for theta in (0.0, 1.0, -0.2, float("nan")):
        with pytest.raises(ValueError, match="theta"):
            Treecode(x, y, k, 1.0, theta=theta)
    with pytest.raises(ValueError, match="leaf"):
        Treecode(x, y, k, 1.0, leaf=0)
    with pytest.raises(ValueError, match="symmetric"):
        Treecode(x, y, RegularisedBlake(wall=Wall(z=-0.5), eps=0.02), 1.0)
