"""The treecode of the design model: accuracy against the direct sum, its order in theta, the
exact transpose, the design gradient through it, and bad input."""
import math

import numpy as np
import pytest

from ciliary_carpet.design import model as design_mod
from ciliary_carpet.carpet import layout
from ciliary_carpet.stokes import Direct, RegularisedBlake, Treecode, Wall, make_kernel, stokeslet_velocity
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


@pytest.mark.parametrize("wall", [None, 0.5], ids=["free", "wall"])
def test_design_model_gradient_through_the_treecode(monkeypatch, table, wall):
    """With the treecode forced on, the design model's gradient is still exact for its velocity,
    free and above a wall, with the near field's exact pairs (points on and between cilia)."""
    monkeypatch.setattr(design_mod, "TREE_PAIRS", 0)
    from ciliary_carpet.carpet.carpet import Carpet

    b = layout.square(8, 6, 2.0)
    c = Carpet(b, np.zeros(len(b)), table, layout.random_phases(len(b), 0), wall=wall)
    X = np.concatenate([b[:-1] + 1.0, b[:5] + [0.0, 0.4]])
    rng = np.random.default_rng(2)
    chi = rng.uniform(-120, 120, len(b))
    dm = design_mod.DesignModel(c, X, chi, near=design_mod.NearField(c, X))
    assert dm.tree is not None and dm.near is not None
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
    # the forces and weights of each sum (the points were checked once, at construction)
    tc = Treecode(x, y, k, 1.0, Direct())
    with pytest.raises(ValueError, match=r"forces must have shape \(90, 3\)"):
        tc.apply(f[:, :2])
    with pytest.raises(ValueError, match="forces contains NaN"):
        tc.apply(np.where(np.arange(len(f))[:, None] == 3, np.nan, f))
    with pytest.raises(ValueError, match=r"weights must have shape \(30, 3\)"):
        tc.adjoint(w[:5])
    with pytest.raises(ValueError, match="contains NaN or inf"):
        Treecode(np.where(np.arange(len(x))[:, None] == 1, np.inf, x), y, k, 1.0)

    class Lopsided(RegularisedBlake):
        symmetric = False

    with pytest.raises(ValueError, match="symmetric"):
        Treecode(x, y, Lopsided(wall=Wall(z=-0.5), eps=0.02), 1.0)


def _term_scale(x, y, eps, zw):
    """The size of the largest terms of the regularised image system for the pair (x, y) above
    the wall z = zw (source height h, image distance R_eps): 1/r_eps + 1/R_eps + h^2/R_eps^3 +
    h/R_eps^2, the scale against which the float64 rounding of the tensor is measured."""
    h = y[2] - zw
    r = math.sqrt(float(np.sum((x - y) ** 2)) + eps ** 2)
    ys = y.copy()
    ys[2] = 2 * zw - y[2]
    R = math.sqrt(float(np.sum((x - ys) ** 2)) + eps ** 2)
    return 1 / r + 1 / R + h ** 2 / R ** 3 + h / R ** 2


@pytest.mark.parametrize("planar", [True, False])
def test_regularised_wall_kernel_is_reciprocal(planar):
    """G_ij(x, y) = G_ji(y, x) for the regularised Blake tensor (Smith's corrected image system):
    random pairs above the wall, in one plane (the design's case) and anywhere in 3-d, at
    distances from 1e-3 to 10 L, through the compiled kernel and the numpy reference. The
    tolerance is rounding: 64 ulps of the largest terms' size (_term_scale; measured: asymmetry
    at most 2.7, compiled against numpy 6.3), while a non-reciprocal image system (the O(eps^2)
    the docstring used to claim) would differ by about eps^2 / r^3 relative, 1e-4 here at r = 2."""
    from ciliary_carpet.stokes.kernel import regularised_blake_tensor

    from ciliary_carpet.stokes import stokeslet_velocity_ranges

    rng = np.random.default_rng(7)
    eps, zw, n = 0.02, -0.5, 200
    k = RegularisedBlake(eps=eps, wall=Wall(z=zw))
    x = np.column_stack([rng.uniform(-5, 5, (n, 2)), np.zeros(n) if planar else rng.uniform(zw + 1e-3, 2.0, n)])
    v = rng.standard_normal((n, 3))
    if planar:
        v[:, 2] = 0.0
    y = x + (10.0 ** rng.uniform(-3, 1, n))[:, None] * v / np.linalg.norm(v, axis=1)[:, None]
    y[:, 2] = np.maximum(y[:, 2], zw + 1e-3)

    def pairwise(a, b):
        """(n, 3, 3): G(a_i, b_i) (8 pi mu = 1) through the compiled kernel, one column per unit force."""
        ptr = np.arange(n + 1, dtype=np.int64)
        rng_ = np.column_stack([np.arange(n), np.arange(1, n + 1)]).astype(np.int64)
        return np.stack([stokeslet_velocity_ranges(a, b, np.tile(e, (n, 1)), ptr, rng_, kernel=k, backend=Direct())
                         for e in np.eye(3)], axis=-1) * 8 * math.pi

    G_xy, G_yx = pairwise(x, y), pairwise(y, x)
    sh = np.array([0.0, 0.0, zw])
    idx = np.arange(n)
    ref_xy = regularised_blake_tensor(x - sh, y - sh, eps)[idx, idx]
    ref_yx = regularised_blake_tensor(y - sh, x - sh, eps)[idx, idx]
    scale = np.array([max(_term_scale(a, b, eps, zw), _term_scale(b, a, eps, zw)) for a, b in zip(x, y)])
    tol = 64 * np.finfo(float).eps * scale[:, None, None]
    assert np.all(np.abs(G_xy - G_yx.transpose(0, 2, 1)) <= tol)
    assert np.all(np.abs(ref_xy - ref_yx.transpose(0, 2, 1)) <= tol)
    assert np.all(np.abs(G_xy - ref_xy) <= tol)  # the compiled kernel is the reference's tensor
    assert np.abs(G_xy - G_yx.transpose(0, 2, 1)).max() > 0  # the comparison is live (rounding differs)
    assert k.symmetric


def test_treecode_with_the_regularised_wall_kernel():
    """The treecode takes the regularised wall kernel: its adjoint is the exact transpose of its
    operator and both approximate the direct sums."""
    x, y, f, w = _scene(18, 15, seed=3)
    k = RegularisedBlake(eps=0.02, wall=Wall(z=-0.5))
    tc = Treecode(x, y, k, 1.0, Direct())
    lhs = float(np.sum(tc.apply(f) * w))
    rhs = float(np.sum(f * tc.adjoint(w)))
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)
    ud = stokeslet_velocity(x, y, f, kernel=k, backend=Direct())
    assert np.linalg.norm(tc.apply(f) - ud, axis=1).max() / np.linalg.norm(ud, axis=1).max() < 1e-3
    gd = stokeslet_velocity(y, x, w, kernel=k, backend=Direct())
    assert np.linalg.norm(tc.adjoint(w) - gd) / np.linalg.norm(gd) < 1e-2
