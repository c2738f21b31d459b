"""What the carpet model leaves out, sized (ciliary_carpet/carpet/omissions.py; issues 26 and 27)."""
import json
import math
from pathlib import Path

import numpy as np
import pytest

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.carpet.carpet import sbt_viscosity
from ciliary_carpet.carpet.omissions import TARGET_RATIO, omissions, wall_drag_formula, wall_drag_ratios
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
    assert "1.85 times as hard to move across" in o.lines()[2]
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
    for the sample (12 cilia, seed 0: 30.9 % pointwise) and the instants chosen."""
    from ciliary_carpet.scenes.assembly import assemble
    from ciliary_carpet.scenes.scene import load_scene

    c = assemble(load_scene(ROOT / "designs" / "uniform_deflection.toml")).carpet()
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
    assert len(s["lines"]) == 4


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

    data = {"name": "tiny", "carpet": {"lattice": "square", "shape": [3, 3], "spacing": 2.0, "chi_N": 3.0},
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
