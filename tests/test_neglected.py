"""What the carpet model leaves out, sized (ciliary_carpet/carpet/omissions/; issues 26 and 27)."""
import json
import math
from pathlib import Path

import numpy as np
import pytest

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.carpet.carpet import sbt_viscosity
from ciliary_carpet.carpet.omissions import (TARGET_RATIO, drag_tensor, omissions, thrust_shift, wall_drag_formula,
                                             wall_drag_ratios)
from single_cilium.table import ThrustTable

ROOT = Path(__file__).resolve().parents[1]
CHI_N = 92.0  # the uniform_deflection scene's curvature: a fluttering cilium


@pytest.fixture(scope="module")
def table():
    return ThrustTable.default()


def _pair(table, R, wall=None):
    """Two cilia R apart along x, phases 0 and 0.3."""
    return Carpet(np.array([[0.0, 0.0], [R, 0.0]]), CHI_N, table, np.array([0.0, 0.3]), wall=wall)


def test_single_cilium_feels_nothing(table):
    o = omissions(Carpet(np.zeros((1, 2)), CHI_N, table))
    assert o.ratio_tip.shape == (6, 1)
    # the carpet's flow minus the cilium's own resolved line: rounding only
    assert np.max(o.ratio_mid) < 1e-12 and np.max(o.ratio_tip) < 1e-12
    assert o.pushback_max < 1e-12
    assert math.isnan(o.spacing) and math.isnan(o.spacing_10)
    json.dumps(o.summary(), allow_nan=False)


def test_far_pair_is_a_stokeslet(table):
    """Cilium 1 far from cilium 0: the flow it induces at 0's tip is its instantaneous force's
    Stokeslet, (I + e e^T) F_1(t) / (8 pi mu R) (the dipole term is a / R ~ 1 % here), so the
    ratio falls as 1 / R; the others' mean flow at 0's force centre is Fbar_1's Stokeslet."""
    out = {}
    for R in (40.0, 80.0):
        c = _pair(table, R)
        o = omissions(c, tol=1e-4, spacing=False)
        w = np.ones(c.s.size)
        w[1:-1:2], w[2:-1:2] = 4.0, 2.0
        w /= 3.0 * (c.s.size - 1)
        est = []
        for t in o.instants:
            pos, frc, _ = c.state(t)
            F1 = np.append((frc[1] * w[:, None]).sum(axis=0), 0.0)
            d = np.append(c.centres[1] - pos[0, -1], 0.0)
            e = d / np.linalg.norm(d)
            est.append(np.linalg.norm(F1 + e * (e @ F1)) / (8 * math.pi * c.mu * np.linalg.norm(d)))
        induced = o.ratio_tip[:, 0] * o.beat_speed_tip[0]
        np.testing.assert_allclose(induced, est, rtol=0.02)  # measured: within 0.8 % at 40 L
        Fbar = np.append(c.mean_thrust[1], 0.0)
        d = np.append(c.centres[1] - c.centres[0], 0.0)
        e = d / np.linalg.norm(d)
        mono = np.linalg.norm(Fbar + e * (e @ Fbar)) / (8 * math.pi * c.mu * np.linalg.norm(d))
        pushed = o.pushback_max / (c.table.eta / np.linalg.norm(c.mean_thrust[0]))  # cilia 0 and 1 alike
        assert pushed == pytest.approx(mono, rel=0.05)
        out[R] = o.ratio_tip[:, 0]
    np.testing.assert_allclose(out[40.0] / out[80.0], 2.0, rtol=0.1)


def test_near_wall_coefficients_against_the_blake_kernel():
    """Katz, Blake & Paveri-Fontana's constants for a << h << L, from this package's Blake kernel:
    a uniform line force, the velocity averaged round the surface at the middle of a long filament:
    2 pi mu u / f = ln(2h/a) along it, 4 pi mu u / f = ln(2h/a) across it parallel to the wall and
    ln(2h/a) - 1 normal to the wall."""
    from ciliary_carpet.stokes import Wall, make_kernel, stokeslet_velocity

    a, h = 0.001, 0.02
    x = np.unique(np.concatenate([np.linspace(0, 0.49, 20000, endpoint=False), 0.5 + np.linspace(-0.01, 0.01, 40001),
                                  np.linspace(0.51, 1, 20000)]))
    src = np.stack([x, 0 * x, 0 * x], axis=1)
    phi = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    tg = np.stack([0.5 + 0 * phi, a * np.cos(phi), a * np.sin(phi)], axis=1)
    lg = math.log(2 * h / a)
    for e, k, expect in (([1, 0, 0], 2, lg), ([0, 1, 0], 4, lg), ([0, 0, 1], 4, lg - 1)):
        e = np.array(e, float)
        u = (stokeslet_velocity(tg, src, np.gradient(x)[:, None] * e, kernel=make_kernel(Wall(z=-h), 0.0)) @ e).mean()
        assert k * math.pi * u == pytest.approx(expect, rel=0.005)


def test_wall_ratio_formula_and_limits():
    a = 0.02
    assert wall_drag_formula(0.1, a) == pytest.approx((math.log(2 / a) - 0.5) / math.log(2 * 0.1 / a), rel=1e-12)
    assert wall_drag_formula(0.61, a) == 1.0 and wall_drag_formula(None, a) == 1.0
    hs = [0.05, 0.1, 0.2, 0.5, 1.0, 10.0]
    r = np.array([wall_drag_ratios(h, a) for h in hs])
    assert np.all(np.diff(r, axis=0) < 0) and np.all(r > 1)  # the wall's effect falls as it recedes ...
    assert np.all(r[hs.index(1.0)] < 1.1) and np.all(r[-1] < 1.01)  # ... within 10 % at h = L, to 1
    # the finite filament brackets the closed form for a << h << L (along below, across above)
    for h in (0.05, 0.1, 0.2):
        along, across = wall_drag_ratios(h, a)
        assert along < wall_drag_formula(h, a) < across
        assert across / along < 1.25
    # measured: 1.55 along, 1.85 across at h = 0.1 (closed form 1.78)
    np.testing.assert_allclose(wall_drag_ratios(0.1, a), (1.552, 1.852), atol=0.005)
    assert wall_drag_ratios(None, a) == (1.0, 1.0)
    assert all(math.isnan(v) for v in wall_drag_ratios(0.025, a))  # touching the wall: no slender theory


def test_wall_and_viscosity_on_a_carpet(table):
    o = omissions(_pair(table, 3.0, wall=0.1), spacing=False)
    assert (o.wall_drag_along, o.wall_drag_across) == wall_drag_ratios(0.1, 0.02)
    assert o.wall_drag_formula == wall_drag_formula(0.1, 0.02)
    assert o.wall_regime == "a << h << L"
    assert "1.85 times as hard to move across" in o.lines()[3]
    assert o.mu_sbt == pytest.approx(sbt_viscosity(1.0, 0.02)) == pytest.approx(0.6534, abs=1e-4)
    assert o.mu == o.mu_sbt and o.mu_source == "filaments"  # the default: consistent with the drag
    assert abs(o.flow_speed_error) < 1e-15 and "set to" in o.lines()[-1]
    one = omissions(Carpet(np.array([[0.0, 0.0], [3.0, 0.0]]), CHI_N, table, viscosity=1.0), n_instants=1,
                    spacing=False)
    assert one.flow_speed_error == pytest.approx(-0.3466, abs=1e-4)  # issue 27: mu = eta made flows 35 % too slow
    assert one.mu_source == "given" and "too slow" in one.lines()[-1]
    free = omissions(_pair(table, 3.0), spacing=False)
    assert (free.wall_drag_along, free.wall_drag_across, free.wall_height) == (1.0, 1.0, None)


def test_subsampling_is_deterministic(table):
    from ciliary_carpet.carpet import layout

    c = Carpet(layout.square(4, 4, 2.0), CHI_N, table, layout.random_phases(16, 0))
    a = omissions(c, n_cilia=5, n_instants=2, seed=7, spacing=False)
    b = omissions(c, n_cilia=5, n_instants=2, seed=7, spacing=False)
    other = omissions(c, n_cilia=5, n_instants=2, seed=8, spacing=False)
    assert len(a.cilia) == 5 and np.array_equal(a.cilia, b.cilia) and not np.array_equal(a.cilia, other.cilia)
    np.testing.assert_array_equal(a.ratio_tip, b.ratio_tip)
    assert a.summary() == b.summary()


def test_uniform_deflection_against_issue_27():
    """Issue 27 measured a median 32 % at the tip and 18 % at mid-length (pointwise: the others'
    flow over the instantaneous own speed; 12 cilia x 6 instants, tol 1e-4; its 90th percentile
    66-69 %). Here (64 of 100 cilia, seed 0) the pointwise medians are 29.5 % and 18.9 % and the
    tip's 90th percentile 65 %; the r.m.s.-normalised medians 28.0 % and 18.5 %. The band allows
    for the sample (12 cilia, seed 0: 30.9 % pointwise) and the instants chosen. The issue's carpet
    was uncoupled, in still fluid (scenes are coupled by default since: the same layout with
    coupling = "none" and the still-fluid table)."""
    from ciliary_carpet.scenes.assembly import assemble
    from ciliary_carpet.scenes.scene import load_scene

    sc = assemble(load_scene(ROOT / "designs" / "uniform_deflection.toml")).carpet()
    c = Carpet(sc.bases, sc.chi_N, ThrustTable.default(), sc.phases, direction=sc.direction, wall=sc.wall,
               blob=sc.blob)
    o = omissions(c, tol=1e-4)
    # the issue measured with the former viscosity mu = 1; the induced flow scales as 1 / mu and
    # the beat speed does not, so the ratios at mu = 1 are the default's (mu = 0.653) times mu
    assert o.mu == pytest.approx(0.6534, abs=1e-4)
    assert 0.26 <= o.tip_pointwise_median * o.mu <= 0.38
    assert 0.15 <= o.mid_pointwise_median * o.mu <= 0.22
    assert 0.22 <= o.tip_median * o.mu <= 0.36
    assert o.mid_median < o.tip_median < o.tip_p90 <= o.tip_max
    assert o.interaction_error < 1e-3  # the evaluation's bound, in units of the ratio
    assert 0.8 <= o.spacing_exponent <= 1.3  # the instantaneous coupling falls about like 1 / spacing
    assert o.spacing_10 > 2.0 * (o.tip_median / TARGET_RATIO) ** 0.5
    s = o.summary()
    json.dumps(s, allow_nan=False)
    assert s["interaction"]["tip"]["median"] == o.tip_median
    assert len(s["lines"]) == 5
    # the oscillating part of the others' flow (section (d)): uncoupled 0.52 (max 1.34), coupled 1.2 (max 3.1)
    assert 0.3 <= o.oscillation_ratio_median <= 2.0 and o.oscillation_ratio_max > o.oscillation_ratio_median
    assert 0.01 <= o.thrust_shift_median <= 0.2 and o.oscillation_window <= 0.02
    assert s["oscillation"]["ratio"]["median"] == o.oscillation_ratio_median and "first-order" in s["lines"][2]


def test_consistent_viscosity_is_said(table):
    mu = sbt_viscosity(1.0, 0.02)
    c = Carpet(np.array([[0.0, 0.0], [3.0, 0.0]]), CHI_N, table, viscosity=mu)
    o = omissions(c, n_instants=1, spacing=False)
    assert abs(o.flow_speed_error) < 1e-12 and "agree" in o.lines()[-1] and "given as" in o.lines()[-1]


def test_still_carpet_has_nothing_to_size(table):
    top = float(table.ds.chi_N.values[-1])  # the flutter cutoff: the filaments stand still
    c = Carpet(np.array([[0.0, 0.0], [3.0, 0.0]]), top, table)
    assert not c.flutter.any()
    o = omissions(c)
    assert len(o.cilia) == 0 and math.isnan(o.tip_median) and math.isnan(o.pushback_median)
    s = o.summary()
    json.dumps(s, allow_nan=False)
    assert s["interaction"]["tip"]["median"] is None and s["lines"][0].startswith("No cilium flutters")


def test_render_summary_sizes_what_the_model_leaves_out(tmp_path):
    """Every render's summary carries the omissions (JSON) and says them in words (summary.md)."""
    import json

    from ciliary_carpet.render import render
    from ciliary_carpet.scenes.scene import scene_from_dict

    data = {"name": "tiny", "carpet": {"lattice": "square", "shape": [3, 3], "spacing": 2.0, "chi_N": 3.0,
                                       "coupling": "none"},  # uncoupled: the coupling's linear estimate below
            "output": {"n_seeds": 4, "periods": 1.0, "field_shape": [10, 10], "snapshots": 0, "frames": 0,
                       "ftle": False, "preview": False}}
    res = render(scene_from_dict(data), tmp_path / "tiny")
    s = json.loads((res.out_dir / "summary.json").read_text())
    om = s["omissions"]
    assert om["interaction"]["sampled_cilia"] == 9 and 0 < om["interaction"]["tip"]["median"] < 1
    assert om["viscosity"]["mu"] == om["viscosity"]["mu_sbt"] and 0.6 < om["viscosity"]["mu_sbt"] < 0.7
    assert om["viscosity"]["source"] == "filaments"
    md = (res.out_dir / "summary.md").read_text()
    assert "## What the model leaves out" in md and om["lines"][0] in md
    cp = s["coupling"]  # uncoupled (still-fluid table): the coupling's size by the linear drag estimate
    assert cp["model"] == "linear drag estimate" and cp["status"] == "not solved"
    assert 0 < cp["median_speed_coupled"] < cp["median_speed_uncoupled"]
    assert "## Cilia that feel the flow" in md and "linear estimate" in md


# ------------------------------------------------------------------ (d) the oscillating part of the others' flow
def _line_flow(c, x, pos, frc):
    """The flow at the point x (3,) of one cilium's resolved line (n_s, 2) of forces per length:
    the carpet's kernel and viscosity, Simpson's rule."""
    from ciliary_carpet.carpet.cycles import simpson
    from ciliary_carpet.stokes import stokeslet_velocity

    w = simpson(c.s.size)
    pad = lambda a: np.concatenate([a, np.zeros((a.shape[0], 1))], axis=1)  # noqa: E731
    return stokeslet_velocity(x[None], pad(pos), pad(frc * w[:, None]), c.mu, kernel=c.kernel)[0]


def _direct_drag(c, j, t):
    """K_j(t) from the shape at t by another quadrature: chord tangents, midpoint rule."""
    pos = c.state(t, [j])[0][0]
    d = np.diff(pos, axis=0)
    ds = np.linalg.norm(d, axis=1, keepdims=True)
    tg = d / ds
    return -c.table.eta * (2.0 * np.eye(2) * ds.sum() - np.einsum("sa,sb,s->ab", tg, tg, ds[:, 0]))


def test_far_pair_oscillation_is_the_direct_sum(table):
    """Two cilia 20 L apart (same period): at cilium 0's force centre u'(t) is cilium 1's resolved
    line at t less its mean over the table's 64 phase samples, summed here with the Stokeslets of
    ciliary_carpet.stokes; the ratio and the thrust shift follow from it (K by another quadrature)."""
    c = _pair(table, 20.0)
    o = omissions(c, tol=0.0, n_instants=1, spacing=False)  # every sum resolved: the two agree to rounding
    T, n = float(c.periods[0]), o.oscillation_instants
    x0 = np.append(c.centres[0], 0.0)
    xs, fs = c.cycle_samples([1])
    U = np.mean([_line_flow(c, x0, xs[0, p], fs[0, p]) for p in range(xs.shape[1])], axis=0)[:2]
    ts = T * np.arange(n) / n  # equal periods: the instants are the group's own
    up = np.array([_line_flow(c, x0, *[a[1] for a in c.state(t)[:2]])[:2] - U for t in ts])
    ratio = math.sqrt(np.mean((up ** 2).sum(axis=1))) / np.linalg.norm(U)
    assert o.oscillation_ratio[0] == pytest.approx(ratio, rel=1e-9)
    assert 2.0 < ratio < 20.0  # measured 8.2: one neighbour's force oscillates far more than its mean
    dF = np.mean([_direct_drag(c, 0, t) @ u for t, u in zip(ts, up)], axis=0)
    np.testing.assert_allclose(o.thrust_shift[0], dF, rtol=0.01, atol=1e-3 * np.linalg.norm(dF))
    assert o.thrust_shift_ratio[0] == pytest.approx(np.linalg.norm(o.thrust_shift[0])
                                                    / np.linalg.norm(c.mean_thrust[0]))
    # the carpet's levels of detail (tol 1e-4) give the same to their tolerance
    lod = omissions(c, tol=1e-4, n_instants=1, spacing=False)
    np.testing.assert_allclose(lod.oscillation_ratio, o.oscillation_ratio, rtol=2e-3)
    assert o.oscillation_window == 0.0 and o.oscillation_groups == 1 and not o.coupled
    assert math.isnan(o.thrust_shift_of_coupling_median) and "the model leaves this out" in o.lines()[2]


def test_lone_cilium_has_no_oscillating_flow(table):
    o = omissions(Carpet(np.zeros((1, 2)), CHI_N, table), n_instants=1)
    assert np.all(np.isnan(o.oscillation_ratio)) and np.all(np.isnan(o.thrust_shift))
    assert math.isnan(o.oscillation_ratio_median) and math.isnan(o.thrust_shift_median)
    s = o.summary()
    json.dumps(s, allow_nan=False)
    assert s["oscillation"]["ratio"]["median"] is None and s["oscillation"]["thrust_shift"]["max"] is None
    assert s["lines"][2].startswith("No other cilium beats")


def test_synchronous_phases_oscillate_more(table):
    """A uniform 4 x 4 carpet: the others' mean flow does not depend on the phases, but in step the
    neighbours' oscillations add up at a force centre, out of step they partly cancel. Measured:
    synchronous 6.0 (median), random 2.7; thrust shift 11 % and 6.2 % of |Fbar|."""
    from ciliary_carpet.carpet import layout

    sync = omissions(Carpet(layout.square(4, 4, 2.0), CHI_N, table, np.zeros(16)), n_instants=1, spacing=False)
    rand = omissions(Carpet(layout.square(4, 4, 2.0), CHI_N, table, layout.random_phases(16, 0)), n_instants=1,
                     spacing=False)
    assert sync.pushback_median == pytest.approx(rand.pushback_median, rel=1e-9)  # the same mean flow
    assert sync.oscillation_ratio_median > 1.5 * rand.oscillation_ratio_median
    assert sync.thrust_shift_median > rand.thrust_shift_median
    np.testing.assert_allclose([sync.oscillation_ratio_median, rand.oscillation_ratio_median], [5.98, 2.69], rtol=0.02)


def test_twelve_instants_resolve_the_cycle(table):
    """The cycle averages converge fast in the number of instants (exact sums): against 24, 12
    instants give the ratio to 6e-8 and the shift to 2e-6 of itself, 8 to 2e-5 and 6e-4 (measured)."""
    from ciliary_carpet.carpet import layout

    c = Carpet(layout.square(4, 4, 2.0), CHI_N, table, layout.random_phases(16, 0))
    o = {n: omissions(c, tol=0.0, n_instants=1, spacing=False, n_oscillation=n) for n in (8, 12, 24)}
    err = {n: (np.max(np.abs(o[n].oscillation_ratio / o[24].oscillation_ratio - 1)),
               np.max(np.linalg.norm(o[n].thrust_shift - o[24].thrust_shift, axis=1)
                      / np.linalg.norm(o[24].thrust_shift, axis=1))) for n in (8, 12)}
    assert err[12][0] < 1e-6 and err[12][1] < 1e-5
    assert err[8][0] > 10 * err[12][0] and err[8][1] > 10 * err[12][1]
    assert o[12].oscillation_instants == 12


def test_thrust_shift_of_a_uniform_oscillating_flow(table):
    """u'(t) = a cos(2 pi t / T) e_x on one cilium: dF = < K(t) u'(t) > against the same formula
    evaluated directly (K from the shape at each instant by another quadrature, 48 instants); and a
    still, nearly straight filament at angle theta_lim has K = -eta (2 I - t t^T)."""
    c = Carpet(np.zeros((1, 2)), CHI_N, table, np.array([0.3]))
    T, a = float(c.periods[0]), 0.7
    for n in (12, 48):
        ts = T * np.arange(n) / n
        flow = a * np.cos(2 * np.pi * ts / T)[:, None, None] * np.array([1.0, 0.0])
        got = thrust_shift(c, [0], ts, flow)[0]
        if n == 12:
            first = got
    direct = np.mean([_direct_drag(c, 0, t) @ (a * math.cos(2 * math.pi * t / T) * np.array([1.0, 0.0]))
                      for t in ts], axis=0)
    np.testing.assert_allclose(got, direct, rtol=0.01, atol=0.01 * np.linalg.norm(direct))
    np.testing.assert_allclose(first, got, rtol=1e-6, atol=1e-9)  # 12 instants already the cycle average
    assert np.linalg.norm(got) > 1e-3 * a  # the drag's first harmonic correlates with the flow
    # linear in the flow, and a steady flow sees the cycle-mean drag
    np.testing.assert_allclose(thrust_shift(c, [0], ts, 2 * flow)[0], 2 * got, rtol=1e-12)
    u0 = np.array([0.2, -0.1])
    Kbar = drag_tensor(c, [0], np.arange(64) / 64).mean(axis=1)[0]
    np.testing.assert_allclose(thrust_shift(c, [0], ts, np.broadcast_to(u0, (n, 1, 2)))[0], Kbar @ u0, rtol=1e-9)
    # a still filament (the flutter cutoff): straight at theta_lim but for the clamp's boundary layer
    top = float(table.ds.chi_N.values[-1])
    still = Carpet(np.zeros((1, 2)), top, table)
    th = float(table.ds.theta_lim.values[-1])
    t_ = np.array([-math.sin(th), math.cos(th)])
    np.testing.assert_allclose(drag_tensor(still, [0], [0.0])[0, 0], -table.eta * (2 * np.eye(2) - np.outer(t_, t_)),
                               atol=0.03)


def _flow_table():
    return ThrustTable.default(flow=True)  # the shipped table over the background flow


def test_coupled_carpet_oscillation_and_its_share_of_the_coupling():
    """A coupled 3 x 3 carpet: its cilia beat in flows of their own, at periods a little apart, so
    each one's window is interpolated from its group's instants; against a cilium's own instants
    (12 evaluations) the shift agrees to 1 %, the ratio to 1e-3; the share of the coupling's own
    change of the thrust is |dF| over |Fbar(U) - Fbar(0)| from the table's mean thrust."""
    from ciliary_carpet.carpet import layout
    from ciliary_carpet.carpet.carpet import Instant

    ft = _flow_table()
    c = Carpet(layout.square(3, 3, 2.0), CHI_N, ft, layout.random_phases(9, 1), coupling="mean")
    assert c.coupled.converged
    o = omissions(c, n_instants=1, spacing=False)
    assert o.coupled and o.oscillation_groups == 1 and 0 < o.oscillation_window <= 0.02
    # one cilium's own window, evaluated directly
    j = int(np.argmax(np.abs(c.periods / np.median(c.periods) - 1)))
    T, n = float(c.periods[j]), o.oscillation_instants
    Tg = float(np.median(c.periods))
    ts = Tg * (n - 1) / (2 * n) + (np.arange(n) - (n - 1) / 2) * T / n
    U = c.others_mean_flow([j])[0, :2]
    x = np.append(c.centres[j], 0.0)
    up = np.array([c.velocity(x[None], Instant(t), 1e-4)[0, :2]
                   - _line_flow(c, x, *[a[0] for a in c.state(t, [j])[:2]])[:2] - U for t in ts])
    k = int(np.flatnonzero(o.cilia == j)[0])
    assert o.oscillation_ratio[k] == pytest.approx(math.sqrt(np.mean((up ** 2).sum(axis=1))) / np.linalg.norm(U),
                                                   rel=1e-3)
    np.testing.assert_allclose(o.thrust_shift[k], thrust_shift(c, [j], ts, up[:, None])[0], rtol=0.01,
                               atol=0.01 * np.linalg.norm(o.thrust_shift[k]))
    # the share of the coupling: the table's mean thrust at U_j and at rest
    u = c.background @ c.rotation
    F = lambda par, perp: np.stack([ft.scalar(q, c.chi_N, U_par=par, U_perp=perp)  # noqa: E731
                                    for q in ("thrust_x", "thrust_y")], axis=-1) @ c.rotation.T
    dF = (F(u[:, 1], u[:, 0]) - F(0 * u[:, 1], 0 * u[:, 0]))[o.cilia]
    np.testing.assert_allclose(o.thrust_shift_of_coupling,
                               np.linalg.norm(o.thrust_shift, axis=1) / np.linalg.norm(dF, axis=1), rtol=1e-9)
    assert np.all(np.isfinite(o.thrust_shift_of_coupling)) and o.thrust_shift_of_coupling_median > 0
    line = o.lines()[2]
    assert line.startswith("The coupling lets each cilium beat") and "of the coupling's own change" in line
    assert "first-order estimate" in line and "an issue to come" in line
    json.dumps(o.summary(), allow_nan=False)
