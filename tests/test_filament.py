import numpy as np
import pytest

from single_cilium import Filament, Mesh, equilibrium
from single_cilium.dynamics import initial_state

TWO_PI = 2 * np.pi


@pytest.fixture
def fil(published):
    return Filament(published, Mesh.for_params(published, degree=8))


def _state(fil, seed=1, amp=0.2):
    rng = np.random.default_rng(seed)
    s = fil.mesh.nodes
    theta = equilibrium(fil.params, s) + amp * np.sin(2.3 * s) * rng.standard_normal()
    theta[0] = 0
    kappa = -fil.params.chi_E * np.sin(theta) + rng.standard_normal(s.size)
    return fil.join(theta, kappa)


def test_resistance_matrix_is_spd_and_matches_matrix_free(fil):
    y = _state(fil)
    theta, _ = fil.split(y)
    D = fil.resistance_matrix(theta)
    assert np.allclose(D, D.T, rtol=0, atol=1e-15 * np.abs(D).max())
    assert np.linalg.eigvalsh(D).min() > 0
    v = np.random.default_rng(2).standard_normal(fil.n - 1)
    mv = fil.resistance(theta, np.concatenate([[0.0], v]))
    assert np.max(np.abs(D @ v - mv)) < 1e-13 * np.abs(mv).max()


def test_dissipation_identity(fil):
    """dE_h/dt = -theta_t^T D theta_t (kappa frozen): the semi-discrete gradient-flow structure."""
    y = _state(fil)
    theta, kappa = fil.split(y)
    yd = fil.velocity(y)
    tht, _ = fil.split(yd)
    D = fil.resistance_matrix(theta)
    eps = 1e-6
    dE = (fil.bending_energy(theta + eps * tht, kappa) - fil.bending_energy(theta - eps * tht, kappa)) / (2 * eps)
    assert dE == pytest.approx(-tht[1:] @ D @ tht[1:], rel=1e-7)
    assert dE < 0


@pytest.mark.parametrize("sigma", [3.7, 50.0 + 20.0j, 1e4 - 3e3j])
@pytest.mark.parametrize("frozen", [False, True])
def test_schur_factor_solves_the_newton_system(published, sigma, frozen):
    fil = Filament(published, Mesh.for_params(published, degree=6), kappa_frozen=frozen)
    y = _state(fil)
    theta, _ = fil.split(y)
    n = fil.n
    D = fil.resistance_matrix(theta)
    M = np.eye(fil.size)
    M[: n - 1, : n - 1] = D
    J = np.zeros((fil.size, fil.size))
    J[: n - 1, : n - 1] = -fil._K[1:, 1:]
    J[: n - 1, n - 1:] = fil._B[1:, :]
    if not frozen:
        J[n:, : n - 1] = -published.chi_E * np.diag(np.cos(theta[1:]))
        J[n - 1:, n - 1:] = -np.eye(n)
    # J is the exact Jacobian of f
    e = 1e-7
    col = 5
    dy = np.zeros(fil.size); dy[col] = e
    fd = (fil.rhs(y + dy) - fil.rhs(y - dy)) / (2 * e)
    assert np.max(np.abs(fd - J[:, col])) < 1e-6 * np.abs(J[:, col]).max()
    b = np.random.default_rng(3).standard_normal(fil.size)
    x = fil.factor(y, [sigma])[0].solve(b.astype(complex) if np.iscomplexobj(sigma) else b)
    assert np.max(np.abs((sigma * M - J) @ x - b)) < 1e-9 * np.abs(b).max()


def test_mirror_symmetry_is_exact(published):
    fil = Filament(published, Mesh.for_params(published, degree=8))
    mir = Filament(published.mirrored(), fil.mesh)
    y = _state(fil)
    v = np.random.default_rng(4).standard_normal(fil.size)
    assert np.array_equal(mir.rhs(-y), -fil.rhs(y))
    assert np.array_equal(mir.residual(-y[None], -v[None]), -fil.residual(y[None], v[None]))
    assert np.array_equal(mir.mass_apply(-y, -v), -fil.mass_apply(y, v))


def test_discrete_equilibrium(published):
    for deg, tol in ((8, 1e-5), (12, 1e-8)):
        fil = Filament(published, Mesh.for_params(published, degree=deg))
        y = fil.equilibrium_state()
        theta, kappa = fil.split(y)
        elastic = np.abs(fil._K @ theta).max()  # size of the terms that must cancel
        assert np.max(np.abs(fil.rhs(y))) < 1e-12 * elastic
        assert np.max(np.abs(theta - equilibrium(published, fil.mesh.nodes))) < tol
        assert np.max(np.abs(fil.clamp_force(fil.drag(theta, np.zeros_like(theta))))) == 0


def test_initial_perturbation_keeps_the_tip_conditions(published):
    fil = Filament(published, Mesh.for_params(published, degree=12))
    y0 = fil.equilibrium_state()
    y = initial_state(fil, amplitude=1e-3, seed=7)
    th0, _ = fil.split(y0)
    th, _ = fil.split(y)
    d = th - th0
    assert np.max(np.abs(d)) == pytest.approx(1e-3)
    ds = fil.mesh.derivative_at_nodes(d)
    assert abs(ds[-1, -1]) < 1e-12 and abs(d[0]) == 0  # zero slope at the tip, clamp fixed
    assert not np.array_equal(initial_state(fil, 1e-3, seed=8), y)  # the seed matters


@pytest.mark.parametrize("frozen", [False, True])
def test_compiled_residual_matches_numpy(published, frozen):
    fil = Filament(published, Mesh.for_params(published, degree=8), kappa_frozen=frozen)
    rng = np.random.default_rng(5)
    Y = np.stack([_state(fil, seed=k) for k in range(3)])
    K = rng.standard_normal(Y.shape)
    ref = fil.rhs(Y) - fil.mass_apply(Y, K)
    assert np.max(np.abs(fil.residual(Y, K) - ref)) < 1e-12 * np.abs(ref).max()
