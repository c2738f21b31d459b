import numpy as np
import pytest

from single_cilium import CiliumParams, Mesh
from single_cilium.mesh import gll


@pytest.mark.parametrize("p", [2, 5, 12, 20])
def test_gll_exact_to_degree_2p_minus_1(p):
    x, w = gll(p)
    for k in range(2 * p):
        exact = (1 - (-1) ** (k + 1)) / (k + 1)
        assert abs(w @ x**k - exact) < 1e-13
    assert abs(w @ x ** (2 * p) - 2 / (2 * p + 1)) > 1e-13  # and not beyond


def test_composite_rules_on_graded_mesh():
    m = Mesh.graded(0.005, degree=10)
    s = m.nodes
    assert s[0] == 0 and s[-1] == 1 and np.all(np.diff(s) > 0)
    assert abs(m.weights @ np.exp(s) - (np.e - 1)) < 1e-14
    assert np.max(np.abs(m.cumulative @ np.cos(3 * s) - np.sin(3 * s) / 3)) < 1e-13
    d = np.concatenate(m.derivative_at_nodes(np.sin(3 * s)))
    assert np.max(np.abs(d - 3 * np.cos(3 * s[m.element_nodes]).ravel())) < 1e-10
    q = np.linspace(0, 1, 101)
    assert np.max(np.abs(m.interpolate(np.sin(3 * s), q) - np.sin(3 * q))) < 1e-12


def test_graded_mesh_resolves_the_layer_exponentially():
    q = np.linspace(0, 1, 3001)
    errs = []
    for p in (6, 9, 12, 15):
        m = Mesh.graded(0.005, degree=p)
        errs.append(np.max(np.abs(m.interpolate(np.exp(-m.nodes / 0.005), q) - np.exp(-q / 0.005))))
    ratios = np.array(errs[:-1]) / np.array(errs[1:])
    assert np.all(ratios > 8), errs  # geometric decay: exponential convergence in the degree


def test_for_params_grading_follows_the_layer():
    thin = Mesh.for_params(CiliumParams(1000, 1, 0))
    wide = Mesh.for_params(CiliumParams(20, 1, 0))
    assert thin.sizes[0] < 0.005 < wide.sizes[0]
    coiled = Mesh.for_params(CiliumParams(50, 1, 16 * 2 * np.pi))
    assert coiled.n_elements >= 32  # one element per half turn of the coil


@pytest.mark.parametrize("breaks,degree", [((0, 0.5, 0.4, 1), 4), ((0, 1), 1), ((0.1, 1), 4), ((0, np.nan, 1), 4)])
def test_bad_meshes(breaks, degree):
    with pytest.raises(ValueError):
        Mesh(breaks, degree)


def test_for_params_refines_an_interior_fold():
    """chi_E < 0 with a small chi_N: theta climbs from 0 to about pi in a front near
    s = ln(|chi_E| / chi_N) / |chi_E|; the mesh is bisected there until it is resolved."""
    from single_cilium import equilibrium
    p = CiliumParams(-50, 1, 0.01 * 2 * np.pi)
    m = Mesh.for_params(p, degree=12)
    assert m.tail(equilibrium(p, m.nodes)) < 1e-5
    plain = Mesh.graded(1 / 50, degree=12)
    assert plain.tail(equilibrium(p, plain.nodes)) > 1e-3  # the plain graded mesh is not enough
