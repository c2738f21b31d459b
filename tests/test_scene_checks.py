"""Scene values that are accepted only where they make sense, numbers in the summary in the units
it states, carpets that own their arrays, and the Python front door."""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

import ciliary_carpet as cc
from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.scenes.scene import SceneError, load_scene, scene_from_dict
from single_cilium.table import ThrustTable


@pytest.fixture(scope="module")
def table():
    return ThrustTable.default()


# ------------------------------------------------------------------------------ reading
def test_numpy_scalars_read_as_the_numbers_they_hold():
    s = scene_from_dict({"field": {"eta": np.float32(2.0)}, "carpet": {"shape": [np.int64(3), np.int64(2)],
                                                                       "spacing": np.float64(3.0)},
                         "output": {"pathlines": np.bool_(False), "n_seeds": np.int32(5)}})
    assert s.field.eta == 2.0 and s.carpet.shape == (3, 2) and s.output.pathlines is False
    assert s.output.n_seeds == 5 and type(s.output.n_seeds) is int
    with pytest.raises(SceneError, match="output.pathlines must be true or false, got 1"):
        scene_from_dict({"output": {"pathlines": np.int64(1)}})


def test_utf8_byte_order_mark_and_other_encodings(tmp_path):
    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf[carpet]\nspacing = 3.0\n")
    assert load_scene(p).carpet.spacing == 3.0
    q = tmp_path / "latin1.toml"
    q.write_bytes('description = "caf\u00e9"\n'.encode("latin-1"))
    with pytest.raises(SceneError, match=r"latin1.toml: not UTF-8 text \(byte 0xe9 at offset 18\).*save it as UTF-8"):
        load_scene(q)


@pytest.mark.parametrize("text, message", [
    ("[carpet]\nspacing = 0.3\n", r"carpet.spacing must be a number in \[1, 1e\+06\] \(L; at least the filament "
                                  r"length: closer cilia can touch\), got 0.3"),
    ('[carpet]\nlattice = "points"\npoints = [[0, 0], [5, 0], [0.5, 0.2]]\n',
     r"carpet.points\[0\] and carpet.points\[2\] are 0.539 L apart; base points must lie at least 1 L apart"),
    ("[carpet]\nviscosity = 1e-300\n", r"carpet.viscosity must be a number in \[0.00653, 65.3\] \(within a factor "
                                       r"100 of 0.653, .* got 1e-300"),
    ("[field]\neta = 10.0\n[carpet]\nviscosity = 0.05\n", r"carpet.viscosity must be a number in \[0.0653, 653\]"),
    ("[carpet]\nwall = 1e-300\n", r"carpet.wall must be at least a filament diameter, 2 blob = 0.04 L"),
    ("[carpet]\nwall = 1e300\n", r"carpet.wall must be a number in \[0, 1e\+06\], got 1e\+300"),
    ("[carpet]\nblob = 1e-300\n", r"carpet.blob must be a length in \[0.0001, 0.5\) L"),
    ("[field]\neta = 1e-300\n", r"field.eta must be a number in \[0.001, 1000\]"),
    ("[field]\nchi_E = 1e300\n", r"field.chi_E must be a number in \[-10000, 10000\]"),
    ("[output]\nframes = 1000000000\n", r"output.frames must be an integer in \[0, 10000\]"),
    ("[output]\nfield_margin = 1e300\n", r"output.field_margin must be a number in \[0, 1e\+06\]"),
])
def test_values_that_overflow_hang_or_overlap_are_scene_errors(tmp_path, text, message):
    p = tmp_path / "s.toml"
    p.write_text(text)
    with pytest.raises(SceneError, match=f"^{re.escape(str(p))}: {message}"):
        load_scene(p)


def test_bounds_are_not_too_tight():
    """The bounds' edges are scenes: spacing 1 L, the filaments' viscosity times 100, a wall a
    filament diameter below the plane, a standing carpet's wall at its substrate."""
    s = scene_from_dict({"carpet": {"spacing": 1.0, "viscosity": 65.3, "wall": 0.04}})
    assert s.carpet.spacing == 1.0 and s.carpet.viscosity == 65.3 and s.carpet.wall == 0.04
    assert scene_from_dict({"carpet": {"geometry": "standing", "wall": 0.0}}).carpet.wall == 0.0


def test_front_door_takes_a_scene_or_a_path(tmp_path):
    with pytest.raises(TypeError, match=r"design\(\) takes a Scene .* or the path of a scene file, got int"):
        cc.design(3)
    with pytest.raises(TypeError, match=r"render\(\) takes a Scene"):
        cc.render(3.0, tmp_path / "out")
    with pytest.raises(TypeError, match=r"assemble\(\) takes a Scene"):
        cc.assemble(None)
    p = tmp_path / "x.toml"
    p.write_text("[carpet]\nshape = [2, 2]\n")
    d, carpet = cc.design(str(p))
    assert d is None and carpet.n == 4
    with pytest.raises(SceneError, match="cannot read the scene file"):
        cc.design(tmp_path / "missing.toml")


# ------------------------------------------------------------------------------ carpets
def test_carpet_owns_read_only_copies_of_its_arrays(table):
    b, chi, ph = layout.square(3, 3), np.full(9, 30.0), np.linspace(0, 0.8, 9)
    c = Carpet(b, chi, table, ph)
    x = np.array([[1.0, 1.0, 0.5]])
    u = c.velocity(x, CycleMean())
    b += 1.0
    chi[:] = 60.0
    ph[:] = 0.0
    assert np.array_equal(c.velocity(x, CycleMean()), u)
    assert np.all(c.chi_N == 30.0) and c.bases[0, 0] == 0.0 and c.phases[1] > 0
    for name in ("bases", "chi_N", "phases"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(c, name)[0] = 1.0
    s = Carpet(layout.row(2, 2.0), 30.0, table, geometry="standing", wall=0.0, azimuth=np.array([0.1, 0.2]))
    with pytest.raises(ValueError, match="read-only"):
        s.azimuth[0] = 0.0


def test_carpet_refuses_cilia_within_their_reach(table):
    with pytest.raises(ValueError, match=r"cilia 0 and 1 stand 0.3 L apart, within the 0.9\d* L that their beat "
                                         r"reaches.*smallest spacing allowed is 0.9\d* L"):
        Carpet(layout.square(2, 2, spacing=0.3), 30.0, table)
    for geometry, wall in (("planar", None), ("standing", 0.0)):
        c = Carpet(layout.square(2, 2, spacing=1.0), 30.0, table, geometry=geometry, wall=wall)
        assert np.all((c.reach > 0.5) & (c.reach <= 1.0))


# ------------------------------------------------------------------------------ summary units
_L, _T = 1e-3, 1e-2  # [units] of the second render: distinct powers of length and time tell apart
_MACHINE = r"^seconds\.|\.work\.|^threads\.|\.parallel\.|\.wall_s$|_seconds$|\.startup_seconds\."
"""Measurements of the machine (timings, work counters): not numbers of the flow."""
_DIMENSIONS = [  # (dotted path pattern, power of length, power of time); the first match counts
    (r"^(T0|beat\.period(_min|_max)?|beat\.loop_until|pathlines\.duration|mixing\.duration)$", 0, 1),
    (r"^mixing\.ftle_max$", 0, -1),
    (r"^(mean_field(\.section)?\.(max_speed|max_error_bound)|coupling\.median_speed_(un)?coupled)$", 1, -1),
    (r"^(design\.worst\[\]\.[xy]|design\.surface_height|design\.reachability\.(line|width|width_min)"
     r"|design\.reachability\.width_scan\[\]\[0\]|pathlines\.atol|pathlines\.end_point_error\.(max|median)"
     r"|standing\.(wall_below_clamps|target_height)|mean_field\.height|mean_field\.section\.(y|top))$", 1, 0),
    # dimensionless: counts, fractions, angles, relative residuals, curvatures, the scene as written, and
    # the omissions section (model units by its own "units" key and its key names)
    (r"^(n_cilia|tolerance|beat\.beating|layout\.|design\.(residual_(rms|max|error|threshold|error_tol)|local_rms|objective"
     r"|local_objective|control_points|cilia_near_cutoff|worst\[\]\.(index|residual)|speed_ratio_min|clipped"
     r"|reachability\.(\w+_deg|width_rms|residual_threshold|width_scan\[\]\[1\])|inside_swept\.|tolerance\.)"
     r"|mean_field\.(points|fidelity\.|section\.points|section\.fidelity\.)|snapshots\.|pathlines\.(tracers|periods|points"
     r"|beats|flow_tol|rtol|samples_per_period|outcome\.|stopped_early|end_point_error\.tracers)"
     r"|mixing\.(mixing_number|grid|defined_fraction|uniform_pump\.)|omissions\.|table\.|coupling\.(relative_change_\w+"
     r"|residual|rtol|iterations|evaluations|history|contraction|normal_flow)|scene_resolved\.|standing\.azimuth_deg\.)",
     0, 0),
]


def _numbers(x, path=""):
    """``{dotted path: number}`` of every number in ``x`` (list items as ``[]``, kept in order)."""
    if isinstance(x, dict):
        return [kv for k, v in x.items() for kv in _numbers(v, f"{path}.{k}" if path else k)]
    if isinstance(x, list):
        return [kv for v in x for kv in _numbers(v, path + "[]")]
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        return [(path, x)]
    return []


def test_every_summary_number_is_in_the_units_it_states(tmp_path):
    """One small designed scene rendered without and with [units]: every number of summary.json
    scales by its power of L and tau (the list is the summary's own numbers: a number no rule
    covers fails), the omissions say they are in model units, and summary.md states speeds,
    lengths and bounds in m and s."""
    body = ('[carpet]\nshape = [2, 2]\n[target]\nkind = "uniform"\nangle = 20.0\n[output]\nn_seeds = 2\n'
            'periods = 0.5\nfield_shape = [4, 4]\nsnapshots = 1\nframes = 1\npreview = false\n')
    (tmp_path / "a.toml").write_text(body)
    (tmp_path / "b.toml").write_text(f"[units]\nlength_m = {_L}\ntime_s = {_T}\nviscosity_Pa_s = 1e-3\n" + body)
    a = cc.render(load_scene(tmp_path / "a.toml"), tmp_path / "a").summary
    cc.render(load_scene(tmp_path / "b.toml"), tmp_path / "b")
    sb = json.loads((tmp_path / "b" / "summary.json").read_text())
    sa = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert a["units"] == "L, tau" and sb["units"] == "SI" and sb["omissions"]["units"].startswith("L, tau")
    na, nb = _numbers(sa), _numbers({k: v for k, v in sb.items() if k != "units"})
    nb = [(p, v) for p, v in nb if not p.startswith("scene_resolved.units.")]
    assert [p for p, _ in na] == [p for p, _ in nb]
    for (path, x), (_, y) in zip(na, nb):
        if re.search(_MACHINE, path):
            continue
        rule = next((r for r in _DIMENSIONS if re.search(r[0], path)), None)
        assert rule is not None, f"summary.json number {path} has no unit rule here: say how it scales"
        want = x * _L ** rule[1] * _T ** rule[2]
        assert y == pytest.approx(want, rel=1e-6, abs=1e-300), (path, x, y, rule[1:])
    md = (tmp_path / "b" / "summary.md").read_text()
    bound = sb["mean_field"]["max_error_bound"]
    assert f"accurate to {bound:.2g} m/s" in md and "L/tau" not in md.split("## What the model leaves out")[0]
    assert "(x, y in m)" in md and f"{sb['coupling']['median_speed_uncoupled']:.3g} m/s" in md


def test_expected_memory_counts_the_field_grid():
    """A render's expected peak grows with its field grid by at least the arrays it keeps per
    point (points, velocity, error bound: 7 doubles) and by what an evaluation takes per point."""
    from ciliary_carpet.output.resources import expected_memory

    small = scene_from_dict({"output": {"field_shape": [80, 80]}})
    big = scene_from_dict({"output": {"field_shape": [1000, 1000]}})
    grew = expected_memory(big.needs()) - expected_memory(small.needs())
    n = 1000 * 1000 - 80 * 80
    assert grew >= n * 7 * 8
    assert grew >= n * 860  # an evaluation of the mean flow with its bound, at its peak (tracemalloc)
    no_field = scene_from_dict({"output": {"field_shape": [1000, 1000], "field": False, "snapshots": 0,
                                           "ftle": False}})
    assert expected_memory(no_field.needs()) < expected_memory(small.needs())


def test_design_result_owns_read_only_copies_of_its_arrays():
    from ciliary_carpet.design.result import Design

    chi, res = np.array([1.0, 2.0]), np.array([0.1, 0.2])
    d = Design(chi, np.zeros((2, 2)), np.ones((2, 2)), np.ones((2, 2)), res, 0.15, "angle")
    chi[0], res[0] = 99.0, 9.0
    assert d.chi_N[0] == 1.0 and d.residual[0] == 0.1 and d.worst(1)[0][0] == 1
    with pytest.raises(ValueError, match="read-only"):
        d.chi_N[1] = 0.0


def test_carpet_refuses_a_wall_through_its_filaments(table):
    with pytest.raises(ValueError, match=r"wall must be at least a filament diameter, 2 blob = 0.04 L"):
        Carpet(layout.square(2, 2), 30.0, table, wall=1e-300)
    assert Carpet(layout.square(2, 2), 30.0, table, wall=0.04).wall == 0.04
