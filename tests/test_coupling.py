"""Cilia that feel the flow (issue 27): the carpet's viscosity from its filaments, cilia beating
in a background flow, and the self-consistent (coupled) carpet of
:mod:`ciliary_carpet.carpet.coupling`.

The coupled tests use a small, coarse table over the flow (degree 6, 32 phases, 17 s points,
flows -1, 0, 1 in each component: seconds to build); the coupled flows of a 3 x 3 carpet stay
well inside it. The benchmark (benchmarks/bench_coupling.py) uses the shipped discretisation.
"""
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest

from single_cilium.table import ThrustTable, build_table

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean, sbt_viscosity
from ciliary_carpet.carpet.coupling import CouplingError, couple, coupling_estimate

FAST = dict(degree=6, n_phase=32, n_s=17, error_estimate=False)
GRID = [0.0, 40.0, 80.0, 120.0, 160.0]
CHI = 92.0


@pytest.fixture(scope="module")
def flow():
    with ThreadPoolExecutor(2) as ex:
        return build_table(200, 1, GRID, U_par=[-1.0, 0.0, 1.0], U_perp=[-1.0, 0.0, 1.0], executor=ex, **FAST)


@pytest.fixture(scope="module")
def still():
    return ThrustTable.default()


def _carpet(table, sign=1.0, **kw):
    b = layout.square(3, 3, 2.0)
    return Carpet(b * np.array([sign, 1.0]), sign * CHI, table, layout.random_phases(9, 0), **kw)


def test_viscosity_from_the_filaments_by_default(still):
    c = _carpet(still)
    assert c.mu_source == "filaments" and c.mu == sbt_viscosity(1.0, 0.02) == pytest.approx(0.6534, abs=1e-4)
    given = _carpet(still, viscosity=1.0)
    assert given.mu == 1.0 and given.mu_source == "given"
    x = np.array([[1.0, -3.0, 0.2], [5.0, 2.0, 0.0]])
    # Stokes flow is linear in 1 / mu: the default's flow is 1 / 0.653 times the one at mu = 1
    np.testing.assert_allclose(c.velocity(x, CycleMean()) * c.mu, given.velocity(x, CycleMean()), rtol=1e-10)
    assert replace(c, chi_N=np.full(9, 60.0)).mu_source == "filaments"  # a changed carpet keeps the source
    with pytest.raises(ValueError, match="viscosity must be > 0"):
        _carpet(still, viscosity=-1.0)
    with pytest.raises(ValueError, match="coupling"):
        _carpet(still, coupling="full")


def test_still_background_is_still_fluid(flow):
    """U = 0 on a table over the flow is its grid flow U = 0: the same cycles as that one-flow table."""
    a = _carpet(flow, background=np.zeros((9, 2)))
    b = _carpet(flow.in_still_fluid())
    np.testing.assert_allclose(a.others_mean_flow(), b.others_mean_flow(), rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(a.periods, b.periods, rtol=1e-9)


def test_a_background_flow_changes_the_beat(flow):
    """A flow along the field (from clamp to tip) changes the period and the thrust by amounts
    the table says; the carpet reads them in its field frame (direction rotates U)."""
    U = np.tile([0.0, 0.5], (9, 1))  # lab frame along +y = along the field (direction 0)
    a = _carpet(flow, background=U)
    assert np.allclose(a.periods, flow.scalar("period", CHI, U_par=0.5, U_perp=0.0), rtol=1e-12)
    turned = Carpet(layout.square(3, 3, 2.0), CHI, flow, direction=math.pi / 2,
                    background=np.tile([-0.5, 0.0], (9, 1)))  # the field along -x: the same flow along it
    np.testing.assert_allclose(turned.periods, a.periods, rtol=1e-12)


def test_coupled_carpet_solves_its_equation(flow):
    c = _carpet(flow, coupling="mean")
    r = c.coupled
    assert r.converged and r.residual <= 1e-3 and r.iterations <= 4
    assert all(b < a / 10 for a, b in zip(r.history, r.history[1:]))  # each Newton step gains a digit or more
    # independently: the others' mean flow at each cilium of the carpet beating in U is U
    M = replace(c, coupling="none", background=c.background).others_mean_flow()[:, :2]
    assert np.abs(M - c.background).max() <= 1e-3 * np.abs(M).max()
    np.testing.assert_array_equal(c.background, r.background)
    # the cilia push back: the coupled flow is slower than the uncoupled one, and not zero
    ch = r.change()
    assert 0.2 < ch["median_speed_coupled"] / ch["median_speed_uncoupled"] < 0.95
    s = r.summary()
    assert s["model"] == "mean" and s["status"] == "converged" and "Newton" in s["message"]


def test_coupled_flow_converges_with_rtol(flow):
    """Refinement in the solver's tolerance: the flow at rtol 1e-2 and 1e-3 against rtol 1e-6 (tol
    1e-7): each within twice its own residual (the Newton system's inverse has norm about 1)."""
    c = _carpet(flow)
    ref = couple(c, tol=1e-7, rtol=1e-6)
    assert ref.converged
    scale = np.abs(ref.background).max()
    for rtol in (1e-2, 1e-3):
        r = couple(c, rtol=rtol)
        err = np.abs(r.background - ref.background).max() / scale
        assert r.converged and err <= 2 * r.residual + 2e-4


def test_mirror_symmetry(flow):
    """Bases x -> -x and chi_N -> -chi_N mirror the coupled flow (U_x -> -U_x)."""
    a = _carpet(flow, coupling="mean")
    b = _carpet(flow, sign=-1.0, coupling="mean")
    scale = np.abs(a.background).max()
    np.testing.assert_allclose(b.background * np.array([-1.0, 1.0]), a.background, atol=2e-3 * scale)


def test_linear_estimate_is_near_the_solve(flow):
    c = _carpet(flow)
    est = coupling_estimate(c)
    ch = couple(c).change()
    assert est["median_speed_uncoupled"] == pytest.approx(ch["median_speed_uncoupled"], rel=1e-3)
    assert est["median_speed_coupled"] == pytest.approx(ch["median_speed_coupled"], rel=0.25)


def test_bad_coupling_inputs(flow, still):
    with pytest.raises(CouplingError, match="background flow"):
        _carpet(still, coupling="mean")
    with pytest.raises(ValueError, match="rtol"):
        couple(_carpet(flow), rtol=1e-6, tol=1e-4)
    # a table whose flow grid is too small for the flow the carpet needs
    small = ThrustTable(flow.ds.sel(U_par=[0.0, 1.0]))
    with pytest.raises(CouplingError, match="flow grid"):
        _carpet(small, coupling="mean")


def test_scene_keys(tmp_path, still):
    from ciliary_carpet.scenes.assembly import assemble
    from ciliary_carpet.scenes.schema import SceneError
    from ciliary_carpet.scenes.scene import scene_from_dict

    base = {"name": "c", "carpet": {"lattice": "square", "shape": [3, 3], "chi_N": 50.0}}
    with pytest.raises(SceneError, match="needs a thrust table over the background"):
        assemble(scene_from_dict({**base, "carpet": {**base["carpet"], "coupling": "mean"}}), still)
    with pytest.raises(SceneError, match="coupling"):
        scene_from_dict({**base, "carpet": {**base["carpet"], "coupling": "full"}})
    with pytest.raises(SceneError, match="viscosity"):
        scene_from_dict({**base, "carpet": {**base["carpet"], "viscosity": -1.0}})
    with pytest.raises(SceneError, match="flow_points must be odd"):
        scene_from_dict({**base, "table": {"file": "t.nc", "build": {"flow": 2.0, "flow_points": 4}}})
    with pytest.raises(SceneError, match=r'needs a thrust table over the background.*coupling = "none"'):
        assemble(scene_from_dict(base), still)  # coupled by default: a still-fluid table is refused
    c = assemble(scene_from_dict({**base, "carpet": {**base["carpet"], "viscosity": 2.0, "coupling": "none"}}),
                 still).carpet()
    assert c.mu == 2.0 and c.mu_source == "given"


def test_design_model_answers_through_the_flow(flow):
    """The design model of a coupled carpet (CouplingResponse): a change of the curvatures moves
    the control points' mean flow as the coupled carpet does (measured on 6 x 6 cilia with the
    shipped discretisation, control points among the cilia: 7 % off, against 27 % for the
    still-fluid model), and its gradient is exact for it."""
    from ciliary_carpet.carpet.coupling import CouplingResponse
    from ciliary_carpet.design.model import DesignModel

    n = 4
    c = Carpet(layout.square(n, n, 2.0), CHI, flow, layout.random_phases(n * n, 0), coupling="mean")
    X = np.array([[x, y] for x in np.linspace(-2.0, 8.0, 6) for y in (-4.0, 10.0)])  # beyond the near field
    chi = np.full(n * n, CHI)
    d = np.random.default_rng(1).standard_normal(n * n) * 3.0
    truth = (replace(c, chi_N=chi + d).evaluate(X, CycleMean(), tol=1e-6).velocity
             - c.evaluate(X, CycleMean(), tol=1e-6).velocity)[:, :2]
    err = {}
    for name, resp in (("still", None), ("coupled", CouplingResponse(c))):
        dm = DesignModel(c, X, chi, response=resp)
        du = dm.velocity(chi + d) - dm.velocity(chi)
        err[name] = np.linalg.norm(du - truth) / np.linalg.norm(truth)
    assert err["coupled"] < 0.5 * err["still"] and err["coupled"] < 0.15, err
    g = np.random.default_rng(2).standard_normal((X.shape[0], 2))
    e = np.random.default_rng(3).standard_normal(n * n)
    h = 1e-4
    fd = (np.sum(g * dm.velocity(chi + d + h * e)) - np.sum(g * dm.velocity(chi + d - h * e))) / (2 * h)
    assert dm.gradient(chi + d, g) @ e == pytest.approx(fd, rel=1e-6)


@pytest.mark.slow
def test_scene_builds_a_flow_table_and_couples(tmp_path):
    """A scene with [table.build] flow builds the table over the flow where it names it, and its
    coupled carpet converges (a coarse table: 4 rows, 3 x 3 flows, degree 6: about 15 s)."""
    from ciliary_carpet.scenes.assembly import assemble
    from ciliary_carpet.scenes.scene import load_scene

    (tmp_path / "s.toml").write_text('name = "bt"\n[table]\nfile = "t/flow.nc"\n[table.build]\nn = 4\ndegree = 6\n'
                                     'flow = 1.0\nflow_points = 3\n[carpet]\nshape = [3, 3]\nchi_N = 60.0\n'
                                     'coupling = "mean"\n')
    a = assemble(load_scene(tmp_path / "s.toml"))
    assert (tmp_path / "t" / "flow.nc").is_file() and a.table.U_range == ((-1.0, 1.0), (-1.0, 1.0))
    c = a.carpet()
    assert c.coupled.converged and c.coupled.residual <= 1e-3


def test_coupled_render(tmp_path, flow):
    """A coupled scene renders: its summary gives the solve, its layout.vtp each cilium's flow and
    its thrust angle in that flow."""
    import json

    import pyvista as pv

    from ciliary_carpet.render import render
    from ciliary_carpet.scenes.scene import load_scene

    flow.save(tmp_path / "flow.nc")
    (tmp_path / "s.toml").write_text(
        'name = "cr"\n[table]\nfile = "flow.nc"\n[carpet]\nshape = [3, 3]\nchi_N = 92.0\ncoupling = "mean"\n'
        '[output]\nn_seeds = 4\nperiods = 1.0\nfield_shape = [10, 10]\nsnapshots = 0\nframes = 0\nftle = false\n'
        'preview = false\n')
    res = render(load_scene(tmp_path / "s.toml"), tmp_path / "out")
    s = json.loads((res.out_dir / "summary.json").read_text())
    assert s["coupling"]["model"] == "mean" and s["coupling"]["status"] == "converged"
    assert "Coupled carpet" in (res.out_dir / "summary.md").read_text()
    m = pv.read(res.out_dir / "layout.vtp")
    c = _carpet(flow, coupling="mean")
    np.testing.assert_allclose(m["background_flow"][:, :2], c.background, rtol=1e-9, atol=1e-12)
    u = c.background @ c.rotation
    np.testing.assert_allclose(m["thrust_angle"], flow.scalar("thrust_angle", c.chi_N, U_par=u[:, 1], U_perp=u[:, 0]))


def test_one_cilium_and_a_wall(flow):
    """One cilium feels nothing (no warning, zero flow); a wall screens the coupling and the planar
    filaments cannot feel the mean flow's normal component, which the result reports."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        one = Carpet(np.zeros((1, 2)), CHI, flow, coupling="mean")
    assert one.coupled.converged and one.coupled.contraction == 0.0 and not np.any(one.background)
    free, wall = _carpet(flow, coupling="mean"), _carpet(flow, wall=0.5, coupling="mean")
    assert wall.coupled.converged and wall.coupled.normal_flow > 0 and free.coupled.normal_flow == 0
    assert wall.coupled.change()["relative_change_median"] < free.coupled.change()["relative_change_median"]


def test_first_guess_and_inexact_newton(flow):
    """A coupled carpet with other curvatures (replace(c, chi_N=...), as a design's checks do)
    starts from the last solution: fewer evaluations of M than from still fluid, the same flows
    to the solver's tolerance, and M(0) for the summary evaluated on demand. The certifying
    evaluation is at tol: the final residual is of the accurate M."""
    c = _carpet(flow, coupling="mean")
    cold = c.coupled
    assert cold.converged and cold._uncoupled is not None
    chi = c.chi_N + np.linspace(-2.0, 2.0, c.n)
    warm = replace(c, chi_N=chi).coupled
    fresh = _carpet(flow, coupling="mean")
    fresh = replace(fresh, chi_N=chi, background=None).coupled
    assert warm.converged and fresh.converged
    assert warm.evaluations < fresh.evaluations, (warm.evaluations, fresh.evaluations)
    scale = np.abs(fresh.background).max()
    assert np.abs(warm.background - fresh.background).max() <= 2 * (warm.rtol + fresh.rtol) * scale
    assert warm._uncoupled is None  # not needed by the solve ...
    np.testing.assert_allclose(warm.uncoupled, fresh.uncoupled, rtol=0, atol=1e-3 * scale)  # ... made on demand
    M = replace(warm.carpet).others_mean_flow(tol=1e-4)[:, :2]
    assert np.abs(warm.background - M).max() <= warm.rtol * np.abs(M).max() * 1.01


def test_a_coupling_that_does_not_converge_renders_nothing(tmp_path, monkeypatch, capsys):
    """A scene whose coupled solve stops unconverged: exit 3, one line with the residual history,
    and no render folder (nothing is drawn from a flow that was not solved)."""
    import ciliary_carpet.carpet.carpet as carpet_mod
    from ciliary_carpet.cli import main

    def one_step(c, **kw):  # the solver stopped after a single Newton step, unconverged
        return couple(c, max_iter=0)

    monkeypatch.setattr(carpet_mod, "couple", one_step)
    scene = tmp_path / "s.toml"
    scene.write_text('name = "s"\n[carpet]\nshape = [3, 3]\nchi_N = 92.0\n[output]\nn_seeds = 2\nperiods = 1.0\n'
                     'field_shape = [6, 6]\nsnapshots = 1\nframes = 2\npreview = false\nftle = false\n')
    assert main(["render", str(scene), "-o", str(tmp_path / "out")]) == 3
    err = capsys.readouterr().err
    assert "not solved" in err and "NOT converged" in err and "residual after each Newton step" in err, err
    assert not (tmp_path / "out" / "summary.json").exists()
