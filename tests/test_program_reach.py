"""One layout, several programs: reachability over field strengths and the switch's transient
(ciliary_carpet.design.program_reach)."""
import json
import math
from importlib import resources

import numpy as np
import pytest

from ciliary_carpet.design.program_reach import REGIMES, program_reachability, switch_transient
from single_cilium.lookup import ThrustTable

CUTOFF_150 = 94.59381  # flutter cutoff of chi_E = 150, eta = 1 (the tables' chi_N_cutoff)


@pytest.fixture(scope="module")
def t200():
    return ThrustTable.default()


@pytest.fixture(scope="module")
def t150(tmp_path_factory):
    """The chi_E = 150 table: the shipped one where it is, else a small one built here (13 rows, ~10 s)."""
    shipped = resources.files("single_cilium") / "data" / "flow_chiE150_eta1.nc"
    if shipped.is_file():
        return ThrustTable.load(shipped).in_still_fluid()
    from single_cilium.table import build_table
    path = tmp_path_factory.mktemp("table150") / "t150.nc"
    return build_table(150.0, 1.0, np.linspace(0.0, CUTOFF_150 * 1.05, 12), path=path)


@pytest.fixture(scope="module")
def reach(t150, t200):
    return program_reachability([t150, t200], ["low", "high"], n=201)


def test_the_grid_is_symmetric_and_the_angle_odd_the_thrust_even(reach):
    c = reach.chi_N
    assert np.array_equal(c, -c[::-1]) and 0.0 in c
    for i in range(2):
        ang, thr = reach.angle[i], reach.thrust[i]
        on = reach.beats[i]
        assert np.array_equal(on, on[::-1])
        assert np.array_equal(ang[on], -ang[::-1][on])
        assert np.array_equal(thr, thr[::-1])
        assert np.all(np.isnan(ang[~on])) and np.all(thr[~on] == 0)
        pos = on & (c > 0)
        assert np.all(ang[pos] > 0) and np.all(np.diff(ang[pos]) > 0)  # deflection grows with chi_N
    r = reach.angle_range[1]
    assert r["min"]["angle"] == pytest.approx(-r["max"]["angle"], abs=1e-12)
    assert r["min"]["chi_N"] == pytest.approx(-r["max"]["chi_N"], abs=1e-9)
    p = reach.pairs[0]
    assert p.smallest["delta"] == pytest.approx(-p.largest["delta"], abs=1e-9)
    assert p.smallest["chi_N"] == pytest.approx(-p.largest["chi_N"], abs=1e-6)


def test_on_off_edges_are_the_tables_cutoffs(reach, t150, t200):
    c150, c200 = t150.cutoff(), t200.cutoff()
    assert c150 == pytest.approx(CUTOFF_150, abs=1e-4) and c200 == pytest.approx(162.77486, abs=1e-4)
    assert reach.edges == ((0.0, c150), (0.0, c200))
    p = reach.pair("low", "high")
    assert p.both == (0.0, c150)
    assert [(s.beats, s.still, s.how, s.lo, s.hi) for s in p.switches] == [
        ("high", "low", "rests", c150, 150.0), ("high", "low", "coiled", 150.0, c200)]
    # on the grid the regimes change exactly there
    a = np.abs(reach.chi_N)
    assert np.array_equal(reach.beats[0], a <= c150) and np.array_equal(reach.beats[1], a <= c200)
    low = np.array(REGIMES)[reach.regime[0]]
    assert set(low[(a > c150) & (a <= 150)]) == {"rests"} and set(low[a > 150]) == {"coiled"}
    assert a.max() == c200 and c150 in a
    assert p.ratio["vanishes"] == ((c150, "low"),)
    text = reach.describe()
    assert "94.59 < |chi_N| <= 150.00: beats under 'high', rests under 'low'" in text
    assert "150.00 < |chi_N| <= 162.77: beats under 'high', rests coiled up" in text


def test_the_pair_curve_and_its_extremes(reach, t150, t200):
    p = reach.pair("low", "high")
    assert p.monotone
    d = p.angle_b - p.angle_a
    # refined extremes are at least the grid's, and the fields really differ there
    assert p.largest["delta"] >= d.max() - 1e-12 and p.smallest["delta"] <= d.min() + 1e-12
    x = p.largest["chi_N"]
    assert p.largest["delta"] == pytest.approx(float(t200.scalar("thrust_angle", x) - t150.scalar("thrust_angle", x)),
                                               abs=1e-12)
    # at fixed chi_N the weaker field deflects more (closer to its limit angle arcsin(chi_N / chi_E))
    assert p.largest["delta"] > 0.1 and abs(x) == pytest.approx(t150.cutoff())
    assert 0 < p.largest["error"] < 1e-3
    assert p.ratio["at_straight"] == pytest.approx(t200.scalar("thrust_norm", 0.0) / t150.scalar("thrust_norm", 0.0))
    assert p.ratio["max"]["value"] > p.ratio["min"]["value"] > 1
    swapped = reach.pair("high", "low")
    assert np.array_equal(swapped.angle_a, p.angle_b) and swapped.largest["delta"] == -p.smallest["delta"]
    with pytest.raises(ValueError, match="no pair of states"):
        reach.pair("low", "medium")


def test_identical_tables_make_identical_angles(t200):
    r = program_reachability([t200, t200], ["a", "b"], n=51)
    p = r.pairs[0]
    assert np.array_equal(r.angle[0], r.angle[1], equal_nan=True)
    assert np.array_equal(p.angle_a, p.angle_b)
    assert p.largest["delta"] == 0.0 and p.smallest["delta"] == 0.0
    assert p.switches == () and p.ratio["vanishes"] == ()
    assert np.allclose(p.thrust_ratio[np.isfinite(p.thrust_ratio)], 1.0)


def test_summary_is_strict_json_and_describe_reads(reach):
    s = reach.summary()
    text = json.dumps(s, allow_nan=False)
    assert "NaN" not in text and "Infinity" not in text
    assert [x["name"] for x in s["states"]] == ["low", "high"]
    assert s["states"][1]["beats_for_abs_chi_N"] == [0.0, 162.77]
    assert s["pairs"][0]["angle_b_given_angle_a"].startswith("one value")
    d = reach.describe()
    assert d.count("\n") < 12 and "'low' -> 'high'" in d and "one angle under 'high' for each angle under 'low'" in d


def test_bad_input_raises_naming_the_problem(t200):
    with pytest.raises(ValueError, match="no tables"):
        program_reachability([], [])
    with pytest.raises(ValueError, match="1 table.* but 2 name"):
        program_reachability([t200], ["a", "b"])
    with pytest.raises(ValueError, match="distinct"):
        program_reachability([t200, t200], ["a", "a"])
    with pytest.raises(ValueError, match="n must be an integer >= 3"):
        program_reachability([t200], ["a"], n=2)
    with pytest.raises(ValueError, match="different eta"):
        program_reachability([t200, ThrustTable(t200.ds.assign_attrs(eta=2.0))], ["a", "b"])
    with pytest.raises(TypeError, match="ThrustTable"):
        program_reachability(["table.nc"], ["a"])
    with pytest.raises(ValueError, match=r"chi_N must be finite: chi_N\[1\] = nan"):
        switch_transient(t200, [10.0, math.nan])
    with pytest.raises(ValueError, match="non-empty"):
        switch_transient(t200, [])


def test_the_transient_grows_toward_the_cutoff(t150):
    cut = t150.cutoff()
    c = np.concatenate([np.linspace(40.0, cut - 1.0, 12), [cut]])
    tr = switch_transient(t150, c)
    assert np.all(tr.regime == 0) and np.all(tr.known)
    b = tr.beats_1pct[:-1]
    assert np.all(np.diff(b) > 0) and np.all(np.diff(tr.tau_1pct[:-1]) > 0)
    assert b == pytest.approx(math.log(100) / -np.log(tr.multiplier[:-1]))
    assert tr.tau_1pct[:-1] == pytest.approx(b * tr.period[:-1])
    assert tr.beats_e[:-1] == pytest.approx(b / math.log(100))
    # near the Hopf cutoff 1 - |mu| falls linearly: beats ~ 1/(cutoff - chi_N)
    near = (cut - c[:-1]) < 15
    prod = b[near] * (cut - c[:-1][near])
    assert prod.max() / prod.min() < 1.5
    # at the cutoff |mu| = 1: it does not settle, said so, nothing divided by zero
    assert not tr.settles[-1] and math.isinf(tr.beats_1pct[-1]) and tr.rate[-1] == 0
    s = tr.summary()
    json.dumps(s, allow_nan=False)
    assert s["not_settling"] == {"count": 1, "chi_N": [round(cut, 2)]}
    assert s["worst"]["chi_N"] == round(cut, 2) and s["worst"]["beats_1pct"] is None
    assert "do not settle at this resolution" in tr.statement()
    ok = switch_transient(t150, c[:-1])
    assert ok.summary()["worst_beating"]["chi_N"] == round(c[-2], 2)
    assert "near the flutter cutoff" in ok.statement() and "1/(cutoff - |chi_N|)" in ok.statement()


def test_the_transient_of_resting_coiled_and_mirrored_cilia(t150):
    tr = switch_transient(t150, [-60.0, 60.0, 97.0, 155.0, 5.0])
    assert [REGIMES[k] for k in tr.regime] == ["beats", "beats", "rests", "coiled", "beats"]
    assert tr.beats_1pct[0] == tr.beats_1pct[1]
    assert tr.alpha[2] < 0 and tr.tau_1pct[2] == pytest.approx(math.log(100) / -tr.alpha[2])
    assert math.isnan(tr.beats_1pct[2]) and not tr.known[3] and math.isnan(tr.tau_1pct[3])
    # near chi_N = 0 the settling is the curvature's relaxation: |mu| = exp(-T), 4.6 tau
    # (to the spline's wiggle across the floor's kink, 5e-4 in |mu| on a coarse table: 2e-3 in tau)
    assert tr.curvature_limited[4] and tr.tau_1pct[4] == pytest.approx(math.log(100), rel=5e-3)
    assert not tr.curvature_limited[0] and tr.multiplier[0] > math.exp(-tr.period[0]) + 0.01
    s = tr.summary()
    assert s["coiled"] == 1 and s["unknown"] == 1 and s["worst_resting"]["chi_N"] == 97.0
    assert "1 cilium(s) have no estimate (1 coiled" in tr.statement()


def test_floquet_multiplier_matches_a_direct_simulation(t200):
    """The module docstring's check: a cycle perturbed along its amplitude relaxes by the table's
    |mu| per beat (chi_E = 200, chi_N = 146.5: |mu| = 0.8343, the next multiplier exp(-T) = 0.7213)."""
    from single_cilium.cycle import limit_cycle
    from single_cilium.dynamics import simulate
    from single_cilium.filament import Filament
    from single_cilium.params import CiliumParams
    p = CiliumParams(200.0, 1.0, 146.5)
    cyc = limit_cycle(p, degree=8, n_phase=64, error_estimate=False)
    T, mu = cyc.period, cyc.floquet
    assert mu == pytest.approx(float(t200.scalar("floquet", 146.5)), abs=1e-3)
    fil = Filament(p, cyc.mesh)
    eq = fil.equilibrium_state()
    theta, kappa = fil.split(eq + 1.02 * (cyc.state0 - eq))
    theta = theta.copy()
    theta[0] = 0.0
    beats, per = 25, 128
    sim = simulate(p, beats * T, state=(theta, kappa), mesh=cyc.mesh, rtol=1e-10, n_out=beats * per + 1,
                   error_estimate=False)
    tip = sim.data.theta.values[:, -1]
    amp = []
    for k in range(beats):
        seg = tip[k * per:(k + 1) * per + 1]
        i = int(np.argmax(seg))
        assert 0 < i < per
        a, b, c = seg[i - 1:i + 2]
        amp.append(b - 0.25 * (a - c) ** 2 / (a - 2 * b + c))
    d = np.abs(np.diff(amp))
    k = np.arange(d.size)
    measured = math.exp(np.polyfit(k[14:], np.log(d[14:]), 1)[0])
    assert measured == pytest.approx(mu, abs=3e-3)  # measured 0.8338 against 0.8343
    assert measured - math.exp(-T) > 0.1  # not the curvature floor
    tr = switch_transient(t200, [146.5])
    assert tr.beats_1pct[0] == pytest.approx(math.log(0.01) / math.log(measured), rel=0.05)


def test_a_field_that_makes_nothing_beat_is_a_state_of_on_off_switches(t200):
    from single_cilium.table import build_table
    still = build_table(100.0, 1.0, np.linspace(0.0, 90.0, 4))  # below the flutter onset (chi_E ~ 118)
    with pytest.raises(ValueError, match="no state's field makes any cilium beat"):
        program_reachability([still], ["off"])
    r = program_reachability([still, t200], ["off", "on"], n=21)
    assert r.edges[0] is None and r.angle_range[0] is None and not r.beats[0].any()
    p = r.pairs[0]
    assert p.both is None and p.chi_N.size == 0
    assert [(s.how, s.lo, s.hi) for s in p.switches] == [("rests", 0.0, 100.0), ("coiled", 100.0, t200.cutoff())]
    json.dumps(r.summary(), allow_nan=False)
    assert "|chi_N| <= 100.00: beats under 'on', rests under 'off'" in r.describe()
    tr = switch_transient(still, [0.0, 50.0, 95.0, 120.0])
    assert [REGIMES[k] for k in tr.regime] == ["rests", "rests", "rests", "coiled"]
    assert list(tr.known) == [True, True, False, False]  # 95: beyond the table's rows
    assert np.all(tr.alpha[:2] < 0) and "come to rest within" in tr.statement()
