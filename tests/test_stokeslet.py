"""The flow sums (ciliary_carpet.stokes): numba direct sums against the numpy reference,
identities of the Stokeslet and of the Blake tensor, the FMM backend, the sparse ranges kernel."""
import math

import numpy as np
import pytest

from ciliary_carpet.stokes import fmm as sk
from ciliary_carpet.stokes import (
    C2_FREE,
    FMM,
    Auto,
    Backend,
    Blake,
    Direct,
    RegularisedBlake,
    RegularisedStokeslet,
    Stokeslet,
    Wall,
    make_kernel,
    stokeslet_velocity,
    stokeslet_velocity_numpy,
    stokeslet_velocity_ranges,
)

WALLS = [None, Wall(0.0), Wall(-0.7)]


def rel_err(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def random_case(m, n, seed=0, zmin=0.05):
    rng = np.random.default_rng(seed)
    T = rng.uniform(-1, 1, (m, 3))
    S = rng.uniform(-1, 1, (n, 3))
    T[:, 2] = rng.uniform(0.0, 1.5, m)
    S[:, 2] = rng.uniform(zmin, 1.5, n)
    F = rng.standard_normal((n, 3))
    return T, S, F


def single(x, y, f, mu=1.0, wall=None):
    """Velocity at the points x (K, 3) of one force f at y."""
    return stokeslet_velocity(np.atleast_2d(x), np.atleast_2d(y), np.atleast_2d(f), mu, wall=wall,
                              backend=Direct())


def tensor(x, y, wall=None):
    """8 pi G(x, y) as a 3x3 matrix (column j = velocity of e_j)."""
    return np.column_stack([single(x, y, e, wall=wall)[0] for e in np.eye(3)]) * 8 * math.pi


# ------------------------------------------------------------------ direct vs reference
@pytest.mark.parametrize("wall", WALLS)
def test_direct_matches_numpy_reference(wall):
    T, S, F = random_case(170, 230, seed=1)
    if wall is not None:
        T[:, 2] += wall.z
        S[:, 2] += wall.z
    u = stokeslet_velocity(T, S, F, 0.7, wall=wall, backend=Direct())
    ref = stokeslet_velocity_numpy(T, S, F, 0.7, wall=wall)
    assert u.shape == (170, 3) and u.dtype == np.float64
    assert rel_err(u, ref) < 1e-12


def test_reference_chunking_does_not_change_result():
    T, S, F = random_case(50, 40, seed=2)
    for wall in (None, Wall(0.0)):
        a = stokeslet_velocity_numpy(T, S, F, wall=wall)
        b = stokeslet_velocity_numpy(T, S, F, wall=wall, chunk_pairs=7)
        assert rel_err(a, b) < 1e-15


def test_default_backend_is_auto_and_matches_direct():
    T, S, F = random_case(30, 20, seed=3)
    assert np.array_equal(stokeslet_velocity(T, S, F), stokeslet_velocity(T, S, F, backend=Direct()))


def test_two_dimensional_inputs_are_padded():
    rng = np.random.default_rng(4)
    T2, S2, F2 = rng.random((20, 2)), rng.random((15, 2)) + 2.0, rng.standard_normal((15, 2))
    pad = lambda a: np.column_stack([a, np.zeros(len(a))])  # noqa: E731
    u = stokeslet_velocity(T2, S2, F2, backend=Direct())
    assert u.shape == (20, 3)
    assert np.array_equal(u, stokeslet_velocity(pad(T2), pad(S2), pad(F2), backend=Direct()))
    # planar forces in the plane z = 0 give planar flow in free space
    assert np.all(u[:, 2] == 0.0)
    # mixed widths
    assert np.array_equal(stokeslet_velocity(T2, pad(S2), F2, backend=Direct()), u)


@pytest.mark.parametrize("m,n", [(0, 5), (4, 0), (0, 0)])
@pytest.mark.parametrize("backend", [Direct(), FMM(), Auto(), None])
def test_empty_inputs_give_zeros(m, n, backend):
    T, S, F = np.ones((m, 3)), np.ones((n, 3)), np.ones((n, 3))
    u = stokeslet_velocity(T, S, F, backend=backend)
    assert u.shape == (m, 3) and not np.any(u)
    assert stokeslet_velocity_numpy(T, S, F).shape == (m, 3)
    u = stokeslet_velocity_ranges(T, S, F, np.zeros(m + 1, dtype=np.int64), np.zeros((0, 2), dtype=np.int64))
    assert u.shape == (m, 3) and not np.any(u)


# ------------------------------------------------------------------ validation
GOOD = dict(targets=np.zeros((3, 3)), sources=np.ones((2, 3)), forces=np.ones((2, 3)))


@pytest.mark.parametrize(
    "change,name",
    [
        (dict(targets=np.zeros(3)), "targets"),
        (dict(targets=np.zeros((3, 4))), "targets"),
        (dict(targets=np.zeros((3, 1))), "targets"),
        (dict(sources=np.zeros((2, 3, 1))), "sources"),
        (dict(sources=np.ones((2, 5))), "sources"),
        (dict(forces=np.ones((3, 3))), "forces"),
        (dict(forces=np.ones(6)), "forces"),
        (dict(targets=[[0.0, np.nan, 0.0]]), "targets"),
        (dict(sources=[[1.0, 1.0, np.inf], [1.0, 2.0, 3.0]]), "sources"),
        (dict(forces=[[1.0, -np.inf, 0.0], [0.0, 0.0, 0.0]]), "forces"),
        (dict(targets=[["a", "b", "c"]]), "targets"),
        (dict(mu=0.0), "mu"),
        (dict(mu=-1.0), "mu"),
        (dict(mu=np.nan), "mu"),
        (dict(mu=np.inf), "mu"),
        (dict(mu="x"), "mu"),
    ],
)
def test_validation_names_the_argument(change, name):
    kw = {**GOOD, **change}
    for fn in (stokeslet_velocity, stokeslet_velocity_numpy):
        with pytest.raises(ValueError, match=name):
            fn(**kw)
    m = np.asarray(kw["targets"]).shape[0] if np.asarray(kw["targets"]).ndim else 0
    with pytest.raises(ValueError, match=name):
        stokeslet_velocity_ranges(**kw, ptr=np.zeros(m + 1, dtype=np.int64), ranges=np.zeros((0, 2), dtype=np.int64))


def test_wall_validation():
    T = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    S = np.array([[0.0, 0.0, 0.5]])
    F = np.ones((1, 3))
    stokeslet_velocity(T, S, F, wall=Wall(0.0))  # target on the wall: allowed
    with pytest.raises(ValueError, match="targets"):
        stokeslet_velocity(T, S, F, wall=Wall(0.1))
    on = stokeslet_velocity(T[:1], S, F, wall=Wall(0.5))  # a source on the wall: allowed, and it makes no flow
    assert np.all(on == 0.0)
    on = stokeslet_velocity(T[:1], S, F, wall=Wall(0.5), kernel=make_kernel(Wall(0.5), 0.02))
    assert np.abs(on).max() < 1e-15
    with pytest.raises(ValueError, match="sources"):
        stokeslet_velocity(T[:1], S, F, wall=Wall(0.55))  # a source below the wall: not allowed
    with pytest.raises(ValueError, match="sources"):
        stokeslet_velocity_numpy(T, S, F, wall=Wall(0.6))
    with pytest.raises(ValueError, match="Wall.z"):
        Wall(np.nan)
    with pytest.raises(ValueError, match="Wall.z"):
        Wall("low")
    assert Wall(1).z == 1.0 and isinstance(Wall(1).z, float)
    with pytest.raises(TypeError, match="wall"):
        stokeslet_velocity(T, S, F, wall=0.0)
    with pytest.raises(TypeError, match="backend"):
        stokeslet_velocity(T, S, F, backend="direct")


def test_backend_parameter_validation():
    for bad in (0.0, -1e-6, 1.0, np.nan):
        with pytest.raises(ValueError, match="eps"):
            FMM(bad)
    with pytest.raises(ValueError, match="threshold"):
        Auto(threshold=0.0)
    with pytest.raises(TypeError, match="dense"):
        Backend().dense(Stokeslet(), *GOOD.values(), 1.0)


# ------------------------------------------------------------------ coincident points
@pytest.mark.parametrize("wall", [None, Wall(0.0)])
def test_coincident_point_is_skipped(wall):
    T, S, F = random_case(6, 9, seed=5)
    S[4] = [0.25, -0.5, 0.75]  # dyadic, so that S[4] +- d below is exact
    T[2] = S[4]
    u = stokeslet_velocity(T, S, F, wall=wall, backend=Direct())
    assert np.all(np.isfinite(u))
    keep = np.arange(9) != 4
    others = stokeslet_velocity(T[2:3], S[keep], F[keep], wall=wall, backend=Direct())
    assert np.allclose(stokeslet_velocity_numpy(T, S, F, wall=wall), u, rtol=0, atol=1e-14)
    if wall is None:
        assert rel_err(u[2:3], others) < 1e-14
    else:
        # only the singular Stokeslet is skipped: the regular image part of source 4 is kept,
        # i.e. u = lim_{d -> 0} [u(x + d) - G^S(d) f_4 / (8 pi)]
        # (symmetric average over +-d: the singular part is even in d, the error O(d^2))
        d = np.array([1.0, -2.0, 1.5]) * 2.0 ** -20
        near = stokeslet_velocity(T[2:3] + [d, -d], S, F, wall=wall, backend=Direct()).mean(axis=0)
        near -= stokeslet_velocity(d[None], np.zeros((1, 3)), F[4:5], backend=Direct())[0]
        assert rel_err(u[2], near) < 1e-9
        assert rel_err(u[2:3], others) > 1e-3


# ------------------------------------------------------------------ Stokeslet identities
def test_tensor_symmetric_and_exact_values():
    rng = np.random.default_rng(6)
    for _ in range(5):
        x, y = rng.standard_normal(3), rng.standard_normal(3)
        G = tensor(x, y)
        R = x - y
        r = np.linalg.norm(R)
        assert np.allclose(G, G.T, rtol=0, atol=1e-15 * np.abs(G).max())
        assert np.allclose(G, np.eye(3) / r + np.outer(R, R) / r ** 3, rtol=1e-14, atol=0)
    # force parallel / perpendicular to R
    R = np.array([0.3, -1.2, 0.4])
    r = np.linalg.norm(R)
    mu = 2.5
    par = 1.7 * R / r
    perp = np.cross(R, [1.0, 0.0, 0.0])
    u = single(R, np.zeros(3), par, mu)[0]
    assert np.allclose(u, 2 * par / (8 * math.pi * mu * r), rtol=1e-14, atol=0)
    u = single(R, np.zeros(3), perp, mu)[0]
    assert np.allclose(u, perp / (8 * math.pi * mu * r), rtol=1e-14, atol=1e-17)


@pytest.mark.parametrize("wall", [None, Wall(0.0)])
def test_pointwise_accuracy_over_many_scales(wall):
    # The fast-math flags must not approximate 1/sqrt: free space, each target's velocity (not
    # only the largest) to a few ulps (2e-15), for distances from 1e-8 to 1e8. With a wall, the velocity
    # close to the wall (height << h) or far away (r >> h) is a small difference of O(|f|/r)
    # terms in any implementation of the image system: there the error is ~1e-16 of the
    # free-space scale |f| / (8 pi mu r), not of |u|.
    rng = np.random.default_rng(20)
    dirs = rng.standard_normal((33, 3))
    dirs[:, 2] = np.abs(dirs[:, 2])
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    S = np.array([[0.0, 0.0, 0.5]])
    T = S + dirs * np.geomspace(1e-8, 1e8, 33)[:, None]
    F = np.array([[0.3, -1.0, 0.7]])
    u = stokeslet_velocity(T, S, F, wall=wall, backend=Direct())
    ref = stokeslet_velocity_numpy(T, S, F, wall=wall)
    R = T - S
    r = np.linalg.norm(R, axis=1)[:, None]
    if wall is None:
        exact = (F / r + R * (R @ F[0])[:, None] / r ** 3) / (8 * math.pi)
        assert np.all(np.abs(u - exact) <= 2e-15 * np.abs(exact).max(axis=1, keepdims=True))
        assert np.all(np.abs(u - ref) <= 2e-15 * np.abs(ref).max(axis=1, keepdims=True))
    else:
        scale = np.linalg.norm(F) / (8 * math.pi * r)
        assert np.all(np.abs(u - ref) <= 1e-14 * scale)


@pytest.mark.parametrize("wall", [None, Wall(-0.3)])
def test_linear_in_force_and_inverse_in_mu(wall):
    T, S, F1 = random_case(40, 30, seed=7)
    F2 = np.random.default_rng(8).standard_normal(F1.shape)
    u = lambda F, mu=1.0: stokeslet_velocity(T, S, F, mu, wall=wall, backend=Direct())  # noqa: E731
    assert rel_err(u(2.0 * F1 - 3.0 * F2), 2.0 * u(F1) - 3.0 * u(F2)) < 1e-13
    assert rel_err(u(F1, 4.0), u(F1) / 4.0) < 1e-15


def test_translation_invariance():
    T, S, F = random_case(40, 30, seed=9)
    shift = np.array([3.7, -1.1, 0.6])
    u = stokeslet_velocity(T, S, F, backend=Direct())
    assert rel_err(stokeslet_velocity(T + shift, S + shift, F, backend=Direct()), u) < 1e-12
    # with a wall: any shift that moves the wall along
    uw = stokeslet_velocity(T, S, F, wall=Wall(0.0), backend=Direct())
    uw2 = stokeslet_velocity(T + shift, S + shift, F, wall=Wall(shift[2]), backend=Direct())
    assert rel_err(uw2, uw) < 1e-12


def divergence(x, S, F, wall, h=1e-3):
    """Fourth-order central differences of div u at x."""
    div = 0.0
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        pts = np.array([x - 2 * e, x - e, x + e, x + 2 * e])
        u = stokeslet_velocity(pts, S, F, wall=wall, backend=Direct())[:, k]
        div += (u[0] - 8 * u[1] + 8 * u[2] - u[3]) / (12 * h)
    return div


@pytest.mark.parametrize("wall", [None, Wall(0.0)])
def test_divergence_free(wall):
    rng = np.random.default_rng(10)
    S = rng.uniform(-1, 1, (4, 3))
    S[:, 2] = rng.uniform(0.2, 1.0, 4)
    F = rng.standard_normal((4, 3))
    for x in ([1.5, 0.2, 0.5], [-0.3, 1.8, 1.2], [0.1, -0.2, 2.0], [2.0, 2.0, 0.3]):
        x = np.array(x)
        u = stokeslet_velocity(x[None], S, F, wall=wall, backend=Direct())
        # scale: |u| / (distance to the nearest source)
        scale = np.abs(u).max() / np.min(np.linalg.norm(S - x, axis=1))
        assert abs(divergence(x, S, F, wall)) < 1e-7 * scale


# ------------------------------------------------------------------ Blake tensor
def test_wall_velocity_vanishes_on_the_wall():
    T, S, F = random_case(300, 200, seed=11, zmin=1e-3)
    for z in (0.0, -2.0, 1.0):
        Tw = T.copy()
        Tw[:, 2] = z
        Sw = S + [0.0, 0.0, z]
        free = stokeslet_velocity(Tw, Sw, F, backend=Direct())
        u = stokeslet_velocity(Tw, Sw, F, wall=Wall(z), backend=Direct())
        assert np.max(np.abs(u)) < 1e-13 * np.max(np.abs(free))
        ref = stokeslet_velocity_numpy(Tw, Sw, F, wall=Wall(z))
        assert np.max(np.abs(ref)) < 1e-13 * np.max(np.abs(free))


def test_wall_tends_to_free_space_far_from_the_wall():
    rng = np.random.default_rng(12)
    S = rng.uniform(-0.5, 0.5, (5, 3))
    F = rng.standard_normal((5, 3))
    T = rng.uniform(-1, 1, (20, 3))
    free = stokeslet_velocity(T, S, F, backend=Direct())
    H = np.array([10.0, 100.0, 1000.0, 10000.0])
    rel = np.array([rel_err(stokeslet_velocity(T, S, F, wall=Wall(-h), backend=Direct()), free) for h in H])
    assert np.all(np.diff(rel) < 0)
    slope = np.polyfit(np.log(H), np.log(rel), 1)[0]
    assert slope == pytest.approx(-1.0, abs=0.05)  # relative image correction ~ (distance) / H


@pytest.mark.parametrize("force,ray,fixed", [([1.0, 0.3, 0.0], -2.0, -3.0), ([0.0, 0.0, 1.0], -3.0, -4.0)])
def test_wall_far_field_decay(force, ray, fixed):
    # Far from the source the image system leaves a stresslet (force parallel to the wall, |u| ~ 1/r^2)
    # or a source dipole (normal force, ~ 1/r^3), along rays leaving the wall at a fixed angle. At a fixed
    # height above the wall, the no-slip condition costs one more power: 1/r^3 and 1/r^4.
    src = np.array([[0.0, 0.0, 1.0]])
    r = np.geomspace(1e2, 1e4, 9)
    for z, exponent in ((1.3 + 0.5 * r, ray), (np.full_like(r, 1.3), fixed)):
        T = np.column_stack([r * math.cos(0.4), r * math.sin(0.4), z])
        u = np.linalg.norm(stokeslet_velocity(T, src, [force], wall=Wall(0.0), backend=Direct()), axis=1)
        d = np.linalg.norm(T - src, axis=1)
        assert np.polyfit(np.log(d), np.log(u), 1)[0] == pytest.approx(exponent, abs=0.01)
    # free space decays as 1/r
    uf = np.linalg.norm(stokeslet_velocity(T, src, [force], backend=Direct()), axis=1)
    assert np.polyfit(np.log(r), np.log(uf), 1)[0] == pytest.approx(-1.0, abs=0.01)


def test_wall_far_field_coefficient_parallel_force():
    # Blake (1971): 8 pi mu u_a -> 12 h z x_a x_b F_b / r^5 at large lateral distance r
    h, z, X, mu = 0.8, 1.3, 1e3, 2.0
    u = stokeslet_velocity([[X, 0.0, z]], [[0.0, 0.0, h]], [[1.0, 0.0, 0.0]], mu, wall=Wall(0.0),
                           backend=Direct())[0]
    assert 8 * math.pi * mu * u[0] / (12 * h * z / X ** 3) == pytest.approx(1.0, rel=1e-4)
    assert u[1] == 0.0


def test_wall_normal_force_flow_is_axisymmetric():
    src = np.array([[0.4, -0.2, 0.8]])
    f = np.array([[0.0, 0.0, 1.3]])
    rng = np.random.default_rng(13)
    T = rng.uniform(-2, 2, (30, 3))
    T[:, 2] = rng.uniform(0.0, 2.0, 30)
    u = stokeslet_velocity(T, src, f, wall=Wall(0.0), backend=Direct())
    for a in (0.3, 1.9, math.pi):
        c, s = math.cos(a), math.sin(a)
        Q = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        Tr = (T - src) @ Q.T + src
        Tr[:, 2] = T[:, 2]
        ur = stokeslet_velocity(Tr, src, f, wall=Wall(0.0), backend=Direct())
        assert rel_err(ur, u @ Q.T) < 1e-13
    # no swirl: the azimuthal velocity vanishes
    rho = T[:, :2] - src[0, :2]
    swirl = rho[:, 0] * u[:, 1] - rho[:, 1] * u[:, 0]
    assert np.max(np.abs(swirl)) < 1e-14 * np.max(np.abs(u))


def test_wall_reciprocity_and_mirror_symmetry():
    rng = np.random.default_rng(14)
    w = Wall(-0.5)
    for _ in range(5):
        a = rng.uniform(-0.5, 1, 3)
        b = rng.uniform(-0.5, 1, 3)
        G_ab = tensor(a, b, wall=w)
        G_ba = tensor(b, a, wall=w)
        assert np.allclose(G_ab, G_ba.T, rtol=0, atol=1e-13 * np.abs(G_ab).max())
        # the wall breaks the symmetry of G itself
        assert not np.allclose(G_ab, G_ab.T, rtol=0, atol=1e-6 * np.abs(G_ab).max())
    # mirror y -> -y of a force along x
    src = np.array([[0.0, 0.0, 0.7]])
    T = rng.uniform(-1, 1, (10, 3)) + [0.0, 0.0, 1.0]
    P = np.diag([1.0, -1.0, 1.0])
    u = stokeslet_velocity(T, src, [[1.0, 0.0, 0.0]], wall=Wall(0.0), backend=Direct())
    um = stokeslet_velocity(T @ P, src, [[1.0, 0.0, 0.0]], wall=Wall(0.0), backend=Direct())
    assert rel_err(um, u @ P) < 1e-14


# ------------------------------------------------------------------ FMM and Auto
def test_fmm_matches_direct():
    pytest.importorskip("fmm3dpy")
    rng = np.random.default_rng(15)
    T, S, F = rng.random((2000, 3)), rng.random((2000, 3)), rng.standard_normal((2000, 3))
    T[:3] = S[10:13]  # coincident pairs are skipped by both
    u = stokeslet_velocity(T, S, F, 0.3, backend=Direct())
    uf = stokeslet_velocity(T, S, F, 0.3, backend=FMM(eps=1e-12))
    assert rel_err(uf, u) < 1e-10
    assert rel_err(stokeslet_velocity(T, S, F, 0.3, backend=Auto(threshold=1.0)), u) < 1e-10
    # single source and target
    assert rel_err(stokeslet_velocity(T[:1], S[:1], F[:1], backend=FMM()),
                   stokeslet_velocity(T[:1], S[:1], F[:1], backend=Direct())) < 1e-10


def test_fmm_rejects_wall():
    T, S, F = random_case(5, 5, seed=16)
    with pytest.raises(ValueError, match="Direct"):
        stokeslet_velocity(T, S, F, wall=Wall(0.0), backend=FMM())


def test_fmm_missing_gives_install_hint_and_auto_falls_back(monkeypatch):
    monkeypatch.setattr(sk, "_import_fmm3dpy", lambda: None)
    T, S, F = random_case(5, 5, seed=17)
    with pytest.raises(ImportError, match=r"pip install cilia-flow\[fmm\]"):
        stokeslet_velocity(T, S, F, backend=FMM())
    assert isinstance(Auto(threshold=1.0).choose(5, 5, None), Direct)
    assert np.array_equal(stokeslet_velocity(T, S, F, backend=Auto(threshold=1.0)),
                          stokeslet_velocity(T, S, F, backend=Direct()))


def test_auto_choice():
    auto = Auto(threshold=100.0)
    assert isinstance(auto.choose(5, 19, None), Direct)
    assert isinstance(auto.choose(50, 50, Wall()), Direct)
    if sk.fmm_available():
        assert auto.choose(10, 10, None) == FMM(1e-12)
    assert Auto().threshold == sk.FMM_CROSSOVER_PAIRS


# ------------------------------------------------------------------ ranges kernel
def ranges_reference(T, S, F, ptr, ranges, mu, wall):
    out = np.zeros((len(T), 3))
    for i in range(len(T)):
        for k in range(ptr[i], ptr[i + 1]):
            lo, hi = ranges[k]
            if hi > lo:
                out[i] += stokeslet_velocity_numpy(T[i:i + 1], S[lo:hi], F[lo:hi], mu, wall=wall)[0]
    return out


@pytest.mark.parametrize("wall", [None, Wall(-0.2)])
def test_ranges_kernel_matches_reference(wall):
    rng = np.random.default_rng(18)
    M, N = 60, 80
    T, S, F = random_case(M, N, seed=19)
    counts = rng.integers(0, 5, M)
    counts[:3] = 0
    ptr = np.concatenate([[0], np.cumsum(counts)])
    K = ptr[-1]
    lo = rng.integers(0, N, K)
    hi = np.minimum(N, lo + rng.integers(0, 30, K))
    ranges = np.column_stack([lo, hi])
    ranges[0] = ranges[1]  # a repeated block counts twice
    T[5] = S[ranges[ptr[5], 0]] if counts[5] and ranges[ptr[5], 1] > ranges[ptr[5], 0] else T[5]
    u = stokeslet_velocity_ranges(T, S, F, ptr, ranges, 1.3, wall=wall)
    ref = ranges_reference(T, S, F, ptr, ranges, 1.3, wall)
    assert rel_err(u, ref) < 1e-12
    assert not np.any(u[:3])
    # all sources for every target = the dense sum; int32 indices accepted
    full = stokeslet_velocity_ranges(T, S, F, np.arange(M + 1, dtype=np.int32),
                                     np.tile(np.array([0, N], dtype=np.int32), (M, 1)), 1.3, wall=wall)
    assert rel_err(full, stokeslet_velocity(T, S, F, 1.3, wall=wall, backend=Direct())) < 1e-12


@pytest.mark.parametrize(
    "ptr,ranges,name",
    [
        ([0, 1, 1], [[0, 2]], "ptr"),                    # wrong length (M = 3)
        ([0, 1, 0, 1], [[0, 2]], "ptr"),                 # not monotone
        ([0, 1, 1, 2], [[0, 2]], "ptr"),                 # beyond K
        ([-1, 0, 0, 0], [[0, 2]], "ptr"),
        ([0.0, 1.0, 1.0, 1.0], [[0, 2]], "ptr"),         # not integer
        ([0, 1, 1, 1], [[0, 3]], "ranges"),              # beyond N = 2
        ([0, 1, 1, 1], [[-1, 1]], "ranges"),
        ([0, 1, 1, 1], [[2, 1]], "ranges"),              # reversed
        ([0, 1, 1, 1], [0, 2], "ranges"),                # not (K, 2)
        ([0, 1, 1, 1], [[0.0, 2.0]], "ranges"),
    ],
)
def test_ranges_validation(ptr, ranges, name):
    with pytest.raises(ValueError, match=name):
        stokeslet_velocity_ranges(GOOD["targets"], GOOD["sources"], GOOD["forces"], np.array(ptr),
                                  np.array(ranges))


# ------------------------------------------------------------------ regularised kernels
REG = [RegularisedStokeslet(0.05), RegularisedBlake(0.05, Wall(-0.3)), RegularisedStokeslet(0.3),
       RegularisedBlake(0.01, Wall(0.0))]


@pytest.mark.parametrize("kernel", REG, ids=lambda k: f"{type(k).__name__}-{k.eps}")
def test_regularised_direct_and_ranges_match_numpy_reference(kernel):
    T, S, F = random_case(120, 90, seed=30, zmin=0.02)
    u = stokeslet_velocity_numpy(T, S, F, 0.7, kernel=kernel)
    assert rel_err(stokeslet_velocity(T, S, F, 0.7, kernel=kernel, backend=Direct()), u) < 1e-12
    ptr = np.arange(0, 2 * len(T) + 1, 2)
    ranges = np.tile([[0, 40], [40, 90]], (len(T), 1))
    assert rel_err(stokeslet_velocity_ranges(T, S, F, ptr, ranges, 0.7, kernel=kernel), u) < 1e-12


def test_regularised_far_field_difference_decays_as_eps2_over_r3():
    """|G^eps - G^S| f ~ eps^2 / r^3: halving eps quarters it, doubling r divides it by 8."""
    f = np.array([[0.3, -1.0, 0.4]])
    src = np.array([[0.0, 0.0, 0.0]])
    d = np.array([0.6, 0.48, 0.64])
    for eps in (0.02, 0.01):
        diffs = []
        for r in (2.0, 4.0, 8.0):
            x = (r * d)[None]
            diffs.append(np.abs(stokeslet_velocity(x, src, f, kernel=RegularisedStokeslet(eps))
                                - stokeslet_velocity(x, src, f)).max())
        order = np.log2(np.array(diffs[:-1]) / np.array(diffs[1:]))
        assert np.allclose(order, 3.0, atol=0.01), order
        if eps == 0.02:
            d02 = diffs[0]
    assert abs(np.log2(d02 / diffs[0]) - 2.0) < 0.01
    # the leading term: eps^2 (f/2 - 3 R (R.f) / (2 r^2)) / r^3 / (8 pi)
    x = 8.0 * d
    lead = 0.01 ** 2 * (f[0] / 2 - 1.5 * d * (d @ f[0])) / 8.0 ** 3 / (8 * math.pi)
    du = (stokeslet_velocity(x[None], src, f, kernel=RegularisedStokeslet(0.01))
          - stokeslet_velocity(x[None], src, f))[0]
    assert np.allclose(du, lead, rtol=1e-3, atol=0)


@pytest.mark.parametrize("kernel", [RegularisedStokeslet(0.05), RegularisedBlake(0.05, Wall(-1.0))])
def test_regularised_core_is_bounded(kernel):
    """At the source the regularised Stokeslet is 2 f / (8 pi mu eps) (plus bounded images); the
    velocity is bounded near it, largest at the source."""
    f = np.array([[1.0, 0.0, 0.0]])
    src = np.array([[0.0, 0.0, 0.0]])
    r = np.concatenate([[0.0], np.geomspace(1e-8, 1.0, 60)])
    x = np.column_stack([r, np.zeros_like(r), np.zeros_like(r)])
    u = stokeslet_velocity(x, src, f, kernel=kernel)
    speed = np.linalg.norm(u, axis=1)
    assert np.all(np.isfinite(speed))
    assert speed.max() == pytest.approx(speed[0], rel=1e-9)
    if kernel.wall is None:
        assert u[0, 0] == pytest.approx(2.0 / (8 * math.pi * kernel.eps), rel=1e-14)


def test_regularised_wall_vanishes_on_the_wall_and_tends_to_blake():
    T, S, F = random_case(60, 50, seed=31, zmin=0.02)
    w = Wall(-1.0)
    Tw = T.copy()
    Tw[:, 2] = w.z
    for eps in (0.01, 0.1, 0.5):
        k = RegularisedBlake(eps, w)
        scale = np.abs(stokeslet_velocity(T, S, F, kernel=k)).max()
        assert np.abs(stokeslet_velocity(Tw, S, F, kernel=k)).max() < 1e-13 * scale
    blake = stokeslet_velocity(T, S, F, wall=w)
    errs = [rel_err(stokeslet_velocity(T, S, F, kernel=RegularisedBlake(e, w)), blake) for e in (1e-3, 5e-4)]
    assert errs[0] < 1e-2 and 3.0 < errs[0] / errs[1] < 5.0  # O(eps^2) away from the sources


def test_regularised_kernel_is_divergence_free():
    rng = np.random.default_rng(32)
    S = rng.uniform(-0.2, 0.2, (5, 3)) + [0, 0, 0.5]
    F = rng.normal(size=(5, 3))
    x0 = np.array([[0.03, -0.05, 0.45]])  # inside the blobs
    for k in (RegularisedStokeslet(0.1), RegularisedBlake(0.1, Wall(0.0))):
        h = 1e-4
        div = sum((stokeslet_velocity(x0 + h * e, S, F, kernel=k) - stokeslet_velocity(x0 - h * e, S, F, kernel=k))
                  [0, i] / (2 * h) for i, e in enumerate(np.eye(3)))
        assert abs(div) < 1e-6 * np.abs(stokeslet_velocity(x0, S, F, kernel=k)).max() / 0.1


def test_kernel_objects():
    assert make_kernel() == Stokeslet() and make_kernel(Wall(1.0)) == Blake(Wall(1.0))
    assert make_kernel(None, 0.1) == RegularisedStokeslet(0.1)
    assert make_kernel(Wall(), 0.1) == RegularisedBlake(0.1, Wall())
    assert all(k.symmetric for k in (Stokeslet(), Blake(), RegularisedStokeslet(0.1)))
    assert RegularisedBlake(0.1).symmetric  # exactly reciprocal (tests/test_treecode.py)
    assert RegularisedStokeslet(0.1).c2 == C2_FREE
    for bad in (0.0, -1.0, np.nan, "x"):
        with pytest.raises(ValueError, match="blob"):
            RegularisedStokeslet(bad)
    with pytest.raises(ValueError, match="Direct"):
        stokeslet_velocity(*random_case(3, 3), kernel=RegularisedStokeslet(0.1), backend=FMM())
    assert isinstance(Auto(threshold=1.0).choose(50, 50, RegularisedStokeslet(0.1)), Direct)
    with pytest.raises(ValueError, match="contradicts"):
        stokeslet_velocity(*random_case(3, 3), wall=Wall(-5.0), kernel=Blake(Wall(-4.0)))


def test_regularised_taylor_constant_bounded_by_singular():
    """sup over unit h, f at unit distance of |(h.grad)^2 G^eps f| <= C2_FREE for eps <= 0.5."""
    rng = np.random.default_rng(33)
    hs = rng.normal(size=(200, 3))
    hs /= np.linalg.norm(hs, axis=1)[:, None]
    fs = rng.normal(size=(200, 3))
    fs /= np.linalg.norm(fs, axis=1)[:, None]
    d = 1e-3
    x = np.array([[1.0, 0.0, 0.0]])
    src = np.zeros((1, 3))
    for eps in (0.05, 0.2, 0.5):
        k = RegularisedStokeslet(eps)
        worst = 0.0
        for h, f in zip(hs, fs):
            u = [stokeslet_velocity(x + s * d * h, src, f[None], kernel=k)[0] * 8 * math.pi for s in (-1, 0, 1)]
            worst = max(worst, np.linalg.norm(u[0] - 2 * u[1] + u[2]) / d ** 2)
        assert worst <= C2_FREE


# ------------------------------------------------------------------ registries and capabilities
def test_every_registered_green_function_sums_as_its_reference():
    """Each Green's function of KERNELS, through the compiled loops (dense and ranged) and its own
    numpy reference; its code indexes PAIRS, derived from the registry."""
    from ciliary_carpet.stokes.kernel import KERNELS, PAIRS

    assert PAIRS == tuple(dict.fromkeys(k.pair for k in KERNELS.values()))
    T, S, F = random_case(40, 50, seed=40, zmin=0.02)
    T[:, 2] -= 0.3
    S[:, 2] -= 0.3
    ptr = np.arange(0, 2 * len(T) + 1, 2)
    ranges = np.tile([[0, 20], [20, 50]], (len(T), 1))
    for name, cls in KERNELS.items():
        k = cls(wall=Wall(-0.4)) if "blake" in name else cls()
        assert cls.name == name and PAIRS[k.code] is cls.pair
        ref = stokeslet_velocity_numpy(T, S, F, 0.9, kernel=k)
        assert rel_err(stokeslet_velocity(T, S, F, 0.9, kernel=k, backend=Direct()), ref) < 1e-12
        assert rel_err(stokeslet_velocity_ranges(T, S, F, ptr, ranges, 0.9, kernel=k), ref) < 1e-12
        assert (k.c1, k.c2, k.c3) == ((4.0, 16.0, 64.0) if k.wall is not None else (2.0, 4.0, 16.0))


def test_the_direct_loops_were_compiled_for_these_pair_formulas():
    """The cache guard of ciliary_carpet.stokes.direct: the cached loops carry the fingerprint of
    the pair formulas they inline."""
    from ciliary_carpet.stokes import direct

    assert direct._compiled_for() == direct._FINGERPRINT


def test_ranged_sums_of_a_backend_without_them_run_on_direct_and_say_so(caplog):
    """FMM does no ranged sums: the front door runs them on Direct, logs it, and FMM's description
    says so; calling FMM.ranged itself is an error, not a silent fallback."""
    import logging

    from ciliary_carpet.stokes import BACKENDS, backend_named, ranged_backend

    T, S, F = random_case(20, 30, seed=41)
    ptr = np.arange(0, 2 * len(T) + 1, 2)
    ranges = np.tile([[0, 10], [5, 30]], (len(T), 1))
    assert not FMM.ranged_sums and Direct.ranged_sums and Auto.ranged_sums
    with pytest.raises(NotImplementedError, match="no ranged sums"):
        FMM().ranged(Stokeslet(), T, S, F, ptr, ranges, 1.0)
    with caplog.at_level(logging.INFO, logger="ciliary_carpet.stokes.dispatch"):
        u = stokeslet_velocity_ranges(T, S, F, ptr, ranges, backend=FMM(1e-9))
    assert np.array_equal(u, stokeslet_velocity_ranges(T, S, F, ptr, ranges, backend=Direct()))
    assert "fmm (fmm3dpy, eps 1e-09; ranged sums: direct, CPU) does no ranged sums: they run on direct" in caplog.text
    assert isinstance(ranged_backend(FMM()), Direct) and ranged_backend(Auto()) == Auto()
    for name in BACKENDS:
        if name.startswith("cuda"):
            continue  # needs a GPU (tests/test_cuda.py)
        b = backend_named(name)
        if not b.ranged_sums:
            assert ranged_backend(b).describe().split(" (")[0] in b.describe()


def test_a_greens_function_without_its_pair_or_reference_cannot_be_made():
    """The Kernel contract is enforced: a subclass missing ``pair`` or ``reference`` is refused
    when instantiated, not discovered later inside a compiled loop."""
    from dataclasses import dataclass

    from ciliary_carpet.stokes import Kernel

    @dataclass(frozen=True)
    class Half(Kernel):
        name = "half"
        c1, c2, c3 = 1.0, 1.0, 1.0

        def reference(self, x, xi, f):
            return np.zeros((len(x), 3))

    with pytest.raises(TypeError, match="pair"):
        Half()


# --------------------------------------------------------------------------- fp32 on the CPU
@pytest.mark.parametrize("name", ["stokeslet", "regularised-stokeslet", "blake", "regularised-blake"])
def test_fp32_sums_within_their_bound(name):
    """Direct("fp32"), dense and ranged, every Green's function: within the rounding bound of
    ciliary_carpet.stokes.precision against fp64, with ranges longer than a block (FP32_BLOCK: the
    block sums added in fp64), and fp32 did run (errors above fp64's). Points 50 L from the origin:
    the shift to their centre keeps the accuracy."""
    from ciliary_carpet.stokes.kernel import KERNELS
    from ciliary_carpet.stokes.precision import FP32_BLOCK, fp32_error_bound

    cls = KERNELS[name]
    k = cls(wall=Wall(-0.4)) if "blake" in name else cls()
    T, S, F = random_case(40, 3 * FP32_BLOCK + 17, seed=41, zmin=0.02)
    T[:, :2] += 50.0
    S[:, :2] += 50.0
    n = S.shape[0]
    ref = Direct().dense(k, T, S, F, 0.9)
    u = Direct("fp32").dense(k, T, S, F, 0.9)
    assert u.dtype == np.float64
    err = np.max(np.abs(u - ref), axis=1)
    bound = fp32_error_bound(k, T, S, F, 0.9, block=FP32_BLOCK)
    assert np.all(err <= bound), np.max(err / bound)
    assert 1e-10 < rel_err(u, ref) < 1e-5
    # ranged: a long range (three blocks and a part), a short one, an empty one, no range at all
    ptr = np.concatenate([[0, 0], np.arange(1, 3 * (len(T) - 1) + 1, 3)])
    ranges = np.tile([[0, n], [5, 30], [7, 7]], (len(T) - 1, 1))
    ref = stokeslet_velocity_ranges(T, S, F, ptr, ranges, 0.9, kernel=k)
    u = Direct("fp32").ranged(k, T, S, F, ptr, ranges, 0.9)
    assert not np.any(u[0])
    terms = np.diff(ptr) * 0 + n + 25
    err = np.max(np.abs(u - ref), axis=1)[1:]
    assert np.all(err <= fp32_error_bound(k, T, S, F, 0.9, terms=terms, block=FP32_BLOCK)[1:])
    assert 1e-10 < rel_err(u, ref) < 1e-5


def test_fp32_precision_is_checked_and_described():
    with pytest.raises(ValueError, match="precision must be one of"):
        Direct("fp16")
    assert "fp32" in Direct("fp32").describe() and "fp32" not in Direct().describe()


def test_in_fp32_moves_only_the_cpu_sums():
    """The path lines' far sums run in fp32 where the ranged sums would run on the CPU in fp64
    (Auto without a GPU, Direct); any other backend is kept (a GPU keeps its own precision)."""
    from ciliary_carpet.stokes import in_fp32

    assert in_fp32(Auto()) == Direct("fp32") and in_fp32(Direct()) == Direct("fp32")
    assert in_fp32(FMM()) == Direct("fp32")  # FMM's ranged sums run on Direct
    assert in_fp32(Direct("fp32")) == Direct("fp32")

    class Unhashable(Direct):  # a user's backend: kept as it is, and no TypeError from the cache
        __hash__ = None

    mine = Unhashable()
    assert in_fp32(mine) is mine
